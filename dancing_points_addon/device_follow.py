"""The tracked dancer's head and hands turn as the devices turn.

The networks see where the three devices are, not how they are turned, so a
synthesised head looks ahead while the wearer looks down, and a wrist's twist
is a guess. :class:`DeviceFollow` runs after the head and wrist IK, on the
tracked dancer's final pose, and turns

* the skull (bone ``head``) to the head device's orientation, within
  :data:`HEAD_LIMIT_DEG` of the chest (bone ``thorax``: the neck bones'
  twist about themselves moves nothing and is no reference, some mocap takes
  have it half a turn off);
* for ``joints`` devices, whose hand orientation is the ``*wrist`` bone's
  (SPEC §3: the forearm's end), each arm's elbow round the shoulder–wrist
  line (the wrist stays) so that the forearm points as the device says (an
  ``openxr`` grip turns with the hand, whose bend at the wrist is unknown:
  its elbow stays the network's);
* each forearm's end (bone ``*wrist``, which the CMU skeleton twists: the
  forearm's pronation) about its own axis towards the hand device's
  orientation, within :data:`TWIST_LIMIT_DEG` of the rest of the forearm
  (for ``joints`` devices, this is all);
* for ``openxr`` devices, whose grip poses carry the hand bones'
  (``*hand``) orientation, then also the hand (``*hand`` and ``*fingers``)
  about the wrist point, within :data:`FLEX_LIMIT_DEG` of the forearm.

Only rotations change and the children move rigidly with their bones: the
head point and the wrists stay where the IK put them. A device that is lost
on a frame (its orientation a guess) turns nothing.
"""
from __future__ import annotations

from math import atan2, cos, pi, sin, sqrt

import numpy as np

from .ik import two_bone_ik
from .representation import DEVICE_FROM_HEAD
from .skeleton import JOINT_INDEX

HEAD_LIMIT_DEG = 90.0
TWIST_LIMIT_DEG = 110.0  # the salsa dancers' forearm twist: -105..73 degrees (0.1..99.9 percentiles, train frames)
FLEX_LIMIT_DEG = 85.0
_J = JOINT_INDEX


def _quat(R) -> tuple:
    """One rotation matrix as a unit quaternion ``(w, x, y, z)``, ``w >= 0``."""
    m00, m01, m02 = R[0]
    m10, m11, m12 = R[1]
    m20, m21, m22 = R[2]
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


