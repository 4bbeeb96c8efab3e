"""Rotation maths in numpy, vectorised over any leading axes.

Conventions (SPEC §1): quaternions are ``(w, x, y, z)``; matrices act on
column vectors (``v' = R @ v``); angles are radians unless a name says ``deg``.
"""
from __future__ import annotations

import numpy as np

_AXES = {"X": 0, "Y": 1, "Z": 2}


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about a principal axis, shape ``angle.shape + (3, 3)``."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(angle.shape + (3, 3))
    i = _AXES[axis.upper()]
    j, k = (i + 1) % 3, (i + 2) % 3
    out[..., i, i] = 1.0
    out[..., j, j] = c
    out[..., k, k] = c
    out[..., j, k] = -s
    out[..., k, j] = s
    return out


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """Compose rotations applied in ``order`` (first letter first).

    ``angles[..., i]`` is the angle about axis ``order[i]``. With column vectors
    the result is ``R[order[-1]] @ ... @ R[order[0]]``: the ASF/AMC ``dof`` and
    ``axis`` convention and BVH channel order read right to left as applied.
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = None
    for i, ax in enumerate(order):
        r = axis_rotation(ax, angles[..., i])
        out = r if out is None else r @ out
    if out is None:
        out = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    return out


def matrix_to_euler(m: np.ndarray, order: str) -> np.ndarray:
    """Inverse of :func:`euler_to_matrix` for a 3-letter order of distinct axes.

    Returns angles with ``euler_to_matrix(angles, order) == m``. Works for any
    permutation of XYZ (Tait-Bryan); the middle angle lies in [-pi/2, pi/2].
    """
    m = np.asarray(m, dtype=np.float64)
    i, j, k = (_AXES[a] for a in order.upper())
    # R = R_k(c) R_j(b) R_i(a); parity of the permutation decides signs.
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    sb = np.clip(-sign * m[..., k, i], -1.0, 1.0)
    b = np.arcsin(sb)
    a = np.arctan2(sign * m[..., k, j], m[..., k, k])
    c = np.arctan2(sign * m[..., j, i], m[..., i, i])
    # Gimbal lock: cos(b) ~ 0 -> c = 0 and a from R_j(b)^T m = R_i(a).
    lock = np.abs(sb) > 1.0 - 1e-9
    if np.any(lock):
        rem = np.swapaxes(axis_rotation(order[1], b), -1, -2) @ m
        a_lock = np.arctan2(rem[..., (i + 2) % 3, (i + 1) % 3], rem[..., (i + 1) % 3, (i + 1) % 3])
        a = np.where(lock, a_lock, a)
        c = np.where(lock, 0.0, c)
    return np.stack([a, b, c], axis=-1)


def quat_to_matrix(q) -> np.ndarray:
    """Quaternions ``(w, x, y, z)`` (any length, normalised through
    ``2 / |q|²``) to rotation matrices ``(…, 3, 3)``. One quaternion (shape
    (4,)) takes a path on Python floats, the frame loop's (2 µs against 18 µs
    through numpy), with the same arithmetic, so the same bits."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1:
        w, x, y, z = q.tolist()
        d = w * w + x * x + y * y + z * z
        n = 2.0 / d if d > 0.0 else float("nan")  # a zero quaternion: no rotation (NaN)
        return np.array([[1 - n * (y * y + z * z), n * (x * y - w * z), n * (x * z + w * y)],
                         [n * (x * y + w * z), 1 - n * (x * x + z * z), n * (y * z - w * x)],
                         [n * (x * z - w * y), n * (y * z + w * x), 1 - n * (x * x + y * y)]])
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    d = w * w + x * x + y * y + z * z
    n = 2.0 / np.where(d > 0.0, d, np.nan)
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - n * (y * y + z * z)
    out[..., 0, 1] = n * (x * y - w * z)
    out[..., 0, 2] = n * (x * z + w * y)
    out[..., 1, 0] = n * (x * y + w * z)
    out[..., 1, 1] = 1 - n * (x * x + z * z)
    out[..., 1, 2] = n * (y * z - w * x)
    out[..., 2, 0] = n * (x * z - w * y)
    out[..., 2, 1] = n * (y * z + w * x)
    out[..., 2, 2] = 1 - n * (x * x + y * y)
    return out


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices to unit quaternions ``(w, x, y, z)`` with w >= 0."""
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = np.stack([
        1 + tr,
        1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
        1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
        1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
    ], axis=1)
    best = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    s = np.sqrt(np.maximum(cand[np.arange(len(best)), best], 1e-300)) * 2.0
    b0, b1, b2, b3 = (best == 0), (best == 1), (best == 2), (best == 3)
    # w largest
    q[b0, 0] = 0.25 * s[b0]
    q[b0, 1] = (m[b0, 2, 1] - m[b0, 1, 2]) / s[b0]
    q[b0, 2] = (m[b0, 0, 2] - m[b0, 2, 0]) / s[b0]
    q[b0, 3] = (m[b0, 1, 0] - m[b0, 0, 1]) / s[b0]
    # x largest
    q[b1, 0] = (m[b1, 2, 1] - m[b1, 1, 2]) / s[b1]
    q[b1, 1] = 0.25 * s[b1]
    q[b1, 2] = (m[b1, 0, 1] + m[b1, 1, 0]) / s[b1]
    q[b1, 3] = (m[b1, 0, 2] + m[b1, 2, 0]) / s[b1]
    # y largest
    q[b2, 0] = (m[b2, 0, 2] - m[b2, 2, 0]) / s[b2]
    q[b2, 1] = (m[b2, 0, 1] + m[b2, 1, 0]) / s[b2]
    q[b2, 2] = 0.25 * s[b2]
    q[b2, 3] = (m[b2, 1, 2] + m[b2, 2, 1]) / s[b2]
    # z largest
    q[b3, 0] = (m[b3, 1, 0] - m[b3, 0, 1]) / s[b3]
    q[b3, 1] = (m[b3, 0, 2] + m[b3, 2, 0]) / s[b3]
    q[b3, 2] = (m[b3, 1, 2] + m[b3, 2, 1]) / s[b3]
    q[b3, 3] = 0.25 * s[b3]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(shape + (4,))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation, shortest arc, vectorised; ``t`` broadcasts."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    small = sin_t < 1e-8
    safe = np.where(small, 1.0, sin_t)
    w0 = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(small, t, np.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def quat_to_axis_angle(q: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` (w, x, y, z) to Blender's axis-angle ``(..., 4)``
    (angle in [0, pi], then a unit axis; +Y for the identity)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    s = np.linalg.norm(q[..., 1:], axis=-1)
    ang = 2.0 * np.arctan2(s, q[..., 0])  # accurate near the identity, unlike arccos(w)
    axis = np.where(s[..., None] > 1e-12, q[..., 1:] / np.maximum(s, 1e-300)[..., None], np.array([0.0, 1.0, 0.0]))
    return np.concatenate([ang[..., None], axis], axis=-1)


def axis_angle_to_quat(aa: np.ndarray) -> np.ndarray:
    """Blender's axis-angle ``(..., 4)`` (angle, axis; the axis need not be unit)
    to quaternions (w, x, y, z)."""
    aa = np.asarray(aa, dtype=np.float64)
    h = aa[..., :1] / 2
    ax = aa[..., 1:] / np.maximum(np.linalg.norm(aa[..., 1:], axis=-1, keepdims=True), 1e-12)
    return np.concatenate([np.cos(h), np.sin(h) * ax], axis=-1)


def rotation_angle(m: np.ndarray) -> np.ndarray:
    """Angle (radians) of rotation matrices."""
    tr = np.trace(m, axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0))
