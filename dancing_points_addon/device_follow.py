"""The tracked dancer's head and hands turn as the devices turn.

The networks see where the three devices are, not how they are turned, so a
synthesised head looks ahead while the wearer looks down, and a wrist's twist
is a guess. :class:`DeviceFollow` runs after the head and wrist IK, on the
tracked dancer's final pose, and turns

* the skull (bone ``head``) to the head device's orientation, within
  ``head_limit_deg`` of the chest (bone ``thorax``: the neck bones'
  twist about themselves moves nothing and is no reference, some mocap takes
  have it half a turn off);
* for ``joints`` devices, whose hand orientation is the ``*wrist`` bone's
  (SPEC §3: the forearm's end), each arm by two-bone IK so that the forearm's
  end points as the device says, its end (the tracked wrist) where it was
  (an ``openxr`` grip turns with the hand, whose bend at the wrist is
  unknown: its elbow stays the network's);
* each forearm's end (bone ``*wrist``, which the CMU skeleton twists: the
  forearm's pronation) about its own axis towards the hand device's
  orientation, within ``twist_limit_deg`` of the rest of the forearm
  (for ``joints`` devices, this is all);
* for ``openxr`` devices, whose grip poses carry the hand bones'
  (``*hand``) orientation, then also the hand (``*hand`` and ``*fingers``)
  about the wrist point, within ``flex_limit_deg`` of the forearm.

For ``openxr`` devices the forearm's direction is not measured: the hand's
bend at the wrist is unknown. It is estimated as the grip's orientation with
the hand bent as in the dancer's start-up pose (``hand_flex``; the training
leader's is within 5–7° of his mean bend), and the forearm's end is pointed
``forearm_share`` of the way from the network's direction to it, as for
``joints`` devices (:class:`DeviceFollowOptions`; figures in models/README.md).

Only rotations change and the children move rigidly with their bones: the
head point and the wrists stay where the IK put them. A device that is lost
on a frame (its orientation a guess) turns nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import atan2, cos, dist, pi, sin, sqrt

import numpy as np

from .option_checks import check_range
from .scalar_kernels import mat_mul, mat_vec, rot_between_s, transpose_s, two_bone_s
from .representation import DEVICE_FROM_HEAD
from .skeleton import JOINT_INDEX, joint_block



@dataclass(frozen=True)
class DeviceFollowOptions:
    """How far the tracked dancer's head and hands turn as the devices do
    (see the module docstring); degrees."""

    head_limit_deg: float = 90.0  # the skull against the chest
    # the forearm's end against the rest of the forearm (the salsa dancers' twist: -105..73 degrees,
    # 0.1..99.9 percentiles of the train frames)
    twist_limit_deg: float = 110.0
    flex_limit_deg: float = 85.0  # openxr: the hand against the forearm
    forearm_share: float = 0.7  # openxr: how far the forearm's end turns to the grip's estimate (chosen on val)

    def __post_init__(self):
        for name in ("head_limit_deg", "twist_limit_deg", "flex_limit_deg"):
            check_range("DeviceFollowOptions", name, getattr(self, name), 0.0, 180.0)
        check_range("DeviceFollowOptions", "forearm_share", self.forearm_share, 0.0, 1.0)
_J = JOINT_INDEX
# An arm's joints (consecutive in the SPEC order), and where each lies among them
_ARM = ("clavicle", "humerus", "radius", "wrist", "hand", "fingers", "thumb")
_CLAVICLE, _HUMERUS, _RADIUS, _WRIST, _HAND = range(5)
_FOREARM, _TURNED, _FLEXED = (2, 3, 4, 5, 6), (3, 4, 5, 6), (4, 5)  # the bones each kind of turn moves
_DEVICE_FROM_HEAD = tuple(DEVICE_FROM_HEAD.ravel().tolist())


def _quat(m) -> tuple:
    """A row-major 9-sequence rotation as a unit quaternion ``(w, x, y, z)``, ``w >= 0``."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = sqrt(tr + 1.0) * 2.0
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = sqrt(1.0 + m00 - m11 - m22) * 2.0
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = sqrt(1.0 + m11 - m00 - m22) * 2.0
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = sqrt(1.0 + m22 - m00 - m11) * 2.0
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    return q if q[0] >= 0.0 else tuple(-v for v in q)


def _axis_angle(axis, angle) -> tuple:
    """The rotation of ``angle`` radians about the unit ``axis``, row-major 9-tuple."""
    x, y, z = axis
    c, s = cos(angle), sin(angle)
    t = 1.0 - c
    return (c + x * x * t, x * y * t - z * s, x * z * t + y * s,
            y * x * t + z * s, c + y * y * t, y * z * t - x * s,
            z * x * t - y * s, z * y * t + x * s, c + z * z * t)


