"""Headless batch conversion: a folder of takes in, baked duets out, on every core.

``python -m dancing_points_addon batch IN... -o OUT_DIR --format blend|fbx|bvh|npz``
and, inside Blender, ``blender --background --command dancing_points convert ...``
(``operators/batch_cli.py``) both run :func:`run`.

* Inputs: files, or folders searched recursively by extension (``.csv``, ``.bvh``,
  ``.amc``; also ``.fbx`` when Blender does the conversion). Hidden files and
  folders and the output folder are not searched. One output per take, named
  after it (``take.npz``, ``take.blend``, ``take.fbx``; ``take_leader.bvh`` +
  ``take_follower.bvh``; ``--render`` adds ``take.mp4``), in the output folder,
  under the input's sub-folder when it was found inside a folder. Two takes
  that would get the same name get their source extension appended
  (``take_csv.npz``, ``take_bvh.npz``).
* Work: ``--jobs`` worker processes (default: one per core), each a fresh
  interpreter (never a fork: ``bpy`` is not fork-safe) that loads the networks
  once, with one ONNX Runtime thread, and converts one take at a time. The
  ``bvh``/``npz`` formats run the bpy-free core only; ``blend``/``fbx`` (and
  ``--render``) import ``bpy`` in the worker and bake through the extension's
  operators. Longest files are dispatched first (better load balance); results
  are reported in input order.
* Output: a progress bar on stderr (per-file and overall progress, ETA; ``\\r``
  updates on a terminal, plain lines otherwise), one result line per file on
  stdout, and a JSON report (``OUT_DIR/batch_report.json`` or ``--report``)
  with ``input, output, outputs, status, error, frames, seconds`` per file.
* Faults: a bad file is reported (``status: failed`` and the reason) and
  skipped, the rest go on; the exit status is 1 if any file failed. Workers
  write temporary files (``.NAME.part.EXT`` beside the output); the parent
  renames them into place only once a file is complete, and never over an
  existing file unless ``--overwrite``. Ctrl-C (SIGINT) or SIGTERM stops the
  workers, removes their temporary files, writes the report and exits with
  130 (143 for SIGTERM); ``--resume`` then skips the takes whose outputs exist
  (``status: skipped``) and converts the rest.

Worker protocol: the parent writes one JSON job per line to a worker's stdin;
the worker answers with JSON lines on its stdout, each prefixed by
:data:`MSG_PREFIX` (everything else a library prints there is ignored; the
worker moves its own stdout to stderr, which goes to a log file whose tail is
reported if the worker dies).
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import datetime
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

from .errors import InputError, one_line

FORMATS = ("npz", "bvh", "blend", "fbx")
BPY_FORMATS = ("blend", "fbx")
CORE_INPUTS = (".csv", ".bvh", ".amc")
BPY_INPUTS = CORE_INPUTS + (".fbx",)
REPORT_NAME = "batch_report.json"
MSG_PREFIX = "@@dancing_points.batch@@ "
PART = ".part"
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 130, 143
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout / extension folder


# =========================================================================== arguments

def default_jobs() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def add_arguments(p: argparse.ArgumentParser, default_format: str = "npz") -> None:
    """The batch options (shared by the ``batch`` subcommand and Blender's ``convert``)."""
    from .cli import height_metres, positive_float, positive_int
    from .runtime import MODEL_ENV

    p.add_argument("inputs", nargs="+", metavar="IN",
                   help="take files (.csv), BVH (.bvh) or CMU AMC (.amc) files, or folders searched "
                        "recursively for them")
    p.add_argument("-o", "--output-dir", required=True, metavar="OUT_DIR",
                   help="folder for the outputs (created if missing)")
    p.add_argument("--format", choices=FORMATS, default=default_format,
                   help=f"output format (default {default_format}): npz = SPEC §4 arrays, bvh = "
                        "NAME_leader.bvh + NAME_follower.bvh, blend = a scene with the baked duet, "
                        "fbx = the two skinned armatures with their animation")
    p.add_argument("-j", "--jobs", type=positive_int, default=None, metavar="N",
                   help=f"worker processes (default: the number of cores, {default_jobs()} here)")
    p.add_argument("--render", action="store_true",
                   help="also render a Workbench preview video NAME.mp4 (needs Blender's bpy)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--resume", action="store_true",
                   help="skip the takes whose outputs already exist (e.g. after an interrupted run)")
    p.add_argument("--report", default=None, metavar="PATH",
                   help=f"JSON report (default: OUT_DIR/{REPORT_NAME})")
    p.add_argument("--models", default=None, metavar="DIR",
                   help=f"folder with the ONNX models (default: ${MODEL_ENV}, else the bundled models/)")
    p.add_argument("--threads", type=positive_int, default=1, metavar="N",
                   help="onnxruntime threads per worker (default 1)")
    p.add_argument("--input-fps", type=positive_float, default=None, metavar="F",
                   help="override every input's frame rate")
    p.add_argument("--asf", default=None, metavar="PATH",
                   help="ASF skeleton for the AMC inputs (default: found beside each)")
    p.add_argument("--height", type=height_metres, default=None, metavar="H",
                   help="the leader's height in metres (default: the take's height_m, else estimated)")
    p.add_argument("--no-foot-lock", action="store_true", help="turn contact-based foot locking off")
    p.add_argument("--no-hand-ik", action="store_true",
                   help="leave the leader's head and wrists where the network puts them (no IK onto the input)")
    p.add_argument("--leader-rig", default=None, metavar="FILE",
                   help="also retarget the leader onto the armature of this .blend, .glb/.gltf or .fbx file "
                        "(formats blend and fbx, --render; a file without an armature fails each take)")
    p.add_argument("--follower-rig", default=None, metavar="FILE",
                   help="the same for the follower")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (result lines only)")


# =========================================================================== planning

def discover(paths, exts, exclude=()):
    """``[(path, rel_dir)]``: the files among ``paths`` and, for folders, the files
    below them (recursively, sorted) whose extension is in ``exts``; ``rel_dir`` is
    the file's sub-folder relative to the folder it was found in ("" for a file
    given directly). A file given directly is kept whatever its extension (its
    conversion then reports the problem). Hidden entries, the folders in
    ``exclude`` and duplicates are left out."""
    exts = tuple(e.lower() for e in exts)
    excluded = {os.path.realpath(e) for e in exclude}
    out, seen = [], set()

    def add(path, rel):
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            out.append((os.path.abspath(path), rel))

    for p in paths:
        p = os.fspath(p)
        if os.path.isdir(p):
            for dirpath, dirnames, filenames in os.walk(p):
                dirnames[:] = sorted(d for d in dirnames if not d.startswith(".")
                                     and os.path.realpath(os.path.join(dirpath, d)) not in excluded)
                rel = os.path.relpath(dirpath, p)
                rel = "" if rel == "." else rel
                for f in sorted(filenames):
                    if not f.startswith(".") and os.path.splitext(f)[1].lower() in exts:
                        add(os.path.join(dirpath, f), rel)
        else:
            add(p, "")
    return out


def output_bases(entries):
    """Output base name (relative path without extension) of each ``(path, rel_dir)``:
    the input's stem; on a clash the source extension is appended, then a number."""
    bases = [os.path.join(rel, os.path.splitext(os.path.basename(p))[0]) for p, rel in entries]
    counts = collections.Counter(b.lower() for b in bases)
    for i, (p, _) in enumerate(entries):
        if counts[bases[i].lower()] > 1:
            ext = os.path.splitext(p)[1].lower().lstrip(".")
            if ext:
                bases[i] = f"{bases[i]}_{ext}"
    used, final = set(), []
    for b in bases:
        cand, k = b, 2
        while cand.lower() in used:
            cand, k = f"{b}_{k}", k + 1
        used.add(cand.lower())
        final.append(cand)
    return final


def output_kinds(fmt: str, render: bool):
    """``[(kind, suffix)]`` of the files one take produces."""
    kinds = {"npz": [("npz", ".npz")], "blend": [("blend", ".blend")], "fbx": [("fbx", ".fbx")],
             "bvh": [("bvh_leader", "_leader.bvh"), ("bvh_follower", "_follower.bvh")]}[fmt]
    return kinds + ([("mp4", ".mp4")] if render else [])


def temp_path(final: str) -> str:
    """The temporary name a worker writes before the rename: ``.NAME.part.EXT``
    beside ``final`` (the real extension kept last, which some writers need)."""
    folder, name = os.path.split(final)
    stem, ext = os.path.splitext(name)
    return os.path.join(folder, f".{stem}{PART}{ext}")


def temp_leftovers(tmp: str):
    """Everything a writer may leave for the temporary ``tmp``: the file itself,
    Blender's ``tmp@`` save file, a render folder ``tmp.d``."""
    return [tmp, tmp + "@", tmp + ".d"]


def remove_temps(tmps) -> None:
    for tmp in tmps:
        for p in temp_leftovers(tmp):
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError, IsADirectoryError, PermissionError):
                    os.unlink(p)


