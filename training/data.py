"""Training samples for the mapping and tracking networks, from train-split clips.

Every sample's window lies inside one clip's train frames: the past window is
padded by repeating the clip's first frame (as the runtime pads at start-up)
and the future window must fit (t + 30 < n), so no sample reaches a test frame.
"""
from __future__ import annotations

import numpy as np

from dancing_points_addon import features as F
from dancing_points_addon.representation import root_from_head, to_local
from dancing_points_addon.skeleton import TRACKED


def _tracked(d):
    return d.positions[:, TRACKED]


def sample_times(n: int) -> np.ndarray:
    return np.arange(0, max(n - F.FUTURE, 0))


def mapping_samples(clips):
    xs, ys = [], []
    past = np.arange(-F.PAST + 1, 1)
    fut = np.arange(1, F.FUTURE + 1)
    for c in clips:
        if c.follower is None:
            continue
        n = c.n_frames
        t = sample_times(n)
        if len(t) == 0:
            continue
        L, Fo = c.leader, c.follower
        pi = F.window_indices(t, n, past)
        fi = t[:, None] + fut[None, :]
        xs.append(F.mapping_input(L.roots[pi], _tracked(L)[pi]))
        ys.append(F.mapping_target(L.roots[t], L.roots[fi], _tracked(L)[fi], Fo.roots[fi], _tracked(Fo)[fi]))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


def tracking_samples(clips, role: str, past_input: bool = False):
    """Tracker samples of one dancer (``role`` 'leader' or 'follower').

    ``past_input`` builds ablation (b): the future-key slots carry the *past*
    three-point trajectory (frames t − k) instead of the future one.
    """
    xs, ys = [], []
    keys = F.TRACK_KEYS
    for c in clips:
        d = getattr(c, role)
        if d is None:
            continue
        n = c.n_frames
        t = sample_times(n)
        if len(t) == 0:
            continue
        f0 = d.roots[t]
        pos_l = to_local(d.positions[t], f0)
        from dancing_points_addon.representation import rot_to_local
        rot_l = rot_to_local(d.rotations[t], f0)
        pose = F.pose_features(pos_l, rot_l, d.contacts[t])
        ki = t[:, None] + keys[None, :]
        src = F.window_indices(t, n, -keys) if past_input else ki
        key_roots = d.roots[src]
        key_tr = to_local(_tracked(d)[src], key_roots)
        xs.append(F.tracking_input(pose, f0, key_roots, key_tr))
        ys.append(F.tracking_target(f0, d.roots[ki], d.positions[ki], d.rotations[ki], d.contacts[ki]))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


def head_root(positions, device_rot):
    return root_from_head(positions, device_rot)
