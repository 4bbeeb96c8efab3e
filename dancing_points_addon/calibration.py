"""Calibration to the wearer: a take's devices, height and floor, and the
take as the networks want it (SPEC §2 points, the floor at y = 0).

:func:`calibrate` decides, for one take, what its devices are (SPEC §3
``devices``), how tall the tracked dancer is and where the real floor lies —
each given (an option, then the take's metadata) or estimated from the take —
and :func:`apply_calibration` turns the take into §2 points above a floor at
y = 0, with a start where tracking is lost filled from where each device is
first seen (offline synthesis looks ahead for that).

Estimates (paper §7 calibrates the tracker by the user's height; a headset
gives neither the height nor, exactly, the floor):

* **height**, when none is given: the base of the skull's 90th-percentile
  height over the take (the upright head, not its dips) against the training
  leader's over the train frames, :data:`TRAIN_HEAD_HEIGHT`, which stands for
  :data:`TRAIN_HEIGHT`. The floor is then taken as given (y = 0, or
  ``floor_y``): one head height cannot tell a tall wearer from a low floor.
* **floor**, when the height is given and no ``floor_y`` is: the same upright
  head height against the one the given height stands for. A floor a headset
  calibrated 10 cm off is then found to within the wearer's posture.

Device orientations (SPEC §3 "these orientations are measured"):

* a **turn** given for a device (metadata ``head_turn`` / ``lhand_turn`` /
  ``rhand_turn``, or ``--head-turn`` / ``--hand-turn``; see
  :class:`~.formats.devices.DeviceTurns`) is taken off its poses before they
  are read;
* orientations that **carry nothing** are not followed: a device whose
  orientation turns faster than :data:`ORIENTATION_SPEED_LIMIT` on the median
  row (no head or hand turns so; a sender that fills the orientation with
  noise does), or every device of a take whose metadata say
  ``orientations=none`` (a rig whose bones could not be read as SPEC §3 means
  them). Such a device's points are still read (an ``openxr`` device's body
  offset then without its orientation: straight down for the head, none for
  a hand), and :meth:`Calibration.notice` says so in one line.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .formats.devices import (DEVICE_KINDS, REFERENCE_HEIGHT_M, DeviceOffsets, DeviceTurns, check_devices, offsets_for,
                              openxr_to_points, points_to_openxr, turns_for)
from .formats.limits import FLOOR_RANGE_M
from .formats.take import ORIENTATIONS_PROBLEM_KEY, Take, take_orientations_usable
from .representation import root_from_head, to_local, to_world
from .resample import NET_FPS, resample_plan, tracked_after_resampling
from .rotations import matrix_to_quat, quat_to_matrix

# The training leader: his nominal standing height, and the 90th percentile of
# the height of the base of his skull (SPEC §2 head point) over the train
# frames of the 13 salsa takes (1.5298 m); calibration scales by their ratio.
TRAIN_HEIGHT = 1.70
TRAIN_HEAD_HEIGHT = 1.530
HEAD_PERCENTILE = 90.0
ESTIMATE_RANGE_M = (1.0, 2.3)  # an estimate beyond these is clipped (a child to a very tall adult)
ROLES = ("leader", "follower")  # SPEC §3 role: whose three points a take holds
# A device whose orientation turns faster than this on the median row (degrees a
# second) carries no orientation. The salsa takes' devices turn 17-132 (head) and
# 92-232 (hands) degrees a second on the median row (val frames); an orientation
# drawn at random on every row of a 60 Hz take turns about 7,500.
ORIENTATION_SPEED_LIMIT = 1500.0
DEVICE_LABELS = ("head", "left hand", "right hand")


@dataclass(frozen=True)
class Calibration:
    """How a take was read: ``devices`` (SPEC §3), the tracked dancer's
    standing ``height`` (m) and the real floor's ``floor_y`` (m, in the take's
    frame), each with where it came from (``"given"`` by an option or the
    take's metadata, ``"estimated"`` from the take, ``"assumed"``: the floor
    at y = 0 when nothing tells it), the device ``offsets`` (``openxr``) and
    the tracked dancer's ``role`` (SPEC §3: ``leader`` or ``follower``)."""

    devices: str = "joints"
    height: float = TRAIN_HEIGHT
    height_source: str = "assumed"
    floor_y: float = 0.0
    floor_source: str = "assumed"
    offsets: DeviceOffsets = field(default_factory=DeviceOffsets)
    role: str = "leader"
    turns: DeviceTurns = field(default_factory=DeviceTurns)
    # per device (head, lhand, rhand): whether the tracked dancer follows its orientation
    followed: tuple = (True, True, True)
    # per device: the median speed (degrees a second) at which its orientation turns (NaN: unknown)
    turn_speeds: tuple = (float("nan"),) * 3
    orientations_given: str = "measured"  # the take's ``orientations`` metadata
    orientations_problem: str = ""  # why a full-body file's rig gave none (``formats.rig_rest``)

    def describe(self) -> str:
        """One line for a user: what was given and what estimated."""
        line = (f"{self.role} tracked, height {self.height:.2f} m ({self.height_source}), floor at "
                f"y = {self.floor_y:+.3f} m ({self.floor_source}), devices {self.devices}")
        if self.turns:
            line += ", device turns " + "; ".join(f"{k} {v}" for k, v in self.turns.meta().items())
        return line

    def notice(self) -> str | None:
        """One line when some device orientations are not followed, else None."""
        off = [d for d, f in zip(DEVICE_LABELS, self.followed) if not f]
        if not off:
            return None
        if self.orientations_given == "none":
            why = self.orientations_problem or "the take says its orientations carry nothing (orientations=none)"
        else:
            speeds = [f"{s:,.0f}" for s, f in zip(self.turn_speeds, self.followed) if not f]
            why = (f"they turn {', '.join(speeds)} degrees a second on the median row (no body turns faster than "
                   f"{ORIENTATION_SPEED_LIMIT:,.0f}): they carry no orientation")
        return f"the {', '.join(off)} orientations are not followed: {why}; only the points are used"

    def meta(self) -> dict:
        """The take metadata (SPEC §3 keys) that reproduce this calibration."""
        out = {"height_m": f"{self.height:.4f}", "floor_y": f"{self.floor_y:.4f}", "devices": self.devices,
               "role": self.role}
        out.update(self.turns.meta())
        if self.orientations_given == "none":
            out["orientations"] = "none"
        return out

    def read(self, positions, quats):
        """Device poses ``(..., 3, 3)``, ``(..., 3, 4)`` of the take's frame as
        SPEC §2 points and the orientations they carry (:func:`read_poses`)."""
        return read_poses(positions, quats, self.devices, self.offsets.at(self.height), self.turns, self.followed,
                          self.height)


