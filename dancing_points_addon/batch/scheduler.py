"""The parent of a batch: runs the planned tasks on worker processes.

* Work: ``jobs`` workers (:mod:`.worker`), each started with its own log file
  for stderr; the longest files are dispatched first (better load balance); a
  worker that dies fails its take (with the tail of its log) and a new one takes
  over; two that die before they are ready end the run (``fatal``).
* Outputs: a finished take's temporary files are renamed onto its outputs
  (:func:`commit`: all or none new, never over an existing file unless the task
  may replace it); a failed take's temporary files are removed.
* Stopping: Ctrl-C (SIGINT) or SIGTERM stops the workers (they run in their own
  session, so Ctrl-C at the terminal reaches the parent only), removes their
  temporary files and leaves the unfinished takes ``interrupted``; the command
  then exits with 130 (143 for SIGTERM).
"""
from __future__ import annotations

import collections
import contextlib
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

from ..errors import InputError, one_line
from . import messages
from .options import task_needs_bpy
from .plan import remove_temps, settle_unfinished
from .progress import result_line
from ..argtypes import SINGLE_THREAD_ENV
from .worker import worker_command


class WorkerProcess:
    """One worker process, seen from the parent: its stdin (jobs), a thread that
    reads its stdout into the queue ``q`` (``(worker, message)``; ``(worker,
    None)`` when the output ends), its stderr in a log file, the task it has."""

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
                msg = messages.decode_reply(raw)
                if msg is not None:
                    q.put((self, msg))
        except (OSError, ValueError):
            pass
        q.put((self, None))

    def send(self, msg) -> bool:
        try:
            self.proc.stdin.write(messages.encode_request(msg))
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


def commit(task) -> None:
    """Rename a finished task's temporary files onto its outputs, all or none new
    (:func:`~..formats.files.install_all`: never over an existing file unless the
    task may replace it; on a failure the outputs are as they were)."""
    from ..formats.files import install_all

    try:
        install_all(list(zip(task.temps, task.outputs)), replace=task.replace)
    except FileExistsError as exc:
        raise InputError(exc.filename, "output exists (use --overwrite to replace it or --resume to skip "
                                       "this take)") from None
    finally:
        remove_temps(task.temps)  # whatever else a writer left beside them


class Batch:
    """The parent: runs ``tasks`` (from :func:`.plan.plan`) on ``jobs`` workers
    started with ``worker_cmd`` (default: :func:`.worker.worker_command`)."""

    def __init__(self, tasks, jobs, job_options, fmt, worker_cmd=None, progress=None, out_dir=None,
                 env=None):
        self.tasks = tasks
        self.jobs = max(1, int(jobs))
        self.options = job_options
        self.fmt = fmt
        self.worker_cmd = worker_cmd or worker_command(any(self._needs_bpy(t) for t in tasks))
        self.progress = progress
        self.out_dir = out_dir
        self.env = dict(os.environ if env is None else env)
        for k in SINGLE_THREAD_ENV:
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
            w = WorkerProcess(self.worker_cmd, self.env, log_dir, q, self._serial)
        except OSError as exc:
            self.fatal = f"cannot start a worker process ({self.worker_cmd[0]}: {exc.strerror or exc})"
            return None
        workers.append(w)
        self._assign(w, pending)
        return w

    def _needs_bpy(self, task):
        return task_needs_bpy(self.fmt, task)

    def _job(self, task):
        return messages.job(task.index, task.input, dict(zip(task.kinds, task.temps)), self._needs_bpy(task),
                            self.options)

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
        task.finish(status, error, frames, seconds)
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
                if kind == messages.READY:
                    w.ready = True
                    start_failures = 0
                    continue
                task = w.task
                if task is None or msg.get("id") != task.index:
                    continue
                if kind == messages.PROGRESS:
                    task.fraction = float(msg.get("fraction", 0.0))
                    self._draw(workers)
                    continue
                if kind == messages.DONE:
                    w.task = None
                    try:
                        commit(task)
                    except InputError as exc:
                        self._finish(task, "failed", one_line(exc), msg.get("frames"), msg.get("seconds"))
                    except OSError as exc:
                        self._finish(task, "failed", f"cannot write output ({exc.strerror or exc})",
                                     msg.get("frames"), msg.get("seconds"))
                    else:
                        self._finish(task, "ok", None, msg.get("frames"), msg.get("seconds"))
                elif kind == messages.ERROR:
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
        return settle_unfinished(self.tasks, self.fatal, self.stop_signal)

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
