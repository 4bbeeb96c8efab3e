"""A batch on a Dask cluster: ``batch IN... -o OUT --cluster tcp://HOST:8786``
(or ``--cluster local:N``, a :class:`distributed.LocalCluster` of N worker
processes on this machine).

Only the dispatch changes: the plan, the lock, the progress bar, the result
lines, the report, ``--resume``/``--overwrite`` and the exit statuses are the
local batch's (:func:`.run`); :class:`ClusterBatch` replaces :class:`.scheduler.Batch`.

* Each take is one Dask task (:func:`run_take`) carrying everything the worker
  needs: the input file's bytes (and its ASF, the ``--asf`` file, the rig files),
  the job options and the client's identity. The worker converts it in a
  scratch folder of its own and returns the output files' bytes; the client
  writes them under the temporary names of the plan and renames them into
  place (:func:`.scheduler.commit`), exactly as the local batch does. So the
  workers need not share the client's file system, and nothing a worker does
  ever leaves a file in the output folder.
* At most a few takes per worker thread are in flight at once (longest first),
  so the scheduler never holds a whole library's bytes.
* A worker that dies mid-take costs that take only: the scheduler runs it again
  elsewhere, up to its ``allowed-failures`` (Dask's setting, 3 by default),
  after which the take fails (``KilledWorker``). Each attempt announces itself
  (Dask events on a topic of this run), so the report's ``attempts`` and
  ``workers`` say what happened.
* Identity: each task carries the client's :func:`identity` (project version, a
  hash of the extension's Python files, a hash of the models' bytes); a worker
  that differs refuses (:func:`check_worker`). :func:`connect` asks every worker
  up front (before any work: one line, exit 2); a worker that joins later and
  differs refuses its first task, which stops the run (exit 2).
* Ctrl-C / SIGTERM: the tasks are cancelled on the cluster (a running take
  stops at its next progress step), the takes not finished are
  ``interrupted``, no partial file is left; ``--resume`` finishes.
* ``blend``/``fbx``/``--render``: the worker runs the Blender-side worker
  (:data:`.worker.BPY_WORKER_SCRIPT`, the ``bpy`` module in the worker's Python)
  as a subprocess of its own, one per worker thread, kept for the next take.

Dask (``dask`` and ``distributed``) is imported only here, inside the functions
that need it: without ``--cluster`` nothing imports it, and it is not bundled
with the extension (``pip install dask distributed`` beside the command line).
"""
from __future__ import annotations

import collections
import contextlib
import hashlib
import os
import queue
import shutil
import signal
import sys
import tempfile
import threading
import time
import uuid

from ..errors import InputError, UserError, error_message, one_line
from .options import BPY_FORMATS, task_needs_bpy
from .plan import remove_temps, settle_unfinished
from .progress import result_line
from .worker import ROOT

# What identifies the code a worker runs: the extension's Python files (where present) and its manifest.
CODE_PARTS = ("dancing_points_addon", "operators", "panels", "__init__.py", "preferences.py")
MANIFEST = "blender_manifest.toml"
LOCAL = "local"
DEFAULT_PORT = 8786
CONNECT_TIMEOUT = 30.0  # seconds to reach the scheduler
WORKER_WAIT = 60.0  # seconds to wait for a first worker
TOPIC = "dancing-points-batch-"  # + run id: the attempts and progress of one run's takes
# local:N workers: no statistical profiler (it samples the converting thread every 10 ms), calmer
# monitors (README, Batch on a cluster, recommends the same for a farm's workers).
LOCAL_WORKER_CONFIG = {"distributed.worker.profile.enabled": False,
                       "distributed.worker.memory.monitor-interval": "1s",
                       "distributed.admin.system-monitor.interval": "2s"}
INSTALL_HINT = "pip install -r requirements-dev.txt, or pip install dask distributed"


class ClusterError(UserError):
    """The cluster cannot run this batch (one line, exit status 2)."""


