"""Benchmark: the frame loop's cost against an earlier build, side by side.

    .venv/bin/python benchmarks/bench_frame_loop_vs.py [--base 5502a28] [--rounds 3]

Checks out ``--base`` (default 5502a28: the end of the first build, the
paper's three networks alone) in a temporary ``git worktree`` and runs, in
this tree and in that one, alternating round by round so that both see the
same machine, ``python -m dancing_points_addon synthesize`` on one core (ONNX
Runtime, OpenMP and BLAS on one thread; pinned to one CPU where ``taskset``
exists) of

* a whole salsa take (the leader of CMU take 08 as AMC, 1,711 frames at 30 Hz),
* a short take (the first 2 s of the embedded sample take),

each build with its own networks. The short take's time (start-up, model
loading, writing) is subtracted: per character-frame = (long − short) /
(frames long − frames short) / 2. Prints every round, the medians and their
ratio (this tree / the base). Not collected by pytest.
"""
import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"
SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _short_take(path, seconds=2.0):
    """The sample take's first ``seconds`` (its header and comment lines kept)."""
    lines = SAMPLE.read_text(encoding="utf-8").splitlines()
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("time")]
    rows = [ln for ln in lines if ln and not ln.startswith("#") and not ln.startswith("time")]
    t0 = float(rows[0].split(",", 1)[0])
    keep = [r for r in rows if float(r.split(",", 1)[0]) - t0 < seconds]
    path.write_text("\n".join(head + keep) + "\n", encoding="utf-8")


def _run(tree, args, out):
    cmd = [sys.executable, "-m", "dancing_points_addon", "synthesize", *args, "-o", str(out), "--threads", "1"]
    if shutil.which("taskset"):
        cmd = ["taskset", "-c", "0", *cmd]
    env = {**os.environ, **ONE_THREAD, "PYTHONPATH": str(tree)}
    t = time.perf_counter()
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    dt = time.perf_counter() - t
    with np.load(out) as z:
        return dt, len(z["time"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="5502a28", help="the build to compare with (a commit of this repository)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    long_args = [str(SALSA / "60_08.amc"), "--asf", str(SALSA / "60.asf")]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        base = tmp / "base"
        subprocess.run(["git", "worktree", "add", "--detach", "-q", str(base), args.base], cwd=ROOT, check=True)
        try:
            short = tmp / "short.csv"
            _short_take(short)
            per = {"this tree": [], args.base: []}
            for r in range(args.rounds):
                for name, tree in (("this tree", ROOT), (args.base, base)):
                    t_long, n_long = _run(tree, long_args, tmp / "long.npz")
                    t_short, n_short = _run(tree, [str(short)], tmp / "short.npz")
                    ms = 1000.0 * (t_long - t_short) / (n_long - n_short) / 2.0
                    per[name].append(ms)
                    print(f"round {r + 1} {name:>10}: whole take {t_long:.2f} s ({n_long} frames), short take "
                          f"{t_short:.2f} s ({n_short} frames): {ms:.3f} ms per character-frame", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)
    a, b = np.median(per["this tree"]), np.median(per[args.base])
    print(f"median per character-frame: this tree {a:.3f} ms, {args.base} {b:.3f} ms; ratio {a / b:.2f}")


if __name__ == "__main__":
    main()