def _axis_angle(axis, angle) -> np.ndarray:
    """The rotation matrix of ``angle`` radians about the unit ``axis``."""
    x, y, z = axis
    c, s = cos(angle), sin(angle)
    t = 1.0 - c
    return np.array([[c + x * x * t, x * y * t - z * s, x * z * t + y * s],
                     [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
                     [z * x * t - y * s, z * y * t + x * s, c + z * z * t]])


def twist_angle(R, axis) -> float:
    """The twist of rotation ``R`` about the unit ``axis`` (swing-twist), radians in (−π, π]."""
    w, x, y, z = _quat(R)
    return 2.0 * atan2(x * axis[0] + y * axis[1] + z * axis[2], w)


def limit_rotation(R, limit: float) -> np.ndarray:
    """``R`` with its angle cut to at most ``limit`` radians about the same axis."""
    w, x, y, z = _quat(R)
    n = sqrt(x * x + y * y + z * z)
    angle = 2.0 * atan2(n, w)
    if angle <= limit or n < 1e-12:
        return np.asarray(R, dtype=np.float64)
    return _axis_angle((x / n, y / n, z / n), limit)


class DeviceFollow:
    """Turn a pose's skull, forearm ends and (``hand_bone="hand"``) hands to
    the devices' orientations (see the module docstring). ``bone_vectors``:
    the skeleton's rest bone vectors ``(31, 3)`` at the pose's scale."""

    def __init__(self, bone_vectors, hand_bone: str = "wrist", head_limit=HEAD_LIMIT_DEG,
                 twist_limit=TWIST_LIMIT_DEG, flex_limit=FLEX_LIMIT_DEG):
        if hand_bone not in ("wrist", "hand"):
            raise ValueError(f"DeviceFollow: hand_bone must be 'wrist' or 'hand', not {hand_bone!r}")
        bv = np.asarray(bone_vectors, dtype=np.float64)
        self.head_vec = bv[_J["head"]]
        self.hand_bone = hand_bone
        self.limits = tuple(np.radians([head_limit, twist_limit, flex_limit]))
        self.sides = []
        for s in "lr":
            e = bv[_J[s + "wrist"]]
            self.sides.append({"clavicle": _J[s + "clavicle"], "humerus": _J[s + "humerus"],
                               "forearm": [_J[s + n] for n in ("radius", "wrist", "hand", "fingers", "thumb")],
                               "radius": _J[s + "radius"], "wrist": _J[s + "wrist"], "hand": _J[s + "hand"],
                               "moved": [_J[s + "hand"], _J[s + "fingers"], _J[s + "thumb"]],
                               "flexed": [_J[s + "hand"], _J[s + "fingers"]],
                               "axis": e / np.linalg.norm(e)})

    def step(self, positions, rotations, head_device=None, hands=(None, None)):
        """``positions (31, 3)``, ``rotations (31, 3, 3)`` (modified in place and
        returned); ``head_device``: the head device's rotation (3, 3) or None;
        ``hands``: per hand the rotation its device measures (of bone
        ``*wrist`` or ``*hand``, see ``hand_bone``) or None."""
        P, R = positions, rotations
        if head_device is not None:
            un, hd, th = _J["upperneck"], _J["head"], _J["thorax"]
            target = np.asarray(head_device, dtype=np.float64) @ DEVICE_FROM_HEAD
            R[hd] = R[th] @ limit_rotation(R[th].T @ target, self.limits[0])
            P[hd] = P[un] + R[hd] @ self.head_vec
        for side, target in zip(self.sides, hands):
            if target is not None:
                self._hand(P, R, side, np.asarray(target, dtype=np.float64))
        return P, R

    def _hand(self, P, R, side, target):
        w, rad = side["wrist"], side["radius"]
        axis_rest = side["axis"]
        if self.hand_bone == "wrist":  # the device gives the forearm's direction
            self._elbow(P, R, side, target @ axis_rest)
        d = R[w] @ axis_rest  # the forearm's direction
        bone = R[w] if self.hand_bone == "wrist" else R[side["hand"]]
        phi = twist_angle(target @ bone.T, d)
        # the forearm end's twist relative to the rest of the forearm, kept within its limit
        tau = twist_angle(R[rad].T @ R[w], axis_rest)
        lim = self.limits[1]
        want = (tau + phi + pi) % (2.0 * pi) - pi  # the new twist, in (-pi, pi]
        phi = min(max(want, -lim), lim) - tau
        if abs(phi) > 1e-9:
            self._turn(P, R, [w] + side["moved"], _axis_angle(d, phi), P[w])
        if self.hand_bone == "hand":
            h = side["hand"]
            local = limit_rotation(R[w].T @ target, self.limits[2])  # the hand within its limit of the forearm
            self._turn(P, R, side["flexed"], R[w] @ local @ R[h].T, P[w])

    @staticmethod
    def _elbow(P, R, side, forearm):
        """Swing the elbow round the shoulder–wrist line towards where a forearm
        pointing along ``forearm`` (unit) would put it; the wrist stays."""
        hum, fore = side["humerus"], side["forearm"]
        sh, el, wr = P[side["clavicle"]], P[hum], P[side["wrist"]]
        pole = wr - forearm * float(np.linalg.norm(wr - el))
        new_el, _, r1, r2 = two_bone_ik(sh, el, wr, wr, pole)
        R[hum] = r1 @ R[hum]
        R[fore] = r2 @ R[fore]
        P[fore] = new_el + (P[fore] - el) @ r2.T
        P[hum] = new_el

    @staticmethod
    def _turn(P, R, bones, D, pivot):
        """Bones ``bones`` turned by ``D`` about ``pivot`` (their end points move along)."""
        for b in bones:
            R[b] = D @ R[b]
        P[bones] = pivot + (P[bones] - pivot) @ D.T
