"""Benchmark: a 60 s take through the ``synthesize`` command line, end to end.

    .venv/bin/python benchmarks/bench_cli.py [--rounds 3] [--seconds 60]

Builds a 60 s three-point take at 60 Hz from real CMU salsa mocap (the leader
of take 08, 57 s, continued by the start of take 09), writes it as a take
file, and times ``python -m dancing_points_addon synthesize TAKE -o out.npz``
and ``-o out.bvh`` as a user runs them: a fresh interpreter each time, so
start-up, model loading, parsing, the frame loop and writing are all in the
figure. Prints the wall time of each round and the best; fails (exit 1) when
the best is over the 5 s goal. Not collected by pytest: speed goals are checked
by benchmarks that print their figures.
"""
import argparse
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"
GOAL = 5.0


def make_take(path, seconds):
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.resample import resample_take
    from dancing_points_addon.formats.take import Take, take_from_motion, write_take

    parts, total = [], 0.0
    for name in ("60_08.amc", "60_09.amc"):
        t = resample_take(take_from_motion(load_amc(str(SALSA / name))), 60.0)
        parts.append(t)
        total += t.n_frames / 60.0
        if total >= seconds:
            break
    n = int(round(seconds * 60))
    pos = np.concatenate([p.positions for p in parts])[:n]
    quat = np.concatenate([p.quats for p in parts])[:n]
    write_take(path, Take(np.arange(n) / 60.0, pos, quat, {"source": "CMU salsa 60_08 + 60_09 (leader)"}))
    return n


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        take = os.path.join(tmp, "take60.csv")
        n = make_take(take, args.seconds)
        print(f"take: {n} rows at 60 Hz = {n / 60:.1f} s ({os.path.getsize(take) / 1e6:.1f} MB)")
        best = {}
        for r in range(args.rounds):
            for ext in ("npz", "bvh"):
                out = os.path.join(tmp, f"out_{r}.{ext}")
                t = time.perf_counter()
                subprocess.run([sys.executable, "-m", "dancing_points_addon", "synthesize", take, "-o", out],
                               cwd=ROOT, check=True)
                dt = time.perf_counter() - t
                best[ext] = min(best.get(ext, dt), dt)
                print(f"round {r + 1}: synthesize -> .{ext}: {dt:.2f} s")
        print("best: " + ", ".join(f".{k} {v:.2f} s" for k, v in best.items()) + f" (goal < {GOAL:.0f} s)")
        return 0 if max(best.values()) < GOAL else 1


if __name__ == "__main__":
    raise SystemExit(main())
