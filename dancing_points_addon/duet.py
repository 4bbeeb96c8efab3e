"""A synthesised duet (SPEC §4): :class:`Duet`, one frame of it
(:class:`DuetFrame`), and writing it (:func:`save_npz`, :func:`duet_motions`
for BVH)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import features as F
from .calibration import Calibration
from .skeleton import JOINT_NAMES


@dataclass
class DuetFrame:
    positions: np.ndarray  # (31, 3) world
    rotations: np.ndarray  # (31, 3, 3) world
    contacts: np.ndarray  # (4,)


@dataclass
class Duet:
    """A synthesised duet (SPEC §4)."""

    time: np.ndarray
    leader_positions: np.ndarray
    leader_rotations: np.ndarray
    leader_contacts: np.ndarray
    follower_positions: np.ndarray
    follower_rotations: np.ndarray
    follower_contacts: np.ndarray
    fps: float = F.FPS
    bone_vectors: dict | None = None  # each dancer's skeleton (rest bone vectors, output scale)
    # The mapping network's 1 s predictions made at each frame (``Synthesizer(record_predictions=True)``):
    # (T, 2 dancers, FUTURE frames t+1…, 3 tracked points, 3) world positions at the output scale,
    # float32; None when not recorded. Not part of the SPEC §4 output (:meth:`arrays`).
    predictions: np.ndarray | None = None
    # Each dancer's foot points held by the foot lock at each frame (T, 2 dancers, 4 points in
    # ``contacts`` order), bool; None without foot locking. What the method view's discs show.
    # Not part of the SPEC §4 output (:meth:`arrays`).
    planted: np.ndarray | None = None
    # How the take was read (devices, the tracked dancer's height, the floor): written
    # beside the SPEC §4 arrays (:meth:`arrays`) so that a user sees what was estimated.
    calibration: Calibration | None = None
    tracked_role: str = "leader"  # whose three points the take held (SPEC §4)
    # The song the take was danced to (:class:`~.audio.Song`), set by whoever writes the duet
    # (the synthesis never reads it): ``audio``, ``audio_offset_s``, ``beats``, ``tempo_bpm`` (SPEC §4).
    song: object | None = None

    @property
    def n_frames(self):
        return len(self.time)

    def arrays(self) -> dict:
        """The SPEC §4 arrays (with the song's keys when it has one), and the calibration
        (``height_m``, ``height_source``, ``floor_y``, ``floor_source``, ``devices``) when known."""
        out = {"fps": np.float64(self.fps), "time": self.time, "joint_names": np.array(JOINT_NAMES),
               "leader_positions": self.leader_positions, "leader_rotations": self.leader_rotations,
               "leader_contacts": self.leader_contacts, "follower_positions": self.follower_positions,
               "follower_rotations": self.follower_rotations, "follower_contacts": self.follower_contacts,
               "tracked_role": np.array(self.tracked_role)}
        c = self.calibration
        if c is not None:
            out.update(height_m=np.float64(c.height), height_source=np.array(c.height_source),
                       floor_y=np.float64(c.floor_y), floor_source=np.array(c.floor_source),
                       devices=np.array(c.devices),
                       # per device (head, lhand, rhand): its orientation followed, and its turn (w, x, y, z)
                       orientations_followed=np.array(c.followed, dtype=bool),
                       device_turns=np.array([t if t is not None else (1.0, 0.0, 0.0, 0.0) for t in
                                              (c.turns.head, c.turns.lhand, c.turns.rhand)], dtype=np.float64))
        if self.song is not None:
            out.update(self.song.arrays(self.time))
        return out


class DuetFrames:
    """The frames of a duet as they are made, one slot per dancer (``0`` the
    tracked dancer, ``1`` the partner), in arrays allocated once for ``T``
    frames; :meth:`duet` makes the :class:`Duet` of them in dance roles.
    ``predictions``, ``planted``: keep those too (see :class:`Duet`)."""

    def __init__(self, T: int, predictions: bool = False, planted: bool = False, future: int = F.FUTURE):
        self.pos = np.empty((2, T, 31, 3))
        self.rot = np.empty((2, T, 31, 3, 3))
        self.con = np.empty((2, T, 4))
        self.predictions = np.empty((T, 2, future, 3, 3), dtype=np.float32) if predictions else None
        self.planted = np.zeros((T, 2, 4), dtype=bool) if planted else None

    def put(self, t: int, tracked: DuetFrame, partner: DuetFrame, prediction=None, planted=None) -> None:
        for w, f in enumerate((tracked, partner)):
            self.pos[w, t], self.rot[w, t], self.con[w, t] = f.positions, f.rotations, f.contacts
        if self.predictions is not None:
            self.predictions[t] = prediction
        if self.planted is not None:
            self.planted[t] = planted

    def duet(self, time, tracked_role: str, floor_y: float = 0.0, **kw) -> Duet:
        """The :class:`Duet` at ``time``, back on the take's floor (``floor_y``),
        the slots put in dance roles (``tracked_role``: the tracked dancer's);
        ``kw``: :class:`Duet`'s other fields."""
        if floor_y:
            self.pos[..., 1] += floor_y
            if self.predictions is not None:
                self.predictions[..., 1] += np.float32(floor_y)
        slots = [(self.pos[w], self.rot[w], self.con[w]) for w in (0, 1)]
        if tracked_role == "follower":
            slots = slots[::-1]
        return Duet(time, *slots[0], *slots[1], predictions=self.predictions, planted=self.planted,
                    tracked_role=tracked_role, **kw)


def save_npz(duet: Duet, path) -> None:
    """Write a duet (SPEC §4) atomically: nothing is left at ``path`` on failure
    (a full disk, Ctrl-C: the temporary file is removed, the zip writer closed
    without a word)."""
    from .formats.files import atomic_output, write_npz

    with atomic_output(path, "wb") as f:
        write_npz(f, duet.arrays())


def duet_motions(duet: Duet, bone_vectors: dict | None = None):
    """The two dancers as SPEC :class:`~.skeleton.Motion` clips (for BVH export)."""
    from .skeleton import Motion

    bone_vectors = bone_vectors or duet.bone_vectors
    return {role: Motion(getattr(duet, f"{role}_positions"), getattr(duet, f"{role}_rotations"), duet.fps,
                         bone_vectors[role], source=role)
            for role in ("leader", "follower")}