# An openxr hand whose grip orientation is not followed: its wrist is put the grip's
# body offset away from the fist, towards the shoulder, taken this far below the base
# of the skull and to its side (m, for a wearer of REFERENCE_HEIGHT_M). Measured on
# the salsa takes' val frames: the wrist 4.3 cm off on average, against 7.4 cm for
# the fist itself and 4.0 cm towards the true shoulder.
SHOULDER_BELOW_HEAD = 0.22
SHOULDER_SIDE = 0.17


def read_poses(positions, quats, devices, offsets, turns: DeviceTurns = DeviceTurns(),
               followed=(True, True, True), height=TRAIN_HEIGHT):
    """Device poses ``(..., 3, 3)``, ``(..., 3, 4)`` as SPEC §2 points and the
    orientations they carry: the ``turns`` taken off, then for ``openxr``
    devices the body ``offsets (3, 3)`` (:meth:`DeviceOffsets.at`) applied
    (:func:`~.formats.devices.openxr_to_points`). An ``openxr`` device whose
    orientation is not ``followed`` is offset without it: the head straight
    down by its offset's height, a hand's wrist towards the shoulder
    (:data:`SHOULDER_BELOW_HEAD`, :data:`SHOULDER_SIDE`, scaled to the wearer's
    ``height``). Lost devices (NaN) stay lost."""
    positions = np.asarray(positions, dtype=np.float64)
    quats = np.asarray(quats, dtype=np.float64)
    if turns:
        quats = turns.remove(quats)
    if devices != "openxr":
        return positions, quats
    if all(followed):
        return openxr_to_points(positions, quats, offsets)
    offsets = np.array(offsets, dtype=np.float64)
    reach = np.linalg.norm(offsets, axis=-1)
    drop = offsets[0, 1]
    kept = offsets.copy()
    for d in range(3):
        if not followed[d]:
            kept[d] = 0.0
    points, quats = openxr_to_points(positions, quats, kept)
    points = points.copy()
    if not followed[0]:
        points[..., 0, 1] += drop
    s = float(height) / REFERENCE_HEIGHT_M
    head = points[..., 0, :]
    left = np.zeros(head.shape)
    if followed[0]:  # the body's left: the head device's +X is its right
        R = quat_to_matrix(np.nan_to_num(quats[..., 0, :]))
        left = -R[..., :, 0]
        left[..., 1] = 0.0
        left /= np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-9)
    for d, side in ((1, 1.0), (2, -1.0)):
        if followed[d]:
            continue
        shoulder = head + side * SHOULDER_SIDE * s * left
        shoulder[..., 1] -= SHOULDER_BELOW_HEAD * s
        to = shoulder - points[..., d, :]
        n = np.linalg.norm(to, axis=-1, keepdims=True)
        points[..., d, :] += to * np.where(n > reach[d], reach[d] / np.maximum(n, 1e-9), 0.0)
    return points, quats


