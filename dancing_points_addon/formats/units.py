"""Length units of motion and rig files, and the guess of a file's unit from
the size of its skeleton (BVH files, imported rigs)."""
from __future__ import annotations

import numpy as np

#: Length units to metres. ``'cmu'`` is the CMU ASF unit (``length 0.45``:
#: 1/0.45 inch), the unit of the popular CMU BVH conversion.
UNIT_SCALES = {
    "m": 1.0,
    "cmu": 0.0254 / 0.45,
    "inch": 0.0254,
    "cm": 0.01,
    "mm": 0.001,
}
#: Assumed body size for an automatic unit (metres).
TYPICAL_HEIGHT_M = 1.7


def unit_scale_for_height(height: float) -> float:
    """Factor to metres for a skeleton whose rest size is ``height`` in its own
    units: the unit of :data:`UNIT_SCALES` that makes it closest (on a log
    scale) to :data:`TYPICAL_HEIGHT_M`; 1 for a size that is not positive."""
    if not (np.isfinite(height) and height > 0):
        return 1.0
    return float(min(UNIT_SCALES.values(), key=lambda s: abs(np.log(height * s / TYPICAL_HEIGHT_M))))