class Task:
    """One input take and what became of it."""

    def __init__(self, index, path, outputs, kinds):
        self.index = index
        self.input = path
        self.outputs = list(outputs)  # final paths, in kind order
        self.kinds = list(kinds)
        self.temps = [temp_path(o) for o in self.outputs]
        self.status = "pending"  # ok | failed | skipped | interrupted | pending
        self.error = None
        self.frames = None
        self.seconds = None
        self.replace = False  # may replace existing outputs
        self.fraction = 0.0
        self.started = None
        try:
            self.size = os.path.getsize(path)
        except OSError:
            self.size = 0

    @property
    def name(self):
        return os.path.basename(self.input)

    def record(self):
        return {"input": self.input, "output": self.outputs[0] if self.outputs else None,
                "outputs": self.outputs, "status": self.status, "error": self.error,
                "frames": self.frames, "seconds": None if self.seconds is None else round(self.seconds, 3)}


def plan(entries, out_dir, fmt, render=False, overwrite=False, resume=False):
    """Tasks for ``entries`` (see :func:`discover`); outputs that already exist make a
    task ``skipped`` (``resume``) or ``failed`` (neither ``resume`` nor ``overwrite``)."""
    kinds = output_kinds(fmt, render)
    tasks = []
    for i, ((path, _), base) in enumerate(zip(entries, output_bases(entries))):
        outs = [os.path.join(out_dir, base + suffix) for _, suffix in kinds]
        t = Task(i, path, outs, [k for k, _ in kinds])
        exist = [o for o in outs if os.path.lexists(o)]
        if resume and exist and len(exist) == len(outs):
            t.status, t.error = "skipped", "output exists"
        elif exist and (overwrite or resume):
            t.replace = True  # --overwrite; or --resume over an incomplete set of outputs
        elif exist:
            t.status = "failed"
            t.error = (f"{exist[0]}: output exists (use --overwrite to replace it or --resume to "
                       f"skip this take)")
        tasks.append(t)
    return tasks