def orientation_speeds(take: Take) -> tuple:
    """Per device the median speed (degrees a second) at which its orientation
    turns between consecutive rows where it is tracked (NaN: fewer than 2 such rows)."""
    q = np.asarray(take.quats, dtype=np.float64)
    dt = np.diff(np.asarray(take.time, dtype=np.float64))
    out = []
    for d in range(q.shape[1]):
        a, b = q[:-1, d], q[1:, d]
        ok = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
        if not ok.any():
            out.append(float("nan"))
            continue
        na, nb = np.linalg.norm(a[ok], axis=-1), np.linalg.norm(b[ok], axis=-1)
        dots = np.abs((a[ok] * b[ok]).sum(-1)) / (na * nb)
        angle = 2.0 * np.degrees(np.arccos(np.clip(dots, 0.0, 1.0)))
        out.append(float(np.median(angle / dt[ok])))
    return tuple(out)


def upright_head(head_y) -> float:
    """The height of the base of the skull when the dancer stands upright: a
    high percentile (:data:`HEAD_PERCENTILE`) of the heights ``head_y`` it takes."""
    return float(np.percentile(head_y, HEAD_PERCENTILE))


def height_from_head(head_y) -> float:
    """A standing height (m) from the heights of the base of the skull above the floor."""
    h = TRAIN_HEIGHT * upright_head(head_y) / TRAIN_HEAD_HEIGHT
    return float(np.clip(h, *ESTIMATE_RANGE_M))


def floor_from_head(head_y, height: float) -> float:
    """Where the floor lies (its y) under heads ``head_y`` of a dancer ``height`` m tall."""
    return upright_head(head_y) - float(height) * TRAIN_HEAD_HEIGHT / TRAIN_HEIGHT


def _meta_float(meta, key, path):
    v = meta.get(key)
    if v in (None, ""):
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(path, f"{key} is not a number: {v!r}") from None
    if not np.isfinite(x):
        raise InputError(path, f"{key} must be a finite number, got {v!r}")
    return x


def head_points(take: Take, devices: str, offsets: DeviceOffsets, height, turns: DeviceTurns = DeviceTurns(),
                followed=(True, True, True)) -> np.ndarray:
    """``(T, 3)`` the base of the skull on every row (NaN where the head is lost)."""
    if devices == "joints":
        return np.asarray(take.positions[:, 0], dtype=np.float64)
    if turns or not followed[0]:
        return read_poses(take.positions, take.quats, devices, offsets.at(height), turns, followed, height)[0][:, 0]
    R = quat_to_matrix(np.nan_to_num(take.quats[:, 0]))
    return take.positions[:, 0] + R @ offsets.at(height)[0]


def check_role(value, path="<take>", line=None) -> str:
    """A SPEC §3 ``role`` value (``leader`` or ``follower``), else an :class:`InputError`."""
    v = str(value).strip().lower()
    if v not in ROLES:
        raise InputError(path, f"unknown role {value!r} (expected {' or '.join(ROLES)})", line)
    return v


