"""A worker process of a batch: converts one take at a time.

Each worker is a fresh interpreter (never a fork: ``bpy`` is not fork-safe)
started by the parent (:mod:`.scheduler`) with :func:`worker_command`; it loads
the networks once, with one ONNX Runtime thread, and runs :func:`worker_main`:
jobs from its stdin, messages to its stdout (:mod:`.messages`).

The worker loop never imports ``bpy``. The ``npz``/``bvh`` formats run the core
converter (:class:`CoreConverter`); the jobs that need Blender (``blend``,
``fbx``, ``--render``) go to the converter the Blender side passes to
:func:`worker_main`: inside the Blender binary its ``worker`` command
(``operators/batch_cli.py``); with the ``bpy`` module the standalone script
:data:`BPY_WORKER_SCRIPT` (``operators/batch_worker.py``), which enables this
checkout as the extension and bakes each take with the extension's own
``convert_job``.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import time

from ..errors import InputError, error_message
from . import messages
from ..argtypes import EXIT_FAILURE, EXIT_TERMINATED, SINGLE_THREAD_ENV, after_imports
from .options import job_song, synthesis_options
from .plan import remove_temps

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the checkout / extension folder
# The entry of a worker in a ``bpy``-module process: a standalone script on the
# Blender side, run as a program (never imported by the core).
BPY_WORKER_SCRIPT = os.path.join(ROOT, "operators", "batch_worker.py")
NO_BPY = "the blend/fbx formats and --render need Blender's bpy module"


def worker_command(needs_bpy=False):
    """How to start a worker: this interpreter, importing the core from the checkout
    (``needs_bpy``: running the Blender side's :data:`BPY_WORKER_SCRIPT`)."""
    if needs_bpy:
        return [sys.executable, BPY_WORKER_SCRIPT]
    boot = (f"import sys; sys.path.insert(0, {ROOT!r}); "
            f"from dancing_points_addon.batch.worker import worker_main; sys.exit(worker_main())")
    return [sys.executable, "-c", boot]


# =========================================================================== converting one take

class CoreConverter:
    """npz / bvh through the bpy-free core; the networks are loaded once."""

    def __call__(self, job, progress):
        from ..inputs import load_input
        from ..runtime import Synthesizer

        o = job["options"]
        take = load_input(job["input"], asf=o.get("asf"), input_fps=o.get("input_fps"), height=o.get("height"),
                      role=o.get("role"))
        song = job_song(o, take)
        progress(0.05)
        synth = Synthesizer(synthesis_options(o, take.height))
        duet = synth.synthesize(take, progress=lambda i, n: progress(0.05 + 0.9 * i / max(n, 1)))
        duet.song = song
        write_duet_files(job["temps"], duet)
        return {"frames": int(duet.n_frames)}


def write_duet_files(temps: dict, duet) -> None:
    """Write the core formats among ``temps`` (``{kind: path}``): ``npz``,
    ``bvh_leader``, ``bvh_follower``. Plain writes (the paths are temporary; the
    worker removes them when a write fails); a failed write is an
    :class:`InputError` naming the output folder (a full disk, say)."""
    try:
        _write_duet_files(temps, duet)
    except OSError as exc:
        folder = os.path.dirname(os.path.abspath(next(iter(temps.values()))))
        raise InputError(folder, f"cannot write output ({exc.strerror or exc})") from None


def _write_duet_files(temps: dict, duet) -> None:
    from ..formats.files import write_npz

    if "npz" in temps:  # (not duet.save_npz: its own temporary file would escape a killed worker's cleanup)
        with open(temps["npz"], "wb") as f:
            write_npz(f, duet.arrays())  # (a failed write leaves no zip writer behind to complain)
            f.flush()
            os.fsync(f.fileno())
    if "bvh_leader" in temps or "bvh_follower" in temps:
        from ..formats.bvh import bvh_text
        from ..duet import duet_motions

        for role, motion in duet_motions(duet).items():
            path = temps.get("bvh_" + role)
            if path:
                with open(path, "w", encoding="utf-8", newline="\n") as f:
                    f.write(bvh_text(motion))
                    f.flush()
                    os.fsync(f.fileno())


# =========================================================================== the worker loop

class _Terminated(BaseException):
    """SIGTERM in a worker: unwind (removing temporary files) and exit."""


_TERM_RECEIVED = []  # set by the handler: a library may turn the raised _Terminated into its own error


def worker_main(bpy_converter=None) -> int:
    """A worker process: jobs from stdin, messages to stdout (:mod:`.messages`).
    ``bpy_converter(job, progress) -> {"frames": n}`` converts the jobs that need
    Blender (given by the Blender side; without it they fail with one line)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C

    with contextlib.suppress(ValueError, AttributeError):
        signal.signal(signal.SIGTERM, after_imports(lambda signum: _Terminated(), _TERM_RECEIVED))
    for k in SINGLE_THREAD_ENV:
        os.environ.setdefault(k, "1")
    # Our channel is the original stdout; anything else printed goes to stderr.
    sys.stdout.flush()
    chan = messages.Channel(os.fdopen(os.dup(sys.stdout.fileno()), "w", encoding="utf-8", buffering=1))
    with contextlib.suppress(OSError):
        os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    sys.stdout = sys.stderr
    core = CoreConverter()
    try:
        chan.send(messages.ready(os.getpid()))
        while True:
            line = sys.stdin.readline()
            if not line:
                return 0
            job = messages.decode_request(line)
            if job is None:
                continue
            if job.get("type") == messages.EXIT:
                return 0
            _run_job(job, chan, core, bpy_converter)
    except _Terminated:
        return EXIT_TERMINATED
    except messages.Orphaned:
        return EXIT_FAILURE


def _run_job(job, chan, core, bpy_converter):
    jid = job["id"]
    temps = job["temps"]
    t0 = time.perf_counter()
    last = [0.0]

    def progress(fraction):
        now = time.perf_counter()
        if now - last[0] >= 0.2:
            last[0] = now
            chan.send(messages.progress(jid, fraction))
        return True

    try:
        if job["needs_bpy"]:
            if bpy_converter is None:
                raise RuntimeError(NO_BPY)
            info = bpy_converter(job, progress)
        else:
            info = core(job, progress)
        missing = [k for k, p in temps.items() if not os.path.isfile(p)]
        if missing:
            raise RuntimeError(f"the converter wrote no {', '.join(missing)} output")
    except (_Terminated, messages.Orphaned, SystemExit):
        remove_temps(temps.values())
        raise
    except BaseException as exc:  # noqa: BLE001 - one bad file never stops the worker
        remove_temps(temps.values())
        if _TERM_RECEIVED:  # SIGTERM inside onnxruntime's import comes back as an ImportError
            raise _Terminated() from None
        if os.environ.get("DP_DEBUG", "") not in ("", "0"):
            import traceback
            traceback.print_exc()
        chan.send(messages.error(jid, error_message(exc), time.perf_counter() - t0))
        return
    try:
        chan.send(messages.done(jid, info.get("frames"), time.perf_counter() - t0))
    except BaseException:
        remove_temps(temps.values())
        raise
