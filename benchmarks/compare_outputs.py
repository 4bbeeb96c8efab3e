"""Check: the duets of this tree against an earlier build's, to the bit.

    .venv/bin/python benchmarks/compare_outputs.py --base 207248c [--takes 08,10]

Writes the inputs once, with this tree's take writer: the embedded sample take
and, per salsa take (SPEC §6 test frames, ``training.dataset.split_range``),
the leader's three points as a ``joints`` take, as a headset's ``openxr``
take (``inputs.load_headset_input``) and the follower's as a ``role=follower``
take. Then runs ``python -m dancing_points_addon synthesize`` on each in this
tree and in ``--base`` (checked out in a temporary ``git worktree``, with its
own networks) and prints, per input, the largest difference over every float
array of the two npz files (and the arrays only one of them has). Exits 1 when
any differs by more than ``--tol`` (default 1e-6 m, SPEC units). Not collected
by pytest.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SALSA = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared")) / "data" / "cmu_salsa"
SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def write_inputs(folder: pathlib.Path, takes) -> list:
    """The input files (see the module docstring), as paths."""
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.formats.take import Take, take_from_motion, write_take
    from dancing_points_addon.inputs import load_headset_input
    from training.dataset import split_range

    def test_frames(take, n60):
        a, _ = split_range(n60, "test")  # a 30 Hz frame index (of the take at 60 Hz, SPEC §5)
        t0 = a / 30.0
        keep = take.time - take.time[0] >= t0 - 1e-9
        return Take(take.time[keep] - take.time[keep][0], take.positions[keep], take.quats[keep], dict(take.meta))

    out = [SAMPLE]
    for no in takes:
        lead = load_amc(SALSA / f"60_{no}.amc")
        n60 = int(round(lead.n_frames * 60.0 / lead.fps))
        cases = {"joints": take_from_motion(lead),
                 "openxr": load_headset_input(str(SALSA / f"60_{no}.amc"), asf=str(SALSA / "60.asf"))}
        her = take_from_motion(load_amc(SALSA / f"61_{no}.amc"))
        her.meta["role"] = "follower"
        cases["follower"] = her
        for kind, take in cases.items():
            path = folder / f"{no}_{kind}.csv"
            write_take(path, test_frames(take, n60))
            out.append(path)
    return out


def synthesize(tree: pathlib.Path, src: pathlib.Path, out: pathlib.Path) -> dict:
    env = {**os.environ, **ONE_THREAD, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "dancing_points_addon", "synthesize", str(src), "-o", str(out), "--threads", "1"]
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    with np.load(out) as z:
        return {k: z[k] for k in z.files if z[k].dtype.kind == "f"}


def main(argv=None) -> int:
    from training.dataset import SALSA_TAKES

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the build to compare with (a commit of this repository)")
    ap.add_argument("--takes", default=",".join(SALSA_TAKES), help="salsa takes (default: all 13)")
    ap.add_argument("--tol", type=float, default=1e-6)
    args = ap.parse_args(argv)
    worst_all = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        base = tmp / "base"
        subprocess.run(["git", "worktree", "add", "--detach", "-q", str(base), args.base], cwd=ROOT, check=True)
        try:
            for src in write_inputs(tmp, [t.strip() for t in args.takes.split(",") if t.strip()]):
                a = synthesize(ROOT, src, tmp / "a.npz")
                b = synthesize(base, src, tmp / "b.npz")
                only = sorted(set(a) ^ set(b))
                worst = max((float(np.nanmax(np.abs(a[k] - b[k]))) if a[k].size else 0.0
                             for k in set(a) & set(b) if a[k].shape == b[k].shape), default=0.0)
                shapes = sorted(k for k in set(a) & set(b) if a[k].shape != b[k].shape)
                worst_all = max(worst_all, worst if not shapes else float("inf"))
                extra = (f"; only in one: {', '.join(only)}" if only else "") + \
                        (f"; shapes differ: {', '.join(shapes)}" if shapes else "")
                print(f"{src.name}: largest difference {worst:.3g}{extra}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)
    print(f"largest difference over all inputs: {worst_all:.3g} (tolerance {args.tol:g})")
    return 0 if worst_all <= args.tol else 1


if __name__ == "__main__":
    sys.exit(main())