def head_heights(take: Take, devices: str, offsets: DeviceOffsets, height, turns: DeviceTurns = DeviceTurns(),
                 followed=(True, True, True)) -> np.ndarray:
    """The heights of the base of the skull at the networks' 30 Hz frames where
    the head is tracked: converted on the take's own rows, then interpolated, so
    a take and its copy at another rate (a 60 Hz file and the 30 fps keys
    Blender imports it to) estimate the same height and floor."""
    y = head_points(take, devices, offsets, height, turns, followed)[:, 1]
    ok = np.isfinite(y) & np.isfinite(take.quats[:, 0]).all(-1)
    if len(y) < 2:
        return y[ok]
    _, i, a = resample_plan(take.time, NET_FPS)
    keep = tracked_after_resampling(ok[:, None], i, a)[:, 0]
    y0 = np.where(ok, y, 0.0)
    return (y0[i] + (y0[i + 1] - y0[i]) * a)[keep]


def calibrate(take: Take, height=None, floor_y=None, devices=None, offsets: DeviceOffsets | None = None,
              head_offset=None, hand_offset=None, role=None, head_turn=None, hand_turn=None) -> Calibration:
    """The calibration of ``take``: each of ``devices``, ``height``, ``floor_y``
    and ``role`` given here wins over the take's metadata (``devices``,
    ``height_m``, ``floor_y``, ``role``), which wins over an estimate (see the
    module's docstring) or the default. ``offsets`` replaces the take's device
    offsets; ``head_offset`` / ``hand_offset`` (x,y,z at the wearer's size)
    replace single ones; ``head_turn`` / ``hand_turn`` (quaternions) the
    take's device turns. Which device orientations are followed: those that
    carry one (see the module's docstring)."""
    path = take.source or "<take>"
    meta = take.meta
    devices = check_devices(devices if devices is not None else meta.get("devices") or "joints", path)
    role = check_role(role if role is not None else meta.get("role") or "leader", path)
    if offsets is None:
        offsets = offsets_for(meta, head_offset, hand_offset, path)
    turns = turns_for(meta, head_turn, hand_turn, path)
    given_o = "measured" if take_orientations_usable(meta) else "none"
    speeds = orientation_speeds(take)
    followed = tuple(bool(given_o != "none" and not s > ORIENTATION_SPEED_LIMIT) for s in speeds)
    if height in ("auto", ""):
        height = None
    given_h = float(height) if height is not None else take.height
    given_f = float(floor_y) if floor_y is not None else _meta_float(meta, "floor_y", path)

    def heads(h):
        return head_heights(take, devices, offsets, h, turns, followed)

    def made(h, h_src, f, f_src):
        return Calibration(devices, h, h_src, f, f_src, offsets, role, turns, followed, speeds, given_o,
                           str(meta.get(ORIENTATIONS_PROBLEM_KEY) or ""))

    seen = heads(TRAIN_HEIGHT).size > 0  # the head on a 30 Hz frame
    if given_h is not None:
        h_src, h = "given", given_h
        if given_f is not None:
            f_src, f = "given", given_f
        elif seen:
            f_src, f = "estimated", floor_from_head(heads(h), h)
            if abs(f) > FLOOR_RANGE_M:
                raise InputError(path, f"with a height of {h:.2f} m the floor would lie at y = {f:+.2f} m: "
                                       f"check the height, or give floor_y")
        else:
            f_src, f = "assumed", 0.0
        return made(h, h_src, f, f_src)
    f_src, f = ("given", given_f) if given_f is not None else ("assumed", 0.0)
    if not seen:
        return made(TRAIN_HEIGHT, "assumed", f, f_src)
    h = TRAIN_HEIGHT
    # openxr: the skull base depends on the offsets, which scale with the height: a fixed point
    for _ in range(1 if devices == "joints" else 20):
        h, h0 = height_from_head(heads(h) - f), h
        if abs(h - h0) < 1e-9:
            break
    return made(h, "estimated", f, f_src)