def cluster_spec(text: str) -> str:
    """``--cluster``: ``local`` / ``local:N`` or a scheduler address
    (``tcp://HOST:PORT``, ``tls://...``, ``HOST:PORT``; ``HOST`` alone takes port 8786)."""
    import argparse

    t = text.strip()
    if t == LOCAL or t.startswith(LOCAL + ":"):
        n = t[len(LOCAL) + 1:]
        if n and (not n.isdigit() or int(n) < 1):
            raise argparse.ArgumentTypeError(f"local:N takes a number of workers (at least 1), got {text!r}")
        return t
    if not t or any(c.isspace() for c in t):
        raise argparse.ArgumentTypeError(f"not a scheduler address: {text!r} (e.g. tcp://HOST:{DEFAULT_PORT})")
    if "://" not in t:
        t = "tcp://" + t
    if t.split("://", 1)[1].rfind(":") < 0 or t.endswith("]"):
        t += f":{DEFAULT_PORT}"
    return t


# =========================================================================== identity

def project_version(root=ROOT) -> str:
    try:
        with open(os.path.join(root, MANIFEST), encoding="utf-8") as f:
            for line in f:
                key, _, value = line.partition("=")
                if key.strip() == "version":
                    return value.strip().strip('"\'')
    except OSError:
        pass
    return "unknown"


def code_hash(root=ROOT) -> str:
    """SHA-256 of the extension's Python files (relative names and bytes, sorted)."""
    files = []
    for part in CODE_PARTS:
        path = os.path.join(root, part)
        if os.path.isfile(path):
            files.append(part)
        elif os.path.isdir(path):
            for dirpath, dirnames, filenames in os.walk(path):
                dirnames[:] = sorted(d for d in dirnames if not d.startswith((".", "__pycache__")))
                files.extend(os.path.relpath(os.path.join(dirpath, n), root).replace(os.sep, "/")
                             for n in filenames if n.endswith(".py"))
    h = hashlib.sha256()
    for rel in sorted(files):
        with open(os.path.join(root, rel), "rb") as f:
            data = f.read()
        h.update(rel.encode("utf-8") + b"\0" + str(len(data)).encode() + b"\0" + data)
    return h.hexdigest()


_MODEL_HASHES: dict = {}


def models_hash(model_dir) -> str:
    """SHA-256 of a models folder's network files (cached per file size and time)."""
    from ..nets import MODEL_FILES

    paths = [os.path.join(model_dir, MODEL_FILES[k]) for k in sorted(MODEL_FILES)]
    key = tuple((p, os.path.getsize(p), os.path.getmtime(p)) for p in paths)
    if key not in _MODEL_HASHES:
        h = hashlib.sha256()
        for p in paths:
            with open(p, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
        _MODEL_HASHES[key] = h.hexdigest()
    return _MODEL_HASHES[key]


_CODE: dict = {}


def identity(model_dir) -> dict:
    """What a worker must share with the client: the project version, the code and the models."""
    if "code" not in _CODE:  # once per process: the code it imported
        _CODE.update(version=project_version(), code=code_hash())
    return {"version": _CODE["version"], "code": _CODE["code"], "models": models_hash(model_dir)}


def _short(h) -> str:
    return str(h)[:12]


def _worker_model_dir(expected: dict, client_dir: str):
    """The models folder on this worker whose bytes are the client's: the client's
    path, ``$DP_MODEL_DIR`` or the bundled ``models/``; ``(folder, None)`` or
    ``(None, why not)``."""
    from ..nets import MODEL_DIR, MODEL_ENV, resolve_model_dir

    seen = []
    for cand in (client_dir, os.environ.get(MODEL_ENV, ""), MODEL_DIR):
        if not cand:
            continue
        try:
            d = resolve_model_dir(cand)
            h = models_hash(d)
        except (UserError, OSError):
            continue
        if h == expected["models"]:
            return d, None
        seen.append(f"{d} (models {_short(h)})")
    return None, (f"has no models matching this client's (models {_short(expected['models'])} from "
                  f"{client_dir}; found {', '.join(seen) or 'none'}): put the client's models folder on the "
                  f"workers at the same path, in $DP_MODEL_DIR or as the bundled models/")


def check_worker(expected: dict, client_dir: str, needs_bpy: bool = False):
    """On a worker: ``(models folder, None)`` when it runs the client's version,
    code and models (and has ``bpy`` when ``needs_bpy``); else ``(None, why)``."""
    if "code" not in _CODE:
        _CODE.update(version=project_version(), code=code_hash())
    if (_CODE["version"], _CODE["code"]) != (expected["version"], expected["code"]):
        return None, (f"runs Dancing Points {_CODE['version']} (code {_short(_CODE['code'])}), this client "
                      f"{expected['version']} (code {_short(expected['code'])}): install the client's version "
                      f"on every worker and restart them")
    model_dir, why = _worker_model_dir(expected, client_dir)
    if model_dir is None:
        return None, why
    if needs_bpy:
        import importlib.util

        if importlib.util.find_spec("bpy") is None:
            return None, (f"has no bpy module (needed for blend, fbx and --render): pip install bpy in the "
                          f"workers' Python ({sys.executable}), or convert to npz or bvh on the cluster")
    return model_dir, None


def _handshake(expected, client_dir, needs_bpy):
    """``client.run`` on every worker: None when it can run this batch, else why not."""
    _, why = check_worker(expected, client_dir, needs_bpy)
    return why


# =========================================================================== the worker side

class _Cancelled(BaseException):
    """The client cancelled this task (Ctrl-C): stop converting."""


def _current():
    """``(worker, key)`` of the task running in this thread (``(None, None)`` outside a worker)."""
    try:
        from distributed import get_worker

        w = get_worker()
        return w, w.get_current_task()
    except (ImportError, ValueError):
        return None, None


def _cancelled(worker, key) -> bool:
    if worker is None or key is None:
        return False
    try:
        ts = worker.state.tasks.get(key)
    except Exception:  # noqa: BLE001 - a look at the worker's state only
        return False
    return ts is None or ts.state in ("cancelled", "released", "forgotten")


def _announce(worker, topic, msg):
    if worker is not None and topic:
        with contextlib.suppress(Exception):
            worker.log_event(topic, msg)


def _write_file(path, data):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)


