"""Live at any input rate: ``live`` fed by ``stream`` at each rate, on an idle
machine and with one core kept busy by another process; prints, per run, the
latency from a packet's arrival to its duet frame after the first seconds
(median, 99th percentile), samples lost, the input rate the status showed, the
live process's memory while it records (resident, after 5 s and at the end;
the take's rows grow it by about 185 bytes a sample) and,
with ``--check``, the largest difference between the live duet and
``synthesize`` of the kept take.

With ``--rounds N`` each load runs the rates N times, in turn forwards and
backwards (72, 250, 500, 1,000, then 1,000 … 72), so that every rate sees the
machine as the others do (a shared machine's tail latency drifts by half
within minutes); it then prints, per rate, the median over the rounds of its
99th percentile and that median's ratio to the first rate's, beside each
round's own ratios.

    .venv/bin/python benchmarks/bench_live_rate.py [--rates 72,250,500,1000] [--seconds 60] [--load idle,busy]
        [--rounds 1] [--check]
"""
from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
PY = sys.executable
LATENCY = re.compile(r"after the calibration's catch-up: median ([\d.na]+) ms, 99th percentile ([\d.na]+) ms")
RECEIVED = re.compile(r"lost on the way (\d+) samples")
WROTE = re.compile(r"\((\d+) rows, ([\d.]+) s, (\d+) samples a second\)")
STATUS_RATE = re.compile(r"\| in (\d+) Hz")
SPEC_KEYS = ("leader_positions", "leader_rotations", "follower_positions", "follower_rotations")


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def run(rate: float, seconds: float, busy: bool, check: bool, work: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    hog = subprocess.Popen([PY, "-c", "while True: pass"]) if busy else None
    out = work / f"live_{int(rate)}_{'busy' if busy else 'idle'}.npz"
    port = _free_port()
    live = subprocess.Popen([PY, "-m", "dancing_points_addon", "live", "--bind", "127.0.0.1", "--port", str(port),
                             "--duration", str(seconds), "-o", str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        while "listening" not in line:
            line = live.stdout.readline()
            if not line:
                raise SystemExit(live.stderr.read())
        sender = subprocess.Popen([PY, "-m", "dancing_points_addon", "stream", str(SAMPLE), "--port", str(port),
                                   "--rate", f"{rate:g}", "--loop", "--duration", str(seconds + 3)], cwd=ROOT, env=env,
                                  stdout=subprocess.DEVNULL)
        rss = []  # (seconds since the stream started, resident MB) while recording (not the writing at the end)
        t0 = time.perf_counter()
        while live.poll() is None and time.perf_counter() - t0 < seconds + 60:
            time.sleep(1.0)
            if time.perf_counter() - t0 < seconds:
                rss.append((time.perf_counter() - t0, _rss_mb(live.pid)))
        stdout, stderr = live.communicate(timeout=300)
        sender.wait(timeout=30)
    finally:
        for p in (live, hog):
            if p is not None and p.poll() is None:
                p.kill()
    if live.returncode != 0:
        raise SystemExit(stderr)
    med, p99 = (float(v) for v in LATENCY.search(stdout).groups())
    rows, span, mean_rate = WROTE.search(stdout).groups()
    rates = [int(v) for v in STATUS_RATE.findall(stdout)]
    rss = [m for t, m in rss if np.isfinite(m)]
    res = {"rate": rate, "load": "busy" if busy else "idle", "p50_ms": med, "p99_ms": p99,
           "lost": int(RECEIVED.search(stdout).group(1)), "rows": int(rows), "seconds": float(span),
           "status_hz": rates[1:] or rates, "rss_mb": (rss[min(4, len(rss) - 1)], rss[-1]) if rss else (0, 0)}
    if check:
        off = work / "offline.npz"
        subprocess.run([PY, "-m", "dancing_points_addon", "synthesize", str(out.with_suffix(".csv")), "-o", str(off)],
                       cwd=ROOT, env=env, check=True, capture_output=True)
        a, b = np.load(out), np.load(off)
        res["duet_vs_synthesize"] = max(float(np.max(np.abs(a[k] - b[k]))) for k in SPEC_KEYS)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rates", default="72,250,500,1000")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--load", default="idle,busy", help="idle, busy (one core kept busy by another process), or both")
    ap.add_argument("--check", action="store_true", help="also synthesize each kept take and compare the duets")
    ap.add_argument("--rounds", type=int, default=1, help="runs of every rate, in turn forwards and backwards")
    args = ap.parse_args()
    print(f"{os.cpu_count()} cores; load average before: {os.getloadavg()[0]:.2f}", flush=True)
    rates = [float(r) for r in args.rates.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        for load in args.load.split(","):
            p99 = {rate: [] for rate in rates}
            for rnd in range(max(1, args.rounds)):
                for rate in (rates if rnd % 2 == 0 else rates[::-1]):
                    r = run(rate, args.seconds, load == "busy", args.check, Path(tmp))
                    p99[rate].append(r["p99_ms"])
                    d = r.get("duet_vs_synthesize")
                    extra = "" if d is None else f", live duet vs synthesize {d:g}"
                    print(f"{r['rate']:6g} Hz {r['load']}: latency after the first seconds median {r['p50_ms']:.1f} "
                          f"ms, p99 {r['p99_ms']:.1f} ms; lost {r['lost']}; {r['rows']} rows in {r['seconds']:.1f} s; "
                          f"status input rate {r['status_hz']} Hz; memory while recording {r['rss_mb'][0]:.0f} MB at "
                          f"5 s, {r['rss_mb'][1]:.0f} MB at the end (the take's rows: "
                          f"{r['rows'] * 185 / 2**20:.0f} MB)"
                          f"{extra}; load average {os.getloadavg()[0]:.2f}", flush=True)
            if args.rounds > 1:
                base = np.array(p99[rates[0]])
                for rate in rates:
                    v = np.array(p99[rate])
                    print(f"{rate:6g} Hz {load}: p99 over {len(v)} rounds {', '.join(f'{x:.1f}' for x in v)} ms, "
                          f"median {np.median(v):.1f} ms, {np.median(v) / np.median(base):.2f} x the {rates[0]:g} Hz "
                          f"median (per round: {', '.join(f'{x:.2f}' for x in v / base)})", flush=True)

if __name__ == "__main__":
    main()
