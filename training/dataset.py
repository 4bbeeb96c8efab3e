"""Salsa pairs at 30 Hz with the SPEC §5 split, mirror augmentation, npz cache.

Subject 60 leads and 61 follows; take ``NN`` of both was captured together.
Each 60 Hz take is resampled to 30 Hz by keeping every other frame
(``n30 = ceil(n60 / 2)``); frames ``[0, floor(0.8 · n30))`` are train, the rest
test. Only the split asked for is returned, so a training caller cannot touch a
test frame. Mirroring reflects the world across x = 0 and swaps left/right
joints; the mirrored leader is paired with the mirrored follower.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass

import numpy as np

from dancing_points_addon.features import FUTURE
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.representation import contact_labels, root_from_motion
from dancing_points_addon.skeleton import MIRROR

SALSA_TAKES = tuple(f"{i:02d}" for i in range(1, 14))
LEADER, FOLLOWER = "60", "61"
SOLO_TRAIN_TAKES = tuple(f"05_{i:02d}" for i in range(1, 11))  # SPEC §5: the trackers may learn from these
SOLO_HELD_OUT = tuple(f"05_{i:02d}" for i in range(11, 21))  # SPEC §5: never trained on or chosen by
TRAIN_SHARE = 0.8
FIT_SHARE = 0.8  # of the train frames: "fit" then "val", for choosing a recipe without the test frames
CACHE_VERSION = 2


def n_train_frames(n30: int) -> int:
    return int(np.floor(TRAIN_SHARE * n30))


def split_range(n60: int, split: str) -> tuple[int, int]:
    """30 Hz frame range ``[a, b)`` of a split for a take with ``n60`` frames:
    "train" and "test" (SPEC §5), and the train frames cut in two, "fit" (the
    first 80 %) and "val" (the rest), to choose a recipe without the test frames."""
    n30 = (n60 + 1) // 2
    k = n_train_frames(n30)
    if split == "train":
        return 0, k
    if split == "test":
        return k, n30
    if split in ("fit", "val"):
        f = int(np.floor(FIT_SHARE * k))
        return (0, f) if split == "fit" else (f, k)
    raise ValueError(f"unknown split {split!r}")


_M = np.diag([-1.0, 1.0, 1.0])


def mirror(positions: np.ndarray, rotations: np.ndarray):
    """Reflect across x = 0 and swap left/right: a valid motion of the mirrored body."""
    pos = positions[:, MIRROR] * np.array([-1.0, 1.0, 1.0])
    rot = _M @ rotations[:, MIRROR] @ _M
    return pos, rot


@dataclass
class Dancer:
    positions: np.ndarray  # (T, 31, 3)
    rotations: np.ndarray  # (T, 31, 3, 3)
    roots: np.ndarray  # (T, 4)
    contacts: np.ndarray  # (T, 4) float 0/1

    @classmethod
    def from_arrays(cls, positions, rotations, fps=30.0):
        return cls(positions, rotations, root_from_motion(positions, rotations),
                   contact_labels(positions, fps).astype(np.float32))


@dataclass
class Clip:
    name: str
    leader: Dancer
    follower: Dancer | None
    mirrored: bool = False

    @property
    def n_frames(self) -> int:
        return len(self.leader.positions)


def load_pair(data_dir, take: str, split: str):
    """Leader and follower 30 Hz positions/rotations of one take's split."""
    lead = load_amc(os.path.join(data_dir, f"{LEADER}_{take}.amc"))
    fol = load_amc(os.path.join(data_dir, f"{FOLLOWER}_{take}.amc"))
    if lead.n_frames != fol.n_frames:
        raise ValueError(f"take {take}: leader and follower frame counts differ")
    a, b = split_range(lead.n_frames, split)
    lead, fol = lead.subsample(2), fol.subsample(2)
    return (lead.positions[a:b], lead.rotations[a:b]), (fol.positions[a:b], fol.rotations[a:b])


