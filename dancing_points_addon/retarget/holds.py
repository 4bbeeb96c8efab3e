"""Hands that hold each other: :func:`close_hands` keeps the hands of leader
and follower that hold each other together (source wrists < 15 cm apart): both
target wrists move to meet at the source's gap (scaled), by two-bone arm IK
(``Retargeter.reach``)."""
from __future__ import annotations

import numpy as np

from ..ik import smoothstep
from .mapping import SIDES
from .solver import Retargeter


def close_hands(ret_a: Retargeter, pose_a, src_a, src_b, ret_b: Retargeter = None, pose_b=None, wrists_b=None,
                near: float = 0.15, far: float = 0.20):
    """Keep hands that hold each other together.

    ``src_a``/``src_b``: source wrist positions ``(T, 2, 3)`` (world; left,
    right) of the two dancers. Where the closest leader/follower wrist pair of
    the source (and the complementary pair) is nearer than ``near`` (fading out
    at ``far``), the two target wrists are moved to meet at the source's gap
    vector (scaled by the mean of both rigs' scales): half each when ``pose_b``
    is given, else only ``a`` moves to the fixed partner wrists ``wrists_b (T, 2, 3)``.
    Returns the per-frame gap of the handled pairs ``(T, 2)`` before and after
    (NaN where no pair is held)."""
    T = src_a.shape[0]
    tw_a = ret_a.wrists(pose_a.W)
    tw_b = ret_b.wrists(pose_b.W) if pose_b is not None else np.asarray(wrists_b, dtype=np.float64)
    scale = 0.5 * (ret_a.scale + (ret_b.scale if ret_b is not None else ret_a.scale))
    d = np.linalg.norm(src_a[:, :, None] - src_b[:, None, :], axis=-1)  # (T, 2, 2)
    flat = d.reshape(T, 4)
    first = np.argmin(flat, axis=1)
    pairs = [(first // 2, first % 2), (1 - first // 2, 1 - first % 2)]
    rows = np.arange(T)
    goal_a = np.zeros((T, 2, 3))
    goal_b = np.zeros((T, 2, 3))
    wt_a = np.zeros((T, 2))
    wt_b = np.zeros((T, 2))
    before = np.full((T, 2), np.nan)
    for k, (ia, ib) in enumerate(pairs):
        ds = d[rows, ia, ib]
        w = 1.0 - smoothstep((ds - near) / max(far - near, 1e-9))
        gap = (src_b[rows, ib] - src_a[rows, ia]) * scale
        pa, pb = tw_a[rows, ia], tw_b[rows, ib]
        before[:, k] = np.where(w > 0, np.linalg.norm(pb - pa, axis=-1), np.nan)
        if pose_b is not None:
            mid = 0.5 * (pa + pb)
            ga, gb = mid - 0.5 * gap, mid + 0.5 * gap
        else:
            ga, gb = pb - gap, pb
        goal_a[rows, ia] = ga
        wt_a[rows, ia] = w
        goal_b[rows, ib] = gb
        wt_b[rows, ib] = w
    for s, side in enumerate(SIDES):
        ret_a.reach(pose_a, side, goal_a[:, s], wt_a[:, s])
    pose_a.W = ret_a.fk(pose_a)
    if pose_b is not None:
        for s, side in enumerate(SIDES):
            ret_b.reach(pose_b, side, goal_b[:, s], wt_b[:, s])
        pose_b.W = ret_b.fk(pose_b)
    tw_a = ret_a.wrists(pose_a.W)
    tw_b = ret_b.wrists(pose_b.W) if pose_b is not None else tw_b
    after = np.full((T, 2), np.nan)
    for k, (ia, ib) in enumerate(pairs):
        held = ~np.isnan(before[:, k])
        after[held, k] = np.linalg.norm(tw_b[rows, ib] - tw_a[rows, ia], axis=-1)[held]
    return before, after