def apply_calibration(take: Take, calib: Calibration, fill_start: bool = True) -> Take:
    """``take`` as §2 points in a frame whose floor is y = 0 (the head device's
    and the hands' orientations as the devices give them: for ``openxr`` the
    hands' are the hand bones', see :func:`~.formats.devices.openxr_to_points`).
    ``fill_start``: rows before a device is first seen take its first pose
    (the hands relative to the head), so a take that starts lost starts where
    the dancer is first seen."""
    pos, quats = calib.read(take.positions, take.quats)
    pos, quats = np.array(pos, dtype=np.float64), np.array(quats, dtype=np.float64)
    if calib.floor_y:
        pos[..., 1] -= calib.floor_y
    if fill_start:
        fill_lost_start(pos, quats)
    meta = dict(take.meta)
    meta.update(calib.meta())
    return Take(np.asarray(take.time, dtype=np.float64), pos, quats, meta, take.source)


def fill_lost_start(pos: np.ndarray, quats: np.ndarray) -> None:
    """In place: the rows before each device's first tracked row take that
    row's pose; a hand's, relative to the head's root (position and heading),
    so it stays where it was first seen relative to the dancer."""
    valid = np.isfinite(pos).all(-1) & np.isfinite(quats).all(-1)
    first = [int(np.argmax(valid[:, d])) if valid[:, d].any() else None for d in range(3)]
    f0 = first[0]
    if f0 is None:
        return
    if f0 > 0:
        pos[:f0, 0] = pos[f0, 0]
        quats[:f0, 0] = quats[f0, 0]
    for d in (1, 2):
        f = first[d]
        if not f:  # never seen (None: the runtime fills it), or seen from the start (0)
            continue
        roots = root_from_head(pos[:f + 1, 0], quat_to_matrix(quats[:f + 1, 0]))
        if not np.isfinite(roots).all():  # the head lost somewhere there: hold the hand in the world
            pos[:f, d] = pos[f, d]
            quats[:f, d] = quats[f, d]
            continue
        local = to_local(pos[f, d][None], roots[f])[0]
        pos[:f, d] = to_world(np.broadcast_to(local, (f, 1, 3)), roots[:f])[:, 0]
        # the hand's orientation turned with the head's heading
        turn = np.arctan2(roots[:f, 3], roots[:f, 2]) - np.arctan2(roots[f, 3], roots[f, 2])
        c, s = np.cos(turn), np.sin(turn)
        yaw = np.zeros((f, 3, 3))
        yaw[:, 0, 0], yaw[:, 0, 2], yaw[:, 1, 1], yaw[:, 2, 0], yaw[:, 2, 2] = c, s, 1.0, -s, c
        quats[:f, d] = matrix_to_quat(yaw @ quat_to_matrix(quats[f, d]))


def headset_take(take: Take, hand_rotations=None, height=None, offsets: DeviceOffsets | None = None) -> Take:
    """The take a headset and two controllers would record of the dancer of the
    ``joints`` take ``take``: the view pose and the grip poses (SPEC §3
    ``openxr``), placed by ``offsets`` (default :class:`DeviceOffsets`) for a
    wearer ``height`` m tall (default: the take's ``height_m``, else estimated
    from it as :func:`calibrate` would). ``hand_rotations (T, 2, 3, 3)``: the
    hand bones' global rotations (default: the take's hand orientations). The
    metadata say ``devices=openxr``; a height is written only when it was given,
    so a reader estimates it again (and finds the same)."""
    offsets = offsets or DeviceOffsets()
    given = height if height is not None else take.height
    h = given
    if h is None:
        h = calibrate(take, devices="joints").height
    if hand_rotations is None:
        hand_rotations = quat_to_matrix(np.nan_to_num(take.quats[:, 1:]))
    poses, quats = points_to_openxr(take.positions, take.quats[:, 0], hand_rotations, offsets.at(h))
    lost = ~(np.isfinite(take.positions).all(-1) & np.isfinite(take.quats).all(-1))
    poses[lost] = np.nan
    quats[lost] = np.nan
    meta = {k: v for k, v in take.meta.items() if k not in ("devices", "height_m")}
    meta["devices"] = "openxr"
    if given is not None:
        meta["height_m"] = f"{float(given):.4f}"
    return Take(np.asarray(take.time, dtype=np.float64), poses, quats, meta, take.source)


__all__ = ["headset_take", "Calibration", "DEVICE_KINDS", "ROLES", "check_role", "TRAIN_HEIGHT", "TRAIN_HEAD_HEIGHT",
           "apply_calibration", "calibrate", "fill_lost_start", "floor_from_head", "height_from_head", "upright_head"]