def build_clips(data_dir, split: str = "train", mirror_aug: bool = True):
    """The salsa clips of a split."""
    clips = []
    for take in SALSA_TAKES:
        (lp, lr), (fp, fr) = load_pair(data_dir, take, split)
        clips.append(Clip(take, Dancer.from_arrays(lp, lr), Dancer.from_arrays(fp, fr)))
        if mirror_aug:
            clips.append(Clip(take + "m", Dancer.from_arrays(*mirror(lp, lr)),
                              Dancer.from_arrays(*mirror(fp, fr)), True))
    return clips


def solo_clips(solo_dir, split: str = "train", mirror_aug: bool = True):
    """The solo dancer's clips for the trackers (SPEC §5: takes ``05_01``–``05_10``
    only; ``05_11``–``05_20`` are held out). Each 120 Hz take gives four 30 Hz
    clips, one per phase of every 4th frame; "train" is the whole take, "fit"
    and "val" its first 80 % and the rest (as the salsa takes' train frames)."""
    if split not in ("train", "fit", "val"):
        raise ValueError(f"the solo takes have no {split!r} frames (SPEC §5: 05_11-05_20 are held out)")
    clips = []
    for take in SOLO_TRAIN_TAKES:
        m = load_amc(os.path.join(solo_dir, f"{take}.amc"))
        f = int(np.floor(FIT_SHARE * m.n_frames))
        a, b = {"train": (0, m.n_frames), "fit": (0, f), "val": (f, m.n_frames)}[split]
        for phase in range(4):
            pos, rot = m.positions[a + phase:b:4], m.rotations[a + phase:b:4]
            if len(pos) <= FUTURE:  # no sample fits
                continue
            clips.append(Clip(f"{take}p{phase}", Dancer.from_arrays(pos, rot), None))
            if mirror_aug:
                clips.append(Clip(f"{take}p{phase}m", Dancer.from_arrays(*mirror(pos, rot)), None, True))
    return clips


_KEYS = ("positions", "rotations", "roots", "contacts")


def _cache_key(data_dir, split, mirror_aug):
    h = hashlib.sha1()
    for f in sorted(os.listdir(data_dir)):
        st = os.stat(os.path.join(data_dir, f))
        h.update(f"{f}:{st.st_size}:{int(st.st_mtime)}".encode())
    h.update(json.dumps([split, mirror_aug, False, CACHE_VERSION]).encode())  # (False: the keys of earlier caches)
    return h.hexdigest()[:16]


def load_clips(data_dir, split="train", mirror_aug=True, cache_dir="cache"):
    """:func:`build_clips` through an ``.npz`` cache (keyed by the source files)."""
    key = _cache_key(data_dir, split, mirror_aug)
    path = os.path.join(cache_dir, f"salsa_{split}_{key}.npz") if cache_dir else None
    if path and os.path.exists(path):
        z = np.load(path, allow_pickle=False)
        clips = []
        for i, name in enumerate(z["names"]):
            def dancer(role):
                if f"{role}{i}_positions" not in z:
                    return None
                return Dancer(*(z[f"{role}{i}_{k}"] for k in _KEYS))
            clips.append(Clip(str(name), dancer("L"), dancer("F"), bool(z["mirrored"][i])))
        return clips
    clips = build_clips(data_dir, split, mirror_aug)
    if path:
        os.makedirs(cache_dir, exist_ok=True)
        arrays = {"names": np.array([c.name for c in clips]),
                  "mirrored": np.array([c.mirrored for c in clips])}
        for i, c in enumerate(clips):
            for role, d in (("L", c.leader), ("F", c.follower)):
                if d is not None:
                    for k in _KEYS:
                        arrays[f"{role}{i}_{k}"] = getattr(d, k)
        tmp = path + ".tmp.npz"
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    return clips


def swap_roles(clips):
    """The duet clips with the dancers exchanged (role reversal: the follower
    in the leader's place, the tracked dancer, and the leader synthesised);
    clips without a follower are dropped."""
    return [Clip(c.name, c.follower, c.leader, c.mirrored) for c in clips if c.follower is not None]
