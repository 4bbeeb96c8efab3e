"""What the three rows of a take's poses are (SPEC §3 ``devices``), and the
conversion between a headset's own poses and the SPEC §2 tracked points.

``joints`` takes carry the tracked points themselves (what ``extract`` writes
from mocap). ``openxr`` takes carry what a headset and two controllers record:

* **head: the view pose**, the point between the eyes, axes −Z forward, +Y up,
  +X right: the same axes as the ``joints`` head device, so its orientation is
  the skull's (``R_head · Ry(180°)``). The base of the skull (the end of the
  CMU ``upperneck``, SPEC §2's head point) lies behind and below the eyes.
* **hands: the grip poses**, origin at the centre of the closed fist, +X
  perpendicular to the palm (out of the back of the right hand, out of the palm
  of the left), −Z along the handle towards the thumb. The grip is rigid on the
  hand (the CMU ``lhand``/``rhand`` bone, which starts at the wrist point), so
  the wrist is found exactly, however the wrist flexes.

Body offsets (:class:`DeviceOffsets`), for a wearer of
:data:`REFERENCE_HEIGHT_M` and scaled with the wearer's height:

* the eyes 8.0 cm in front of and 7.5 cm above the base of the skull. Adult
  heads measure about 19–20 cm from the brow to the back of the head (ANSUR II
  "head length": 19.7 cm men, 18.9 cm women; Gordon et al. 2014, *2012
  Anthropometric Survey of U.S. Army Personnel*), and the atlanto-occipital
  joint sits a little behind the middle of that depth, below eye level by
  about the height of the ear canal above it plus the joint's depth below the
  ear (these figures are approximations of that geometry);
* the fist centre 7.0 cm past the wrist along the hand and 2.5 cm towards the
  palm: the middle of an adult palm (ANSUR II "hand length" 19.4 cm men,
  17.9 women, of which the palm is a little over half) and half a closed
  hand's thickness.

People and controllers differ from these by centimetres, so the duet must not
hinge on them: the networks that read the leader's points are trained with a
random constant offset of a few centimetres per clip on each device (see
``training.data.offset_clip``). Each offset can be replaced per take
(metadata ``head_offset_m``, ``lhand_offset_m``, ``rhand_offset_m``: ``x,y,z``
in the device's own axes, metres at the wearer's own size) or on the command
line (``--head-offset``, ``--hand-offset``).

Device turns (:class:`DeviceTurns`). A device that reports another convention
than the one above (a runtime's raw controller pose instead of the grip, a
tracker strapped to the wrist, a headset worn tilted) differs from it by a
constant rotation in the device's own axes: ``reported = true · turn``. Such a
turn is given per take (metadata ``head_turn``, ``lhand_turn``, ``rhand_turn``:
a quaternion ``w,x,y,z``) or on the command line (``--head-turn``,
``--hand-turn``: the left hand's, mirrored for the right) and taken off every
pose before the pose is read (``true = reported · turnᵀ``), for ``joints`` and
``openxr`` takes alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..rotations import matrix_to_quat, quat_to_matrix

DEVICE_KINDS = ("joints", "openxr")
REFERENCE_HEIGHT_M = 1.70  # the wearer the default offsets are given for

# Device axes of a grip pose in the rest frame of the CMU hand bones (their
# rest pose: arms along ±X, palms down, thumbs forward (+Z)): columns are the
# grip's +X, +Y, +Z. Left: +X out of the palm (down), −Z towards the thumb.
_GRIP_AXES = {
    "l": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T,
    "r": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T,
}
# The fist centre in each hand bone's rest frame (m, at the reference height).
_FIST_REST = {"l": np.array([0.070, -0.025, 0.0]), "r": np.array([-0.070, -0.025, 0.0])}


def _grip_offset(side: str) -> tuple:
    """The wrist relative to the grip pose, in the grip's own axes."""
    return tuple(float(v) for v in _GRIP_AXES[side].T @ -_FIST_REST[side])


# The default offsets, at the reference height: the base of the skull from the
# view pose (x right, y up, z back), each wrist from its grip pose.
DEFAULT_OFFSETS = {"head": (0.0, -0.075, 0.080), "lhand": _grip_offset("l"), "rhand": _grip_offset("r")}