def _map_paths(text, mapping):
    """The worker's scratch paths in ``text`` replaced by the client's (longest first)."""
    for src in sorted(mapping, key=len, reverse=True):
        text = text.replace(src, mapping[src])
    return text


def run_take(spec: dict) -> dict:
    """The Dask task of one take (on a worker): check the identity, convert, return
    ``{"status": "ok", "frames", "seconds", "outputs": {kind: bytes}}``,
    ``{"status": "failed", "error"}`` or ``{"status": "refused", "error"}``.
    Never raises for a bad take (Dask would count it as a failure to retry);
    a killed worker is what the scheduler retries."""
    t0 = time.perf_counter()
    worker, key = _current()
    addr = getattr(worker, "address", None) or f"pid {os.getpid()}"
    topic = spec.get("topic")
    _announce(worker, topic, {"id": spec["id"], "start": True, "worker": addr})
    model_dir, why = check_worker(spec["identity"], spec["options"]["models"], spec["needs_bpy"])
    if model_dir is None:
        return {"status": "refused", "error": f"worker {addr} {why}", "worker": addr}
    base = getattr(worker, "local_directory", None) or None
    if base:
        os.makedirs(base, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix="dp-take-", dir=base)
    mapping = {}
    try:
        # The files of the take, under their own names (the reader goes by the extension
        # and the CMU subject number of the name; an AMC finds its ASF beside it).
        in_dir = os.path.join(scratch, "in")
        inp = os.path.join(in_dir, spec["input_name"])
        _write_file(inp, spec["input_bytes"])
        mapping[inp] = spec["input"]
        if spec.get("beside"):  # the ASF found beside an AMC on the client
            name, data = spec["beside"]
            _write_file(os.path.join(in_dir, name), data)
            mapping[os.path.join(in_dir, name)] = os.path.join(os.path.dirname(spec["input"]), name)
        mapping[in_dir + os.sep] = os.path.dirname(spec["input"]) + os.sep
        options = dict(spec["options"], models=model_dir)
        for opt, (name, data) in (spec.get("files") or {}).items():  # --asf, --leader-rig, --follower-rig
            path = os.path.join(scratch, opt, name)
            _write_file(path, data)
            mapping[path] = options[opt]
            options[opt] = path
        out_dir = os.path.join(scratch, "out")
        os.makedirs(out_dir)
        temps = {kind: os.path.join(out_dir, name) for kind, name in spec["outputs"].items()}
        last = [0.0]

        def progress(fraction):
            now = time.perf_counter()
            if now - last[0] >= 0.5:
                last[0] = now
                if _cancelled(worker, key):
                    raise _Cancelled()
                _announce(worker, topic, {"id": spec["id"], "fraction": round(float(fraction), 3)})
            return True

        job = {"id": spec["id"], "input": inp, "source": spec["input"], "temps": temps, "options": options,
               "needs_bpy": spec["needs_bpy"]}
        try:
            if spec["needs_bpy"]:
                info = _BPY.convert(job, progress, worker, key, scratch)
                missing = [k for k, p in temps.items() if not os.path.isfile(p)]
                if missing:
                    raise RuntimeError(f"the converter wrote no {', '.join(missing)} output")
                outputs = {}
                for kind, p in temps.items():
                    with open(p, "rb") as f:
                        outputs[kind] = f.read()
            else:
                info, outputs = core_convert(job, progress)
        except _Cancelled:
            return {"status": "cancelled", "worker": addr}
        except Exception as exc:  # noqa: BLE001 - one bad take never stops the worker
            if os.environ.get("DP_DEBUG", "") not in ("", "0"):
                import traceback
                traceback.print_exc()
            return {"status": "failed", "error": _map_paths(error_message(exc), mapping),
                    "seconds": time.perf_counter() - t0, "worker": addr}
        return {"status": "ok", "frames": info.get("frames"), "seconds": time.perf_counter() - t0,
                "outputs": outputs, "worker": addr}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def core_convert(job, progress):
    """npz / bvh in memory: what :class:`.worker.CoreConverter` writes to its
    files (the same readers, synthesis and writers: the same bytes), as
    ``({"frames": n}, {kind: bytes})``."""
    import io

    from ..formats.bvh import bvh_text
    from ..formats.files import write_npz
    from ..formats.inputs import load_input
    from ..runtime import Synthesizer, duet_motions
    from .options import synthesis_options

    o = job["options"]
    kinds = set(job["temps"])
    take = load_input(job["input"], asf=o.get("asf"), input_fps=o.get("input_fps"), height=o.get("height"))
    progress(0.05)
    synth = Synthesizer(synthesis_options(o, take.height))
    duet = synth.synthesize(take, progress=lambda i, n: progress(0.05 + 0.9 * i / max(n, 1)))
    outputs = {}
    if "npz" in kinds:
        buf = io.BytesIO()
        write_npz(buf, duet.arrays())
        outputs["npz"] = buf.getvalue()
    if kinds & {"bvh_leader", "bvh_follower"}:
        for role, motion in duet_motions(duet).items():
            if "bvh_" + role in kinds:
                outputs["bvh_" + role] = bvh_text(motion).encode("utf-8")  # (written with newline="\n")
    missing = kinds - set(outputs)
    if missing:
        raise RuntimeError(f"the converter made no {', '.join(sorted(missing))} output")
    return {"frames": int(duet.n_frames)}, outputs


