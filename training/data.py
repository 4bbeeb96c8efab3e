"""Training samples for the mapping and tracking networks, from train-split clips.

Every sample's window lies inside one clip's train frames: the past window is
padded by repeating the clip's first frame (as the runtime pads at start-up)
and the future window must fit (t + 30 < n), so no sample reaches a test frame.

Tracker samples are built the way the runtime feeds the tracker (see
``runtime``): the state is the pose at frame t in the dancer's anchored root;
key 1 (frame t + 1) is the observed input for the leader and the mapping's
last prediction for the follower; keys k >= 2 come from the mapping network
run on the input up to t + 1. :func:`rollout_states` then replaces the ground
truth state by the tracker's own closed-loop poses (DAgger-style), with the
ground truth future kept as the target.
"""
from __future__ import annotations

import numpy as np

from dancing_points_addon import features as F
from dancing_points_addon.representation import hip_frame, rot_to_local, to_local
from dancing_points_addon.skeleton import LOWER_BODY, TRACKED


def _tracked(d):
    return d.positions[:, TRACKED]


def sample_times(n: int) -> np.ndarray:
    return np.arange(0, max(n - F.FUTURE, 0))


def mapping_inputs(clip) -> np.ndarray:
    """Mapping input at every frame of a clip (past window padded at the start)."""
    n = clip.n_frames
    pi = F.window_indices(np.arange(n), n, np.arange(-F.PAST + 1, 1))
    return F.mapping_input(clip.leader.roots[pi], _tracked(clip.leader)[pi])


def mapping_samples(clips):
    xs, ys = [], []
    fut = np.arange(1, F.FUTURE + 1)
    for c in clips:
        if c.follower is None:
            continue
        t = sample_times(c.n_frames)
        if len(t) == 0:
            continue
        L, Fo = c.leader, c.follower
        fi = t[:, None] + fut[None, :]
        xs.append(mapping_inputs(c)[t])
        ys.append(F.mapping_target(L.roots[t], L.roots[fi], _tracked(L)[fi], Fo.roots[fi], _tracked(Fo)[fi]))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


def placement_samples(clips):
    """The placement network's samples: the mapping's (:func:`mapping_samples`)
    with her true roots at ``PLACEMENT_LAGS`` frames back (clamped at the clip's
    start) relative to the leader's current root beside each input: ``x (n, PLACE_IN)``,
    ``y (n, MAP_OUT)``. Clean: :func:`noisy_placement_state` perturbs them."""
    x, y = mapping_samples(clips)
    states = []
    for c in clips:
        if c.follower is None:
            continue
        t = sample_times(c.n_frames)
        lag = np.maximum(t[:, None] - np.array(F.PLACEMENT_LAGS)[None], 0)
        states.append(F.placement_state(c.leader.roots[t], c.follower.roots[lag]))
    return np.concatenate([x, np.concatenate(states).astype(np.float32)], axis=1), y


def noisy_placement_state(x, rng, position_sd, heading_sd, jitter_sd=0.02):
    """A copy of placement inputs ``x (n, PLACE_IN)`` whose state (her past roots)
    is moved as a whole by a random offset and turn (each sample a uniform share of
    ``position_sd`` m and ``heading_sd`` rad, from clean to the full draw), plus
    ``jitter_sd`` m of noise per root: at run time the state is her own placement,
    never her true one, and the network must read the leader's lead beside it."""
    x = np.array(x, dtype=np.float32, copy=True)
    n, k = len(x), len(F.PLACEMENT_LAGS)
    s = x[:, F.MAP_IN:].reshape(n, k, 4).astype(np.float64)
    share = rng.uniform(0.0, 1.0, (n, 1))
    s[:, :, :2] += (rng.normal(0.0, position_sd, (n, 2)) * share)[:, None]
    s[:, :, :2] += rng.normal(0.0, jitter_sd, (n, k, 2))
    turn = rng.normal(0.0, heading_sd, (n, 1)) * share
    c, si = s[:, :, 2].copy(), s[:, :, 3].copy()
    s[:, :, 2], s[:, :, 3] = c * np.cos(turn) - si * np.sin(turn), si * np.cos(turn) + c * np.sin(turn)
    x[:, F.MAP_IN:] = s.reshape(n, -1)
    return x


