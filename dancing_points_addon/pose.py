"""Pose recovery (paper Appendix B): one rigid transform per bone from the
network's independently predicted joint positions and rotations.

The predicted positions give each bone's direction, the skeleton gives its
length; rotations are turned minimally so that ``R · rest bone vector`` lands
exactly on the recovered bone. The result is a consistent skeleton pose: bone
lengths exact, every bone's end on its joint, ready for skinning or baking.
"""
from __future__ import annotations

import numpy as np

from .representation import dot3, norm
from .skeleton import PARENTS

N = len(PARENTS)
# ANCESTORS[n, k] = 1 when bone k lies on the chain from the root to bone n (k != root)
ANCESTORS = np.zeros((N, N))
for _n in range(1, N):
    _k = _n
    while _k > 0:
        ANCESTORS[_n, _k] = 1.0
        _k = PARENTS[_k]
_PAR = np.maximum(PARENTS, 0)
_EYE_COL = np.eye(3)[:, :, None]


def bone_vectors_from_pose(positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Rest bone vectors ``(31, 3)`` of a skeleton from one consistent posed frame
    (``posed bone vector = R · rest bone vector``)."""
    vec = positions - positions[_PAR]
    vec[0] = 0.0
    return np.einsum("nba,nb->na", rotations, vec)


def _align(u, v):
    """Rotations ``(…, 3, 3)`` taking unit vectors ``u`` to ``v`` by the shortest arc,
    as two reflections: across the plane normal to ``u + v`` (u -> −v), then
    across the plane normal to ``v`` (−v -> v). Undefined only for ``u = −v``."""
    w = u + v
    ww = 2.0 / np.maximum(np.einsum("...i,...i->...", w, w), 1e-12)
    hw = np.eye(3) - (w[..., :, None] * w[..., None, :]) * ww[..., None, None]
    hv = np.eye(3) - 2.0 * (v[..., :, None] * v[..., None, :])
    return hv @ hw


class PoseRecovery:
    """:func:`recover_pose` for one skeleton, with its constants precomputed
    (the runtime calls it once per dancer and frame)."""

    def __init__(self, bone_vectors: np.ndarray):
        self.bone_vectors = np.asarray(bone_vectors, dtype=np.float64)
        self.lengths = norm(self.bone_vectors)
        self.rest_dir = self.bone_vectors / np.maximum(self.lengths[:, None], 1e-12)
        self._rest_col = self.rest_dir[:, :, None]

    def __call__(self, positions: np.ndarray, rotations: np.ndarray):
        if positions.ndim == 2:
            return self._one(positions, rotations)
        d = positions - positions[..., _PAR, :]
        n = norm(d)[..., None]
        # Direction from positions; a collapsed bone falls back on its rotation.
        rot_dir = (rotations @ self.rest_dir[:, :, None])[..., 0]
        dirs = np.where(n > 1e-6, d / np.maximum(n, 1e-12), rot_dir)
        dirs[..., 0, :] = 0.0
        out_pos = positions[..., :1, :] + ANCESTORS @ (dirs * self.lengths[:, None])
        out_rot = rotations.copy()
        out_rot[..., 1:, :, :] = _align(rot_dir[..., 1:, :], dirs[..., 1:, :]) @ rotations[..., 1:, :, :]
        return out_pos, out_rot

    def _one(self, positions, rotations):
        """:meth:`__call__` for one frame ``(31, 3)``, ``(31, 3, 3)``, the same
        arithmetic on component-major rows ``(3, 31)`` (fewer, cheaper numpy
        calls); the matrix products stay the same BLAS calls."""
        p = np.ascontiguousarray(positions.T)
        d = p - p.take(_PAR, axis=1)  # (take: cheaper than fancy indexing)
        n = np.sqrt(dot3(d, d))
        rot_dir = np.ascontiguousarray((rotations @ self._rest_col)[:, :, 0].T)
        dirs = d / np.maximum(n, 1e-12)
        if not n[1:].min() > 1e-6:  # a collapsed (or NaN) bone, rare: its rotation's direction
            dirs = np.where(n > 1e-6, dirs, rot_dir)
        dirs[:, 0] = 0.0
        out_pos = positions[:1] + ANCESTORS @ (dirs * self.lengths).T
        # _align(rot_dir, dirs): hv @ hw, both h = I − k·u uᵀ built at once from
        # rows (u, k) = (w, ww) and (v, 2), then laid out C-ordered (30, 3, 3)
        # like the batched code's, so the products take the same BLAS path.
        u = np.empty((2, 3, N - 1))
        w = np.add(rot_dir[:, 1:], dirs[:, 1:], out=u[0])
        u[1] = dirs[:, 1:]
        outer = u[:, :, None] * u[:, None, :]  # (2, 3, 3, 30): u_i u_j
        outer[0] *= 2.0 / np.maximum(dot3(w, w), 1e-12)
        outer[1] *= 2.0
        hv_hw = np.empty((2, N - 1, 3, 3))
        np.subtract(_EYE_COL, outer, out=hv_hw.transpose(0, 2, 3, 1))
        out_rot = rotations.copy()
        out_rot[1:] = hv_hw[1] @ hv_hw[0] @ rotations[1:]
        return out_pos, out_rot


def recover_pose(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray):
    """Consistent pose ``(…, 31, 3)``, ``(…, 31, 3, 3)`` from network outputs."""
    return PoseRecovery(bone_vectors)(positions, rotations)