class _BpyWorkers:
    """On a Dask worker: one Blender-side worker process (:data:`.worker.BPY_WORKER_SCRIPT`,
    the ``bpy`` module) per worker thread, started at its first take and kept."""

    def __init__(self):
        self._lock = threading.Lock()
        self._procs = {}  # thread id -> (WorkerProcess, queue)
        self._serial = 0
        self._log_dir = None

    def _get(self, base):
        from ..argtypes import SINGLE_THREAD_ENV
        from .scheduler import WorkerProcess
        from .worker import worker_command

        tid = threading.get_ident()
        with self._lock:
            entry = self._procs.get(tid)
            if entry is not None and entry[0].proc.poll() is None:
                return entry
            if self._log_dir is None:
                self._log_dir = tempfile.mkdtemp(prefix="dp-bpy-logs-", dir=base)
            self._serial += 1
            env = dict(os.environ)
            for k in SINGLE_THREAD_ENV:
                env[k] = "1"
            q = queue.Queue()
            entry = (WorkerProcess(worker_command(True), env, self._log_dir, q, self._serial), q)
            self._procs[tid] = entry
            return entry

    def _drop(self, w):
        with self._lock:
            for tid, (p, _) in list(self._procs.items()):
                if p is w:
                    del self._procs[tid]
        w.close()
        w.terminate()
        with contextlib.suppress(Exception):
            w.proc.wait(timeout=10)
        w.kill()

    def convert(self, job, progress, worker, key, base):
        from . import messages

        w, q = self._get(getattr(worker, "local_directory", None) or None)
        msg = messages.job(job["id"], job["input"], job["temps"], True, job["options"])
        msg["source"] = job.get("source")  # the client's path of the input (the take's Source)
        if not w.send(msg):
            self._drop(w)
            raise RuntimeError("the Blender worker process could not be started: " + (w.stderr_tail() or "no output"))
        while True:
            try:
                who, msg = q.get(timeout=0.5)
            except queue.Empty:
                if _cancelled(worker, key):
                    self._drop(w)  # the render or bake stops with it
                    raise _Cancelled() from None
                continue
            if msg is None:
                rc = w.proc.wait()
                tail = w.stderr_tail()
                self._drop(w)
                raise RuntimeError(f"Blender worker process died (exit status {rc})" + (f": {tail}" if tail else ""))
            kind = msg.get("type")
            if kind == messages.PROGRESS and msg.get("id") == job["id"]:
                progress(float(msg.get("fraction", 0.0)))
            elif kind == messages.DONE and msg.get("id") == job["id"]:
                return {"frames": msg.get("frames")}
            elif kind == messages.ERROR and msg.get("id") == job["id"]:
                raise _WorkerError(msg.get("error") or "failed")


