"""Skin weights (step 3 of the package): a soft-min of the weight capsules' signed
distances, kept for the 4 largest, rounded to multiples of 1/1024.
"""
from __future__ import annotations

import numpy as np

from .sdf import sd_round_cone

K_INFLUENCES = 4
WEIGHT_QUANTUM = 1.0 / 1024  # weights are multiples of this (few distinct values: fast vertex groups)


def bone_segment_distances(points: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Distances ``(V, B)`` from points ``(V, 3)`` to segments ``starts → ends (B, 3)``."""
    d = ends - starts
    L2 = np.sum(d * d, axis=1)
    rel = points[:, None, :] - starts[None]
    t = np.einsum("vbk,bk->vb", rel, d) / np.where(L2 > 0, L2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    closest = starts[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1)


def _quantize_rows(w, q):
    """Weights rounded to multiples of ``q`` with rows still summing to 1 (largest remainders)."""
    n = int(round(1.0 / q))
    x = w * n
    base = np.floor(x)
    short = (n - base.sum(1)).astype(np.int64)
    order = np.argsort(-(x - base), axis=1, kind="stable")
    rank = np.argsort(order, axis=1, kind="stable")
    base = base + (rank < short[:, None])
    return base / n


def skin_weights(verts, bones, a, b, r1, r2, tau, k=K_INFLUENCES):
    """Soft-min weights of the weight capsules: ``(indices (V, k), weights (V, k))``."""
    d = np.stack([sd_round_cone(verts, a[i], b[i], r1[i], r2[i]) for i in range(len(bones))], axis=1)
    w = np.exp(-(d - d.min(1, keepdims=True)) / tau)
    order = np.argsort(-w, axis=1, kind="stable")[:, :k + 1]
    ww = np.take_along_axis(w, order, axis=1)
    ww = np.maximum(ww[:, :k] - ww[:, k:k + 1], 0.0)  # continuous where the 4th and 5th swap
    ww = ww / ww.sum(1, keepdims=True)
    ww = np.where(ww < 2e-3, 0.0, ww)
    ww = _quantize_rows(ww / ww.sum(1, keepdims=True), WEIGHT_QUANTUM)
    idx = bones[order[:, :k]]
    # bones of weight 0 point at the first bone (harmless, and tidy)
    idx = np.where(ww > 0, idx, idx[:, :1])
    return idx.astype(np.int64), ww
