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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .formats.devices import (DEVICE_KINDS, DeviceOffsets, check_devices, offsets_for, openxr_to_points,
                              points_to_openxr)
from .formats.limits import FLOOR_RANGE_M
from .formats.take import Take
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

    def describe(self) -> str:
        """One line for a user: what was given and what estimated."""
        return (f"{self.role} tracked, height {self.height:.2f} m ({self.height_source}), floor at "
                f"y = {self.floor_y:+.3f} m ({self.floor_source}), devices {self.devices}")

    def meta(self) -> dict:
        """The take metadata (SPEC §3 keys) that reproduce this calibration."""
        return {"height_m": f"{self.height:.4f}", "floor_y": f"{self.floor_y:.4f}", "devices": self.devices,
                "role": self.role}


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


def head_points(take: Take, devices: str, offsets: DeviceOffsets, height) -> np.ndarray:
    """``(T, 3)`` the base of the skull on every row (NaN where the head is lost)."""
    if devices == "joints":
        return np.asarray(take.positions[:, 0], dtype=np.float64)
    R = quat_to_matrix(np.nan_to_num(take.quats[:, 0]))
    return take.positions[:, 0] + R @ offsets.at(height)[0]


def check_role(value, path="<take>", line=None) -> str:
    """A SPEC §3 ``role`` value (``leader`` or ``follower``), else an :class:`InputError`."""
    v = str(value).strip().lower()
    if v not in ROLES:
        raise InputError(path, f"unknown role {value!r} (expected {' or '.join(ROLES)})", line)
    return v


def head_heights(take: Take, devices: str, offsets: DeviceOffsets, height) -> np.ndarray:
    """The heights of the base of the skull at the networks' 30 Hz frames where
    the head is tracked: converted on the take's own rows, then interpolated, so
    a take and its copy at another rate (a 60 Hz file and the 30 fps keys
    Blender imports it to) estimate the same height and floor."""
    y = head_points(take, devices, offsets, height)[:, 1]
    ok = np.isfinite(y) & np.isfinite(take.quats[:, 0]).all(-1)
    if len(y) < 2:
        return y[ok]
    _, i, a = resample_plan(take.time, NET_FPS)
    keep = tracked_after_resampling(ok[:, None], i, a)[:, 0]
    y0 = np.where(ok, y, 0.0)
    return (y0[i] + (y0[i + 1] - y0[i]) * a)[keep]


def calibrate(take: Take, height=None, floor_y=None, devices=None, offsets: DeviceOffsets | None = None,
              head_offset=None, hand_offset=None, role=None) -> Calibration:
    """The calibration of ``take``: each of ``devices``, ``height``, ``floor_y``
    and ``role`` given here wins over the take's metadata (``devices``,
    ``height_m``, ``floor_y``, ``role``), which wins over an estimate (see the
    module's docstring) or the default. ``offsets`` replaces the take's device
    offsets; ``head_offset`` / ``hand_offset`` (x,y,z at the wearer's size)
    replace single ones."""
    path = take.source or "<take>"
    meta = take.meta
    devices = check_devices(devices if devices is not None else meta.get("devices") or "joints", path)
    role = check_role(role if role is not None else meta.get("role") or "leader", path)
    if offsets is None:
        offsets = offsets_for(meta, head_offset, hand_offset, path)
    if height in ("auto", ""):
        height = None
    given_h = float(height) if height is not None else take.height
    given_f = float(floor_y) if floor_y is not None else _meta_float(meta, "floor_y", path)
    seen = head_heights(take, devices, offsets, TRAIN_HEIGHT).size > 0  # the head on a 30 Hz frame
    if given_h is not None:
        h_src, h = "given", given_h
        if given_f is not None:
            f_src, f = "given", given_f
        elif seen:
            f_src, f = "estimated", floor_from_head(head_heights(take, devices, offsets, h), h)
            if abs(f) > FLOOR_RANGE_M:
                raise InputError(path, f"with a height of {h:.2f} m the floor would lie at y = {f:+.2f} m: "
                                       f"check the height, or give floor_y")
        else:
            f_src, f = "assumed", 0.0
        return Calibration(devices, h, h_src, f, f_src, offsets, role)
    f_src, f = ("given", given_f) if given_f is not None else ("assumed", 0.0)
    if not seen:
        return Calibration(devices, TRAIN_HEIGHT, "assumed", f, f_src, offsets, role)
    h = TRAIN_HEIGHT
    # openxr: the skull base depends on the offsets, which scale with the height: a fixed point
    for _ in range(1 if devices == "joints" else 20):
        h, h0 = height_from_head(head_heights(take, devices, offsets, h) - f), h
        if abs(h - h0) < 1e-9:
            break
    return Calibration(devices, h, "estimated", f, f_src, offsets, role)


def apply_calibration(take: Take, calib: Calibration, fill_start: bool = True) -> Take:
    """``take`` as §2 points in a frame whose floor is y = 0 (the head device's
    and the hands' orientations as the devices give them: for ``openxr`` the
    hands' are the hand bones', see :func:`~.formats.devices.openxr_to_points`).
    ``fill_start``: rows before a device is first seen take its first pose
    (the hands relative to the head), so a take that starts lost starts where
    the dancer is first seen."""
    pos = np.array(take.positions, dtype=np.float64)
    quats = np.array(take.quats, dtype=np.float64)
    if calib.devices == "openxr":
        pos, quats = openxr_to_points(pos, quats, calib.offsets.at(calib.height))
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
