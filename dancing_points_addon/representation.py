"""The paper's motion representation (Method §4.1), in numpy.

A *root* is a floor frame ``F = (t, o)`` stored as ``(x, z, cos θ, sin θ)``:
the head's position projected to the floor and its facing as a unit complex
number. ``θ`` is the heading about +Y measured from +Z (a dancer facing +Z has
θ = 0, facing +X has θ = π/2). Root frame → world: ``p = Ry(θ) · p_local + (x, 0, z)``.
"""
from __future__ import annotations

from math import sqrt

import numpy as np

from .skeleton import FEET, HEAD_BONE, HIPS, TRACKED

# The head device: local −Z forward, +Y up (SPEC §3). Rigid on the `head` bone
# as ``R_device = R_head · Ry(180°)``.
DEVICE_FROM_HEAD = np.diag([-1.0, 1.0, -1.0])

CONTACT_HEIGHT = 0.06  # m above the floor level (SPEC §6)
CONTACT_SPEED = 0.30  # m/s (SPEC §6)
FLOOR_PERCENTILE = 5.0


def norm(x: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (``np.linalg.norm`` costs more on small arrays)."""
    return np.sqrt(np.einsum("...i,...i->...", x, x))


def vector_norm(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1, keepdims=keepdims)`` of a float array, its
    arithmetic (the same bits) without its argument checks."""
    return np.sqrt(np.add.reduce(x * x, axis=-1, keepdims=keepdims))


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products of component-major vectors ``(3, …)``, summed in the order
    :func:`norm`'s einsum uses (``(x + z) + y``), so both give the same bits."""
    p = a * b
    return (p[0] + p[2]) + p[1]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (cheaper than ``np.cross`` on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def device_rotation(head_bone_rotation: np.ndarray) -> np.ndarray:
    """Head device orientation from the global rotation of the ``head`` bone."""
    return head_bone_rotation @ DEVICE_FROM_HEAD


def heading_vector(device_rot: np.ndarray) -> np.ndarray:
    """Horizontal facing ``(…, 2)`` as (x, z), unit length, from device rotations.

    Uses ``forward − up · forward_y``: equal to the forward direction for a level
    head and still well defined when the head pitches straight down or up.
    """
    fwd = -device_rot[..., :, 2]
    up = device_rot[..., :, 1]
    d = fwd - up * fwd[..., 1:2]
    h = np.stack([d[..., 0], d[..., 2]], axis=-1)
    n = np.linalg.norm(h, axis=-1, keepdims=True)
    # Degenerate only for a head lying on its side facing straight up/down.
    return np.where(n > 1e-9, h / np.maximum(n, 1e-12), np.array([0.0, 1.0]))


def root_from_head(head_pos: np.ndarray, device_rot: np.ndarray) -> np.ndarray:
    """Roots ``(…, 4)`` from head positions ``(…, 3)`` and device rotations."""
    if head_pos.ndim == 1:  # one frame: plain floats cost less than array calls
        r = device_rot
        f1 = -float(r[1, 2])
        dx = -float(r[0, 2]) - float(r[0, 1]) * f1
        dz = -float(r[2, 2]) - float(r[2, 1]) * f1
        n = (dx * dx + dz * dz) ** 0.5
        c, s = (dz / n, dx / n) if n > 1e-9 else (1.0, 0.0)
        return np.array([float(head_pos[0]), float(head_pos[2]), c, s])
    h = heading_vector(device_rot)
    # θ measured from +Z towards +X: (sin θ, cos θ) = (hx, hz)
    return np.stack([head_pos[..., 0], head_pos[..., 2], h[..., 1], h[..., 0]], axis=-1)


def root_from_motion(positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Roots ``(T, 4)`` of a SPEC motion from its head point and head bone."""
    return root_from_head(positions[..., TRACKED[0], :], device_rotation(rotations[..., HEAD_BONE, :, :]))


def hip_heading(pos: np.ndarray) -> np.ndarray:
    """Hip heading angles ``(T,)`` (radians about +Y from +Z) of poses ``(T, 31, 3)``:
    forward = (left hip − right hip) × up."""
    across = pos[:, HIPS[0]] - pos[:, HIPS[1]]
    return np.arctan2(-across[:, 2], across[:, 0])


def hip_frame(pos: np.ndarray) -> np.ndarray:
    """Frames ``(T, 4)`` of poses ``(T, 31, 3)`` (one pose ``(31, 3)``: its frame
    ``(4,)``): the pelvis's floor point and the hip heading. A pose in its own
    hip frame is its shape with the placement factored out (the follower's
    pose anchor and the pose metric use it)."""
    if pos.ndim == 2:  # one pose (per frame): numpy's functions on scalars, the same bits, fewer calls
        (lx, _, lz), (rx, _, rz) = pos[HIPS[0]].tolist(), pos[HIPS[1]].tolist()
        h = np.arctan2(-(lz - rz), lx - rx)
        return np.array([float(pos[0, 0]), float(pos[0, 2]), float(np.cos(h)), float(np.sin(h))])
    h = hip_heading(pos)
    return np.stack([pos[:, 0, 0], pos[:, 0, 2], np.cos(h), np.sin(h)], axis=-1)


def root_rotation(root: np.ndarray) -> np.ndarray:
    """``Ry(θ)`` matrices ``(…, 3, 3)``."""
    if root.ndim <= 2 and 0 < root.size <= 16:  # a few frames: a literal costs less than seven array writes
        out = [[[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]] for _, _, c, s in root.reshape(-1, 4).tolist()]
        return np.array(out if root.ndim == 2 else out[0], dtype=root.dtype)
    c, s = root[..., 2], root[..., 3]
    out = np.zeros(root.shape[:-1] + (3, 3), dtype=root.dtype)
    out[..., 0, 0] = c
    out[..., 0, 2] = s
    out[..., 1, 1] = 1.0
    out[..., 2, 0] = -s
    out[..., 2, 2] = c
    return out


def _origin(root):
    if root.ndim <= 2 and 0 < root.size <= 16:
        out = [[x, 0.0, z] for x, z, _, _ in root.reshape(-1, 4).tolist()]
        return np.array(out if root.ndim == 2 else out[0], dtype=root.dtype)
    o = np.zeros(root.shape[:-1] + (3,), dtype=root.dtype)
    o[..., 0] = root[..., 0]
    o[..., 2] = root[..., 1]
    return o


def to_local(points: np.ndarray, root: np.ndarray) -> np.ndarray:
    """World points ``(…, N, 3)`` into the frames ``root (…, 4)``."""
    return (points - _origin(root)[..., None, :]) @ root_rotation(root)


def to_world(points: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Root-frame points ``(…, N, 3)`` to world."""
    return points @ root_rotation(root).swapaxes(-1, -2) + _origin(root)[..., None, :]


def rot_to_local(rot: np.ndarray, root: np.ndarray) -> np.ndarray:
    """World rotations ``(…, N, 3, 3)`` into the root frames."""
    return np.swapaxes(root_rotation(root), -1, -2)[..., None, :, :] @ rot


def rot_to_world(rot: np.ndarray, root: np.ndarray) -> np.ndarray:
    return root_rotation(root)[..., None, :, :] @ rot


def pose_to_world(points: np.ndarray, rot: np.ndarray, root: np.ndarray):
    """:func:`to_world` of ``points`` and :func:`rot_to_world` of ``rot``, sharing ``Ry(θ)``."""
    R = root_rotation(root)
    return points @ R.swapaxes(-1, -2) + _origin(root)[..., None, :], R[..., None, :, :] @ rot


def pose_to_local(points: np.ndarray, rot: np.ndarray, root: np.ndarray):
    """:func:`to_local` of ``points`` and :func:`rot_to_local` of ``rot``, sharing ``Ry(θ)``."""
    R = root_rotation(root)
    return (points - _origin(root)[..., None, :]) @ R, np.swapaxes(R, -1, -2)[..., None, :, :] @ rot


def _on_rows(fn, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``fn`` (a ``*_rows`` function) on roots ``(…, 4)`` of broadcastable shapes."""
    shape = np.broadcast_shapes(a.shape, b.shape)
    rows = [np.broadcast_to(v, shape).reshape(-1, 4).T for v in (a, b)]
    return fn(*rows).T.reshape(shape)


def root_relative(ref: np.ndarray, root: np.ndarray) -> np.ndarray:
    """``ref⁻¹ · root``: ``root`` expressed in the frame ``ref`` (both ``(…, 4)``):
    ``Ry(θ)ᵀ (dx, 0, dz)`` and the heading difference ``o_root · conj(o_ref)``."""
    return _on_rows(relative_rows, ref, root)


def root_compose(ref: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """``ref · rel``: inverse of :func:`root_relative`."""
    if ref.ndim == 1 and rel.ndim == 1:  # one frame (the runtime, per frame), in plain floats
        return np.array(compose_floats(ref.tolist(), rel.tolist()))
    return _on_rows(compose_rows, ref, rel)


def compose_floats(ref, rel) -> list:
    """:func:`root_compose` of one frame's roots given as 4 plain floats each."""
    x0, z0, c, s = ref
    r0, r1, cr, sr = rel
    co, so = cr * c - sr * s, sr * c + cr * s
    n = 1.0 / max(sqrt(co * co + so * so), 1e-300)
    return [x0 + c * r0 + s * r1, z0 - s * r0 + c * r1, co * n, so * n]


# Component-major ("rows") forms: roots as ``(4, n)`` arrays, one row per
# component, ``ref`` of the same shape. The functions above run on them; the
# runtime's features call them directly (numpy calls on contiguous rows of
# equal shape cost a fraction of those on strided or broadcast arrays).

_REL_SIGN = np.array([[-1.0], [1.0], [1.0], [-1.0]])


def relative_rows(ref: np.ndarray, root: np.ndarray) -> np.ndarray:
    """:func:`root_relative` on rows ``(4, n)``: with ``u = (dx, dz, cos_r, sin_r)``,
    ``c·u + s·(dz, dx, sin_r, cos_r)·(−1, 1, 1, −1)`` (the same products and sums)."""
    u = root.copy()
    u[:2] -= ref[:2]
    swapped = u.reshape(2, 2, -1)[:, ::-1].reshape(u.shape)
    return ref[2] * u + ref[3] * (swapped * _REL_SIGN)


def compose_rows(ref: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """:func:`root_compose` on rows ``(4, n)``."""
    x0, z0, c, s = ref
    r0, r1, cr, sr = rel
    out = np.empty(rel.shape)
    np.add(x0 + c * r0, s * r1, out=out[0])
    np.add(z0 - s * r0, c * r1, out=out[1])
    co, so = cr * c - sr * s, sr * c + cr * s
    n = 1.0 / np.maximum(np.sqrt(co * co + so * so), 1e-300)
    np.multiply(co, n, out=out[2])
    np.multiply(so, n, out=out[3])
    return out


def blend_root(a, b, w: float) -> list:
    """Root ``w`` of the way from ``a`` to ``b`` (4 numbers each; position
    linear, heading normalised), as a list of plain floats."""
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    x, z, c, s = a0 + w * (b0 - a0), a1 + w * (b1 - a1), a2 + w * (b2 - a2), a3 + w * (b3 - a3)
    n = max(sqrt(c * c + s * s), 1e-9)
    return [x, z, c / n, s / n]


def segments_gap(p0, p1, q0, q1) -> np.ndarray:
    """Vectors ``(…, 3)`` from the closest point of the segments q0–q1 to that of
    the segments p0–p1 (their closest distance is the norm), all ``(…, 3)``."""
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    A, B, C = (u * u).sum(-1), (u * v).sum(-1), (v * v).sum(-1)
    D, E = (u * w).sum(-1), (v * w).sum(-1)
    den = A * C - B * B
    s = np.where(den > 1e-12, np.clip((B * E - C * D) / np.maximum(den, 1e-12), 0.0, 1.0), 0.0)
    t = np.clip((B * s + E) / np.maximum(C, 1e-12), 0.0, 1.0)
    s = np.clip((B * t - D) / np.maximum(A, 1e-12), 0.0, 1.0)
    return (p0 + s[..., None] * u) - (q0 + t[..., None] * v)


def floor_levels(foot_heights: np.ndarray) -> np.ndarray:
    """Per-point floor level ``(4,)``: 5th percentile of the height over a take."""
    return np.nanpercentile(foot_heights, FLOOR_PERCENTILE, axis=0)


def foot_speeds(feet: np.ndarray, fps: float) -> np.ndarray:
    """Speed ``(T, 4)`` of the foot points ``(T, 4, 3)``; frame 0 takes frame 1's."""
    v = np.linalg.norm(np.diff(feet, axis=0), axis=-1) * fps
    return np.concatenate([v[:1], v], axis=0) if len(v) else np.zeros(feet.shape[:2])


def contact_labels(positions: np.ndarray, fps: float, floor: np.ndarray | None = None) -> np.ndarray:
    """SPEC §6 foot contacts ``(T, 4)`` bool of a motion's joint positions ``(T, 31, 3)``.

    In contact: less than 6 cm above the point's floor level (5th percentile of
    its height over the take unless ``floor`` is given) and slower than 0.30 m/s.
    """
    feet = positions[:, FEET]
    if floor is None:
        floor = floor_levels(feet[..., 1])
    return ((feet[..., 1] - floor) < CONTACT_HEIGHT) & (foot_speeds(feet, fps) < CONTACT_SPEED)


def rot6d(rot: np.ndarray) -> np.ndarray:
    """First two columns of rotation matrices, flattened: ``(…, 3, 3) -> (…, 6)``."""
    return np.concatenate([rot[..., :, 0], rot[..., :, 1]], axis=-1)


_GS_ROWS = np.array([0, 1, 2, 0, 1, 2, 3, 4, 5, 3, 4, 5])


def rot6d_to_matrix(x: np.ndarray) -> np.ndarray:
    """Gram–Schmidt back to rotation matrices: ``(…, 6) -> (…, 3, 3)``."""
    x = np.asarray(x, dtype=np.float64)
    lead = x.shape[:-1]
    # Component-major rows, all frames at once (few numpy calls on contiguous
    # rows); both input vectors and e1, e2 twice over (x y z x y z), so the
    # cross product reads them rotated as plain slices. e[k]: column k.
    a, b = x.reshape(-1, 6).T.take(_GS_ROWS, axis=0).reshape(2, 6, -1)
    e = np.empty((3, 6, a.shape[1]))
    e1, e2 = e[0], e[1]
    np.divide(a, np.maximum(np.sqrt(dot3(a[:3], a[:3])), 1e-12), out=e1)
    b = b - dot3(e1[:3], b[:3]) * e1
    np.divide(b, np.maximum(np.sqrt(dot3(b[:3], b[:3])), 1e-12), out=e2)
    np.subtract(e1[1:4] * e2[2:5], e1[2:5] * e2[1:4], out=e[2, :3])  # e1 × e2
    return e[:, :3].transpose(2, 1, 0).copy().reshape(lead + (3, 3))