@dataclass(frozen=True)
class DeviceOffsets:
    """Where each §2 point lies relative to its OpenXR pose, in the device's
    own axes, metres: ``head`` the base of the skull from the view pose,
    ``lhand`` / ``rhand`` the wrist from the grip pose. ``None`` takes the
    default (:data:`DEFAULT_OFFSETS`, scaled with the wearer's height); a
    given offset is the wearer's own and used as it is."""

    head: tuple | None = None
    lhand: tuple | None = None
    rhand: tuple | None = None

    def at(self, height) -> np.ndarray:
        """``(3, 3)`` offsets (head, lhand, rhand) for a wearer ``height`` m tall."""
        s = float(height) / REFERENCE_HEIGHT_M if height else 1.0
        return np.array([DEFAULT_OFFSETS[k] if v is None else v for k, v in
                         (("head", self.head), ("lhand", self.lhand), ("rhand", self.rhand))], dtype=np.float64) \
            * np.array([[s if v is None else 1.0] for v in (self.head, self.lhand, self.rhand)])


META_OFFSET_KEYS = ("head_offset_m", "lhand_offset_m", "rhand_offset_m")
MAX_OFFSET_M = 0.5  # a body offset beyond half a metre is a mistake, not a body


def parse_offset(text, where="offset", path="<take>", line=None) -> tuple:
    """``"x,y,z"`` (metres) as a tuple; an :class:`InputError` otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        v = tuple(float(p) for p in parts)
    except ValueError:
        v = ()
    if len(v) != 3 or not all(np.isfinite(v)):
        raise InputError(path, f"{where} must be three numbers x,y,z in metres, got {text!r}", line)
    if max(abs(c) for c in v) > MAX_OFFSET_M:
        raise InputError(path, f"{where} {text!r} is more than {MAX_OFFSET_M:g} m: not a body offset", line)
    return v


META_TURN_KEYS = ("head_turn", "lhand_turn", "rhand_turn")


def parse_turn(text, where="turn", path="<take>", line=None) -> tuple:
    """``"w,x,y,z"`` (a rotation quaternion, normalised) as a tuple; an :class:`InputError` otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        q = np.array([float(p) for p in parts])
    except ValueError:
        q = np.zeros(0)
    if q.shape != (4,) or not np.isfinite(q).all():
        raise InputError(path, f"{where} must be a quaternion w,x,y,z, got {text!r}", line)
    n = float(np.linalg.norm(q))
    if not 0.5 <= n <= 2.0:
        raise InputError(path, f"{where} {text!r} is not a rotation (its norm {n:.3g} is not within [0.5, 2])", line)
    return tuple(float(v) for v in q / n)


def mirror_turn(q) -> tuple:
    """The left hand's turn as the right hand's: its mirror image across the body's
    mid-plane (``w, x, −y, −z``), as the right grip's axes mirror the left's."""
    w, x, y, z = q
    return (w, x, -y, -z)


@dataclass(frozen=True)
class DeviceTurns:
    """Per device (head, lhand, rhand) the constant rotation between the pose
    it reports and the convention of SPEC §3, in its own axes
    (``reported = true · turn``), a quaternion ``(w, x, y, z)``; None: none."""

    head: tuple | None = None
    lhand: tuple | None = None
    rhand: tuple | None = None

    def __bool__(self) -> bool:
        return any(t is not None for t in (self.head, self.lhand, self.rhand))

    def remove(self, quats) -> np.ndarray:
        """``quats (..., 3, 4)`` with each device's turn taken off (``reported · turnᵀ``)."""
        quats = np.array(quats, dtype=np.float64)
        for d, t in enumerate((self.head, self.lhand, self.rhand)):
            if t is not None:
                q = quats[..., d, :]
                R = quat_to_matrix(np.nan_to_num(q)) @ quat_to_matrix(np.asarray(t)).T
                lost = ~np.isfinite(q).all(-1)
                quats[..., d, :] = matrix_to_quat(R)
                quats[..., d, :][lost] = np.nan
        return quats

    def meta(self) -> dict:
        """The take metadata that give these turns."""
        return {k: ",".join(f"{v:.6f}" for v in t) for k, t in zip(META_TURN_KEYS, (self.head, self.lhand, self.rhand))
                if t is not None}