class _WorkerError(Exception):
    """A take the Blender-side worker reported as failed (its one line)."""


_BPY = _BpyWorkers()


# =========================================================================== the client side

# This module as the workers import it (inside Blender it is a submodule of the extension's package).
MODULE = __name__[__name__.find("dancing_points_addon."):] if "dancing_points_addon." in __name__ else __name__


def remote(func_name):
    """A function that imports this module where it runs and calls ``func_name``
    there: a nested function, so Dask pickles it by value (cloudpickle). The
    scheduler, which unpickles every task, then needs Dask only, not this
    project; the workers need this project (on their ``PYTHONPATH``)."""
    module = MODULE

    def call(*args):
        import importlib

        return getattr(importlib.import_module(module), func_name)(*args)

    call.__qualname__ = call.__name__ = "dancing_points_" + func_name
    return call


def _import_distributed():
    if os.environ.get("DP_DEBUG", "") in ("", "0"):
        # Dask's own log lines (connections, restarts) would break the one-line-per-file output;
        # the report says what happened. (Read at import, also by LocalCluster's worker processes.)
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")
    try:
        import distributed
    except ImportError as exc:
        raise ClusterError(f"--cluster needs Dask's distributed package in this Python ({sys.executable}): "
                           f"{INSTALL_HINT} ({one_line(exc)})") from None
    return distributed


class Cluster:
    """A connection to the cluster (and the :class:`distributed.LocalCluster` it
    started for ``local:N``): :func:`connect` makes one; :meth:`close`."""

    def __init__(self, spec, client, local=None):
        self.spec = spec
        self.client = client
        self.local = local
        self.address = client.scheduler.address
        self.identity = None
        self.model_dir = None
        self.workers = {}
        self.allowed_failures = None

    def threads(self) -> int:
        """Worker threads now on the cluster (0 when unknown)."""
        try:
            info = self.client.scheduler_info()
        except Exception:  # noqa: BLE001
            return sum(int(w.get("nthreads", 1)) for w in self.workers.values())
        self.workers = dict(info.get("workers", {}))
        return sum(int(w.get("nthreads", 1)) for w in self.workers.values())

    def close(self):
        with contextlib.suppress(Exception):
            self.client.close(timeout=10)
        if self.local is not None:
            with contextlib.suppress(Exception):
                self.local.close(timeout=20)


