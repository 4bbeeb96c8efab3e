"""The training skeleton (SPEC §2), generic forward kinematics and motion clips.

Every skeleton here is a tree of *joints*. A joint has an ``offset``: where it
starts relative to its parent's start, in the parent's rest frame (motion
space, metres). Forward kinematics composes local rotations down the tree;
positions are the joint starts. For ASF skeletons each ASF bone is a joint and
its children start at its end, so the SPEC §2 joint position of bone ``n`` (the
bone's *end*) is ``start + R · rest bone vector``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# SPEC §2: the 31 CMU bones, in this order.
JOINT_NAMES = (
    "root", "lhipjoint", "lfemur", "ltibia", "lfoot", "ltoes",
    "rhipjoint", "rfemur", "rtibia", "rfoot", "rtoes",
    "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head",
    "lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb",
    "rclavicle", "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rthumb",
)
JOINT_INDEX = {n: i for i, n in enumerate(JOINT_NAMES)}
PARENT_NAMES = {
    "lhipjoint": "root", "lfemur": "lhipjoint", "ltibia": "lfemur", "lfoot": "ltibia",
    "ltoes": "lfoot", "rhipjoint": "root", "rfemur": "rhipjoint", "rtibia": "rfemur",
    "rfoot": "rtibia", "rtoes": "rfoot", "lowerback": "root", "upperback": "lowerback",
    "thorax": "upperback", "lowerneck": "thorax", "upperneck": "lowerneck",
    "head": "upperneck", "lclavicle": "thorax", "lhumerus": "lclavicle",
    "lradius": "lhumerus", "lwrist": "lradius", "lhand": "lwrist", "lfingers": "lhand",
    "lthumb": "lwrist", "rclavicle": "thorax", "rhumerus": "rclavicle",
    "rradius": "rhumerus", "rwrist": "rradius", "rhand": "rwrist", "rfingers": "rhand",
    "rthumb": "rwrist",
}
PARENTS = np.array([-1] + [JOINT_INDEX[PARENT_NAMES[n]] for n in JOINT_NAMES[1:]], dtype=np.int64)

# Tracked points (head, left hand, right hand) and foot contact points (SPEC §2).
TRACKED_NAMES = ("upperneck", "lwrist", "rwrist")
TRACKED = np.array([JOINT_INDEX[n] for n in TRACKED_NAMES])
HEAD_BONE = JOINT_INDEX["head"]  # the skull: the head device is rigid on it
FOOT_NAMES = ("ltibia", "lfoot", "rtibia", "rfoot")
FEET = np.array([JOINT_INDEX[n] for n in FOOT_NAMES])
HIPS = (JOINT_INDEX["lhipjoint"], JOINT_INDEX["rhipjoint"])
WRISTS = (JOINT_INDEX["lwrist"], JOINT_INDEX["rwrist"])
# The lower body: hip joints, thighs, shins, feet, toes (the follower's pose anchor).
LOWER_BODY = np.arange(JOINT_INDEX["lhipjoint"], JOINT_INDEX["rtoes"] + 1)


def joint_rows(indices):
    """Joint indices as an index into an array's joint axis: a slice (a view,
    cheaper per frame than an index list) where they are evenly spaced and
    ascending, else the list."""
    idx = [int(i) for i in indices]
    step = idx[1] - idx[0] if len(idx) > 1 else 1
    if step > 0 and idx == list(range(idx[0], idx[-1] + 1, step)):
        return slice(idx[0], idx[-1] + 1, step)
    return idx


def joint_block(indices) -> slice:
    """Joints consecutive in the SPEC order, in that order, as a slice of an
    array's joint axis (code that reads and writes them as one block); a
    ValueError naming them otherwise."""
    idx = [int(i) for i in indices]
    if idx != list(range(idx[0], idx[0] + len(idx))):
        raise ValueError("joints " + ", ".join(JOINT_NAMES[i] for i in idx) + " are not consecutive")
    return slice(idx[0], idx[0] + len(idx))


# Left/right mirror: index permutation of the 31 joints.
_UNSIDED = ("root", "lowerback", "lowerneck")
MIRROR = np.array([
    JOINT_INDEX[n if n in _UNSIDED or n[0] not in "lr" else {"l": "r", "r": "l"}[n[0]] + n[1:]]
    for n in JOINT_NAMES
])

# CMU-converted BVH naming (the widely used conversion of the CMU database).
CMU_BVH_NAMES = {
    "root": "Hips", "lhipjoint": "LHipJoint", "lfemur": "LeftUpLeg", "ltibia": "LeftLeg",
    "lfoot": "LeftFoot", "ltoes": "LeftToeBase", "rhipjoint": "RHipJoint",
    "rfemur": "RightUpLeg", "rtibia": "RightLeg", "rfoot": "RightFoot",
    "rtoes": "RightToeBase", "lowerback": "LowerBack", "upperback": "Spine",
    "thorax": "Spine1", "lowerneck": "Neck", "upperneck": "Neck1", "head": "Head",
    "lclavicle": "LeftShoulder", "lhumerus": "LeftArm", "lradius": "LeftForeArm",
    "lwrist": "LeftHand", "lhand": "LeftFingerBase", "lfingers": "LeftHandIndex1",
    "lthumb": "LThumb", "rclavicle": "RightShoulder", "rhumerus": "RightArm",
    "rradius": "RightForeArm", "rwrist": "RightHand", "rhand": "RightFingerBase",
    "rfingers": "RightHandIndex1", "rthumb": "RThumb",
}


def forward_kinematics(parents: np.ndarray, offsets: np.ndarray, root_position: np.ndarray,
                       local_rotations: np.ndarray):
    """Global rotations ``(T, J, 3, 3)`` and joint starts ``(T, J, 3)``.

    ``parents[j] < j`` for every non-root joint (topological order).
    ``offsets (J, 3)`` place a joint in its parent's frame; the root's offset is
    added to ``root_position (T, 3)``.
    """
    local_rotations = np.asarray(local_rotations, dtype=np.float64)
    T, J = local_rotations.shape[:2]
    glob = np.empty_like(local_rotations)
    pos = np.empty((T, J, 3))
    for j in range(J):
        p = parents[j]
        if p < 0:
            glob[:, j] = local_rotations[:, j]
            pos[:, j] = root_position + offsets[j]
        else:
            glob[:, j] = glob[:, p] @ local_rotations[:, j]
            pos[:, j] = pos[:, p] + glob[:, p] @ offsets[j]
    return glob, pos


def rest_joints(bone_vectors: np.ndarray, parents: np.ndarray | None = None) -> np.ndarray:
    """Rest-pose forward kinematics: joint positions ``(J, 3)`` (SPEC §2: the ends
    of the bones) with the root at the origin; ``parents[j] < j``."""
    parents = PARENTS if parents is None else parents
    bv = np.asarray(bone_vectors, dtype=np.float64)
    ends = np.zeros((len(parents), 3))
    for n in range(1, len(parents)):
        ends[n] = ends[parents[n]] + bv[n]
    return ends


def rest_starts(bone_vectors: np.ndarray, parents: np.ndarray | None = None) -> np.ndarray:
    """Rest-pose start of every bone ``(J, 3)``: the root at the origin, a child
    at its parent's end."""
    parents = PARENTS if parents is None else parents
    return rest_joints(bone_vectors, parents)[np.maximum(parents, 0)]


@dataclass
class Motion:
    """A full-body clip on the SPEC §2 skeleton (31 bones).

    ``positions[t, n]`` is the end of bone ``n`` (the root translation for
    ``root``), ``rotations[t, n]`` its global rotation; motion space, metres.
    ``bone_vectors`` are the rest bone vectors (31, 3).
    """

    positions: np.ndarray
    rotations: np.ndarray
    fps: float
    bone_vectors: np.ndarray
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / float(self.fps)

    def subsample(self, step: int) -> "Motion":
        return Motion(self.positions[::step], self.rotations[::step], self.fps / step,
                      self.bone_vectors, self.source, dict(self.meta))

    def bone_lengths(self) -> np.ndarray:
        return np.linalg.norm(self.bone_vectors, axis=-1)


def bone_lengths_from_positions(positions: np.ndarray) -> np.ndarray:
    """Per-frame bone lengths ``(T, 31)`` from SPEC joint positions (root: 0)."""
    starts = positions[:, np.maximum(PARENTS, 0)]
    starts[:, 0] = positions[:, 0]
    return np.linalg.norm(positions - starts, axis=-1)
