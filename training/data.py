"""Training samples for the mapping and tracking networks, from train-split clips.

Every sample's window lies inside one clip's train frames: the past window is
padded by repeating the clip's first frame (as the runtime pads at start-up)
and the future window must fit (t + 30 < n), so no sample reaches a test frame.

Tracker samples are teacher-forced: the state is the pose at frame t in the
dancer's own root, the keys the dancer's ground-truth future (the runtime feeds
the mapping's prediction in their place).
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
    from dancing_points_addon.partner_pose import HIP_BINS, hip_heading_bins
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


def tracking_samples(clips, role: str, past_input: bool = False):
    """Tracker samples of one dancer (``role`` 'leader' or 'follower').

    The keys are the ground truth future (teacher forcing).
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
        else:
            key_roots, key_tr = d.roots[ki], to_local(_tracked(d)[ki], d.roots[ki])
        pos_l = to_local(d.positions[t], f0)
        rot_l = rot_to_local(d.rotations[t], f0)
        pose = F.pose_features(pos_l, rot_l, d.contacts[t])
        xs.append(F.tracking_input(pose, f0, key_roots, key_tr))
        ys.append(F.tracking_target(f0, d.roots[ki], d.positions[ki], d.rotations[ki], d.contacts[ki]))
        where.append(np.stack([np.full(len(t), ci), t], axis=1))
    return (np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32),
            np.concatenate(where))


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


# body-shape augmentation: bone groups scaled together, both sides alike
SHAPE_GROUPS = {
    "spine": ("lowerback", "upperback", "thorax"),
    "neck": ("lowerneck", "upperneck", "head"),
    "shoulders": ("lclavicle", "rclavicle"),
    "upper arms": ("lhumerus", "rhumerus"),
    "forearms": ("lradius", "rradius"),
    "hands": ("lwrist", "lhand", "lfingers", "lthumb", "rwrist", "rhand", "rfingers", "rthumb"),
    "hips": ("lhipjoint", "rhipjoint"),
    "thighs": ("lfemur", "rfemur"),
    "shins": ("ltibia", "rtibia"),
    "feet": ("lfoot", "ltoes", "rfoot", "rtoes"),
}


def head_height(positions) -> float:
    """A body's upright head height (``calibration.upright_head``, as the
    runtime's calibration reads it) over its clips' positions ``(T, 31, 3)``."""
    from dancing_points_addon.calibration import upright_head

    return upright_head(np.concatenate([p[:, TRACKED[0], 1] for p in positions]))


def reshape_body(positions, rotations, factors) -> np.ndarray:
    """Positions ``(T, 31, 3)`` of the same motion (root path and bone
    rotations) on a skeleton whose bones are ``factors (31,)`` times as long."""
    from dancing_points_addon.pose import bone_vectors_from_pose, joints_from_rotations

    bv = bone_vectors_from_pose(positions[0], rotations[0]) * factors[:, None]
    return joints_from_rotations(positions[:, 0], rotations, bv)


def body_clips(duet_clips, solo, bodies, train_head: float, rng=None, shape: float = 0.0, copies: int = 0):
    """Single-dancer clips (the dancer in ``leader``) of every body in ``bodies``
    ("leader", "follower": the salsa dancers of ``duet_clips``; "solo": the
    clips ``solo``), each body scaled as a whole so that its upright head is at
    ``train_head`` (as the runtime scales a wearer to the training height), for
    a tracker that serves any body. ``copies`` more copies of every clip with
    each bone group (:data:`SHAPE_GROUPS`) ``1 ± shape`` as long (uniform, one
    draw per clip), scaled back to ``train_head``: bodies between and beyond
    those of the data. Returns the clips, the first body's first, and how many
    of them are the first body's own (unreshaped)."""
    from dancing_points_addon.skeleton import JOINT_INDEX as J
    from training.dataset import Clip, Dancer

    out, n_first = [], None
    for body in bodies:
        if body == "solo":
            src = [(c, c.leader) for c in solo or []]
        else:
            src = [(c, getattr(c, body)) for c in duet_clips if getattr(c, body) is not None]
        if src:
            s = train_head / head_height(d.positions for _, d in src)
            out += [Clip(c.name + ("" if body == "solo" else body[0]), Dancer.from_arrays(d.positions * s, d.rotations),
                         None, c.mirrored) for c, d in src]
        n_first = len(out) if n_first is None else n_first
    if copies and shape > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        base = list(out)
        for k in range(copies):
            for c in base:
                f = np.ones(31)
                for names in SHAPE_GROUPS.values():
                    f[[J[n] for n in names]] = 1.0 + rng.uniform(-shape, shape)
                pos = reshape_body(c.leader.positions, c.leader.rotations, f)
                pos *= train_head / head_height([pos])
                out.append(Clip(f"{c.name}s{k}", Dancer.from_arrays(pos, c.leader.rotations), None, c.mirrored))
    return out, n_first
