"""The sender: a take replayed in real time over UDP (``stream``), for tests
and demonstrations of the live loop.

Each sample is sent when its time comes (the take's own times, or the take
resampled to ``rate``), as the datagrams of :func:`~.protocol.sample_datagrams`
with the sample's number, the keys of the take's metadata
(:data:`~.protocol.META_ANNOUNCE`) and the metadata itself (``devices``,
``height_m``, ``floor_y``, ``role``, the offsets), all under
``/dancing_points/...``, which other VMC receivers ignore. The metadata goes
with every sample of the first :data:`META_EVERY_SAMPLE_S` seconds (the
receiver's calibration window and its wait for metadata: a lossy link loses
all of them only with a vanishing chance), then every :data:`META_EVERY_S`
seconds (for a receiver started later); the keys go with every sample, so
that a receiver knows what it has yet to hear.
``drop``: a share of the datagrams left unsent on purpose (seeded), to test
how the receiver takes lost packets.
"""
from __future__ import annotations

import random
import socket
import time

import numpy as np

from ..errors import UserError
from ..formats.take import Take
from .protocol import META_KEYS, sample_datagrams
from .stream_meta import META_WAIT_S
from .options import LiveOptions

# past the receiver's calibration window and its wait for announced metadata, with a second to spare
META_EVERY_SAMPLE_S = LiveOptions.calibration_s + META_WAIT_S + 1.0
META_EVERY_S = 0.25
SPIN_S = 0.0001  # a sample is waited for by sleeping up to this before its time, then spinning


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
                bundle: bool = True, clock=time.perf_counter, sleep=time.sleep, progress=None,
                source_port: int = 0) -> dict:
    """Send ``take`` to ``host:port`` in real time; returns ``{"sent", "samples",
    "dropped", "seconds", "errors", "source_port"}`` (datagrams sent, samples,
    datagrams left out on purpose, wall time, sends the system refused, the
    port it sent from: the receiver names a sender by it; ``source_port``: send
    from this port, 0: any). ``progress(sent)`` is
    called about once a second."""
    times, pos, quats = stream_rows(take, rate)
    if len(times) < 1:
        return {"sent": 0, "samples": 0, "dropped": 0, "seconds": 0.0, "errors": 0, "source_port": 0}
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0 / 30.0
    period = float(times[-1]) + step  # a loop starts again one sample after the end
    meta = {k: str(v) for k, v in take.meta.items() if k in META_KEYS}
    meta.setdefault("devices", "joints")  # SPEC §3's default: a take without it carries the §2 points
    keys = tuple(meta)
    per_meta = max(1, int(round(META_EVERY_S / step)))
    rng = random.Random(seed)
    sent = dropped = errors = n = 0
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if source_port:
        try:
            sock.bind(("", int(source_port)))
        except OSError as exc:
            sock.close()
            raise UserError(f"cannot send from UDP port {source_port}: {exc.strerror or exc}") from None
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
            if wait > SPIN_S:  # sleep, then spin the last fraction of a millisecond (high rates: not a core busy)
                sleep(wait - SPIN_S)
            while clock() < start + rel:
                pass
            with_meta = rel < META_EVERY_SAMPLE_S or n % per_meta == 0
            dgrams = sample_datagrams(fmt, n, rel, pos[i], quats[i], meta if with_meta else None, bundle, keys)
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
        try:
            source = sock.getsockname()[1]  # the port it sent from (0: it sent nothing)
        except OSError:
            source = 0
        sock.close()
    return {"sent": sent, "samples": n, "dropped": dropped, "seconds": clock() - start, "errors": errors,
            "source_port": source}
