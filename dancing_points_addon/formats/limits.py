"""Bounds on what an input may be (a few hours of a dancer at a plausible rate
and height), checked by every reader before anything the size of the take's
duration is allocated, and by :func:`~..inputs.check_take`. Imports no numpy:
:mod:`..argtypes` shares these bounds before numpy may load (the benchmark's
one BLAS thread is set then)."""
from __future__ import annotations

import math

from ..errors import InputError

MAX_DURATION_S = 4 * 3600.0  # a take may span at most 4 hours (432,000 frames at 30 Hz)
MAX_GAP_S = 10.0  # rows more than 10 s apart are bad input, not a gap to interpolate over
MAX_ABS_TIME_S = 1e10  # |time| in seconds; the Unix epoch (~1.7e9 s) fits, milliseconds do not
INPUT_FPS_RANGE = (1.0, 1000.0)  # Hz: --input-fps, a BVH's Frame Time, a rig's frame rate
HEIGHT_RANGE_M = (0.5, 3.0)  # metres: --height and a take's height_m (as argtypes.height_metres)
FLOOR_RANGE_M = 1.0  # a floor given (take, option, setting) or estimated lies within this many metres of y = 0


def check_rate(path, fps, line=None, what="input frame rate") -> float:
    """``fps`` as a float when it is within :data:`INPUT_FPS_RANGE`, else an
    :class:`InputError` naming ``path`` (and ``line``)."""
    lo, hi = INPUT_FPS_RANGE
    try:
        v = float(fps)
    except (TypeError, ValueError):
        raise InputError(path, f"{what} is not a number: {fps!r}", line) from None
    if not v > 0:
        raise InputError(path, f"{what} must be positive, got {v:g}", line)
    if not lo <= v <= hi:
        raise InputError(path, f"{what} must be between {lo:g} and {hi:g} Hz, got {v:g}", line)
    return v


def check_height(path, height, line=None, what="height") -> float:
    """A dancer's height in metres within :data:`HEIGHT_RANGE_M` (the range of
    ``--height``), else an :class:`InputError` naming ``path`` (and ``line``)."""
    lo, hi = HEIGHT_RANGE_M
    try:
        h = float(height)
    except (TypeError, ValueError):
        raise InputError(path, f"{what} is not a number: {height!r}", line) from None
    if not (math.isfinite(h) and lo <= h <= hi):
        raise InputError(path, f"{what} must be between {lo:g} and {hi:g} m, got {h:g}", line)
    return h


def check_duration(path, seconds, line=None, what="the take") -> None:
    """An :class:`InputError` when ``seconds`` exceeds :data:`MAX_DURATION_S`."""
    if not seconds <= MAX_DURATION_S:
        raise InputError(path, f"{what} spans {seconds:.6g} s, more than the maximum of "
                               f"{MAX_DURATION_S / 3600:g} hours (split it)", line)
