"""Three-point takes (SPEC §3): the leader's head and two hand devices over time."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DEVICES = ("head", "lhand", "rhand")


@dataclass
class Take:
    """``time (T,)`` seconds; ``positions (T, 3, 3)`` metres, motion space, device
    order head/lhand/rhand; ``quats (T, 3, 4)`` device-to-world ``(w, x, y, z)``.
    A device that lost tracking on a row has NaN in its position and quaternion.
    """

    time: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    meta: dict = field(default_factory=dict)
    source: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """``(T, 3)`` bool: device tracked on that row."""
        return np.isfinite(self.positions).all(-1) & np.isfinite(self.quats).all(-1)

    @property
    def height(self):
        h = self.meta.get("height_m")
        return float(h) if h not in (None, "") else None