def twist_angle(R, axis) -> float:
    """The twist of rotation ``R`` (row-major 9-sequence or 3 × 3) about the unit
    ``axis`` (swing-twist), radians in (−π, π]."""
    w, x, y, z = _quat(np.ravel(R).tolist() if isinstance(R, np.ndarray) else R)
    return 2.0 * atan2(x * axis[0] + y * axis[1] + z * axis[2], w)


def limit_rotation(R, limit: float):
    """``R`` (row-major 9-sequence, or 3 × 3 array: the same kind back) with its
    angle cut to at most ``limit`` radians about the same axis."""
    array = isinstance(R, np.ndarray)
    m = np.ravel(R).tolist() if array else R
    w, x, y, z = _quat(m)
    n = sqrt(x * x + y * y + z * z)
    if 2.0 * atan2(n, w) > limit and n >= 1e-12:
        m = _axis_angle((x / n, y / n, z / n), limit)
    return np.reshape(m, (3, 3)) if array else m


def hand_flex(rotations) -> tuple:
    """Per side (left, right) the hand bone's rotation relative to the forearm
    end's, ``R_wristᵀ · R_hand`` (3, 3), in a pose's global rotations ``(31, 3, 3)``."""
    R = np.asarray(rotations, dtype=np.float64)
    return tuple(R[_J[s + "wrist"]].T @ R[_J[s + "hand"]] for s in "lr")


