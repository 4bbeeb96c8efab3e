"""Linear blend skinning of a :class:`.mannequin.Body` with per-bone rigid
transforms (:func:`dancing_points_addon.ik.bone_transforms`).
"""
from __future__ import annotations

import numpy as np

from .mannequin import Body
from .proportions import N_BONES


def _split(transforms):
    if isinstance(transforms, tuple):
        R, t = transforms
        return np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    M = np.asarray(transforms, dtype=np.float64)
    return M[..., :3, :3], M[..., :3, 3]


def lbs(body: Body, transforms, chunk: int = 64) -> np.ndarray:
    """Linear blend skinning: posed vertices ``(T, V, 3)``.

    ``transforms``: ``(R (T, 31, 3, 3), t (T, 31, 3))`` from
    :func:`dancing_points_addon.ik.bone_transforms`, or homogeneous matrices
    ``(T, 31, 4, 4)``. ``v' = Σ_b w_vb (R_b v + t_b)``, evaluated as
    ``(Σ_b w_vb R_b) v + Σ_b w_vb t_b`` with the dense weight matrix (one
    BLAS product per chunk of ``chunk`` frames).
    """
    R, t = _split(transforms)
    single = R.ndim == 3
    if single:
        R, t = R[None], t[None]
    W = body.dense_weights()
    V = body.vertices
    T = R.shape[0]
    out = np.empty((T, len(V), 3))
    for a in range(0, T, chunk):
        b = min(a + chunk, T)
        M = np.matmul(W, R[a:b].reshape(b - a, N_BONES, 9)).reshape(b - a, len(V), 3, 3)
        out[a:b] = np.einsum("tvij,vj->tvi", M, V) + np.matmul(W, t[a:b])
    return out[0] if single else out


def lbs_frame(body: Body, transforms) -> np.ndarray:
    """One frame: ``transforms`` of one frame (``(R (31,3,3), t (31,3))`` or
    ``(31, 4, 4)``) → posed vertices ``(V, 3)``. Uses the sparse weights."""
    R, t = _split(transforms)
    Rv = R[body.indices]  # (V, k, 3, 3)
    p = np.einsum("vkij,vj->vki", Rv, body.vertices) + t[body.indices]
    return np.einsum("vk,vki->vi", body.weights, p)