def connect(spec: str, model_dir: str, needs_bpy: bool = False, err=None) -> Cluster:
    """Connect to the cluster of ``--cluster`` (or start ``local:N``), wait for a
    worker, and check that every worker runs this version with these models
    (and ``bpy`` when ``needs_bpy``). A :class:`ClusterError` (one line) otherwise."""
    distributed = _import_distributed()
    err = err if err is not None else sys.stderr
    local = None
    try:
        if spec == LOCAL or spec.startswith(LOCAL + ":"):
            import logging

            from .options import default_jobs

            n = int(spec[len(LOCAL) + 1:] or default_jobs())
            import dask

            dask.config.set(LOCAL_WORKER_CONFIG)  # (the worker processes get this process's config)
            old = None
            if threading.current_thread() is threading.main_thread():
                # The worker processes ignore Ctrl-C (it is the client's): they inherit this.
                old = signal.signal(signal.SIGINT, signal.SIG_IGN)
            try:
                local = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                 host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                                 silence_logs=logging.CRITICAL)
            finally:
                if old is not None:
                    signal.signal(signal.SIGINT, old)
            client = distributed.Client(local, set_as_default=False)
        else:
            client = distributed.Client(spec, timeout=CONNECT_TIMEOUT, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        if local is not None:
            with contextlib.suppress(Exception):
                local.close()
        raise ClusterError(f"--cluster {spec}: cannot reach the Dask scheduler ({one_line(exc)})") from None
    cluster = Cluster(spec, client, local)
    try:
        _check_cluster(cluster, model_dir, needs_bpy, err)
    except BaseException:
        cluster.close()
        raise
    return cluster


def _check_cluster(cluster, model_dir, needs_bpy, err):
    client = cluster.client
    if not cluster.threads():
        print(f"waiting for the cluster's workers (at most {WORKER_WAIT:.0f} s) ...", file=err, flush=True)
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT)
        except (TimeoutError, OSError):
            raise ClusterError(f"--cluster {cluster.spec}: no worker joined the scheduler within "
                               f"{WORKER_WAIT:.0f} s (start them with: dask worker {cluster.address})") from None
        cluster.threads()
    cluster.identity = identity(model_dir)
    cluster.model_dir = model_dir
    try:
        answers = client.run(remote("_handshake"), cluster.identity, model_dir, needs_bpy)
    except Exception as exc:  # noqa: BLE001 - e.g. the workers cannot import this package
        raise ClusterError(f"--cluster {cluster.spec}: a worker cannot run Dancing Points ({type(exc).__name__}: "
                           f"{one_line(exc)}); start the workers with this project on their PYTHONPATH "
                           f"(see README, Batch on a cluster)") from None
    for addr, why in sorted(answers.items()):
        if why:
            raise ClusterError(f"--cluster {cluster.spec}: worker {addr} {why}")
    with contextlib.suppress(Exception):
        cluster.allowed_failures = client.run_on_scheduler(_allowed_failures())


def _allowed_failures():
    """On the scheduler: its ``allowed-failures`` (a function pickled by value)."""
    return lambda dask_scheduler: getattr(dask_scheduler, "allowed_failures", None)


