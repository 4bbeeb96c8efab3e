"""Resampling to the networks' rate (SPEC §1), vectorised.

Output frame ``k`` lies at ``t0 + k / fps`` for every ``k`` with
``t0 + k / fps <= t_last`` (``t0``, ``t_last``: the input's first and last
times). Positions are interpolated linearly, rotations by slerp (shortest arc).
All of it is computed in time relative to ``t0`` (``k / fps`` against
``t - t0``), so an absolute clock such as seconds since the Unix epoch gives
the same frames as the same take starting at 0.
"""
from __future__ import annotations

import numpy as np

from .rotations import matrix_to_quat, quat_slerp, quat_to_matrix
from .skeleton import Motion
from .features import FPS as NET_FPS  # the networks' frame rate: what takes are resampled to
from .formats.take import Take

_EPS = 1e-9  # relative to the take's duration (at least 1 s): an output time this close to a row is on it
_ULPS = 16  # ... or this many units in the last place of the take's largest |time|: the times' own resolution


def _tolerance(time: np.ndarray) -> float:
    """How close (seconds) an output time must be to an input row to be on it.

    Relative to the take's duration, not to ``|t|``: a take logged in seconds
    since the Unix epoch (``t ≈ 1.7e9``) resamples like the same take starting
    at 0; only the resolution of the time values themselves (a few units in the
    last place, ~2.4e-7 s at 1.7e9 s) widens it."""
    t0, t1 = float(time[0]), float(time[-1])
    return max(_EPS * max(1.0, t1 - t0), _ULPS * float(np.spacing(max(abs(t0), abs(t1)))))


def output_offsets(time: np.ndarray, fps: float = NET_FPS) -> np.ndarray:
    """``k / fps`` for every ``k`` with ``t0 + k / fps <= t_last``: the output
    times relative to the first input row (exact, whatever ``t0`` is)."""
    time = np.asarray(time, dtype=np.float64)
    if fps <= 0 or not np.isfinite(fps):
        raise ValueError(f"fps must be positive, got {fps}")
    span = float(time[-1] - time[0])
    tol = _tolerance(time)
    n = int(np.floor((span + tol) * fps)) + 1
    k = np.arange(max(n, 1))
    # Guard against floor() rounding either way.
    out = k / fps
    return out[out <= span + tol]


def output_times(time: np.ndarray, fps: float = NET_FPS) -> np.ndarray:
    """``t0 + k / fps`` for every ``k`` with ``t0 + k / fps <= t_last``."""
    time = np.asarray(time, dtype=np.float64)
    return time[0] + output_offsets(time, fps)


def _bracket_rel(rel: np.ndarray, out: np.ndarray, tol: float):
    """:func:`bracket` on times relative to the first row (``rel[0] == 0``)."""
    i = np.searchsorted(rel, out + tol, side="right") - 1
    i = np.clip(i, 0, len(rel) - 2)
    a = (out - rel[i]) / (rel[i + 1] - rel[i])
    a = np.clip(a, 0.0, 1.0)
    # Snap output times that coincide with an input row onto it.
    a = np.where(np.abs(out - rel[i]) <= tol, 0.0, a)
    a = np.where(np.abs(out - rel[i + 1]) <= tol, 1.0, a)
    return i, a


def bracket(time: np.ndarray, t_out: np.ndarray):
    """Input rows ``i, i + 1`` around each output time and the weight ``a`` of
    row ``i + 1`` (in [0, 1]). Requires at least 2 strictly increasing times.
    Works in time relative to the first row (see :func:`output_offsets`)."""
    time = np.asarray(time, dtype=np.float64)
    t0 = time[0]
    return _bracket_rel(time - t0, np.asarray(t_out, dtype=np.float64) - t0, _tolerance(time))


def resample_plan(time: np.ndarray, fps: float = NET_FPS):
    """``(t_out, i, a)``: the output times of :func:`output_times` and their
    :func:`bracket`, computed relative to the first row (exact for epoch times)."""
    time = np.asarray(time, dtype=np.float64)
    off = output_offsets(time, fps)
    i, a = _bracket_rel(time - time[0], off, _tolerance(time))
    return time[0] + off, i, a


def tracked_after_resampling(valid: np.ndarray, i: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``(T_out, D)`` bool: device tracked on each output frame (a gap stays a
    gap: lost when an input row it interpolates from, weight > 0, is lost)."""
    a3 = a[:, None]
    return (valid[i] | (a3 >= 1.0)) & (valid[i + 1] | (a3 <= 0.0))


def _lerp(x0, x1, a):
    return x0 + (x1 - x0) * a


def resample_take(take: Take, fps: float = NET_FPS) -> Take:
    """``take`` at ``fps`` (SPEC §1). A tracking gap stays a gap: an output frame
    is lost for a device when an input row it interpolates from (weight > 0) is
    lost for that device; an output frame on an input row uses that row only."""
    time = np.asarray(take.time, dtype=np.float64)
    if time.shape[0] < 2:
        return Take(time.copy(), np.array(take.positions, dtype=np.float64),
                    np.array(take.quats, dtype=np.float64), dict(take.meta), take.source)
    t_out, i, a = resample_plan(time, fps)
    valid = take.valid  # (T, 3)
    pos = np.where(valid[..., None], take.positions, 0.0)
    quat = np.where(valid[..., None], take.quats, np.array([1.0, 0.0, 0.0, 0.0]))
    a3 = a[:, None]  # per device
    ok = tracked_after_resampling(valid, i, a)
    p = _lerp(pos[i], pos[i + 1], a3[..., None])
    q = quat_slerp(quat[i], quat[i + 1], np.broadcast_to(a3, ok.shape))
    p[~ok] = np.nan
    q[~ok] = np.nan
    return Take(t_out, p, q, dict(take.meta), take.source)


def resample_motion(motion: Motion, fps: float = NET_FPS) -> Motion:
    """``motion`` at ``fps``: joint positions linear, global rotations by slerp."""
    T = motion.n_frames
    if T < 2 or float(motion.fps) == float(fps):  # nothing to interpolate
        return Motion(np.array(motion.positions), np.array(motion.rotations), float(motion.fps),
                      motion.bone_vectors, motion.source, dict(motion.meta))
    _, i, a = resample_plan(motion.times, fps)
    pos = _lerp(motion.positions[i], motion.positions[i + 1], a[:, None, None])
    quats = matrix_to_quat(motion.rotations)
    q = quat_slerp(quats[i], quats[i + 1], np.broadcast_to(a[:, None], (len(a), quats.shape[1])))
    rot = quat_to_matrix(q)
    # Frames on an input row keep its exact matrices (no round trip through quaternions).
    on0, on1 = a <= 0.0, a >= 1.0
    rot[on0] = motion.rotations[i[on0]]
    rot[on1] = motion.rotations[i[on1] + 1]
    return Motion(pos, rot, float(fps), motion.bone_vectors, motion.source, dict(motion.meta))
