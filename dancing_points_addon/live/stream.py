"""The sender: a take replayed in real time over UDP (``stream``), for tests
and demonstrations of the live loop.

Each sample is sent when its time comes (the take's own times, or the take
resampled to ``rate``), as the datagrams of :func:`~.protocol.sample_datagrams`
with the sample's number and, with the first sample and then once a second,
the take's metadata (``devices``, ``height_m``, ``floor_y``, ``role``, the
offsets) under ``/dancing_points/meta``, which other VMC receivers ignore.
``drop``: a share of the datagrams left unsent on purpose (seeded), to test
how the receiver takes lost packets.
"""
from __future__ import annotations

import random
import socket
import time

import numpy as np

from ..formats.take import Take
from .protocol import META_KEYS, sample_datagrams


def stream_rows(take: Take, rate: float | None = None):
    """``(times from 0, positions, quats)`` to send: the take's rows, or the
    take resampled to ``rate`` Hz (SPEC §1 resampling; lost devices stay lost)."""
    if rate:
        from ..resample import resample_take
        take = resample_take(take, float(rate))
    t = np.asarray(take.time, dtype=np.float64)
    return t - t[0], np.asarray(take.positions), np.asarray(take.quats)


def stream_take(take: Take, port: int, host: str = "127.0.0.1", fmt: str = "vmc", rate: float | None = None,
                loop: bool = False, duration: float | None = None, drop: float = 0.0, seed: int = 0,
                bundle: bool = True, clock=time.perf_counter, sleep=time.sleep, progress=None) -> dict:
    """Send ``take`` to ``host:port`` in real time; returns ``{"sent", "samples",
    "dropped", "seconds", "errors"}`` (datagrams sent, samples, datagrams left
    out on purpose, wall time, sends the system refused). ``progress(sent)`` is
    called about once a second."""
    times, pos, quats = stream_rows(take, rate)
    if len(times) < 1:
        return {"sent": 0, "samples": 0, "dropped": 0, "seconds": 0.0, "errors": 0}
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0 / 30.0
    period = float(times[-1]) + step  # a loop starts again one sample after the end
    meta = {k: str(v) for k, v in take.meta.items() if k in META_KEYS}
    meta.setdefault("devices", "joints")  # SPEC §3's default: a take without it carries the §2 points
    per_meta = max(1, int(round(1.0 / step)))
    rng = random.Random(seed)
    sent = dropped = errors = n = 0
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start = clock()
    next_progress = start + 1.0
    try:
        while True:
            i = n % len(times)
            if n and i == 0 and not loop:
                break
            rel = (n // len(times)) * period + float(times[i])
            if duration is not None and rel > duration:
                break
            wait = start + rel - clock()
            if wait > 0.002:
                sleep(wait - 0.001)
            while clock() < start + rel:
                pass
            dgrams = sample_datagrams(fmt, n, rel, pos[i], quats[i], meta if n % per_meta == 0 else None, bundle)
            for d in dgrams:
                if drop and rng.random() < drop:
                    dropped += 1
                    continue
                try:
                    sock.sendto(d, (host, port))
                    sent += 1
                except OSError:
                    errors += 1
            n += 1
            if progress is not None and clock() >= next_progress:
                next_progress += 1.0
                progress(sent)
    finally:
        sock.close()
    return {"sent": sent, "samples": n, "dropped": dropped, "seconds": clock() - start, "errors": errors}
