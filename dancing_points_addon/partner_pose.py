"""The partner's pose beyond her tracker: :class:`HandHold` bends her arms
onto the leader's hands when the two are in a hold, blended in and out, the
pull following a critically damped spring, and :class:`HipTwist` turns her
hips towards where the hip-heading network says she faces while her upper
body stays turned to him. Causal, deterministic, per frame; their options are
:class:`~.follower.HoldOptions` and :class:`~.follower.HipOptions`."""
from __future__ import annotations

from math import atan2, cos, hypot, pi, sin

import numpy as np

from .follower import PELVIS, HipOptions, HoldOptions
from .foot_lock import KinematicContacts
from .representation import to_world, vector_norm
from .skeleton import HIPS, JOINT_INDEX, LOWER_BODY, WRISTS


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

    def wrist_targets(self, leader_pos, follower_pos, l_tr, f_tr, l_roots, f_roots, arm_length):
        """Her wrists' targets (3, 3) for :class:`~.ik.EndEffectorIK` (the
        head's NaN: untouched), or None when neither hand is in a hold: the
        mapping's predicted wrists of both dancers at the next frame (``l_tr``,
        ``f_tr`` local to ``l_roots``, ``f_roots``) tell which of his hands each
        of hers holds (:meth:`targets`)."""
        lw = to_world(l_tr[0, 1:], l_roots[0])
        fw = to_world(f_tr[0, 1:], f_roots[0])
        pred = vector_norm(lw[:, None] - fw[None])
        tg = self.targets(leader_pos, follower_pos, pred, arm_length)
        if tg[0] is None and tg[1] is None:
            return None
        nan = np.full(3, np.nan)
        return np.array([nan, nan if tg[0] is None else tg[0], nan if tg[1] is None else tg[1]])

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
        # soft partner: his two hands weighted by a softmax of their predicted
        # distances (no discrete choice to flip on noise); its exponents, per
        # hand of hers, from the nearer of his (numpy's exp, both hands in one call)
        near = [pd[1][j] if pd[1][j] < pd[0][j] else pd[0][j] for j in (0, 1)]
        ex = np.exp([-(pd[i][j] - near[j]) / o.soft for j in (0, 1) for i in (0, 1)]).tolist()
        for j in (0, 1):
            e0, e1 = ex[2 * j], ex[2 * j + 1]
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


class PartnerPose:
    """The partner's pose after her tracker's step and pose recovery, the last
    stage of her frame: her feet locked (``locker``, a
    :class:`~.foot_lock.FootLocker`; None without foot locking) as the contact
    network times her steps (``net_steps``; else on her tracker's contacts and
    her own motion), no foot through the floor (``guard``), her thighs' twist
    within ``out_twist`` (radians per leg bone, ``leg_joints``: her
    :class:`~.pose.LegJoints`; None: not limited) and her hands in a hold
    (``effector``, :class:`~.ik.EndEffectorIK`; None without holds)."""

    def __init__(self, locker, guard, effector, net_steps, out_twist, leg_joints):
        self.locker, self.guard, self.effector = locker, guard, effector
        self.net_steps, self.out_twist, self.leg_joints = net_steps, out_twist, leg_joints
        self.kinematic = KinematicContacts()

    def __call__(self, pos, rot, contacts, targets, contact_p):
        """Her pose after the stage; ``contacts``: her tracker's, ``targets``:
        her wrists' in a hold (or None), ``contact_p``: the contact network's
        probabilities (hers the last four)."""
        if self.locker is not None:
            if self.net_steps:  # her steps: planted and lifted as the contact network says, on her floor
                contacts = contact_p[4:]
            else:
                contacts = np.maximum(contacts, self.kinematic(pos))
            pos, rot = self.locker.step(pos, rot, contacts)
        pos, rot = self.guard(pos, rot)  # no foot through the floor
        if self.out_twist is not None:  # her thighs' twist within the real follower's
            pos, rot = self.leg_joints.twist(pos, rot, self.out_twist)
        if targets is not None and self.effector is not None:
            pos, rot = self.effector.step(pos, rot, targets)
        return pos, rot
