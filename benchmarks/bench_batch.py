"""Benchmark: batch throughput with ``--jobs 2`` vs ``--jobs 1`` on the same 8 takes.

    .venv/bin/python benchmarks/bench_batch.py [--models DIR] [--jobs 2] [--formats npz,bvh,blend,fbx]

The takes are 8 real CMU salsa takes (``60_01.amc`` .. ``60_08.amc``, whole,
28-57 s each), converted to npz by ``python -m dancing_points_addon batch`` as a
user runs it; each figure is the wall time of the whole command (worker start-up
included). ``--rounds`` alternating rounds of ``--jobs 1`` and ``--jobs 2``;
the best time of each counts (other processes on a shared machine only ever
slow a run down; each run's figure is printed with the CPU load of other
processes meanwhile). Prints ``jobs1 X s, jobs2 Y s, ratio R`` and fails
(exit 1) when R < 1.7 (the goal on a 2-core machine). ``--formats`` also times each listed
format with ``--jobs N`` on the same takes. Not collected by pytest: speed goals
are checked by benchmarks that print their figures.
"""
import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the tests' support package
from support.helpers import busy_seconds, model_dir  # noqa: E402
from dancing_points_addon.argtypes import positive_int  # noqa: E402
SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"
GOAL = 1.7


def _children_seconds():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed_batch(takes, out, fmt, jobs, models):
    """Wall seconds of one batch command, its duet frames, and the CPU load of
    other processes meanwhile (in cores; None where unknown)."""
    cmd = [sys.executable, "-m", "dancing_points_addon", "batch", *map(str, takes), "-o", str(out),
           "--format", fmt, "--jobs", str(jobs), "--models", models, "--no-progress", "--overwrite"]
    busy0, ours0 = busy_seconds(), _children_seconds()
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    busy1, ours1 = busy_seconds(), _children_seconds()
    if res.returncode != 0:
        sys.exit(f"bench_batch: batch failed ({res.returncode}):\n{res.stdout}{res.stderr}")
    with open(os.path.join(out, "batch_report.json")) as f:
        report = json.load(f)
    frames = sum(r["frames"] for r in report["files"])
    other = None if busy0 is None else max(0.0, (busy1 - busy0) - (ours1 - ours0)) / dt
    return dt, frames, other


def _load(other):
    return "" if other is None else f" (other processes: {other:.2f} cores)"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="")
    ap.add_argument("--jobs", type=positive_int, default=2)
    ap.add_argument("--formats", default="", help="comma-separated formats to time as well")
    ap.add_argument("--rounds", type=positive_int, default=3, help="alternating rounds; the best time of each counts")
    args = ap.parse_args()
    models = model_dir(args.models, "bench_batch")
    takes = [SALSA / f"60_{i:02d}.amc" for i in range(1, 9)]
    print(f"8 takes ({', '.join(t.name for t in takes)}), models {models}, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        tmp = pathlib.Path(tmp)
        times = {1: [], args.jobs: []}
        for r in range(args.rounds):  # alternate, keep the best of each (noise from other processes)
            for jobs in (1, args.jobs):
                dt, frames, other = timed_batch(takes, tmp / f"j{jobs}", "npz", jobs, models)
                times[jobs].append(dt)
                print(f"  round {r + 1}: --jobs {jobs}: {dt:.2f} s{_load(other)}")
        t1, t2 = min(times[1]), min(times[args.jobs])
        ratio = t1 / t2
        print(f"{frames} duet frames; jobs1 {t1:.2f} s, jobs{args.jobs} {t2:.2f} s, ratio {ratio:.2f} "
              f"(goal >= {GOAL}; best of {args.rounds})")
        for fmt in [f for f in args.formats.split(",") if f]:
            dt, fmt_frames, other = timed_batch(takes, tmp / f"f_{fmt}", fmt, args.jobs, models)
            print(f"--format {fmt} --jobs {args.jobs}: {dt:.2f} s ({dt / len(takes):.2f} s per take, "
                  f"{fmt_frames / dt:.0f} duet frames/s){_load(other)}")
    if ratio < GOAL:
        print(f"FAIL: ratio {ratio:.2f} < {GOAL}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
