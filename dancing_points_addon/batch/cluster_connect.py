"""Connecting to a Dask cluster (:mod:`.cluster`): ``--cluster`` (:func:`cluster_spec`),
and :func:`connect`, which reaches the scheduler (or starts ``local:N``), waits
for a worker and asks every worker whether it can run this batch (one line,
exit 2, before any work, when one cannot).

Dask is imported only inside the functions that need it.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

from ..errors import UserError, one_line
from .cluster_identity import identity
from .cluster_worker import remote

LOCAL = "local"
DEFAULT_PORT = 8786
CONNECT_TIMEOUT = 30.0  # seconds to reach the scheduler
WORKER_WAIT = 60.0  # seconds to wait for a first worker
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
