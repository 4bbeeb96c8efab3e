"""What a live session is told (:class:`LiveOptions`) and what it leaves
(:class:`LiveResult`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..formats.take import Take

SOURCE_DEVICES = {"vmc": "openxr", "osc": "joints", "xr": "openxr"}


@dataclass(frozen=True)
class LiveOptions:
    """What a live session is told. ``source``: ``vmc``, ``osc`` or ``xr``
    (Blender's VR session); ``height`` (m) and ``floor_y`` (m): given, or None
    (the stream's metadata, else estimated from the first ``calibration_s``
    seconds); ``devices``: SPEC §3 devices of the poses (None: the stream's
    metadata, else :data:`SOURCE_DEVICES`); ``role``: whose points these are
    (SPEC §3; None: the stream's ``role``, else ``leader``); ``gap_s``: a
    device unheard for longer is lost; ``record_predictions``: keep the mapping's predictions and the planted
    feet (for Blender's method view)."""

    source: str = "vmc"
    height: float | None = None
    floor_y: float | None = None
    devices: str | None = None
    head_offset: tuple | None = None
    hand_offset: tuple | None = None
    head_turn: tuple | None = None
    hand_turn: tuple | None = None
    role: str | None = None
    calibration_s: float = 1.0
    gap_s: float = 0.1
    models: str | None = None
    threads: int = 1
    foot_lock: bool = True
    hand_ik: bool = True
    follow_devices: bool = True
    record_predictions: bool = False

    def synthesis_options(self):
        from ..synthesis_options import SynthesisOptions

        return SynthesisOptions(models=self.models, threads=self.threads, height=self.height,
                                foot_lock=self.foot_lock, hand_ik=self.hand_ik, floor_y=self.floor_y,
                                devices=self.devices, head_offset=self.head_offset, hand_offset=self.hand_offset,
                                head_turn=self.head_turn, hand_turn=self.hand_turn,
                                follow_devices=self.follow_devices, role=self.role)


@dataclass
class LiveResult:
    """What a session leaves: the ``take`` (its metadata reproduce the
    calibration), the ``duet`` synthesised from it (None when the take is too
    short for one) and the counters."""

    take: Take
    duet: object
    counters: dict
    latency_ms: tuple  # (median, 99th percentile) of the frames made live, or (nan, nan)
    steady_ms: tuple = (math.nan, math.nan)  # the same from a second after the calibration (caught up)


def ignored_senders_text(ignored) -> str:
    """``ignored 2 other senders (1,234 packets)`` of :meth:`~.senders.SenderGate.ignored`'s list."""
    n = len(ignored)
    return (f"ignored {n} other sender{'s' if n != 1 else ''} "
            f"({sum(p for _, p in ignored):,} packets)")