class DeviceFollow:
    """Turn a pose's skull, forearm ends and (``hand_bone="hand"``) hands to
    the devices' orientations (see the module docstring). ``bone_vectors``:
    the skeleton's rest bone vectors ``(31, 3)`` at the pose's scale."""

    def __init__(self, bone_vectors, hand_bone: str = "wrist", options: DeviceFollowOptions = DeviceFollowOptions(),
                 hand_flex=None):
        """``options``: a :class:`DeviceFollowOptions`; ``hand_flex``: for
        ``hand_bone="hand"``, per side (left, right) the hand bone's rotation
        relative to the forearm end's (``*wrist``), each ``(3, 3)``, as in a
        pose of the dancer (:func:`hand_flex`); None: the forearm is left as
        the network made it."""
        if hand_bone not in ("wrist", "hand"):
            raise ValueError(f"DeviceFollow: hand_bone must be 'wrist' or 'hand', not {hand_bone!r}")
        self.forearm_share = float(options.forearm_share)
        head_limit, twist_limit, flex_limit = options.head_limit_deg, options.twist_limit_deg, options.flex_limit_deg
        bv = np.asarray(bone_vectors, dtype=np.float64)
        self.head_vec = bv[_J["head"]]
        self.hand_bone = hand_bone
        self.limits = tuple(np.radians([head_limit, twist_limit, flex_limit]))
        self.sides = []
        for s in "lr":
            e = bv[_J[s + "wrist"]]
            self.sides.append({"block": joint_block(_J[s + n] for n in _ARM),
                               "axis": tuple((e / np.linalg.norm(e)).tolist())})
        if hand_flex is not None and hand_bone == "hand":
            for side, flex in zip(self.sides, hand_flex):  # the forearm end from the hand: R_w = R_h · flexᵀ
                side["unflex"] = tuple(np.asarray(flex, dtype=np.float64).T.ravel().tolist())

    def step(self, positions, rotations, head_device=None, hands=(None, None)):
        """``positions (31, 3)``, ``rotations (31, 3, 3)`` (modified in place and
        returned); ``head_device``: the head device's rotation (3, 3) or None;
        ``hands``: per hand the rotation its device measures (of bone
        ``*wrist`` or ``*hand``, see ``hand_bone``) or None. On Python floats
        (a handful of 3 × 3 products), one numpy product per bone group."""
        P, R = positions, rotations
        rows = R.reshape(-1, 9)
        if head_device is not None:
            un, hd, th = _J["upperneck"], _J["head"], _J["thorax"]
            target = mat_mul(np.ravel(head_device).tolist(), _DEVICE_FROM_HEAD)
            chest = rows[th].tolist()
            head = mat_mul(chest, limit_rotation(mat_mul(transpose_s(chest), target), self.limits[0]))
            rows[hd] = head
            P[hd] = P[un] + np.reshape(head, (3, 3)) @ self.head_vec
        for side, target in zip(self.sides, hands):
            if target is not None:  # the arm's points and rotations as lists, back in one write each
                block = side["block"]
                pts, rts = P[block].tolist(), rows[block].tolist()
                self._hand(pts, rts, side, np.ravel(target).tolist())
                P[block], rows[block] = pts, rts
        return P, R

    def _hand(self, P, rows, side, target):
        """One arm (:data:`_ARM`'s points ``P`` and rotation rows ``rows``,
        lists, modified) turned to its device's ``target``."""
        e = side["axis"]
        a = None
        if self.hand_bone == "wrist":  # the device gives the forearm's direction
            a = mat_vec(target, *e)
        elif "unflex" in side and self.forearm_share > 0.0:  # estimated from the grip, part of the way
            est = mat_vec(mat_mul(target, side["unflex"]), *e)
            k = self.forearm_share
            v = [k * x + (1.0 - k) * y for x, y in zip(est, mat_vec(rows[_WRIST], *e))]
            n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            a = (v[0] / n, v[1] / n, v[2] / n) if n > 1e-9 else None
        if a is not None and not self._forearm(P, rows, a):  # out of reach: the elbow swung alone
            self._elbow(P, rows, a)
        Rw = rows[_WRIST]
        d = mat_vec(Rw, *e)  # the forearm's direction
        bone = Rw if self.hand_bone == "wrist" else rows[_HAND]
        phi = twist_angle(mat_mul(target, transpose_s(bone)), d)
        # the forearm end's twist relative to the rest of the forearm, kept within its limit
        tau = twist_angle(mat_mul(transpose_s(rows[_RADIUS]), Rw), e)
        lim = self.limits[1]
        want = (tau + phi + pi) % (2.0 * pi) - pi  # the new twist, in (-pi, pi]
        phi = min(max(want, -lim), lim) - tau
        if abs(phi) > 1e-9:
            D = _axis_angle(d, phi)
            Rw = mat_mul(D, Rw)
            self._turn(P, rows, _TURNED, D, P[_WRIST])
        if self.hand_bone == "hand":
            local = limit_rotation(mat_mul(transpose_s(Rw), target), self.limits[2])  # within its limit of the forearm
            D = mat_mul(mat_mul(Rw, local), transpose_s(rows[_HAND]))
            self._turn(P, rows, _FLEXED, D, P[_WRIST])

    @classmethod
    def _forearm(cls, P, rows, axis):
        """Point the forearm's end (bone ``*wrist``) along ``axis`` (unit), its end
        point (the tracked wrist) kept: the arm's two-bone IK takes the radius's
        end to ``wrist − |wrist bone| · axis``, its elbow swung round the shoulder
        towards where a forearm along ``axis`` would put it, then the wrist bone
        turns onto ``axis`` about the radius's end. False (and nothing changed)
        where that radius's end is out of the arm's reach."""
        sh, el, re, wr = P[_CLAVICLE], P[_HUMERUS], P[_RADIUS], P[_WRIST]
        ax, ay, az = axis
        lw, l1, l2 = dist(re, wr), dist(sh, el), dist(el, re)  # wrist bone, humerus, radius
        goal = (wr[0] - lw * ax, wr[1] - lw * ay, wr[2] - lw * az)
        if not abs(l1 - l2) * (1.0 + 1e-9) < dist(sh, goal) < (l1 + l2) * (1.0 - 1e-9):
            return False
        pole = (goal[0] - l2 * ax, goal[1] - l2 * ay, goal[2] - l2 * az)
        cls._bend(P, rows, sh, el, re, goal, pole)
        # the wrist bone onto the tracked wrist (along ``axis``: the radius's end is on its goal)
        re, cur = P[_RADIUS], P[_WRIST]
        D = rot_between_s(cur[0] - re[0], cur[1] - re[1], cur[2] - re[2], wr[0] - re[0], wr[1] - re[1], wr[2] - re[2])
        cls._turn(P, rows, _TURNED, D, re)
        return True

    @classmethod
    def _elbow(cls, P, rows, forearm):
        """Swing the elbow round the shoulder–wrist line towards where a forearm
        pointing along ``forearm`` (unit) would put it; the wrist stays."""
        sh, el, wr = P[_CLAVICLE], P[_HUMERUS], P[_WRIST]
        n = dist(el, wr)
        pole = (wr[0] - forearm[0] * n, wr[1] - forearm[1] * n, wr[2] - forearm[2] * n)
        cls._bend(P, rows, sh, el, wr, wr, pole)

    @classmethod
    def _bend(cls, P, rows, sh, el, end, target, pole):
        """The arm's two-bone IK (shoulder ``sh``, elbow ``el``, ``end`` the lower
        bone's end) to ``target`` with the elbow towards ``pole``, applied: the
        upper arm turned, the forearm's bones turned and moved with the elbow."""
        new_el, _, r1, r2 = two_bone_s(sh, el, end, target, pole)
        rows[_HUMERUS] = mat_mul(r1, rows[_HUMERUS])
        cls._turn(P, rows, _FOREARM, r2, el)
        dx, dy, dz = new_el[0] - el[0], new_el[1] - el[1], new_el[2] - el[2]
        for b in _FOREARM:
            x, y, z = P[b]
            P[b] = (x + dx, y + dy, z + dz)
        P[_HUMERUS] = new_el

    @staticmethod
    def _turn(P, rows, bones, D, pivot):
        """Bones ``bones`` turned by ``D`` (row-major 9-tuple) about ``pivot``
        (their end points move along)."""
        px, py, pz = pivot
        for b in bones:
            rows[b] = mat_mul(D, rows[b])
            x, y, z = P[b]
            vx, vy, vz = mat_vec(D, x - px, y - py, z - pz)
            P[b] = (px + vx, py + vy, pz + vz)