class ClusterBatch:
    """:class:`.scheduler.Batch` with the takes run as Dask tasks on ``cluster``
    (:func:`connect`): the same ``run()``, ``jobs`` and ``fatal``; ``refused``
    when a worker refused (another version or models: exit status 2)."""

    def __init__(self, tasks, cluster, job_options, fmt, progress=None, out_dir=None, jobs=None):
        self.tasks = tasks
        self.cluster = cluster
        self.options = job_options
        self.fmt = fmt
        self.progress = progress
        self.out_dir = out_dir
        self.limit = jobs  # at most this many takes at once (None: as many as the cluster's threads)
        threads = cluster.threads() or 1
        self.jobs = min(threads, jobs) if jobs else threads
        self.stop_signal = None
        self.fatal = None
        self.refused = False
        self.run_id = uuid.uuid4().hex[:12]
        self.finished = 0
        self._old = {}

    # -- signals (as the local batch) -----------------------------------------------------
    def _install_signals(self):
        from .scheduler import Batch

        Batch._install_signals(self)

    def _restore_signals(self):
        from .scheduler import Batch

        Batch._restore_signals(self)

    # -- the tasks ----------------------------------------------------------------------
    def _needs_bpy(self, task):
        return task_needs_bpy(self.fmt, task)

    def _files(self):
        """The option files every task carries: ``{option: (name, bytes)}``."""
        from ..formats.files import open_regular

        files = {}
        for opt in ("asf", "leader_rig", "follower_rig"):
            path = self.options.get(opt)
            if path:
                with open_regular(path, "a file") as f:
                    files[opt] = (os.path.basename(path), f.read())
        return files

    def _spec(self, task, files):
        from ..formats.asf_amc import find_asf
        from ..formats.files import open_regular

        with open_regular(task.input, "an input file", missing="no such file") as f:
            data = f.read()
        beside = None
        if os.path.splitext(task.input)[1].lower() == ".amc" and not self.options.get("asf"):
            with contextlib.suppress(InputError, OSError):
                asf = find_asf(task.input)
                with open_regular(asf, "an ASF file") as f:
                    beside = (os.path.basename(asf), f.read())
        return {"id": task.index, "topic": TOPIC + self.run_id, "identity": self.cluster.identity,
                "input": task.input, "input_name": os.path.basename(task.input), "input_bytes": data,
                "beside": beside, "files": files, "needs_bpy": self._needs_bpy(task), "options": self.options,
                "outputs": {k: os.path.basename(o) for k, o in zip(task.kinds, task.outputs)}}

    def _window(self):
        """How many takes to keep in flight: one per worker thread (``--jobs`` caps it).
        As the local batch, a worker gets its next take when it is done with one
        (never one queued behind another while a worker idles at the end)."""
        threads = self.cluster.threads() or 1
        return min(threads, self.limit) if self.limit else threads

    # -- results ------------------------------------------------------------------------
    def _finish(self, task, status, error=None, frames=None, seconds=None):
        task.finish(status, error, frames, seconds)
        if self.progress is not None:
            line = result_line(task, self.out_dir)
            died = max(0, self.attempts.get(task.index, 0) - 1)
            if died:
                line += f" [ran {died + 1} times: {died} worker{'s' if died > 1 else ''} died running it]"
            self.progress.result(line)
        self.finished += 1

    def _commit(self, task, res):
        """Write the returned bytes to the plan's temporary files, then rename them into place."""
        from .scheduler import commit

        try:
            for kind, tmp in zip(task.kinds, task.temps):
                with open(tmp, "wb") as f:
                    f.write(res["outputs"][kind])
                    f.flush()
                    os.fsync(f.fileno())
            commit(task)
        except InputError as exc:
            remove_temps(task.temps)
            self._finish(task, "failed", one_line(exc), res.get("frames"), res.get("seconds"))
        except (OSError, KeyError) as exc:
            remove_temps(task.temps)
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            self._finish(task, "failed", f"cannot write output ({why})", res.get("frames"), res.get("seconds"))
        else:
            self._finish(task, "ok", None, res.get("frames"), res.get("seconds"))

    def _done(self, task, fut):
        """A task's future finished (or erred): the take's result."""
        status = fut.status
        if status == "finished":
            try:
                res = fut.result(timeout=300)
            except Exception as exc:  # noqa: BLE001 - e.g. its worker died before the bytes came
                return self._finish(task, "failed", f"cluster: cannot fetch the result ({type(exc).__name__}: "
                                                    f"{one_line(exc)})")
            kind = res.get("status")
            if kind == "ok":
                return self._commit(task, res)
            if kind == "refused":
                self.fatal = res.get("error") or "a worker refused the take"
                self.refused = True
                task.started = task.started or time.perf_counter()
                return None  # (left interrupted: not converted, not failed)
            if kind == "cancelled":
                return self._finish(task, "interrupted", "cancelled on the cluster")
            return self._finish(task, "failed", res.get("error") or "failed", None, res.get("seconds"))
        if status == "error":
            exc = fut.exception(timeout=30)
            name = type(exc).__name__
            if name == "KilledWorker":
                n = getattr(exc, "allowed_failures", self.cluster.allowed_failures)
                last = getattr(getattr(exc, "last_worker", None), "address", "?")
                return self._finish(task, "failed", f"worker died while converting it, {n + 1 if n is not None else 'too many'} "
                                                    f"times (the scheduler's allowed-failures; last on {last})")
            return self._finish(task, "failed", f"cluster: {name}: {one_line(exc)}")
        return self._finish(task, "failed", f"cluster: the task was {status} (was the scheduler restarted?)")

    def _on_event(self, msg):
        i = msg.get("id") if isinstance(msg, dict) else None
        task = self.in_flight_by_index.get(i)
        if task is None:
            return
        if msg.get("start"):
            self.attempts[i] = self.attempts.get(i, 0) + 1
            self.workers_of.setdefault(i, []).append(msg.get("worker"))
            task.fraction = 0.0
            self.running.add(i)
        elif "fraction" in msg:
            task.fraction = float(msg["fraction"])

    def _draw(self, force=False):
        if self.progress is not None:
            running = [(self.in_flight_by_index[i].name, self.in_flight_by_index[i].fraction)
                       for i in sorted(self.running) if i in self.in_flight_by_index]
            self.progress.update(self.finished, running, force=force)

    # -- running ------------------------------------------------------------------------
    def run(self) -> str:
        """Run; returns "done", "interrupted", "terminated" or "refused" (a worker
        refused a take: another version or models; ``fatal`` says which)."""
        todo = [t for t in self.tasks if t.status == "pending"]
        pending = collections.deque(sorted(todo, key=lambda t: (-t.size, t.index)))  # longest first
        self.finished = 0
        self.attempts, self.workers_of, self.running = {}, {}, set()
        self.in_flight_by_index = {}
        if not pending:
            return "done"
        client = self.cluster.client
        q = queue.Queue()
        topic = TOPIC + self.run_id
        futures = {}  # key -> (future, task)
        n_todo, rank = len(pending), 0
        self._install_signals()
        subscribed = False
        try:
            client.subscribe_topic(topic, lambda ev: q.put(("event", ev[1])))
            subscribed = True
            files = self._files()
            take_function = remote("run_take")
            window, last_window = self._window(), time.monotonic()
            self._draw(force=True)

            def fill():
                nonlocal rank
                while pending and len(futures) < window and self.stop_signal is None and not self.fatal:
                    task = pending.popleft()
                    task.started = time.perf_counter()
                    task.fraction = 0.0
                    try:
                        spec = self._spec(task, files)
                    except InputError as exc:
                        self._finish(task, "failed", one_line(exc))
                        continue
                    except OSError as exc:
                        self._finish(task, "failed", f"cannot read file ({exc.strerror or exc})")
                        continue
                    key = f"dancing-points-{self.run_id}-{task.index}"
                    rank += 1
                    fut = client.submit(take_function, spec, key=key, pure=False, priority=n_todo - rank)
                    futures[key] = (fut, task)
                    self.in_flight_by_index[task.index] = task
                    fut.add_done_callback(lambda f: q.put(("done", f.key)))

            while True:
                if time.monotonic() - last_window > 2.0:  # workers come and go
                    window, last_window = self._window(), time.monotonic()
                    if client.status in ("closed", "failed"):
                        self.fatal = f"lost the connection to the Dask scheduler at {self.cluster.address}"
                if self.stop_signal is not None or self.fatal:
                    break
                fill()
                if not futures:
                    break
                try:
                    kind, item = q.get(timeout=0.1)
                except queue.Empty:
                    self._draw()
                    continue
                if kind == "event":
                    self._on_event(item)
                    self._draw()
                    continue
                entry = futures.pop(item, None)
                if entry is None:
                    continue
                fut, task = entry
                fill()  # the next take first: the worker is free now
                self._done(task, fut)
                self.in_flight_by_index.pop(task.index, None)
                self.running.discard(task.index)
                with contextlib.suppress(Exception):
                    fut.release()
                self._draw(force=True)
        except KeyboardInterrupt:  # only if our handler could not be installed
            self.stop_signal = signal.SIGINT
        finally:
            if futures:  # stopped: nothing more runs on the cluster for this batch
                with contextlib.suppress(Exception):
                    client.cancel([f for f, _ in futures.values()], force=True)
            for _, task in futures.values():
                remove_temps(task.temps)
            if subscribed:
                with contextlib.suppress(Exception):
                    client.unsubscribe_topic(topic)
            self._restore_signals()
            if self.progress is not None:
                self.progress.finish()
        ending = settle_unfinished(self.tasks, None if self.refused else self.fatal, self.stop_signal)
        if self.refused:
            for t in self.tasks:
                if t.status == "interrupted":
                    t.error = "not converted: " + self.fatal
        return "refused" if self.refused and ending == "done" else ending

    def annotate(self, report: dict) -> None:
        """The cluster's part of the report: ``cluster`` (scheduler, workers,
        threads, allowed failures) and, per file run on it, ``attempts`` and ``workers``."""
        report["cluster"] = {"scheduler": self.cluster.address, "spec": self.cluster.spec,
                             "workers": sorted(self.cluster.workers), "threads": self.jobs,
                             "allowed_failures": self.cluster.allowed_failures,
                             "identity": self.cluster.identity}
        for task, rec in zip(self.tasks, report["files"]):
            if task.index in self.attempts:
                rec["attempts"] = self.attempts[task.index]
                rec["workers"] = self.workers_of.get(task.index, [])
