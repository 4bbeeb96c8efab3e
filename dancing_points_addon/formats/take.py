"""Three-point takes (SPEC §3): the leader's head and two hand devices over time.

The :class:`Take`, its writer and the takes made of a body's motion; the
reader is :mod:`.take_read`. Writing (:func:`write_take`) is atomic: a temporary file in the target folder replaced
onto the target, so a failure never leaves a half-written take behind.

Any supported input (take ``.csv``, CMU ``.amc``, ``.bvh``) becomes a take
through :func:`~..inputs.load_input`, and every take meets the rules of
:func:`~..inputs.check_take`; the bounds are in :mod:`.limits`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from .files import atomic_output
from ..rotations import axis_rotation, matrix_to_quat
from ..skeleton import HEAD_BONE, TRACKED, Motion

DEVICES = ("head", "lhand", "rhand")
DEVICE_FIELDS = ("px", "py", "pz", "qw", "qx", "qy", "qz")
COLUMNS = ("time",) + tuple(f"{d}_{f}" for d in DEVICES for f in DEVICE_FIELDS)
MAX_DISTANCE_M = 1000.0  # SPEC §3: positions farther than 1 km are rejected
QUAT_NORM_RANGE = (0.5, 2.0)  # SPEC §3: other norms are rejected, these normalised
# The head device looks along its local -Z with +Y up (OpenXR); the CMU skull
# (ASF bone ``head``) faces +Z at rest. Device-to-world = R_head · Ry(180°), so a
# wearer facing +Z has device quaternion (0, 0, 1, 0).
HEAD_DEVICE_OFFSET = axis_rotation("Y", np.pi)


# Metadata ``orientations``: ``measured`` (default: the devices' orientations mean
# what SPEC §3 says) or ``none``: they carry nothing, as for a take read from a
# full-body file whose rig's orientations cannot be read (``formats.rig_rest``; its
# quaternions are then placeholders, head facing +Z, hands at rest). Its points are
# used; the head and hands do not follow its orientations.
ORIENTATIONS_KEY = "orientations"
ORIENTATIONS_NONE = "none"
ORIENTATION_VALUES = ("measured", ORIENTATIONS_NONE)
# Why, said once by the reader that loads the take (not written to a take file).
META_KEY = re.compile(r"[A-Za-z_][\w.\-]*")  # a metadata key (letters, digits, _ . -)
ORIENTATIONS_PROBLEM_KEY = "orientations_problem"


def take_orientations_usable(meta) -> bool:
    """Whether a take's device orientations mean what SPEC §3 says (False for
    ``orientations=none``: a full-body file whose rig's orientations could not
    be read; the synthesis then does not follow the devices' orientations)."""
    return str((meta or {}).get(ORIENTATIONS_KEY, "")).strip().lower() != ORIENTATIONS_NONE


@dataclass
class Take:
    """``time (T,)`` seconds; ``positions (T, 3, 3)`` metres, motion space, device
    order head/lhand/rhand; ``quats (T, 3, 4)`` device-to-world ``(w, x, y, z)``.
    A device that lost tracking on a row has NaN in its position and quaternion.
    """

    time: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    meta: dict = field(default_factory=dict)
    source: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """``(T, 3)`` bool: device tracked on that row."""
        return np.isfinite(self.positions).all(-1) & np.isfinite(self.quats).all(-1)

    @property
    def height(self):
        h = self.meta.get("height_m")
        return float(h) if h not in (None, "") else None


# --------------------------------------------------------------------------- writing

WRITE_BLOCK_ROWS = 20_000  # rows formatted at a time (memory: a block's text, not the whole file's)


def _text_parts(take: Take):
    """The CSV text of a take in pieces: the header, then blocks of rows."""
    head = []
    for k, v in take.meta.items():
        v = str(v)
        if META_KEY.fullmatch(str(k)) and "\n" not in v and "\r" not in v:
            head.append(f"# {k}={v}")
    head.append(",".join(COLUMNS))
    yield "\n".join(head) + "\n"
    n = take.n_frames
    if n == 0:
        yield "\n"
        return
    fmt = "%s" + ",%.10g" * 21
    for a in range(0, n, WRITE_BLOCK_ROWS):
        b = min(n, a + WRITE_BLOCK_ROWS)
        time = np.asarray(take.time[a:b], dtype=np.float64)
        dev = np.concatenate([np.asarray(take.positions[a:b], dtype=np.float64),
                              np.asarray(take.quats[a:b], dtype=np.float64)], axis=-1)
        lost = ~np.isfinite(dev).all(-1)
        dev[lost] = np.nan
        rows = dev.reshape(b - a, 21).tolist()
        body = "\n".join([fmt % (t, *r) for t, r in zip(_time_texts(time), rows)])
        yield body.replace("nan", "") + "\n"


