"""Benchmark: the overhead of a Dask cluster, ``--cluster`` (two workers) vs ``--jobs 2`` on this machine.

    .venv/bin/python benchmarks/bench_cluster.py [--models DIR] [--rounds 3] [--formats npz,blend]

The takes are 8 real CMU salsa takes (``60_01.amc`` .. ``60_08.amc``, whole,
28-57 s each), converted by ``python -m dancing_points_addon batch`` as a user
runs it: once with ``--jobs 2`` (two local worker processes, started by the
command) and once with ``--cluster ADDRESS`` on a ``dask scheduler`` and two
``dask worker --nthreads 1`` processes on 127.0.0.1 (with the settings the
README recommends) that this script starts first and keeps running, as a farm's workers are (so the first cluster round
also pays the workers' warm-up: imports, the networks, for blend the bpy
process; it is printed as "cold"). Each figure is the wall time of the whole
command. Rounds alternate local and cluster; each run is printed with the CPU
load of other processes meanwhile, and only the quiet ones (other processes
below ``--max-other`` cores) count: rounds go on until each side has
``--rounds`` quiet runs (at most ``--max-rounds``), and the best quiet time of
each counts (other processes on a shared machine only ever slow a run down; a
loaded run beside a quiet one would say nothing about the cluster). Without
enough quiet runs the figure is reported as inconclusive (exit 2). Prints takes per minute for
each and the ratio cluster / local per format, and fails (exit 1) when the npz
ratio is below 0.9 (the goal). Needs ``dask`` and ``distributed``
(requirements-dev.txt); blend needs the ``bpy`` module in the workers' Python
(this venv). Client and workers run a snapshot of the checkout taken at the
start (the workers refuse a client whose code changed since they started, so
editing the checkout meanwhile would stop the benchmark). Not collected by pytest: speed goals are checked by benchmarks
that print their figures.
"""
import argparse
import json
import os
import pathlib
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the tests' support package
from support.helpers import busy_seconds, model_dir, proc_table  # noqa: E402
from dancing_points_addon.argtypes import positive_int  # noqa: E402

SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"
DASK = os.path.join(os.path.dirname(sys.executable), "dask")
GOAL = 0.9


def _pids_seconds(pids):
    """CPU seconds of the processes ``pids`` and all their descendants (Linux /proc;
    the workers' Blender processes run in sessions of their own)."""
    procs = proc_table()
    ours, grew = set(pids), True
    while grew:
        new = {p for p, (pp, _, _) in procs.items() if pp in ours} - ours
        ours |= new
        grew = bool(new)
    return sum(procs[p][2] for p in ours if p in procs)


SNAPSHOT = ("__init__.py", "blender_manifest.toml", "preferences.py", "LICENSE", "dancing_points_addon", "operators",
            "panels")


def snapshot(dest):
    """A copy of the extension's files of the checkout (the models linked)."""
    dest.mkdir()
    for name in SNAPSHOT:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.is_file():
            shutil.copy2(src, dest / name)
    os.symlink(ROOT / "models", dest / "models")
    return dest


# The workers' settings the README recommends for a farm: no statistical profiler
# (it samples the converting thread every 10 ms), calmer monitors.
WORKER_ENV = {"DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
              "DASK_DISTRIBUTED__WORKER__MEMORY__MONITOR_INTERVAL": "1s",
              "DASK_DISTRIBUTED__ADMIN__SYSTEM_MONITOR__INTERVAL": "2s"}


class Cluster:
    """A ``dask scheduler`` and ``n`` ``dask worker`` processes on 127.0.0.1 (own sessions)."""

    def __init__(self, folder, n, code):
        self.folder, self.procs, self.address, self.code = folder, [], None, code
        env = dict(os.environ, PYTHONPATH=str(code), **WORKER_ENV)
        self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                  "--dashboard-address", "127.0.0.1:0"], env)
        t0 = time.monotonic()
        while self.address is None:
            for line in self._log("scheduler").splitlines():
                if "Scheduler at:" in line:
                    self.address = line.split("Scheduler at:")[1].strip()
            if time.monotonic() - t0 > 60:
                self.stop()
                sys.exit("bench_cluster: the scheduler did not start: " + self._log("scheduler")[-2000:])
            time.sleep(0.05)
        for i in range(n):
            self._start(f"worker{i}", ["worker", self.address, "--nthreads", "1", "--host", "127.0.0.1",
                                       "--no-dashboard", "--local-directory", os.path.join(folder, f"w{i}")], env)
        while sum("Registered to" in self._log(f"worker{i}") for i in range(n)) < n:
            if time.monotonic() - t0 > 120:
                self.stop()
                sys.exit("bench_cluster: the workers did not start")
            time.sleep(0.05)

    def _start(self, name, args, env):
        log = open(os.path.join(self.folder, name + ".log"), "wb")
        self.procs.append(subprocess.Popen([DASK, *args], cwd=str(self.code), stdin=subprocess.DEVNULL, stdout=log,
                                           stderr=subprocess.STDOUT, env=env, start_new_session=True))
        log.close()

    def _log(self, name):
        with open(os.path.join(self.folder, name + ".log"), "rb") as f:
            return f.read().decode("utf-8", "replace")

    def pids(self):
        return [p.pid for p in self.procs]

    def stop(self):
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def timed_batch(code, takes, out, fmt, models, extra, cluster_pids=()):
    """Wall seconds of one batch command, its report, and the CPU load of other
    processes meanwhile (in cores; None where unknown)."""
    cmd = [sys.executable, "-m", "dancing_points_addon", "batch", *map(str, takes), "-o", str(out),
           "--format", fmt, "--models", models, "--no-progress", "--overwrite", *extra]
    busy0, ours0 = busy_seconds(), _children_seconds() + _pids_seconds(cluster_pids)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=code, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    busy1, ours1 = busy_seconds(), _children_seconds() + _pids_seconds(cluster_pids)
    if res.returncode != 0:
        sys.exit(f"bench_cluster: batch failed ({res.returncode}):\n{res.stdout}{res.stderr}")
    with open(os.path.join(out, "batch_report.json")) as f:
        report = json.load(f)
    other = None if busy0 is None else max(0.0, (busy1 - busy0) - (ours1 - ours0)) / dt
    return dt, report, other


