"""Pose recovery (paper Appendix B): one rigid transform per bone from the
network's independently predicted joint positions and rotations.

The predicted positions give each bone's direction, the skeleton gives its
length; rotations are turned minimally so that ``R · rest bone vector`` lands
exactly on the recovered bone. The result is a consistent skeleton pose: bone
lengths exact, every bone's end on its joint, ready for skinning or baking.
"""
from __future__ import annotations

import numpy as np

from .representation import norm
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

    def __call__(self, positions: np.ndarray, rotations: np.ndarray):
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


def recover_pose(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray):
    """Consistent pose ``(…, 31, 3)``, ``(…, 31, 3, 3)`` from network outputs."""
    return PoseRecovery(bone_vectors)(positions, rotations)