def take_to_text(take: Take) -> str:
    """The CSV text of a take (lost devices as empty fields)."""
    return "".join(_text_parts(take))


def _time_texts(time: np.ndarray) -> list:
    """Each time as text that reads back as exactly the same float: 12
    significant digits where they suffice (``0.5``, ``1.25``), else the
    shortest exact form (``repr``: up to 17 digits, e.g. ``0.016666666666666666``
    or ``1700000000.0166667`` for a time since the Unix epoch)."""
    vals = time.tolist()
    texts = ["%.12g" % t for t in vals]
    with np.errstate(invalid="ignore"):
        inexact = np.flatnonzero(np.array(texts, dtype=np.float64) != time)
    for i in inexact.tolist():
        texts[i] = repr(float(vals[i]))
    return texts


def write_take(path, take: Take) -> None:
    """Write ``take`` as a SPEC §3 file, atomically; metadata become ``# key=value``.

    Time is written exactly (it reads back as the same float: 12 significant
    digits, or up to 17 where 12 would round it, as for epoch times);
    positions and quaternions with 10 (better than 1e-6 m anywhere within the
    1 km limit).
    """
    with atomic_output(path, "w", encoding="utf-8", newline="\n") as f:
        for part in _text_parts(take):  # block by block: no copy of the whole text in memory
            f.write(part)


# --------------------------------------------------------------------------- extraction

def head_device_quat(head_rotations: np.ndarray) -> np.ndarray:
    """Head device quaternions from global rotations of the skull (SPEC §2 ``head``)."""
    return matrix_to_quat(np.asarray(head_rotations) @ HEAD_DEVICE_OFFSET)


def take_from_tracked(time, positions, head_rot, lhand_rot, rhand_rot, meta=None, source="",
                      problem="") -> Take:
    """A take from tracked-point positions ``(T, 3, 3)`` and global rotations of the
    skull and the two wrists ``(T, 3, 3)`` each (SPEC §2 rest-pose convention).

    ``problem`` (why a rig's orientations cannot be read, ``formats.rig_rest``):
    the rotations are replaced by the rest pose's and the take says
    ``orientations=none`` (:func:`take_orientations_usable`), the reason in
    :data:`ORIENTATIONS_PROBLEM_KEY`."""
    meta = dict(meta or {})
    if problem:
        head_rot = lhand_rot = rhand_rot = np.broadcast_to(np.eye(3), np.shape(positions)[:1] + (3, 3))
        meta[ORIENTATIONS_KEY] = ORIENTATIONS_NONE
        meta[ORIENTATIONS_PROBLEM_KEY] = str(problem)
    quats = np.stack([head_device_quat(head_rot), matrix_to_quat(lhand_rot),
                      matrix_to_quat(rhand_rot)], axis=1)
    return Take(np.asarray(time, dtype=np.float64), np.array(positions, dtype=np.float64),
                quats, meta, str(source))


def take_from_motion(motion: Motion) -> Take:
    """The three-point take of a full-body clip at its own rate (time ``k / fps``).

    Positions are the SPEC §2 tracked points; the head device is rigid on the
    skull (bone ``head``, device-to-world ``R_head · Ry(180°)``); the hand
    devices carry the wrists' (``lwrist``, ``rwrist``) global rotations.
    No ``height_m`` is written: the user's height is an input (``--height``).
    """
    rot = motion.rotations
    lw, rw = int(TRACKED[1]), int(TRACKED[2])
    time = np.arange(motion.n_frames) / float(motion.fps)
    return take_from_tracked(time, motion.positions[:, TRACKED], rot[:, HEAD_BONE],
                             rot[:, lw], rot[:, rw], {}, motion.source)
