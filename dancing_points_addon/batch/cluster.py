"""A batch on a Dask cluster: ``batch IN... -o OUT --cluster tcp://HOST:8786``
(or ``--cluster local:N``, a :class:`distributed.LocalCluster` of N worker
processes on this machine).

Only the dispatch changes: the plan, the lock, the progress bar, the result
lines, the report, ``--resume``/``--overwrite`` and the exit statuses are the
local batch's (:func:`.run`); :class:`ClusterBatch` replaces :class:`.scheduler.Batch`.

* Each take is one Dask task (:func:`.cluster_worker.run_take`) carrying
  everything the worker needs: the input file's bytes (and its ASF, the
  ``--asf`` file, the rig files), the job options and the client's identity. The worker converts it in a
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
* Identity: each task carries the client's identity (project version, a hash
  of the extension's Python files, a hash of the models' bytes); a worker that
  differs refuses (:mod:`.cluster_identity`). :func:`.cluster_connect.connect`
  asks every worker up front (before any work: one line, exit 2); a worker that
  joins later and differs refuses its first task, which stops the run (exit 2).
* Ctrl-C / SIGTERM: the tasks are cancelled on the cluster (a running take
  stops at its next progress step), the takes not finished are
  ``interrupted``, no partial file is left; ``--resume`` finishes.
* ``blend``/``fbx``/``--render``: the worker runs the Blender-side worker
  (:data:`.worker.BPY_WORKER_SCRIPT`, the ``bpy`` module in the worker's Python)
  as a subprocess of its own, one per worker thread, kept for the next take.

This module is the client loop (:class:`ClusterBatch`); :mod:`.cluster_identity`
the identity, :mod:`.cluster_worker` the worker side, :mod:`.cluster_connect`
the connection. Dask (``dask`` and ``distributed``) is imported only inside the
functions that need it: without ``--cluster`` nothing imports it, and it is not bundled
with the extension (``pip install dask distributed`` beside the command line).
"""
from __future__ import annotations

import collections
import contextlib
import os
import queue
import signal
import time
import uuid

from ..errors import InputError, one_line
from .cluster_worker import remote
from .options import task_needs_bpy
from .plan import remove_temps, settle_unfinished
from .progress import result_line

TOPIC = "dancing-points-batch-"  # + run id: the attempts and progress of one run's takes


class ClusterBatch:
    """:class:`.scheduler.Batch` with the takes run as Dask tasks on ``cluster``
    (:func:`.cluster_connect.connect`): the same ``run()``, ``jobs`` and ``fatal``; ``refused``
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
                times = n + 1 if n is not None else "too many"
                return self._finish(task, "failed", f"worker died while converting it, {times} "
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
