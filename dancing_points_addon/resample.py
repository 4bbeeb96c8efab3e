"""Resampling to the networks' rate (SPEC §1), vectorised.

Output frame ``k`` lies at ``t0 + k / fps`` for every ``k`` with
``t0 + k / fps <= t_last`` (``t0``, ``t_last``: the input's first and last
times). Positions are interpolated linearly, rotations by slerp (shortest arc).
"""
from __future__ import annotations

import numpy as np

from .rotations import matrix_to_quat, quat_slerp, quat_to_matrix
from .skeleton import Motion
from .formats.take import Take

NET_FPS = 30.0
_EPS = 1e-9  # relative tolerance: an output time this close to an input row is on it


def output_times(time: np.ndarray, fps: float = NET_FPS) -> np.ndarray:
    """``t0 + k / fps`` for every ``k`` with ``t0 + k / fps <= t_last``."""
    time = np.asarray(time, dtype=np.float64)
    if fps <= 0 or not np.isfinite(fps):
        raise ValueError(f"fps must be positive, got {fps}")
    t0, t1 = float(time[0]), float(time[-1])
    tol = _EPS * max(1.0, abs(t0), abs(t1))
    n = int(np.floor((t1 - t0 + tol) * fps)) + 1
    k = np.arange(max(n, 1))
    # Guard against floor() rounding either way.
    out = t0 + k / fps
    return out[out <= t1 + tol]


def bracket(time: np.ndarray, t_out: np.ndarray):
    """Input rows ``i, i + 1`` around each output time and the weight ``a`` of
    row ``i + 1`` (in [0, 1]). Requires at least 2 strictly increasing times."""
    time = np.asarray(time, dtype=np.float64)
    tol = _EPS * max(1.0, float(np.abs(time[[0, -1]]).max()))
    i = np.searchsorted(time, t_out + tol, side="right") - 1
    i = np.clip(i, 0, len(time) - 2)
    a = (t_out - time[i]) / (time[i + 1] - time[i])
    a = np.clip(a, 0.0, 1.0)
    # Snap output times that coincide with an input row onto it.
    a = np.where(np.abs(t_out - time[i]) <= tol, 0.0, a)
    a = np.where(np.abs(t_out - time[i + 1]) <= tol, 1.0, a)
    return i, a


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
    t_out = output_times(time, fps)
    i, a = bracket(time, t_out)
    valid = take.valid  # (T, 3)
    pos = np.where(valid[..., None], take.positions, 0.0)
    quat = np.where(valid[..., None], take.quats, np.array([1.0, 0.0, 0.0, 0.0]))
    a3 = a[:, None]  # per device
    ok = (valid[i] | (a3 >= 1.0)) & (valid[i + 1] | (a3 <= 0.0))
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
    time = motion.times
    t_out = output_times(time, fps)
    i, a = bracket(time, t_out)
    pos = _lerp(motion.positions[i], motion.positions[i + 1], a[:, None, None])
    quats = matrix_to_quat(motion.rotations)
    q = quat_slerp(quats[i], quats[i + 1], np.broadcast_to(a[:, None], (len(a), quats.shape[1])))
    rot = quat_to_matrix(q)
    # Frames on an input row keep its exact matrices (no round trip through quaternions).
    on0, on1 = a <= 0.0, a >= 1.0
    rot[on0] = motion.rotations[i[on0]]
    rot[on1] = motion.rotations[i[on1] + 1]
    return Motion(pos, rot, float(fps), motion.bone_vectors, motion.source, dict(motion.meta))
