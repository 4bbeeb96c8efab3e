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
at least ``min_distance`` apart by moving the follower horizontally, and
:class:`HandHold` bends her arms onto the leader's hands when the two are in a
hold, blended in and out, the pull following a critically damped spring, and
:class:`HipTwist` turns her hips towards where the mapping says she faces
while her upper body stays turned to him.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import atan2, cos, hypot, pi, sin

import numpy as np

from .features import FPS
from .foot_lock import FootLockOptions
from .representation import blend_root, compose_floats, relative_rows, segments_gap
from .skeleton import HIPS, JOINT_INDEX, LOWER_BODY, WRISTS

PELVIS, NECK = JOINT_INDEX["root"], JOINT_INDEX["lowerneck"]


def _compose(ref, rel):
    """:func:`~.representation.root_compose` of two roots given as lists."""
    return compose_floats([float(v) for v in ref], [float(v) for v in rel])


def _check(owner, name, value, low=None, high=None, low_open=False):
    """``value`` within ``low`` .. ``high`` (``low`` excluded when ``low_open``), or
    a ValueError naming ``owner.name``."""
    ok = (low is None or (value > low if low_open else value >= low)) and (high is None or value <= high)
    if not ok:
        lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
        hi = "" if high is None else f"<= {high}"
        raise ValueError(f"{owner}.{name} must be {' and '.join(x for x in (lo, hi) if x)}, not {value!r}")


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
        _check("PlacementOptions", "horizon", self.horizon, 1)
        for name in ("pull", "pull_heading", "face_leader", "ease"):
            _check("PlacementOptions", name, getattr(self, name), 0.0, 1.0)
        _check("PlacementOptions", "smooth", self.smooth, 0.0, 1.0)
        for name in ("max_speed", "max_turn", "max_offset", "max_gap"):
            _check("PlacementOptions", name, getattr(self, name), 0.0, low_open=True)
        _check("PlacementOptions", "min_distance", self.min_distance, 0.0)


@dataclass(frozen=True)
class PoseOptions:
    """The partner's body beyond its tracker (``pose.LegJoints``,
    ``ik.ArmTurnLimit``, ``pose.OutputSmoothing``)."""

    anchor: float = 0.3  # share a frame the lower body moves to the pose anchor network's (0: off)
    arm_turn: float = 30.0  # degrees a frame an arm may turn against the chest (0: free)
    out_thigh_twist: float = 30.0  # degrees: the output thighs' twist against the pelvis at most (0: unlimited)
    out_smooth: float | None = None  # share of the last output frame kept in the next (0: none; None: OUT_SMOOTH)

    def __post_init__(self):
        _check("PoseOptions", "anchor", self.anchor, 0.0, 1.0)
        _check("PoseOptions", "arm_turn", self.arm_turn, 0.0)
        _check("PoseOptions", "out_thigh_twist", self.out_thigh_twist, 0.0, 180.0)
        if self.out_smooth is not None:
            _check("PoseOptions", "out_smooth", self.out_smooth, 0.0, 0.99)


@dataclass(frozen=True)
class HipOptions:
    """The partner's hips turned towards where the hip-heading network says
    they face (:class:`HipTwist`)."""

    share: float = 0.5  # share of the predicted turn taken (0: off)
    max_deg: float = 45.0  # degrees, at most
    rate: float = 0.2  # share of the remaining turn eased a frame

    def __post_init__(self):
        _check("HipOptions", "share", self.share, 0.0, 1.0)
        _check("HipOptions", "max_deg", self.max_deg, 0.0, 180.0)
        _check("HipOptions", "rate", self.rate, 0.0, 1.0)


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
        _check("HoldOptions", "on", self.on, 0.0)
        _check("HoldOptions", "off", self.off, self.on)
        _check("HoldOptions", "gap", self.gap, 0.0)
        _check("HoldOptions", "frames", self.frames, 1)
        _check("HoldOptions", "soft", self.soft, 0.0, low_open=True)
        _check("HoldOptions", "spring", self.spring, 0.0, low_open=True)
        for name in ("lead", "lead_smooth", "soft_rate"):
            _check("HoldOptions", name, getattr(self, name), 0.0, 1.0)
        _check("HoldOptions", "reach", self.reach, 0.0, low_open=True)
        _check("HoldOptions", "near", self.near, 0.0)


@dataclass(frozen=True)
class StepOptions:
    """The partner's steps timed by the contact network (the foot lock's
    contacts and where a planting foot goes)."""

    contact_smooth: float = 0.5  # smoothing of the contact probabilities across frames
    lock_floor: float = 0.01  # m: a planting foot is put at most this far above the floor (< 0: where it is)

    def __post_init__(self):
        _check("StepOptions", "contact_smooth", self.contact_smooth, 0.0, 0.99)