def _children_seconds():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _load(other):
    return "" if other is None else f" (other processes: {other:.2f} cores)"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="")
    ap.add_argument("--formats", default="npz,blend", help="comma-separated formats (default npz,blend)")
    ap.add_argument("--rounds", type=positive_int, default=2, help="quiet runs wanted per side (default 2)")
    ap.add_argument("--max-rounds", type=positive_int, default=8, help="at most this many alternating rounds")
    ap.add_argument("--max-other", type=float, default=0.15,
                    help="a run counts when other processes used at most this many cores (default 0.15)")
    args = ap.parse_args()
    models = model_dir(args.models, "bench_cluster")
    takes = [SALSA / f"60_{i:02d}.amc" for i in range(1, 9)]
    print(f"{len(takes)} takes ({', '.join(t.name for t in takes)}), models {models}, {os.cpu_count()} cores")
    ratios = {}
    with tempfile.TemporaryDirectory(prefix="bench_cluster_") as tmp:
        tmp = pathlib.Path(tmp)
        code = snapshot(tmp / "code")
        t0 = time.perf_counter()
        cluster = Cluster(str(tmp), 2, code)
        print(f"dask scheduler + 2 dask workers (--nthreads 1) at {cluster.address}, started in "
              f"{time.perf_counter() - t0:.1f} s")
        try:
            for fmt in [f for f in args.formats.split(",") if f]:
                runs = {"local": ["--jobs", "2"], "cluster": ["--cluster", cluster.address]}
                times = {k: [] for k in runs}
                quiet = {k: [] for k in runs}
                frames = 0
                for r in range(args.max_rounds):
                    for kind, extra in runs.items():
                        dt, report, other = timed_batch(code, takes, tmp / f"{fmt}_{kind}", fmt, models, extra,
                                                        cluster.pids())
                        frames = sum(f["frames"] for f in report["files"])
                        times[kind].append(dt)
                        cold = r == 0 and kind == "cluster"
                        counts = not cold and (other is None or other <= args.max_other)
                        if counts:
                            quiet[kind].append(dt)
                        note = " (cold: the workers' first takes; not counted)" if cold else (
                            "" if counts else " (not counted: machine busy)")
                        print(f"  {fmt} round {r + 1}: {' '.join(extra) if kind == 'local' else '--cluster'}: "
                              f"{dt:.2f} s, {60 * len(takes) / dt:.1f} takes/min{_load(other)}{note}", flush=True)
                    if all(len(v) >= args.rounds for v in quiet.values()):
                        break
                if not all(quiet.values()):
                    ratios[fmt] = None
                    print(f"{fmt}: inconclusive: no quiet run of {'both' if not any(quiet.values()) else 'one'} "
                          f"side in {r + 1} rounds (other processes above {args.max_other} cores)")
                    continue
                best = {k: min(v) for k, v in quiet.items()}
                tpm = {k: 60 * len(takes) / v for k, v in best.items()}
                ratios[fmt] = tpm["cluster"] / tpm["local"]
                print(f"{fmt}: {frames} duet frames; --jobs 2 {best['local']:.2f} s = {tpm['local']:.1f} takes/min, "
                      f"--cluster (2 workers) {best['cluster']:.2f} s = {tpm['cluster']:.1f} takes/min; "
                      f"ratio {ratios[fmt]:.2f} (goal >= {GOAL}; best of {len(quiet['local'])} and "
                      f"{len(quiet['cluster'])} quiet runs; cold cluster round "
                      f"{60 * len(takes) / times['cluster'][0]:.1f} takes/min)")
        finally:
            cluster.stop()
    if "npz" in ratios and ratios["npz"] is None:
        print("INCONCLUSIVE: the machine was never quiet enough; run again")
        return 2
    if ratios.get("npz", GOAL) < GOAL:
        print(f"FAIL: npz ratio {ratios['npz']:.2f} < {GOAL}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
