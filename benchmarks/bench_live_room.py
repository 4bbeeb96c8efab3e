"""Live in a room of senders: ``live`` on one port, the dancer (the sample
take, 72 Hz, 8 s) and N - 1 other senders (other takes at 72-1,000 Hz: CMU
salsa 61_10's follower, a CMU solo take, the sample take 1 m aside), each a
``stream`` process; ``--chosen``: the dancer named with ``--sender`` and half
the others started before it, else all of them after it. Prints whether the
kept take is the dancer's (largest difference from the rows sent), whether
every other sender is named once with its packets, and the largest
difference between the live duet and ``synthesize`` of the kept take.

    .venv/bin/python benchmarks/bench_live_room.py [--senders 5] [--format vmc|osc] [--chosen]
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dancing_points_addon.formats.asf_amc import load_amc  # noqa: E402
from dancing_points_addon.formats.take import Take, take_from_motion, take_to_text  # noqa: E402
from dancing_points_addon.formats.take_read import read_take  # noqa: E402
from dancing_points_addon.live.stream import stream_rows  # noqa: E402
from bench_live_rate import _free_port  # noqa: E402  (beside this script)

SHARED = Path(os.environ.get("DP_SHARED", ROOT.parent / "shared"))
SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
PY = sys.executable
SPEC_KEYS = ("leader_positions", "leader_rotations", "leader_contacts", "follower_positions", "follower_rotations",
             "follower_contacts")
RATES = (500, 1000, 72, 250)


def _other_takes(work: Path) -> list:
    """Other dancers' takes, written as take files."""
    tk = read_take(SAMPLE)
    takes = {"her": take_from_motion(load_amc(SHARED / "data" / "cmu_salsa" / "61_10.amc")),
             "solo": take_from_motion(load_amc(sorted((SHARED / "data" / "cmu_solo_dance").glob("*.amc"))[0])),
             "aside": Take(tk.time, tk.positions + np.array([1.0, 0.0, 0.0]), tk.quats, dict(tk.meta))}
    paths = []
    for name, take in takes.items():
        (work / f"{name}.csv").write_text(take_to_text(take))
        paths.append(work / f"{name}.csv")
    return paths + paths  # (more senders than takes: the same take again, from another sender)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--senders", type=int, default=5, help="senders in all, the dancer's included (2-7)")
    ap.add_argument("--format", choices=("vmc", "osc"), default="vmc")
    ap.add_argument("--chosen", action="store_true", help="name the dancer with --sender; others start before too")
    args = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        others = _other_takes(work)
        port, source = _free_port(), _free_port()
        out = work / "live.npz"
        live = subprocess.Popen([PY, "-m", "dancing_points_addon", "live", "--bind", "127.0.0.1", "--port", str(port),
                                 "--format", args.format, "-o", str(out),
                                 *(("--sender", f"127.0.0.1:{source}") if args.chosen else ())],
                                cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while "listening" not in live.stdout.readline():
            if live.poll() is not None:
                raise SystemExit(live.stderr.read())

        def stream(take, rate, seconds, *extra):
            return subprocess.Popen([PY, "-m", "dancing_points_addon", "stream", str(take), "--port", str(port),
                                     "--format", args.format, "--rate", str(rate), "--duration", str(seconds), *extra],
                                    cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)

        n_other = args.senders - 1
        before = n_other // 2 if args.chosen else 0
        procs = []
        for i in range(before):
            procs.append(stream(others[i], RATES[i % len(RATES)], 12))
            time.sleep(0.3)
        dancer = stream(SAMPLE, 72, 8, "--source-port", str(source))
        time.sleep(0.5)
        for i in range(before, n_other):
            procs.append(stream(others[i], RATES[i % len(RATES)], 6))
            time.sleep(0.3)
        outs = [p.communicate()[0] for p in [dancer, *procs]]
        time.sleep(0.5)
        live.send_signal(signal.SIGINT)
        stdout, stderr = live.communicate()
        if live.returncode != 0:
            raise SystemExit(stderr)
        print(stdout)
        sent = [(int(re.search(r"from port (\d+)", o).group(1)), int(re.search(r"sent (\d+) packets", o).group(1)))
                for o in outs]
        named = sorted((int(a), int(b)) for a, b in
                       re.findall(r"^  ignored sender 127\.0\.0\.1:(\d+): (\d+) packets$", stdout, re.M))
        kept = read_take(out.with_suffix(".csv"))
        _, pos, _ = stream_rows(read_take(SAMPLE), 72.0)
        diff = float(np.nanmax(np.abs(kept.positions - pos[:kept.n_frames])))
        off = work / "offline.npz"
        subprocess.run([PY, "-m", "dancing_points_addon", "synthesize", str(out.with_suffix(".csv")), "-o", str(off)],
                       cwd=ROOT, env=env, check=True, capture_output=True)
        a, b = np.load(out), np.load(off)
        duet = max(float(np.max(np.abs(a[k] - b[k]))) for k in SPEC_KEYS)
        order = f"--sender, {before} before" if args.chosen else "all after"
        print(f"{args.senders} senders ({args.format}, {order} the dancer): the dancer sent {sent[0][1]} "
              f"samples, the take kept {kept.n_frames} rows, largest "
              f"difference from the rows sent {diff:.2g} m; other senders named once each with their packets: "
              f"{named == sorted(sent[1:])} ({named}); live duet vs synthesize of the kept take {duet:g}")


if __name__ == "__main__":
    main()
