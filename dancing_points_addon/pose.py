"""Pose recovery (paper Appendix B): one rigid transform per bone from the
network's independently predicted joint positions and rotations.

The predicted positions give each bone's direction, the skeleton gives its
length; rotations are turned minimally so that ``R · rest bone vector`` lands
exactly on the recovered bone. The result is a consistent skeleton pose: bone
lengths exact, every bone's end on its joint, ready for skinning or baking.
"""
from __future__ import annotations

import numpy as np

from .representation import cross, norm
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
    """Rotations ``(…, 3, 3)`` taking unit vectors ``u`` to ``v`` by the shortest arc."""
    k = cross(u, v)
    c = np.einsum("...i,...i->...", u, v)
    kx = np.zeros(u.shape[:-1] + (3, 3))
    kx[..., 0, 1], kx[..., 0, 2] = -k[..., 2], k[..., 1]
    kx[..., 1, 0], kx[..., 1, 2] = k[..., 2], -k[..., 0]
    kx[..., 2, 0], kx[..., 2, 1] = -k[..., 1], k[..., 0]
    f = 1.0 / np.maximum(1.0 + c, 1e-9)
    eye = np.broadcast_to(np.eye(3), kx.shape)
    return eye + kx + kx @ kx * f[..., None, None]


def recover_pose(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray):
    """Consistent pose ``(…, 31, 3)``, ``(…, 31, 3, 3)`` from network outputs."""
    lengths = norm(bone_vectors)
    d = positions - positions[..., _PAR, :]
    n = norm(d)[..., None]
    rest_dir = bone_vectors / np.maximum(lengths[:, None], 1e-12)
    # Direction from positions; a collapsed bone falls back on its rotation.
    rot_dir = np.einsum("...nab,nb->...na", rotations, rest_dir)
    dirs = np.where(n > 1e-6, d / np.maximum(n, 1e-12), rot_dir)
    dirs[..., 0, :] = 0.0
    vec = dirs * lengths[:, None]
    out_pos = positions[..., :1, :] + np.einsum("nk,...kc->...nc", ANCESTORS, vec)
    out_rot = rotations.copy()
    out_rot[..., 1:, :, :] = _align(rot_dir[..., 1:, :], dirs[..., 1:, :]) @ rotations[..., 1:, :, :]
    return out_pos, out_rot