def _duet_frames(clips, target):
    """The mapping input at every frame of the duet clips, with ``target(clip)``
    ``(n, k)`` beside it (the networks on the mapping's input)."""
    xs, ys = [], []
    for c in clips:
        if c.follower is None:
            continue
        xs.append(mapping_inputs(c))
        ys.append(target(c))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


def contact_samples(clips):
    """The contact network's samples: the mapping input at every frame of the
    duet clips and both dancers' SPEC §6 contacts there ``(n, 8)`` (leader's four
    foot points, then the follower's; each clip's own floor levels)."""
    return _duet_frames(clips, lambda c: np.concatenate([c.leader.contacts, c.follower.contacts], axis=1))


def anchor_samples(clips):
    """The pose anchor's samples: the mapping input at every frame of the duet
    clips and the follower's lower body there, in her own hip frame (pelvis
    floor point, hip heading), ``(n, 3 × len(LOWER_BODY))``."""
    def lower_body(c):
        pos = c.follower.positions
        return to_local(pos, hip_frame(pos))[:, LOWER_BODY].reshape(len(pos), -1)

    return _duet_frames(clips, lower_body)


def hip_heading_samples(clips):
    """The hip-heading network's samples: the mapping input at every frame of the
    duet clips and the bin of the follower's hip heading relative to the
    leader's root heading there, one-hot ``(n, HIP_BINS)``."""
    from dancing_points_addon.follower import HIP_BINS, hip_heading_bins
    from dancing_points_addon.representation import hip_heading

    def bins(c):
        rel = hip_heading(c.follower.positions) - np.arctan2(c.leader.roots[:, 3], c.leader.roots[:, 2])
        return np.eye(HIP_BINS, dtype=np.float32)[hip_heading_bins(rel)]

    return _duet_frames(clips, bins)


def floor_levels_of(clips, role: str) -> list:
    """A dancer's floor level per foot point (m): the median over the duet clips of
    each clip's SPEC §6 floor level (the 5th percentile of the point's height)."""
    from dancing_points_addon.representation import floor_levels
    from dancing_points_addon.skeleton import FEET

    levels = [floor_levels(getattr(c, role).positions[:, FEET, 1]) for c in clips if c.follower is not None]
    return [round(float(v), 5) for v in np.median(levels, axis=0)]


def mapping_predictions(clip, mapping_fn):
    """The mapping network's output at every frame τ of a clip, decoded: per
    dancer, world roots ``(n, FUTURE, 4)`` and own-root tracked points of frames
    τ+1 … τ+30."""
    y = mapping_fn(mapping_inputs(clip).astype(np.float32)).astype(np.float64)
    return F.decode_mapping(y, clip.leader.roots)