# The partner's foot lock: the tracked dancer's (``FootLockOptions()``) with
# looser switches, longer blends and catch-up steps that lift the whole foot.
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
        for name, kind in (("placement", PlacementOptions), ("pose", PoseOptions), ("hips", HipOptions),
                           ("holds", HoldOptions), ("steps", StepOptions), ("foot_lock", FootLockOptions)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"FollowerOptions.{name} must be a {kind.__name__}, not {getattr(self, name)!r}")


# ``PoseOptions.out_smooth`` by the synthesised partner's dance role: his
# output (a follower's take) low-passed, hers not (val: docs/experiments.md)
OUT_SMOOTH = {"leader": 0.3, "follower": 0.0}


class Placement:
    """The follower's root as a state (see the module docstring)."""

    def __init__(self, options: PlacementOptions):
        self.o = options
        self._prev = None
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
            arrays = tuple(b * np.concatenate([p[1:], p[-1:]]) + (1.0 - b) * a for p, a in zip(prev, arrays))
        self._prev = arrays
        roots = arrays[0].copy()  # heading rows back to unit length
        roots[:, 2:] /= np.linalg.norm(roots[:, 2:], axis=-1, keepdims=True)
        return (roots,) + tuple(arrays[1:])

    def target(self, leader_root, l_roots, f_roots):
        """The mapping's placement of the follower relative to the leader, averaged
        over the first ``horizon`` predicted frames (as ``(dx, dz, cos, sin)``),
        and the world root it gives at the leader's current root."""
        h = max(1, min(self.o.horizon, len(f_roots)))
        rel = relative_rows(np.ascontiguousarray(l_roots[:h].T), np.ascontiguousarray(f_roots[:h].T))
        dx, dz, c, s = (float(v) for v in rel.mean(axis=1))
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
        return off, _compose(leader_root.tolist(), off)

    def keys(self, root, f_roots, l_roots, leader_root, offset, key_index):
        """Key roots ``(K, 4)`` for the tracker at frames ``t − 1 + k``: the mapping's
        predicted trajectory shape re-attached to the follower's current root
        ``root`` (frame t − 1), eased towards the target placement.
        ``key_index``: per key k ≥ 2 the mapping index of frame t + k − 1 … (see
        runtime); key 1 uses the predicted first step."""
        base = f_roots[0].tolist()
        # one predicted step (frame t+1 -> t+2), taken for t-1 -> t and t -> t+1
        step = relative_rows(np.array(base)[:, None], f_roots[1][:, None])[:, 0].tolist()
        e1 = _compose(root, step)
        e2 = _compose(e1, step)  # her frame t + 1 on the predicted path
        ease = self.o.ease
        out = [blend_root(e1, _compose(leader_root.tolist(), offset), ease)]
        rels = relative_rows(np.repeat(np.array(base)[:, None], len(key_index), axis=1),
                             np.ascontiguousarray(f_roots[key_index].T)).T.tolist()
        for rel, idx in zip(rels, key_index):
            k = idx + 2  # frames after t - 1
            w = 1.0 - (1.0 - ease) ** k
            out.append(blend_root(_compose(e2, rel), _compose(l_roots[min(idx, len(l_roots) - 1)].tolist(), offset), w))
        return np.array(out)

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
        diff = segments_gap(follower_pos[PELVIS], follower_pos[NECK], leader_pos[PELVIS], leader_pos[NECK])
        dist = float(np.sqrt(diff @ diff))
        if dist >= self.min_distance:
            return 0.0, 0.0
        hx, hz = float(diff[0]), float(diff[2])
        n = hypot(hx, hz)
        if n < 1e-6:  # axes crossing: away from the leader's pelvis
            hx = float(follower_pos[PELVIS, 0] - leader_pos[PELVIS, 0])
            hz = float(follower_pos[PELVIS, 2] - leader_pos[PELVIS, 2])
            n = hypot(hx, hz)
            if n < 1e-6:
                hx, hz, n = 0.0, 1.0, 1.0
        # horizontal move that opens the 3D gap to min_distance (the vertical part stays)
        need = self.min_distance - dist
        return hx / n * need * 1.05, hz / n * need * 1.05


HIP_BINS = 36  # the hip-heading network's bins over the full turn


