"""The worker side of a batch on a Dask cluster (:mod:`.cluster`): :func:`run_take`,
the Dask task of one take, and :func:`remote`, how the client names it.

The worker converts a take in a scratch folder of its own from the bytes the
task carries and returns the output files' bytes; ``blend``/``fbx``/``--render``
go through a Blender-side worker process per worker thread (:class:`_BpyWorkers`).
"""
from __future__ import annotations

import contextlib
import os
import queue
import shutil
import tempfile
import threading
import time

from ..errors import error_message
from .cluster_identity import check_worker

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



def _handshake(expected, client_dir, needs_bpy):
    """``client.run`` on every worker: None when it can run this batch, else why not."""
    _, why = check_worker(expected, client_dir, needs_bpy)
    return why



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
    from ..inputs import load_input
    from ..duet import duet_motions
    from ..runtime import Synthesizer
    from .options import job_song, synthesis_options

    o = job["options"]
    kinds = set(job["temps"])
    take = load_input(job["input"], asf=o.get("asf"), input_fps=o.get("input_fps"), height=o.get("height"),
                      role=o.get("role"))
    song = job_song(o, take)  # (--audio; a take's own relative song is not beside its scratch copy)
    progress(0.05)
    synth = Synthesizer(synthesis_options(o, take.height))
    duet = synth.synthesize(take, progress=lambda i, n: progress(0.05 + 0.9 * i / max(n, 1)))
    duet.song = song
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