def turns_for(meta: dict, head=None, hand=None, path="<take>") -> DeviceTurns:
    """The device turns of a take: its metadata, then the user's (``head``: a
    quaternion; ``hand``: the left hand's, mirrored for the right)."""
    return DeviceTurns(**_per_device(meta, META_TURN_KEYS, parse_turn, head, hand, mirror_turn, path))


def _per_device(meta, keys, parse, head, hand, mirror, path) -> dict:
    """``{device: value}`` of a take: its metadata ``keys`` (head, lhand, rhand)
    read by ``parse``, then the user's ``head`` and ``hand`` (the left hand's,
    ``mirror`` of it for the right)."""
    over = {}
    for key, dev in zip(keys, ("head", "lhand", "rhand")):
        if meta.get(key) not in (None, ""):
            over[dev] = parse(meta[key], key, path)
    if head is not None:
        over["head"] = tuple(head)
    if hand is not None:
        over["lhand"] = tuple(hand)
        over["rhand"] = tuple(mirror(hand))
    return over


def check_devices(value, path="<take>", line=None) -> str:
    v = str(value).strip().lower()
    if v not in DEVICE_KINDS:
        raise InputError(path, f"unknown devices value {value!r} (expected {' or '.join(DEVICE_KINDS)})", line)
    return v


def offsets_for(meta: dict, head=None, hand=None, path="<take>") -> DeviceOffsets:
    """The offsets of a take: the defaults, the take's own (metadata), then the
    user's (``head``: a 3-tuple; ``hand``: the left hand's, mirrored for the right)."""
    # the mirror image: grip +X flips with the side
    return DeviceOffsets(**_per_device(meta, META_OFFSET_KEYS, parse_offset, head, hand,
                                       lambda v: (-v[0], v[1], v[2]), path))


def openxr_to_points(positions, quats, offsets: np.ndarray):
    """OpenXR view and grip poses ``(..., 3, 3)``, ``(..., 3, 4)`` -> SPEC §2
    points ``(..., 3, 3)`` and the orientations they carry: the head device
    (unchanged) and the hand bones (``lhand``, ``rhand``, not ``*wrist``).
    ``offsets (3, 3)``: :meth:`DeviceOffsets.at`. Lost devices (NaN) stay lost."""
    positions = np.asarray(positions, dtype=np.float64)
    quats = np.asarray(quats, dtype=np.float64)
    R = quat_to_matrix(np.nan_to_num(quats))
    points = positions + np.einsum("...ij,...j->...i", R, np.asarray(offsets))
    hand_R = np.stack([R[..., 1, :, :] @ _GRIP_AXES["l"].T, R[..., 2, :, :] @ _GRIP_AXES["r"].T], axis=-3)
    out_q = quats.copy()
    out_q[..., 1:, :] = matrix_to_quat(hand_R)
    lost = ~np.isfinite(quats).all(-1)
    out_q[lost] = np.nan
    return points, out_q


def points_to_openxr(points, head_quats, hand_rotations, offsets: np.ndarray):
    """The inverse of :func:`openxr_to_points`: §2 points ``(T, 3, 3)``, head
    device quaternions ``(T, 4)`` and the global rotations of the hand bones
    ``(T, 2, 3, 3)`` -> view and grip poses ``(T, 3, 3)``, ``(T, 3, 4)``."""
    points = np.asarray(points, dtype=np.float64)
    R = np.empty(points.shape[:-2] + (3, 3, 3))
    R[..., 0, :, :] = quat_to_matrix(np.asarray(head_quats, dtype=np.float64))
    R[..., 1, :, :] = hand_rotations[..., 0, :, :] @ _GRIP_AXES["l"]
    R[..., 2, :, :] = hand_rotations[..., 1, :, :] @ _GRIP_AXES["r"]
    poses = points - np.einsum("...ij,...j->...i", R, np.asarray(offsets))
    return poses, matrix_to_quat(R)