def hip_bin_directions(bins: int = HIP_BINS) -> np.ndarray:
    """``(bins, 2)``: (cos, sin) of each bin's centre, the angles −π … π (bin k
    holds the angles from −π + 2πk / bins)."""
    a = (np.arange(bins) + 0.5) / bins * 2.0 * np.pi - np.pi
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def hip_heading_bins(angles: np.ndarray, bins: int = HIP_BINS) -> np.ndarray:
    """The bin of each angle (radians, any range) (:func:`hip_bin_directions`)."""
    return np.floor((np.asarray(angles) + np.pi) / (2.0 * np.pi) * bins).astype(np.int64) % bins


_HIP_DIRS = hip_bin_directions()


def hip_heading_from_probs(probs, leader_root) -> float:
    """Her hip heading (radians, as ``hip_heading``) from the hip-heading
    network's bin probabilities ``(HIP_BINS,)`` (relative to his root) and his
    root ``(x, z, cos, sin)``: the bins' circular mean, turned into the world."""
    c, s = (np.asarray(probs, dtype=np.float64).reshape(-1) @ _HIP_DIRS).tolist()
    return atan2(s, c) + atan2(float(leader_root[3]), float(leader_root[2]))


class HipTwist:
    """Her hips (pelvis and legs) turned about the vertical through her pelvis,
    her upper body left as it is (see ``HipOptions``). Real
    dancers' hips and heads face apart by 25 degrees on average (the follower's,
    in the salsa val frames); her placement turns her root half way to face
    the leader, which keeps her holds within reach, and the hip-heading
    network's prediction of where her hips face is closer (val: 39 degrees off
    her hips as an estimate). Per frame, in place."""

    _LEGS = [PELVIS] + [int(i) for i in LOWER_BODY]
    # the SPEC joint order has them first: a slice (a view) costs less than an index list
    _ROWS = slice(0, len(_LEGS)) if _LEGS == list(range(len(_LEGS))) else _LEGS

    def __init__(self, options: HipOptions):
        self.o = options
        self.turn = 0.0  # radians, the current twist

    def step(self, positions, rotations, heading):
        """Turn her hips of the pose ``(31, 3)``, ``(31, 3, 3)`` (in place) towards
        ``heading`` (radians about +Y from +Z, as ``hip_heading``)."""
        o = self.o
        lx, _, lz = positions[HIPS[0]].tolist()
        rx, _, rz = positions[HIPS[1]].tolist()
        h = atan2(-(lz - rz), lx - rx)
        d = heading - h
        d = atan2(sin(d), cos(d))
        lim = o.max_deg * pi / 180.0
        goal = min(max(o.share * d, -lim), lim)
        self.turn += o.rate * (goal - self.turn)
        c, s_ = cos(self.turn), sin(self.turn)
        turn = np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
        pivot = positions[PELVIS].copy()
        legs = self._ROWS
        positions[legs] = (positions[legs] - pivot) @ turn.T + pivot
        rotations[legs] = turn @ rotations[legs]
        return positions, rotations