def resolve_model_dir(explicit=None):
    from . import runtime

    d = explicit or os.environ.get(runtime.MODEL_ENV, "") or runtime.MODEL_DIR
    d = os.path.abspath(os.path.expanduser(d))
    missing = [f for f in runtime.MODEL_FILES.values() if not os.path.isfile(os.path.join(d, f))]
    if missing:
        raise InputError(d, f"no synthesis models here (missing {', '.join(missing)}); give the folder "
                            f"with --models")
    return d


# =========================================================================== progress

def fmt_duration(seconds) -> str:
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "--:--"
    s = int(round(max(0.0, seconds)))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def eta(elapsed, fraction):
    """Seconds left at constant throughput (None before any progress)."""
    if fraction <= 0.0:
        return None
    return elapsed * (1.0 - min(fraction, 1.0)) / fraction


class Progress:
    """Overall and per-file progress with an ETA on ``stream`` (stderr): one line
    rewritten with ``\\r`` on a terminal, plain lines otherwise (at each finished
    file and every ``interval`` seconds). Result lines go to ``out`` (stdout)."""

    WIDTH = 24

    def __init__(self, total, stream=None, out=None, enabled=True, tty=None, interval=10.0):
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.out = out if out is not None else sys.stdout
        self.enabled = enabled and self.total > 0
        if tty is None:
            try:
                tty = self.stream.isatty()
            except (AttributeError, ValueError):
                tty = False
        self.tty = tty
        self.interval = interval
        self.t0 = time.perf_counter()
        self.done = 0
        self.running = []  # [(name, fraction)]
        self._shown = False
        self._last_draw = 0.0
        self._last_line = time.perf_counter()
        self._last_done = -1

    def fraction(self):
        if not self.total:
            return 1.0
        return min(1.0, (self.done + sum(f for _, f in self.running)) / self.total)

    def text(self, width=None):
        f = self.fraction()
        elapsed = time.perf_counter() - self.t0
        fill = int(round(self.WIDTH * f))
        bar = "#" * fill + "-" * (self.WIDTH - fill)
        run = ", ".join(f"{n} {100 * x:.0f}%" for n, x in self.running)
        left = eta(elapsed, f) if self.done < self.total else 0.0
        line = (f"[{bar}] {self.done}/{self.total} files {100 * f:3.0f}% "
                f"elapsed {fmt_duration(elapsed)} ETA {fmt_duration(left)}")
        if run:
            line += " | " + run
        if width and len(line) > width:
            line = line[:max(width - 3, 0)] + "..."
        return line

    def update(self, done, running, force=False):
        self.done, self.running = done, list(running)
        if not self.enabled:
            return
        now = time.perf_counter()
        if self.tty:
            if force or now - self._last_draw >= 0.1:
                cols = shutil.get_terminal_size((100, 20)).columns - 1
                self.stream.write("\r\x1b[K" + self.text(cols))
                self.stream.flush()
                self._shown = True
                self._last_draw = now
        elif done != self._last_done or now - self._last_line >= self.interval:
            self.stream.write("progress: " + self.text() + "\n")
            self.stream.flush()
            self._last_line = now
            self._last_done = done

    def _clear(self):
        if self.enabled and self.tty and self._shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._shown = False

    def result(self, line):
        """One result line (stdout), keeping the bar below it on a terminal."""
        self._clear()
        print(line, file=self.out, flush=True)

    def finish(self):
        self._clear()


def result_line(task, out_dir=None) -> str:
    def rel(p):
        if out_dir:
            with contextlib.suppress(ValueError):
                return os.path.join(os.path.basename(out_dir.rstrip(os.sep)), os.path.relpath(p, out_dir))
        return p

    if task.status == "ok":
        outs = ", ".join(rel(o) for o in task.outputs)
        return f"ok      {task.input} -> {outs} ({task.frames} frames, {task.seconds:.2f} s)"
    if task.status == "skipped":
        return f"skipped {task.input} ({task.error})"
    return f"{task.status.upper():7s} {task.input}: {task.error}"


