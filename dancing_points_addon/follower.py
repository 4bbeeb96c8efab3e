"""The follower's own state: where she stands, how her hands meet the leader's,
how far the two torsos stay apart. Causal, deterministic, per frame.

The mapping network re-predicts the follower's three points every frame from
the leader's last 0.5 s; taken as they come, that placement jumps from frame to
frame (she "skates" after it) and nothing ties her to the leader on a long
take. :class:`Placement` keeps her root as a state instead:

* **target**: the mapping's predicted placement of her root *relative to the
  leader* over the next ``horizon`` frames, averaged (a denoised estimate), and
  limited to the distances a couple keeps (``max_offset``);
* **keys**: her tracker is fed the mapping's predicted trajectory *shape*
  (each key relative to the first predicted frame) re-attached to her own
  current root, eased towards the target (``ease``): the tracker walks her
  there with her feet instead of being shown a jump;
* **step**: her new root is the tracker's own next root (tied to the steps it
  takes) pulled the share ``pull`` of the way towards the target, and moved at
  most ``max_speed`` m/s and turned at most ``max_turn`` rad/s.

Why it stays bounded (a take of any length): the target lies within
``max_offset`` of the leader's root, which is the input head's; each frame the
pull closes the share ``pull`` of her distance to it, and she is never farther
than ``max_gap`` from it (a leash that a smooth take never reaches: the pull
alone keeps her within a few centimetres to decimetres of it; the evaluation
counts the frames it engages). So her root is within ``max_offset + max_gap``
of the leader's in every frame. Her body is re-centred on her root and fed
back as a rigid skeleton every frame (see ``runtime``), so it can neither
walk away from the root nor stretch.

:class:`Separation` keeps the two torsos (the pelvis-to-lower-neck axes)
at least ``min_distance`` apart by moving the follower horizontally. Her hips
and her hands in a hold are :mod:`.partner_pose`; the options of all of these
are here.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import atan2, cos, hypot, sin, sqrt

import numpy as np

from .features import FPS
from .foot_lock import FootLockOptions
from .option_checks import check_kinds, check_range
from .representation import blend_root, compose_floats, relative_rows, vector_norm
from .scalar_kernels import segments_gap_s
from .skeleton import JOINT_INDEX, joint_rows

PELVIS, NECK = JOINT_INDEX["root"], JOINT_INDEX["lowerneck"]
_TORSO = joint_rows((PELVIS, NECK))  # the rows (pelvis, lower neck)


@dataclass(frozen=True)
class PlacementOptions:
    """Where the partner stands and faces (:class:`Placement`) and how far the
    two torsos stay apart (:class:`Separation`)."""

    horizon: int = 10  # predicted frames averaged into the placement target
    pull: float = 0.05  # share of the gap to the target closed per frame
    pull_heading: float = 0.05  # the same for the heading
    face_leader: float = 0.5  # share of the target heading turned to face the tracked dancer
    smooth: float = 0.8  # exponential smoothing of the predicted trajectories across frames (0: none)
    ease: float = 0.1  # per-frame easing of the tracker's keys towards the target
    max_speed: float = 2.5  # m/s, the root's horizontal speed
    max_turn: float = 6.0  # rad/s, the root's turn rate
    max_offset: float = 2.0  # m, the farthest target from the tracked dancer's root
    max_gap: float = 0.8  # m, the farthest the partner may lag behind the target (a leash)
    min_distance: float = 0.2  # m, between the torso axes (0: no separation)

    def __post_init__(self):
        check_range("PlacementOptions", "horizon", self.horizon, 1)
        for name in ("pull", "pull_heading", "face_leader", "ease"):
            check_range("PlacementOptions", name, getattr(self, name), 0.0, 1.0)
        check_range("PlacementOptions", "smooth", self.smooth, 0.0, 1.0)
        for name in ("max_speed", "max_turn", "max_offset", "max_gap"):
            check_range("PlacementOptions", name, getattr(self, name), 0.0, low_open=True)
        check_range("PlacementOptions", "min_distance", self.min_distance, 0.0)


@dataclass(frozen=True)
class PoseOptions:
    """The partner's body beyond its tracker (``pose.LegJoints``,
    ``ik.ArmTurnLimit``, ``pose.OutputSmoothing``)."""

    anchor: float = 0.3  # share a frame the lower body moves to the pose anchor network's (0: off)
    arm_turn: float = 30.0  # degrees a frame an arm may turn against the chest (0: free)
    out_thigh_twist: float = 30.0  # degrees: the output thighs' twist against the pelvis at most (0: unlimited)
    out_smooth: float | None = None  # share of the last output frame kept in the next (0: none; None: OUT_SMOOTH)

    def __post_init__(self):
        check_range("PoseOptions", "anchor", self.anchor, 0.0, 1.0)
        check_range("PoseOptions", "arm_turn", self.arm_turn, 0.0)
        check_range("PoseOptions", "out_thigh_twist", self.out_thigh_twist, 0.0, 180.0)
        if self.out_smooth is not None:
            check_range("PoseOptions", "out_smooth", self.out_smooth, 0.0, 0.99)


@dataclass(frozen=True)
class HipOptions:
    """The partner's hips turned towards where the hip-heading network says
    they face (:class:`HipTwist`)."""

    share: float = 0.5  # share of the predicted turn taken (0: off)
    max_deg: float = 45.0  # degrees, at most
    rate: float = 0.2  # share of the remaining turn eased a frame

    def __post_init__(self):
        check_range("HipOptions", "share", self.share, 0.0, 1.0)
        check_range("HipOptions", "max_deg", self.max_deg, 0.0, 180.0)
        check_range("HipOptions", "rate", self.rate, 0.0, 1.0)


@dataclass(frozen=True)
class HoldOptions:
    """Hand holds: the partner's arms bent onto the tracked dancer's hands
    (:class:`HandHold`)."""

    enabled: bool = True  # hand holds by arm IK
    on: float = 0.7  # m, predicted wrist distance under which a hold is full
    off: float = 1.0  # m, over which there is none
    gap: float = 0.09  # m, wrist-to-wrist distance of a hold (wrist joints: the hands between them)
    frames: int = 6  # the hold's weight changes by at most 1 / frames a frame
    soft: float = 0.03  # m: the two hands held weighted by a softmax of distance / soft
    spring: float = 2.0  # Hz: the pull follows a critically damped spring
    lead: float = 0.5  # share of the pull's own (smoothed) velocity fed forward to the spring (0: none)
    lead_smooth: float = 0.7  # smoothing of that velocity across frames
    soft_rate: float = 0.04  # the softmax weights change by at most this much a frame (0: free)
    reach: float = 1.4  # × the arm: a hold whose goal is farther from the shoulder fades out (over 0.1)
    near: float = 0.35  # × the arm: a hold whose goal is this close to the shoulder fades out (±0.1; 0: never)

    def __post_init__(self):
        check_range("HoldOptions", "on", self.on, 0.0)
        check_range("HoldOptions", "off", self.off, self.on)
        check_range("HoldOptions", "gap", self.gap, 0.0)
        check_range("HoldOptions", "frames", self.frames, 1)
        check_range("HoldOptions", "soft", self.soft, 0.0, low_open=True)
        check_range("HoldOptions", "spring", self.spring, 0.0, low_open=True)
        for name in ("lead", "lead_smooth", "soft_rate"):
            check_range("HoldOptions", name, getattr(self, name), 0.0, 1.0)
        check_range("HoldOptions", "reach", self.reach, 0.0, low_open=True)
        check_range("HoldOptions", "near", self.near, 0.0)


@dataclass(frozen=True)
class StepOptions:
    """The partner's steps timed by the contact network (the foot lock's
    contacts and where a planting foot goes)."""

    contact_smooth: float = 0.5  # smoothing of the contact probabilities across frames
    lock_floor: float = 0.01  # m: a planting foot is put at most this far above the floor (< 0: where it is)

    def __post_init__(self):
        check_range("StepOptions", "contact_smooth", self.contact_smooth, 0.0, 0.99)


# The partner's foot lock: the tracked dancer's (``FootLockOptions()``) with
# looser switches, longer blends and catch-up steps that lift the whole foot.
def check_partner_networks(options, nets: dict, foot_lock: bool, floor_levels) -> None:
    """A ``ValueError`` naming the network that her ``options`` (a
    :class:`FollowerOptions`, or None: no partner model) need and ``nets`` lack
    (``floor_levels``: the contact network's, None when it has none)."""
    if options is None:
        return
    if foot_lock and floor_levels is None:
        raise ValueError("the follower's foot lock needs the contact network (contacts.onnx "
                         "with floor_levels in its metadata)")
    if options.pose.anchor > 0.0 and nets.get("anchor") is None:
        raise ValueError("PoseOptions.anchor needs the pose anchor network (pose_anchor.onnx)")
    if options.hips.share > 0 and nets.get("hip") is None:
        raise ValueError("HipOptions.share needs the hip-heading network (hip_heading.onnx)")
    if nets.get("placement") is None:
        raise ValueError("the follower's placement needs the placement network (placement.onnx)")


PARTNER_FOOT_LOCK = FootLockOptions(on=0.4, off=0.3, blend_frames=10, max_drift=0.3, step_height=0.04,
                                    step_max=0.06, step_frames=9, clearance=0.05, clear_rate=0.125,
                                    land_still=True, lift_ball=True)


@dataclass(frozen=True)
class FollowerOptions:
    """The synthesised partner's settings, one small options object per part.
    Chosen on the val frames; the figures behind each are in models/README.md
    ("What the runtime does with them") and docs/experiments.md (what else
    was tried)."""

    placement: PlacementOptions = PlacementOptions()  # where the partner stands and faces
    pose: PoseOptions = PoseOptions()  # the body beyond the tracker
    hips: HipOptions = HipOptions()  # the hips' turn
    holds: HoldOptions = HoldOptions()  # hand holds
    steps: StepOptions = StepOptions()  # steps timed by the contact network
    foot_lock: FootLockOptions = PARTNER_FOOT_LOCK  # the foot lock (``foot_lock.FootLocker``)

    def __post_init__(self):
        check_kinds(self, {"placement": PlacementOptions, "pose": PoseOptions, "hips": HipOptions,
                           "holds": HoldOptions, "steps": StepOptions, "foot_lock": FootLockOptions})


# ``PoseOptions.out_smooth`` by the synthesised partner's dance role: his
# output (a follower's take) low-passed, hers not (val: docs/experiments.md)
OUT_SMOOTH = {"leader": 0.3, "follower": 0.0}


class Placement:
    """The follower's root as a state (see the module docstring)."""

    def __init__(self, options: PlacementOptions):
        self.o = options
        self._prev = None
        self._plan = None  # :meth:`_key_plan`'s
        self._shift = ()  # :meth:`smooth`'s frame indices
        self.leashed = 0  # frames on which the leash engaged (reported, expected rare)

    def smooth(self, *arrays):
        """Exponential smoothing across frames of the mapping's predicted
        trajectories (arrays ``(FUTURE, …)`` of frames t+1 …): this frame's
        prediction of frame t+1+j is blended with last frame's of the same
        frame (its index j+1; the last one held)."""
        b = self.o.smooth
        if b <= 0:
            return arrays
        prev = self._prev
        if prev is not None:
            n = len(prev[0])
            if len(self._shift) != n:  # last frame's predictions one frame on, the last one held
                self._shift = np.minimum(np.arange(1, n + 1), n - 1)
            arrays = tuple(b * p.take(self._shift, axis=0) + (1.0 - b) * a for p, a in zip(prev, arrays))
        self._prev = arrays
        roots = arrays[0].copy()  # heading rows back to unit length
        roots[:, 2:] /= vector_norm(roots[:, 2:], keepdims=True)
        return (roots,) + tuple(arrays[1:])

    def target(self, leader_root, l_roots, f_roots):
        """The mapping's placement of the follower relative to the leader, averaged
        over the first ``horizon`` predicted frames (as ``(dx, dz, cos, sin)``),
        and the world root it gives at the leader's current root."""
        h = max(1, min(self.o.horizon, len(f_roots)))
        rel = relative_rows(l_roots[:h].T, f_roots[:h].T)  # (C-ordered: relative_rows copies its roots)
        dx, dz, c, s = (np.add.reduce(rel, axis=1) / h).tolist()  # (rel.mean(axis=1)'s arithmetic)
        n = max(hypot(c, s), 1e-9)
        d = hypot(dx, dz)
        if d > self.o.max_offset:  # farther than a couple stands: the nearest point within reach
            dx, dz = dx * self.o.max_offset / d, dz * self.o.max_offset / d
        c, s = c / n, s / n
        if self.o.face_leader > 0 and hypot(dx, dz) > 1e-6:
            # facing the leader, in his frame: heading of the direction (−dx, −dz)
            d = hypot(dx, dz)
            fc, fs = -dz / d, -dx / d
            c, s = c + self.o.face_leader * (fc - c), s + self.o.face_leader * (fs - s)
            n = max(hypot(c, s), 1e-9)
            c, s = c / n, s / n
        off = [dx, dz, c, s]
        return off, compose_floats(leader_root.tolist(), off)

    def keys(self, root, f_roots, l_roots, leader_root, offset, key_index):
        """Key roots ``(K, 4)`` for the tracker at frames ``t − 1 + k``: the mapping's
        predicted trajectory shape re-attached to the follower's current root
        ``root`` (frame t − 1), eased towards the target placement.
        ``key_index``: per key k ≥ 2 the mapping index of frame t + k − 1 … (see
        runtime); key 1 uses the predicted first step."""
        weights, lead_index, steps = self._key_plan(key_index, len(l_roots))
        offset = [float(v) for v in offset]
        # one predicted step (frame t+1 -> t+2), taken for t-1 -> t and t -> t+1, and
        # the keys' predicted frames, all relative to the first predicted one (in one call)
        step, *rels = relative_rows(f_roots[0][:, None], f_roots.take(steps, axis=0).T).T.tolist()
        e1 = compose_floats([float(v) for v in root], step)
        e2 = compose_floats(e1, step)  # her frame t + 1 on the predicted path
        out = [blend_root(e1, compose_floats(leader_root.tolist(), offset), self.o.ease)]
        for rel, lead, w in zip(rels, l_roots.take(lead_index, axis=0).tolist(), weights):
            out.append(blend_root(compose_floats(e2, rel), compose_floats(lead, offset), w))
        return np.array(out)

    def _key_plan(self, key_index, n_lead):
        """Per ``key_index`` (kept while it is the same array): each key's ease
        weight, his predicted frame's index, and her predicted frames read
        (the first step's, then the keys')."""
        plan = self._plan
        if plan is None or plan[0] is not key_index or plan[1] != n_lead:
            ease = self.o.ease
            weights = [1.0 - (1.0 - ease) ** (idx + 2) for idx in key_index]  # k = idx + 2: frames after t - 1
            lead = [min(idx, n_lead - 1) for idx in key_index]
            steps = np.concatenate([[1], key_index]).astype(np.intp)
            plan = self._plan = (key_index, n_lead, weights, lead, steps)
        return plan[2:]

    def key_roots(self, root, prev_root, f_roots, l_roots, leader_root, offset, key_index):
        """Her tracker's key roots (:meth:`keys`; ``prev_root``, the prediction
        of her root at this frame, is :class:`PulledRoot`'s)."""
        return self.keys(root, f_roots, l_roots, leader_root, offset, key_index)

    @staticmethod
    def goal(target, key_roots):
        """Where :meth:`step` pulls her root: her target's world root."""
        return target[1]

    def step(self, prev, proposal, target):
        """The new root: ``proposal`` (the tracker's) pulled towards ``target``,
        within the speed and turn limits from ``prev``."""
        x, z, _, _ = blend_root(proposal, target, self.o.pull)
        _, _, c, s = blend_root(proposal, target, self.o.pull_heading)
        px, pz, pc, ps = prev
        dx, dz = x - px, z - pz
        d = hypot(dx, dz)
        lim = self.o.max_speed / FPS
        if d > lim:
            x, z = px + dx * lim / d, pz + dz * lim / d
        gx, gz = x - target[0], z - target[1]
        g = hypot(gx, gz)
        if g > self.o.max_gap:  # the leash: never farther than max_gap from her target
            self.leashed += 1
            x, z = target[0] + gx * self.o.max_gap / g, target[1] + gz * self.o.max_gap / g
        turn = atan2(s * pc - c * ps, c * pc + s * ps)
        tlim = self.o.max_turn / FPS
        if abs(turn) > tlim:
            a = atan2(ps, pc) + (tlim if turn > 0 else -tlim)
            c, s = cos(a), sin(a)
        return [x, z, c, s]


class PulledRoot:
    """Her root without the partner model (``Synthesizer(follower=None)``: the
    evaluation's ablation), with :class:`Placement`'s interface: her keys are
    the mapping's predicted roots as they are, and her tracker's own next root
    is pulled the share :attr:`pull` of the way to the first of them."""

    leashed = 0

    def __init__(self, pull: float = 0.1):
        self.pull = pull

    @staticmethod
    def smooth(*arrays):
        return arrays

    @staticmethod
    def target(leader_root, l_roots, f_roots):
        """No target: ``(None, her predicted root)``, where she starts."""
        return None, f_roots[0]

    @staticmethod
    def key_roots(root, prev_root, f_roots, l_roots, leader_root, offset, key_index):
        return np.concatenate([prev_root[None], f_roots.take(key_index, axis=0)])

    @staticmethod
    def goal(target, key_roots):
        return key_roots[0].tolist()

    def step(self, prev, proposal, goal):
        return blend_root(proposal, goal, self.pull)


class Separation:
    """Keep the follower's torso axis (pelvis to lower neck) at least
    ``min_distance`` from the leader's, horizontally, by moving her."""

    def __init__(self, min_distance: float):
        self.min_distance = float(min_distance)

    def push(self, leader_pos, follower_pos):
        """The horizontal shift (dx, dz) that puts the follower's torso axis
        ``min_distance`` from the leader's (0, 0 when it already is)."""
        if self.min_distance <= 0:
            return 0.0, 0.0
        (f0, f1), (l0, l1) = follower_pos[_TORSO].tolist(), leader_pos[_TORSO].tolist()
        diff = segments_gap_s(f0, f1, l0, l1)  # (on floats: numpy's per-call cost would dominate)
        d = np.array(diff)
        dist = sqrt(float(d @ d))  # (numpy's dot product, whose rounding the plain sum need not share)
        if dist >= self.min_distance:
            return 0.0, 0.0
        hx, hz = diff[0], diff[2]
        n = hypot(hx, hz)
        if n < 1e-6:  # axes crossing: away from the leader's pelvis
            hx = f0[0] - l0[0]
            hz = f0[2] - l0[2]
            n = hypot(hx, hz)
            if n < 1e-6:
                hx, hz, n = 0.0, 1.0, 1.0
        # horizontal move that opens the 3D gap to min_distance (the vertical part stays)
        need = self.min_distance - dist
        return hx / n * need * 1.05, hz / n * need * 1.05