def tracking_samples(clips, role: str, past_input: bool = False, mapping_fn=None):
    """Tracker samples of one dancer (``role`` 'leader' or 'follower').

    Without ``mapping_fn`` the keys are the ground truth future (teacher
    forcing). With it, keys are what the runtime feeds (see the module doc) and
    the follower's root is anchored to the mapping's prediction.
    ``past_input`` builds ablation (b): the key slots carry the dancer's *past*
    three-point trajectory (frames t + 1 − k) and no mapping is used.
    Returns ``x, y`` and the (clip index, t) of every sample.
    """
    xs, ys, where = [], [], []
    keys = F.TRACK_KEYS
    for ci, c in enumerate(clips):
        d = getattr(c, role)
        if d is None:
            continue
        n = c.n_frames
        t = sample_times(n)
        if len(t) == 0:
            continue
        ki = t[:, None] + keys[None, :]
        f0 = d.roots[t]
        if past_input:
            src = F.window_indices(t + 1, n, 1 - keys)
            key_roots, key_tr = d.roots[src], to_local(_tracked(d)[src], d.roots[src])
        elif mapping_fn is None:
            key_roots, key_tr = d.roots[ki], to_local(_tracked(d)[ki], d.roots[ki])
        else:
            who = 0 if role == "leader" else 1
            roots, tr = mapping_predictions(c, mapping_fn)[who]
            nxt = np.minimum(t + 1, n - 1)
            key_roots = np.empty((len(t), len(keys), 4))
            key_tr = np.empty((len(t), len(keys), 3, 3))
            key_roots[:, 1:] = roots[nxt][:, keys[1:] - 2]
            key_tr[:, 1:] = tr[nxt][:, keys[1:] - 2]
            if role == "leader":  # key 1 is the observed input
                key_roots[:, 0] = d.roots[t + 1]
                key_tr[:, 0] = to_local(_tracked(d)[t + 1], d.roots[t + 1])
            else:  # the mapping's previous prediction of frame t + 1; F0 its prediction of t
                key_roots[:, 0], key_tr[:, 0] = roots[t, 0], tr[t, 0]
                prev = np.maximum(t - 1, 0)
                f0 = np.where((t > 0)[:, None], roots[prev, 0], d.roots[t])
        pos_l = to_local(d.positions[t], f0)
        rot_l = rot_to_local(d.rotations[t], f0)
        pose = F.pose_features(pos_l, rot_l, d.contacts[t])
        xs.append(F.tracking_input(pose, f0, key_roots, key_tr))
        ys.append(F.tracking_target(f0, d.roots[ki], d.positions[ki], d.rotations[ki], d.contacts[ki]))
        where.append(np.stack([np.full(len(t), ci), t], axis=1))
    return (np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32),
            np.concatenate(where))


def next_pose_features(y_key1: np.ndarray) -> np.ndarray:
    """The runtime's next state from a tracker's first output key: its pose block
    with the 6D rotations orthonormalised and contacts clipped (batched)."""
    from dancing_points_addon.representation import rot6d, rot6d_to_matrix

    n = len(y_key1)
    pos = y_key1[:, F.KEY_POS]
    rot = rot6d(rot6d_to_matrix(y_key1[:, F.KEY_ROT].reshape(n, F.N_JOINTS, 6).astype(np.float64)))
    con = np.clip(y_key1[:, F.KEY_CON], 0.0, 1.0)
    return np.concatenate([pos, rot.reshape(n, -1), con], axis=1).astype(np.float32)


def rollout_states(model_fn, x, where, steps=10, stride=2, record=(2, 5, 10)):
    """Closed-loop states: from every ``stride``-th sample, roll the tracker
    ``steps`` frames forward on the samples' own key inputs (anchored roots), and
    return the sample indices and the rolled-out pose features at ``record`` steps.

    With the roots anchored, a rolled-out sample differs from its ground-truth
    sample only in the pose block, so its target stays the ground truth's.
    """
    starts = np.arange(0, len(x), stride)
    state = x[starts, :F.POSE_DIM].copy()
    idx_out, pose_out = [], []
    for j in range(1, steps + 1):
        cur = starts + j - 1
        ok = (cur < len(x))
        ok[ok] &= (where[cur[ok], 0] == where[starts[ok], 0]) & (where[cur[ok], 1] == where[starts[ok], 1] + j - 1)
        starts, state, cur = starts[ok], state[ok], cur[ok]
        if len(starts) == 0:
            break
        xin = x[cur].copy()
        xin[:, :F.POSE_DIM] = state
        y = model_fn(xin)
        state = next_pose_features(y[:, :F.KEY_OUT])
        nxt = cur + 1
        ok2 = nxt < len(x)
        ok2[ok2] &= (where[nxt[ok2], 0] == where[cur[ok2], 0]) & (where[nxt[ok2], 1] == where[cur[ok2], 1] + 1)
        if j in record:
            idx_out.append(nxt[ok2])
            pose_out.append(state[ok2])
    return np.concatenate(idx_out), np.concatenate(pose_out)


