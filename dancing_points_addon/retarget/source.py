"""The source dancer: a Dancing Points armature's SPEC pose from its keyed pose
channels, in Blender world space, its landmarks and the duet's centre."""
from __future__ import annotations

import numpy as np

from ..blender_math import C  # motion space (Y up) -> Blender (Z up)
from ..rotations import quat_to_matrix
from ..skeleton import HIPS, JOINT_INDEX, JOINT_NAMES, PARENTS, WRISTS, forward_kinematics

# Source rest body frame in the source armature (Blender axes): left +X, up +Z, forward -Y.
SRC_LEFT = np.array([1.0, 0.0, 0.0])
UP = np.array([0.0, 0.0, 1.0])
SRC_FWD = np.array([0.0, -1.0, 0.0])
# Landmarks compared between source and target (name: source SPEC joint whose end it is).
LANDMARKS = {
    "hips": None,  # midpoint of the hip joints (ends of lhipjoint, rhipjoint)
    "head": "upperneck", "lwrist": "lwrist", "rwrist": "rwrist",
    "lankle": "ltibia", "rankle": "rtibia", "lball": "lfoot", "rball": "rfoot",
}
FOOT_POINTS = ("lankle", "lball", "rankle", "rball")


def spec_pose_from_channels(quats, root_location, rest_rot, rest_heads, bone_vectors):
    """Inverse of ``blender_math.pose_channels``: SPEC ``positions (T, 31, 3)`` and
    global ``rotations (T, 31, 3, 3)`` (motion space) of a Dancing Points armature
    from its keyed pose channels ``quats (T, 31, 4)`` (``matrix_basis``) and the
    root bone's ``location (T, 3)``; ``rest_rot``/``rest_heads`` are the bones'
    ``matrix_local`` rotations and heads (Blender space)."""
    q = np.asarray(quats, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    basis = quat_to_matrix(q)
    B = np.asarray(rest_rot, dtype=np.float64)
    rel = B[None] @ basis @ np.swapaxes(B, -1, -2)[None]
    T = q.shape[0]
    # global rotations (Blender axes) from the local ones; the joint offsets play no part
    rb, _ = forward_kinematics(PARENTS, np.zeros((len(JOINT_NAMES), 3)), np.zeros(3), rel)
    R = C.T[None, None] @ rb @ C[None, None]
    root_b = np.asarray(rest_heads, dtype=np.float64)[0] + np.asarray(root_location, dtype=np.float64) @ B[0].T
    pos = np.empty((T, len(JOINT_NAMES), 3))
    pos[:, 0] = root_b @ C
    bv = np.asarray(bone_vectors, dtype=np.float64)
    for n in range(1, len(JOINT_NAMES)):
        pos[:, n] = pos[:, PARENTS[n]] + np.einsum("tab,b->ta", R[:, n], bv[n])
    return pos, R


def source_frame(source_matrix=None):
    """``(M (4, 4), Rw (3, 3))``: the source armature object's world matrix
    (identity when None) and its rotation, the uniform scale removed."""
    M = np.eye(4) if source_matrix is None else np.asarray(source_matrix, dtype=np.float64)
    S = M[:3, :3]
    return M, S / (np.cbrt(abs(np.linalg.det(S))) or 1.0)


def source_world(positions, rotations, source_matrix=None):
    """SPEC positions / global rotations (motion space) in Blender world space:
    ``(points (T, 31, 3), rotations (T, 31, 3, 3))`` — the rotations are the
    world rotations *relative to the rest pose* (``source_matrix``: the source
    armature object's world matrix)."""
    M, Rw = source_frame(source_matrix)
    pts = np.asarray(positions, dtype=np.float64) @ C.T @ M[:3, :3].T + M[:3, 3]
    rot = Rw @ C @ np.asarray(rotations, dtype=np.float64) @ C.T @ Rw.T
    return pts, rot


def hip_midpoint(points):
    """Midpoint ``(…, d)`` of the hip joints (ends of lhipjoint, rhipjoint) of
    SPEC joint positions ``(…, 31, d)``: the pelvis point."""
    return 0.5 * (points[..., HIPS[0], :] + points[..., HIPS[1], :])


def duet_origin(*points):
    """Horizontal centre ``(2,)`` of dancers given as SPEC world points ``(T, 31, 3)``:
    the mean over frames and dancers of their hip joints' midpoint."""
    c = [hip_midpoint(p[..., :2]).mean(0) for p in points]
    return np.mean(c, axis=0)


def source_landmarks(points):
    """``{landmark: (T, 3)}`` of SPEC joint positions (any space)."""
    out = {}
    for name, bone in LANDMARKS.items():
        if bone is None:
            out[name] = hip_midpoint(points)
        else:
            out[name] = points[:, JOINT_INDEX[bone]]
    return out


def source_wrists(points):
    """Wrist positions ``(T, 2, 3)`` (left, right) of SPEC joint positions ``(T, 31, 3)``."""
    return points[:, list(WRISTS)]