class HandHold:
    """Hand holds of the duet: when one of the four leader/follower wrist
    pairs is predicted close, the follower's wrist of that pair is pulled by
    her arm IK to ``gap`` from the leader's wrist (the leader's wrist is
    his tracked hand) on the side of her shoulder. The hold's weight follows
    a ramp of the predicted distance (full under ``on``, none over
    ``off``), changing by at most 1 / ``frames`` per frame. Her hand's
    partner is soft (``soft``): his two wrists weighted by a softmax of
    their predicted distances, so no discrete choice flips between his hands
    on a millimetre of noise (a hard partner that stayed held while his other
    hand was the close one dragged her arm across: a 112° forearm turn in one
    frame). The soft partner's weights change by at most
    ``soft_rate`` a frame, so when his hands swap as the nearer one her
    wrist goes over in two thirds of a second instead of being swept across. The pull
    (her wrist's offset from where her tracker puts it) follows a critically
    damped spring of ``spring`` Hz, so its acceleration is bounded and the
    arm does not jerk when a hold starts, ends or changes partner (the hold's
    jitter, 258 → 176 m/s³ on val); a share ``lead`` of the pull's own
    velocity (smoothed) is fed forward, so the spring does not trail a hold
    that moves at a steady speed. One pair per follower hand. A hold her
    arm cannot reach (past ``reach`` of its length from her shoulder; her
    clavicle helps beyond its length) fades out instead of wrenching the
    shoulder, and so does one whose goal is within ``near`` of her arm's
    length from her shoulder (his hand on her back: folding her wrist onto her
    own shoulder flipped her arm)."""

    SHOULDERS = (JOINT_INDEX["lclavicle"], JOINT_INDEX["rclavicle"])

    def __init__(self, options: HoldOptions):
        self.o = options
        self.reset()

    def reset(self):
        self.weight = [0.0, 0.0]  # per follower hand
        self._offset = [None, None]
        self._velocity = [None, None]
        self._goal = [None, None]
        self._lead = [None, None]
        self._soft = [None, None]

    def targets(self, leader_pos, follower_pos, pred_dist, arm_length):
        """Per follower hand a target (3,) or None. ``pred_dist (2, 2)``: the
        mapping's predicted distance of leader wrist i to follower wrist j;
        ``arm_length (2,)``: her arms (shoulder to wrist). The element-wise
        arithmetic is on Python floats (all in numpy, a frame's holds cost 30 µs
        per dancer); the exponential and the dot products stay numpy's, whose
        rounding differs (so the duet is bit for bit the same)."""
        o = self.o
        out = [None, None]
        pd = pred_dist.tolist()
        his = None  # his wrists, as lists, once needed
        for j in (0, 1):
            col = (pd[0][j], pd[1][j])
            d = col[1] if col[1] < col[0] else col[0]
            # soft partner: his two hands weighted by a softmax of their
            # predicted distances (no discrete choice to flip on noise)
            e0, e1 = np.exp(-(pred_dist[:, j] - d) / o.soft).tolist()  # numpy's exp, as before
            sm = e0 + e1
            soft = (e0 / sm, e1 / sm)
            if o.soft_rate > 0 and self._soft[j] is not None:
                # his hands swap as her partner gradually: her wrist is not swept across
                r = o.soft_rate
                soft = tuple(p + min(max(q - p, -r), r) for p, q in zip(self._soft[j], soft))
            ds = float(np.array(soft) @ pred_dist[:, j])
            self._soft[j] = soft
            # the weight goes towards a ramp of the distance (full under on,
            # none over off), at most a step per frame
            step = 1.0 / max(o.frames, 1)
            goal_w = min(max((o.off - ds) / max(o.off - o.on, 1e-6), 0.0), 1.0)
            self.weight[j] += min(max(goal_w - self.weight[j], -step), step)
            if self.weight[j] <= 0.0 and (self._offset[j] is None or max(abs(x) for x in self._offset[j]) < 1e-4):
                self._offset[j] = self._velocity[j] = self._goal[j] = self._lead[j] = None
                continue
            if his is None:
                his = leader_pos[list(WRISTS)]
            lw = (np.array(self._soft[j]) @ his).tolist()
            fw = follower_pos[WRISTS[j]].tolist()
            sh = follower_pos[self.SHOULDERS[j]].tolist()
            v = [a - b for a, b in zip(sh, lw)]
            n = hypot(*v)
            goal = [a + b / n * o.gap for a, b in zip(lw, v)] if n > 1e-6 else lw
            # within reach of her shoulder: full weight up to reach - 0.1 of the arm, none past reach
            g = [a - b for a, b in zip(goal, sh)]
            reach = hypot(*g) / max(float(arm_length[j]), 1e-6)
            w = self.weight[j] * min(max((o.reach - reach) / 0.1, 0.0), 1.0)
            if o.near > 0:
                # his hand at her shoulder (his hand on her back, not a hand hold):
                # her wrist is not folded onto her own shoulder
                w *= min(max((reach - o.near + 0.1) / 0.2, 0.0), 1.0)
            w = w * w * (3.0 - 2.0 * w)  # smoothstep
            # her wrist's offset from her body follows the hold's through a
            # critically damped spring (semi-implicit Euler at 30 Hz): the
            # pull's acceleration is bounded, so the wrist does not jerk
            off = [w * (a - b) for a, b in zip(goal, fw)]
            prev = self._offset[j]
            if prev is None:
                prev, vel = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
            else:
                vel = self._velocity[j]
            om = 2.0 * pi * o.spring
            dt = 1.0 / 30.0
            lead = (0.0, 0.0, 0.0)
            if o.lead > 0 and self._goal[j] is not None:
                # the pull's own velocity, fed forward
                lead = [o.lead * (a - b) / dt for a, b in zip(off, self._goal[j])]
                if o.lead_smooth > 0 and self._lead[j] is not None:
                    ls = o.lead_smooth
                    lead = [ls * a + (1.0 - ls) * b for a, b in zip(self._lead[j], lead)]
                self._lead[j] = lead
            self._goal[j] = off
            k1, k2 = om * om, 2.0 * om
            vel = [u + dt * (k1 * (a - p) + k2 * (c - u)) for u, a, p, c in zip(vel, off, prev, lead)]
            off = [p + dt * u for p, u in zip(prev, vel)]
            self._velocity[j] = vel
            self._offset[j] = off
            out[j] = np.array([a + b for a, b in zip(fw, off)])
        return out