# =========================================================================== worker side

class _Terminated(BaseException):
    """SIGTERM in a worker: unwind (removing temporary files) and exit."""


class _Orphaned(BaseException):
    """The parent is gone (a write to it failed): unwind and exit."""


class _Channel:
    def __init__(self, stream):
        self.stream = stream

    def send(self, msg):
        try:
            self.stream.write(MSG_PREFIX + json.dumps(msg) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            raise _Orphaned() from None


def error_text(exc) -> str:
    """The one-line reason of a failed take (the message alone for a user-facing error)."""
    if isinstance(exc, InputError) or getattr(exc, "one_line", False):
        return one_line(exc)
    msg = one_line(exc)
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


class CoreConverter:
    """npz / bvh through the bpy-free core; the networks are loaded once."""

    def __init__(self):
        self._nets = {}

    def nets(self, model_dir, threads):
        key = (model_dir, threads)
        if key not in self._nets:
            from . import runtime
            self._nets.clear()
            self._nets[key] = {k: runtime.OnnxNet(os.path.join(model_dir, f), threads)
                               for k, f in runtime.MODEL_FILES.items()}
        return self._nets[key]

    def __call__(self, job, progress):
        from .runtime import Synthesizer
        from .take import load_input

        o = job["options"]
        take = load_input(job["input"], asf=o.get("asf"), input_fps=o.get("input_fps"), height=o.get("height"))
        progress(0.05)
        synth = Synthesizer(o["models"], o["threads"], height=o.get("height") or take.height,
                            foot_lock=not o.get("no_foot_lock"), hand_ik=not o.get("no_hand_ik"),
                            nets=self.nets(o["models"], o["threads"]))
        duet = synth.synthesize(take, progress=lambda i, n: progress(0.05 + 0.9 * i / max(n, 1)))
        write_duet_files(job["temps"], duet)
        return {"frames": int(duet.n_frames)}


def write_duet_files(temps: dict, duet) -> None:
    """Write the core formats among ``temps`` (``{kind: path}``): ``npz``,
    ``bvh_leader``, ``bvh_follower``. Plain writes (the paths are temporary)."""
    import numpy as np

    if "npz" in temps:  # (not runtime.save_npz: its own temporary file would escape a killed worker's cleanup)
        with open(temps["npz"], "wb") as f:
            np.savez_compressed(f, **duet.arrays())
            f.flush()
            os.fsync(f.fileno())
    if "bvh_leader" in temps or "bvh_follower" in temps:
        from .bvh import bvh_text
        from .runtime import duet_motions

        for role, motion in duet_motions(duet).items():
            path = temps.get("bvh_" + role)
            if path:
                with open(path, "w", encoding="utf-8", newline="\n") as f:
                    f.write(bvh_text(motion))
                    f.flush()
                    os.fsync(f.fileno())


_BPY_REPO = {"dir": None}


def enable_extension_in_bpy() -> str:
    """In a ``bpy``-module process: the module name of this checkout enabled as the
    extension ``dancing_points`` (an existing one, else through a temporary user
    extension repository holding a link to the checkout, removed at exit)."""
    import atexit
    import bpy

    prefs = bpy.context.preferences
    prefs.use_preferences_save = False  # never write the user's preferences
    for addon in prefs.addons:
        if addon.module.split(".")[-1] == "dancing_points":
            return addon.module
    repo_module = "dp_batch"
    if _BPY_REPO["dir"] is None:
        d = tempfile.mkdtemp(prefix="dp_batch_ext_")
        os.symlink(ROOT, os.path.join(d, "dancing_points"), target_is_directory=True)
        repo = prefs.extensions.repos.new(name="Dancing Points batch", module=repo_module,
                                          custom_directory=d, source='USER')
        repo.enabled = True
        _BPY_REPO["dir"] = d

        def cleanup():
            with contextlib.suppress(Exception):
                for r in bpy.context.preferences.extensions.repos:
                    if r.module == repo_module:
                        bpy.context.preferences.extensions.repos.remove(r)
                        break
            link = os.path.join(d, "dancing_points")
            if os.path.islink(link):
                os.unlink(link)  # the link only, never the checkout
            shutil.rmtree(d, ignore_errors=True)

        atexit.register(cleanup)
    module = f"bl_ext.{repo_module}.dancing_points"
    if prefs.addons.get(module) is None:
        res = bpy.ops.preferences.addon_enable(module=module)
        if res != {'FINISHED'} or prefs.addons.get(module) is None:
            raise RuntimeError(f"cannot enable the extension {module} in bpy")
    return module


def _bpy_converter():
    try:
        import bpy  # noqa: F401
    except ImportError:
        raise RuntimeError("the blend/fbx formats and --render need Blender's bpy module") from None
    import importlib

    module = enable_extension_in_bpy()
    return importlib.import_module(module + ".operators.batch_cli").convert_job


def worker_main(bpy_converter=None) -> int:
    """A worker process: jobs from stdin, messages to stdout (see the module doc)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C

    def on_term(signum, frame):
        raise _Terminated()

    with contextlib.suppress(ValueError, AttributeError):
        signal.signal(signal.SIGTERM, on_term)
    for k in THREAD_ENV:
        os.environ.setdefault(k, "1")
    # Our channel is the original stdout; anything else printed goes to stderr.
    sys.stdout.flush()
    chan = _Channel(os.fdopen(os.dup(sys.stdout.fileno()), "w", encoding="utf-8", buffering=1))
    with contextlib.suppress(OSError):
        os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    sys.stdout = sys.stderr
    core = CoreConverter()
    converters = {"bpy": bpy_converter}
    try:
        chan.send({"type": "ready", "pid": os.getpid()})
        while True:
            line = sys.stdin.readline()
            if not line:
                return 0
            line = line.strip()
            if not line:
                continue
            job = json.loads(line)
            if job.get("type") == "exit":
                return 0
            _run_job(job, chan, core, converters)
    except _Terminated:
        return EXIT_TERMINATED
    except _Orphaned:
        return EXIT_FAILED


def _run_job(job, chan, core, converters):
    jid = job["id"]
    temps = job["temps"]
    t0 = time.perf_counter()
    last = [0.0]

    def progress(fraction):
        now = time.perf_counter()
        if now - last[0] >= 0.2:
            last[0] = now
            chan.send({"type": "progress", "id": jid, "fraction": round(float(fraction), 4)})
        return True

    try:
        if job["needs_bpy"]:
            if converters.get("bpy") is None:
                converters["bpy"] = _bpy_converter()
            info = converters["bpy"](job, progress)
        else:
            info = core(job, progress)
        missing = [k for k, p in temps.items() if not os.path.isfile(p)]
        if missing:
            raise RuntimeError(f"the converter wrote no {', '.join(missing)} output")
    except (_Terminated, _Orphaned, SystemExit):
        remove_temps(temps.values())
        raise
    except BaseException as exc:  # noqa: BLE001 - one bad file never stops the worker
        remove_temps(temps.values())
        if os.environ.get("DP_DEBUG", "") not in ("", "0"):
            import traceback
            traceback.print_exc()
        chan.send({"type": "error", "id": jid, "error": error_text(exc),
                   "seconds": time.perf_counter() - t0})
        return
    try:
        chan.send({"type": "done", "id": jid, "frames": info.get("frames"),
                   "seconds": time.perf_counter() - t0})
    except BaseException:
        remove_temps(temps.values())
        raise


def worker_command():
    """How to start a worker: this interpreter, importing the core from the checkout."""
    boot = (f"import sys; sys.path.insert(0, {ROOT!r}); "
            f"from dancing_points_addon.batch import worker_main; sys.exit(worker_main())")
    return [sys.executable, "-c", boot]


# =========================================================================== parent side

class _Worker:
    def __init__(self, cmd, env, log_dir, q, serial):
        self.log_path = os.path.join(log_dir, f"worker{serial}.log")
        self.log = open(self.log_path, "w+b")
        kw = {}
        if os.name == "posix":
            kw["start_new_session"] = True  # Ctrl-C at the terminal reaches the parent only
        elif hasattr(subprocess, "CREATE_NEW_PROCESS_GROUP"):
            kw["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.log,
                                     env=env, **kw)
        self.task = None
        self.ready = False
        self.closed = False
        self.dead = False
        self.thread = threading.Thread(target=self._read, args=(q,), daemon=True,
                                       name=f"dp-batch-reader-{serial}")
        self.thread.start()

    def _read(self, q):
        try:
            for raw in self.proc.stdout:
                line = raw.decode("utf-8", "replace")
                if line.startswith(MSG_PREFIX):
                    try:
                        msg = json.loads(line[len(MSG_PREFIX):])
                    except ValueError:
                        continue
                    q.put((self, msg))
        except (OSError, ValueError):
            pass
        q.put((self, None))

    def send(self, msg) -> bool:
        try:
            self.proc.stdin.write((json.dumps(msg) + "\n").encode("utf-8"))
            self.proc.stdin.flush()
            return True
        except (OSError, ValueError):
            return False  # it died: its end-of-output message follows

    def close(self):
        if not self.closed:
            self.closed = True
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.close()

    def terminate(self):
        with contextlib.suppress(OSError):
            self.proc.terminate()

    def kill(self):
        with contextlib.suppress(OSError):
            self.proc.kill()

    def stderr_tail(self, n=3) -> str:
        try:
            self.log.flush()
            with open(self.log_path, "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - 4000))
                lines = [ln.strip() for ln in f.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        except OSError:
            return ""
        return " | ".join(lines[-n:])


def _commit(task) -> None:
    """Rename a finished task's temporary files onto its outputs (all or none new)."""
    done = []
    try:
        for tmp, final in zip(task.temps, task.outputs):
            if task.replace:
                os.replace(tmp, final)
            else:
                try:
                    os.link(tmp, final)  # fails if ``final`` appeared meanwhile: never overwrite
                except FileExistsError:
                    raise InputError(final, "output exists (use --overwrite to replace it or "
                                            "--resume to skip this take)") from None
                except OSError:  # no hard links on this file system
                    if os.path.lexists(final):
                        raise InputError(final, "output exists (use --overwrite to replace it or "
                                                "--resume to skip this take)") from None
                    os.replace(tmp, final)
                else:
                    os.unlink(tmp)
            done.append(final)
        remove_temps(task.temps)  # whatever else a writer left beside them
    except BaseException:
        if not task.replace:
            for p in done:
                with contextlib.suppress(OSError):
                    os.unlink(p)
        remove_temps(task.temps)
        raise


class Batch:
    """The parent: runs ``tasks`` on ``jobs`` workers (see :func:`run`)."""

    def __init__(self, tasks, jobs, job_options, fmt, worker_cmd=None, progress=None, out_dir=None,
                 env=None):
        self.tasks = tasks
        self.jobs = max(1, int(jobs))
        self.options = job_options
        self.fmt = fmt
        self.worker_cmd = worker_cmd or worker_command()
        self.progress = progress
        self.out_dir = out_dir
        self.env = dict(os.environ if env is None else env)
        for k in THREAD_ENV:
            self.env[k] = "1"
        self.stop_signal = None
        self.fatal = None
        self._serial = 0

    # -- signals ---------------------------------------------------------------
    def _install_signals(self):
        self._old = {}
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            if self.stop_signal is None:
                self.stop_signal = signum

        for sig in (signal.SIGINT, getattr(signal, "SIGTERM", None)):
            if sig is None:
                continue
            with contextlib.suppress(ValueError, OSError):
                self._old[sig] = signal.signal(sig, handler)

    def _restore_signals(self):
        for sig, old in self._old.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(sig, old if old is not None else signal.SIG_DFL)

    # -- running ---------------------------------------------------------------
    def _spawn(self, q, log_dir, workers, pending):
        """Start a worker and give it a take; on failure the run is over (``fatal``)."""
        self._serial += 1
        try:
            w = _Worker(self.worker_cmd, self.env, log_dir, q, self._serial)
        except OSError as exc:
            self.fatal = f"cannot start a worker process ({self.worker_cmd[0]}: {exc.strerror or exc})"
            return None
        workers.append(w)
        self._assign(w, pending)
        return w

    def _job(self, task):
        needs_bpy = self.fmt in BPY_FORMATS or "mp4" in task.kinds
        return {"type": "job", "id": task.index, "input": task.input,
                "temps": dict(zip(task.kinds, task.temps)), "needs_bpy": needs_bpy,
                "options": self.options}

    def _assign(self, w, pending):
        if w.closed:
            return
        if not pending or self.stop_signal is not None or self.fatal:
            w.close()
            return
        task = pending.popleft()
        w.task = task
        task.started = time.perf_counter()
        task.fraction = 0.0
        w.send(self._job(task))

    def _finish(self, task, status, error=None, frames=None, seconds=None):
        task.status, task.error = status, error
        if frames is not None:
            task.frames = int(frames)
        task.seconds = seconds if seconds is not None else (
            time.perf_counter() - task.started if task.started else None)
        if self.progress is not None:
            self.progress.result(result_line(task, self.out_dir))
        self.finished += 1

    def _draw(self, workers, force=False):
        if self.progress is not None:
            running = [(w.task.name, w.task.fraction) for w in workers if w.task is not None]
            self.progress.update(self.finished, running, force=force)

    def run(self) -> str:
        """Run; returns "done", "interrupted" or "terminated"."""
        todo = [t for t in self.tasks if t.status == "pending"]
        todo_sorted = sorted(todo, key=lambda t: (-t.size, t.index))  # longest first
        pending = collections.deque(todo_sorted)
        self.finished = 0
        if not pending:
            return "done"
        q = queue.Queue()
        log_dir = tempfile.mkdtemp(prefix="dp_batch_logs_")
        workers = []
        start_failures = 0
        self._install_signals()
        try:
            for _ in range(min(self.jobs, len(pending))):
                if self._spawn(q, log_dir, workers, pending) is None:
                    break
            self._draw(workers, force=True)
            while any(not w.dead for w in workers):
                if self.stop_signal is not None:
                    break
                try:
                    w, msg = q.get(timeout=0.1)
                except queue.Empty:
                    self._draw(workers)
                    continue
                if msg is None:  # the worker's output ended: it exited
                    w.dead = True
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        w.proc.wait(timeout=5)
                    if self.stop_signal is not None:
                        break
                    rc = w.proc.poll()
                    if w.task is not None:
                        task, w.task = w.task, None
                        remove_temps(task.temps)
                        tail = w.stderr_tail()
                        self._finish(task, "failed", f"worker process died (exit status {rc})"
                                                     + (f": {tail}" if tail else ""))
                    if not w.ready:
                        start_failures += 1
                        if start_failures >= 2:
                            self.fatal = ("cannot start a worker process (exit status "
                                          f"{rc}): {w.stderr_tail() or 'no output'}")
                    if pending and not self.fatal and self.stop_signal is None:
                        self._spawn(q, log_dir, workers, pending)
                    self._draw(workers, force=True)
                    continue
                kind = msg.get("type")
                if kind == "ready":
                    w.ready = True
                    start_failures = 0
                    continue
                task = w.task
                if task is None or msg.get("id") != task.index:
                    continue
                if kind == "progress":
                    task.fraction = float(msg.get("fraction", 0.0))
                    self._draw(workers)
                    continue
                if kind == "done":
                    w.task = None
                    try:
                        _commit(task)
                    except InputError as exc:
                        self._finish(task, "failed", one_line(exc), msg.get("frames"), msg.get("seconds"))
                    except OSError as exc:
                        self._finish(task, "failed", f"cannot write output ({exc.strerror or exc})",
                                     msg.get("frames"), msg.get("seconds"))
                    else:
                        self._finish(task, "ok", None, msg.get("frames"), msg.get("seconds"))
                elif kind == "error":
                    w.task = None
                    remove_temps(task.temps)
                    self._finish(task, "failed", msg.get("error") or "failed", None, msg.get("seconds"))
                else:
                    continue
                self._assign(w, pending)
                self._draw(workers, force=True)
        except KeyboardInterrupt:  # only if our handler could not be installed
            self.stop_signal = signal.SIGINT
        finally:
            self._shutdown(workers)
            self._restore_signals()
            if os.environ.get("DP_DEBUG", "") in ("", "0"):
                shutil.rmtree(log_dir, ignore_errors=True)
            else:
                print(f"worker logs: {log_dir}", file=sys.stderr)
            if self.progress is not None:
                self.progress.finish()
        for t in self.tasks:
            if t.status == "pending" and t.started is not None:
                t.status, t.error = "interrupted", "interrupted before it finished"
                t.seconds = None
        if self.fatal:
            for t in self.tasks:
                if t.status in ("pending", "interrupted"):
                    t.status, t.error = "failed", self.fatal
        if self.stop_signal is not None:
            return "terminated" if self.stop_signal == getattr(signal, "SIGTERM", None) else "interrupted"
        return "done"

    def _shutdown(self, workers):
        """Stop every worker: a clean exit when idle, SIGTERM (then SIGKILL) when
        busy or stopping; then remove the temporary files of unfinished tasks."""
        stopping = self.stop_signal is not None or self.fatal is not None
        for w in workers:
            if w.dead:
                continue
            w.close()
            if stopping or w.task is not None:
                w.terminate()
        deadline = time.monotonic() + (5.0 if stopping else 30.0)
        for w in workers:
            try:
                w.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                w.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    w.proc.wait(timeout=5)
        for w in workers:
            if w.task is not None:
                remove_temps(w.task.temps)
            with contextlib.suppress(OSError, ValueError):
                w.proc.stdout.close()
            with contextlib.suppress(OSError):
                w.log.close()
        for w in workers:
            w.thread.join(timeout=2)


# =========================================================================== report and entry point

def write_report(path, data) -> None:
    from .take import atomic_output

    with atomic_output(path, "w", encoding="utf-8", newline="\n") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def _makedirs(folder):
    """``os.makedirs``; returns the folders it created."""
    new = []
    d = os.path.abspath(folder)
    while not os.path.isdir(d):
        new.append(d)
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    os.makedirs(folder, exist_ok=True)
    return new


def job_options(args, model_dir) -> dict:
    return {"models": model_dir, "threads": int(args.threads or 1),
            "height": args.height, "input_fps": args.input_fps,
            "asf": os.path.abspath(args.asf) if args.asf else None,
            "no_foot_lock": bool(args.no_foot_lock), "no_hand_ik": bool(args.no_hand_ik),
            "leader_rig": _abs(getattr(args, "leader_rig", None)),
            "follower_rig": _abs(getattr(args, "follower_rig", None))}


RIG_TYPES = (".blend", ".glb", ".gltf", ".fbx")


def _abs(path):
    return os.path.abspath(os.path.expanduser(path)) if path else None


def check_rigs(args, needs_bpy) -> None:
    """The ``--leader-rig`` / ``--follower-rig`` files exist, have a rig file type
    and come with an output that holds armatures (blend, fbx, --render)."""
    for opt in ("leader_rig", "follower_rig"):
        path = getattr(args, opt, None)
        if not path:
            continue
        flag = "--" + opt.replace("_", "-")
        if not os.path.isfile(os.path.expanduser(path)):
            raise InputError(path, f"no such file ({flag})")
        if os.path.splitext(path)[1].lower() not in RIG_TYPES:
            raise InputError(path, f"{flag} takes a {', '.join(RIG_TYPES)} file")
        if not needs_bpy:
            raise InputError(path, f"{flag} works with the blend and fbx formats or --render "
                                   f"(npz and bvh hold the Dancing Points skeleton only)")


def run(args, worker_cmd=None, out=None, err=None, in_blender=False) -> int:
    """The batch conversion for parsed :func:`add_arguments` options; returns the
    exit status (0 all done, 1 a file failed, 2 bad options, 130/143 stopped).
    Raises :class:`InputError` for a bad command line (no inputs, no models...)."""
    out = out if out is not None else sys.stdout
    err = err if err is not None else sys.stderr
    t_start = time.perf_counter()
    started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    fmt = args.format
    jobs = args.jobs or default_jobs()
    out_dir = os.path.abspath(os.path.expanduser(args.output_dir))
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError(args.output_dir, "output path exists and is not a folder")
    needs_bpy = fmt in BPY_FORMATS or args.render
    if needs_bpy and not in_blender:
        import importlib.util
        if importlib.util.find_spec("bpy") is None:
            raise InputError(None, f"--format {fmt}{' --render' if args.render else ''} needs Blender: "
                                   f"install the bpy module or run blender --background --command "
                                   f"dancing_points convert ...")
    entries = discover(args.inputs, BPY_INPUTS if needs_bpy else CORE_INPUTS, exclude=[out_dir])
    if not entries:
        exts = ", ".join(BPY_INPUTS if needs_bpy else CORE_INPUTS)
        raise InputError(" ".join(map(str, args.inputs)), f"no input files found (looked for {exts})")
    model_dir = resolve_model_dir(args.models)
    if args.asf and not os.path.isfile(args.asf):
        raise InputError(args.asf, "no such ASF file")
    check_rigs(args, needs_bpy)
    if args.asf and needs_bpy:
        raise InputError(args.asf, "--asf works with the npz and bvh formats only (without --render); "
                                   "put the ASF beside the AMC files instead")
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise InputError(args.output_dir, f"cannot create the output folder ({exc.strerror or exc})") from None
    report_path = os.path.abspath(args.report) if args.report else os.path.join(out_dir, REPORT_NAME)
    tasks = plan(entries, out_dir, fmt, args.render, args.overwrite, args.resume)
    made = []  # sub-folders made for the outputs: removed again if they stay empty
    for t in tasks:
        if t.status == "pending":
            for o in t.outputs:
                try:
                    made.extend(_makedirs(os.path.dirname(o)))
                except OSError as exc:
                    raise InputError(os.path.dirname(o), f"cannot create the output folder "
                                                         f"({exc.strerror or exc})") from None
    n_run = sum(t.status == "pending" for t in tasks)
    prog = Progress(n_run, stream=err, out=out, enabled=not args.no_progress)
    for t in tasks:  # decided before any work: report now
        if t.status != "pending":
            prog.result(result_line(t, out_dir))
    batch = Batch(tasks, min(jobs, max(n_run, 1)), job_options(args, model_dir), fmt, worker_cmd, prog, out_dir)
    outcome = batch.run()
    for d in sorted(set(made), key=len, reverse=True):
        with contextlib.suppress(OSError):
            os.rmdir(d)  # only if empty
    seconds = time.perf_counter() - t_start
    counts = collections.Counter(t.status for t in tasks)
    report = {"format": fmt, "output_dir": out_dir, "jobs": batch.jobs, "models": model_dir,
              "started": started, "seconds": round(seconds, 3), "interrupted": outcome != "done",
              "counts": {k: counts.get(k, 0) for k in ("ok", "failed", "skipped", "interrupted", "pending")},
              "files": [t.record() for t in tasks]}
    if batch.fatal:
        report["error"] = batch.fatal
    try:
        write_report(report_path, report)
    except InputError as exc:
        print(f"error: cannot write the report: {one_line(exc)}", file=err)
        report_path = None
    c = report["counts"]
    summary = (f"{len(tasks)} file(s): {c['ok']} ok, {c['failed']} failed, {c['skipped']} skipped"
               + (f", {c['interrupted'] + c['pending']} not done" if outcome != "done" else "")
               + f" in {seconds:.1f} s ({batch.jobs} job{'s' if batch.jobs != 1 else ''})"
               + (f"; report: {report_path}" if report_path else ""))
    print(summary, file=out, flush=True)
    if batch.fatal:
        print(f"error: {batch.fatal}", file=err)
    if outcome != "done":
        print(f"error: {outcome}; no partial outputs were left; re-run with --resume to convert the rest",
              file=err)
        return EXIT_TERMINATED if outcome == "terminated" else EXIT_INTERRUPTED
    return EXIT_FAILED if c["failed"] else EXIT_OK