def time_warp(clips, rates):
    """Duet clips replayed at other speeds (``rate`` source frames per output
    frame: 1.1 is 10 % faster), by the runtime's resampling (positions linear,
    rotations by slerp); root frames and contacts derived again. For the
    mapping network: partners dance the same figures to other tempi."""
    from training.dataset import Clip, Dancer
    from dancing_points_addon.resample import resample_motion
    from dancing_points_addon.skeleton import Motion

    def warp(d, rate):  # the frames read as if sampled at rate × 30 Hz, resampled to 30 Hz
        m = resample_motion(Motion(d.positions, d.rotations, F.FPS * rate, np.zeros((31, 3))), F.FPS)
        return Dancer.from_arrays(m.positions, m.rotations, F.FPS)

    return [Clip(f"{c.name}x{r:g}", warp(c.leader, r), warp(c.follower, r), c.mirrored)
            for c in clips if c.follower is not None for r in rates]


def time_reverse(clips):
    """Duet clips played backwards (root frames and contacts derived again). For
    the mapping network: a take's start, where the couple walks together from
    about 2 m, played backwards is a couple separating, which no train frame
    shows otherwise (the takes' endings are test frames); and every figure
    played backwards is a lead and its answer all the same."""
    from training.dataset import Clip, Dancer

    def back(d):
        return Dancer.from_arrays(d.positions[::-1].copy(), d.rotations[::-1].copy(), F.FPS)

    return [Clip(f"{c.name}r", back(c.leader), back(c.follower), c.mirrored) for c in clips if c.follower is not None]


def default_pose(x: np.ndarray, where=None, clips=None) -> list:
    """Pose features of the train sample nearest the mean pose (normalised): the
    runtime's start-up pose, placed under the head. Its skeleton becomes the
    runtime's, so it is drawn from the unmirrored clips (a mirrored body has its
    left and right bone lengths swapped)."""
    if where is not None:
        x = x[~np.array([clips[int(c)].mirrored for c in where[:, 0]])]
    pose = x[:, :F.POSE_DIM].astype(np.float64)
    z = (pose - pose.mean(0)) / (pose.std(0) + 1e-6)
    return pose[int(np.argmin((z ** 2).sum(1)))].round(6).tolist()


def device_offset_clips(clips, rng, offset_m: float = 0.03, scale: float = 0.03):
    """A copy of each duet clip as a different wearer and headset would give
    it: the leader's three points each moved by a constant offset in its own
    device's frame (uniform in ±``offset_m`` per axis: the skull for the head,
    the hand bone for a hand, as the body offsets of an OpenXR take are wrong,
    see ``formats.devices``), and the whole couple scaled by a constant
    factor within ±``scale`` (a height misjudged). His roots follow his moved
    head; her points are hers, scaled. For the networks that read his points
    (the mapping and the others on its input), which must not hinge on either."""
    from dancing_points_addon.representation import root_from_motion
    from dancing_points_addon.skeleton import JOINT_INDEX as J

    bones = (J["head"], J["lhand"], J["rhand"])
    out = []
    for c in clips:
        if c.follower is None:
            continue
        s = 1.0 + rng.uniform(-scale, scale)
        off = rng.uniform(-offset_m, offset_m, (3, 3))
        L, Fo = c.leader, c.follower
        pos = L.positions * s
        pos[:, TRACKED] += np.einsum("tdij,dj->tdi", L.rotations[:, list(bones)], off)
        lead = type(L)(pos, L.rotations, root_from_motion(pos, L.rotations), L.contacts)
        fol = type(Fo)(Fo.positions * s, Fo.rotations, Fo.roots * np.array([s, s, 1.0, 1.0]), Fo.contacts)
        out.append(type(c)(c.name + "o", lead, fol, c.mirrored))
    return out
