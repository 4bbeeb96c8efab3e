"""Numpy maths behind the Blender add-on's operators (no ``bpy`` here).

The operators in ``operators/`` only move arrays between Blender and these
functions; everything that can be computed without Blender is computed here, so
it can be tested without it.

Conventions
-----------
- Motion space (SPEC §1) is Y up; Blender is Z up. ``C`` maps motion space to
  Blender: ``(x, y, z) -> (x, -z, y)``; rotations map as ``C · R · Cᵀ``.
- Armatures are built at the origin in the SPEC rest pose (the ASF rest pose,
  facing +Z in motion space = -Y in Blender). Bone ``n`` runs from the joint
  position of its parent to its own joint position (SPEC §2), so its *tail* is
  the SPEC joint position; the root bone is a short bone from the root joint
  straight up (+Z in Blender).
- A Blender bone's rest matrix (``Bone.matrix_local``, 3×3 part ``B``) has its
  Y axis along the bone. A pose with global rotation ``R`` (motion space,
  ``posed bone vector = R · rest bone vector``) gives the bone the armature-space
  orientation ``C R Cᵀ · B``; the pose channel (``matrix_basis``) of a bone with
  parent ``p`` is ``Bₙᵀ · (Rbₚᵀ Rbₙ) · Bₙ`` and only the root has a location.
"""
from __future__ import annotations


import numpy as np

from .rotations import matrix_to_quat, quat_to_matrix
from .skeleton import JOINT_NAMES, PARENTS, rest_joints, rest_starts

# Motion space (Y up) -> Blender (Z up): (x, y, z) -> (x, -z, y).
C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
N_BONES = len(JOINT_NAMES)
_PAR = np.maximum(PARENTS, 0)
ROOT_BONE_LENGTH = 0.1  # m: the root bone points straight up from the root joint


# --------------------------------------------------------------------------- axes

def to_blender(points: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    """Motion-space points ``(…, 3)`` in Blender (``conv`` = file -> Blender, default ``C``)."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(conv).T


def to_motion(points: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    """Blender points ``(…, 3)`` in motion space (inverse of :func:`to_blender`)."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(conv)


def rot_to_blender(rot: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    conv = np.asarray(conv)
    return conv @ np.asarray(rot, dtype=np.float64) @ conv.T


def rot_to_motion(rot: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    conv = np.asarray(conv)
    return conv.T @ np.asarray(rot, dtype=np.float64) @ conv


def _convert_quats(q: np.ndarray, convert, conv: np.ndarray) -> np.ndarray:
    """Quaternions ``(…, 4)`` through a rotation-matrix change of basis; NaN
    quaternions (lost tracking) stay NaN."""
    q = np.asarray(q, dtype=np.float64)
    ok = np.isfinite(q).all(-1)
    out = np.full(q.shape, np.nan)
    if ok.any():
        out[ok] = matrix_to_quat(convert(quat_to_matrix(q[ok]), conv))
    return out


def quat_to_blender(q: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    """Quaternions (w, x, y, z) of motion-space rotations as Blender rotations."""
    return _convert_quats(q, rot_to_blender, conv)


def quat_to_motion(q: np.ndarray, conv: np.ndarray = C) -> np.ndarray:
    """Quaternions (w, x, y, z) of Blender rotations as motion-space rotations."""
    return _convert_quats(q, rot_to_motion, conv)


def continuous_quats(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip quaternion signs along ``axis`` (time) so consecutive ones have a
    non-negative dot product (no interpolation through the long way round)."""
    q = np.moveaxis(np.array(q, dtype=np.float64), axis, 0)
    if q.shape[0] > 1:
        dots = np.sum(q[1:] * q[:-1], axis=-1)
        flips = np.cumsum(dots < 0, axis=0) % 2
        q[1:] *= np.where(flips[..., None] == 1, -1.0, 1.0)
    return np.moveaxis(q, 0, axis)


def fill_gaps(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid rows of ``values (T, …)`` by the last valid row (the first
    valid row before it); all-invalid stays as given with NaN replaced by 0."""
    values = np.array(values, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if valid.all():
        return values
    if not valid.any():
        return np.nan_to_num(values)
    idx = np.where(valid, np.arange(len(valid)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.flatnonzero(valid)[0])
    return values[idx]


# --------------------------------------------------------------------------- skeleton

def armature_rest(bone_vectors: np.ndarray, root_length: float = ROOT_BONE_LENGTH):
    """Edit-bone heads and tails ``(31, 3)`` each, in Blender space, of the rest pose."""
    ends = to_blender(rest_joints(bone_vectors))
    heads = to_blender(rest_starts(bone_vectors))
    tails = ends.copy()
    tails[0] = ends[0] + np.array([0.0, 0.0, root_length])
    return heads, tails


def estimate_bone_vectors(positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Rest bone vectors ``(31, 3)`` of a posed sequence ``(T, 31, 3)``,
    ``(T, 31, 3, 3)``: the per-component median over frames of ``Rᵀ (p − p_parent)``
    (exact for a consistent pose with constant bone lengths)."""
    positions = np.asarray(positions, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    vec = positions - positions[:, _PAR]
    local = np.einsum("tnba,tnb->tna", rotations, vec)
    bv = np.median(local, axis=0)
    bv[0] = 0.0
    return bv


def consistent_pose(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray | None = None):
    """``(bone_vectors, positions, rotations)``: a rigid skeleton (constant bone
    vectors, estimated when not given) and the pose made consistent with it
    (``pose.recover_pose``: every bone's end on ``R · rest vector``)."""
    from .pose import recover_pose

    if bone_vectors is None:
        bone_vectors = estimate_bone_vectors(positions, rotations)
    pos, rot = recover_pose(np.asarray(positions, dtype=np.float64),
                            np.asarray(rotations, dtype=np.float64), bone_vectors)
    return np.asarray(bone_vectors, dtype=np.float64), pos, rot


def pose_channels(positions: np.ndarray, rotations: np.ndarray, rest_rot: np.ndarray,
                  rest_heads: np.ndarray):
    """Blender pose channels of a consistent SPEC pose.

    ``positions (T, 31, 3)``, ``rotations (T, 31, 3, 3)``: motion space.
    ``rest_rot (31, 3, 3)``: the bones' rest orientation (``Bone.matrix_local``
    3×3); ``rest_heads (31, 3)``: rest heads, Blender space.
    Returns ``quats (T, 31, 4)`` (w, x, y, z; continuous in time) of
    ``matrix_basis`` and the root bone's ``location (T, 3)``.
    """
    rb = rot_to_blender(rotations)  # (T, 31, 3, 3)
    rel = rb.copy()
    rel[:, 1:] = np.swapaxes(rb[:, _PAR[1:]], -1, -2) @ rb[:, 1:]
    B = np.asarray(rest_rot, dtype=np.float64)
    basis = np.swapaxes(B, -1, -2)[None] @ rel @ B[None]
    quats = continuous_quats(matrix_to_quat(basis), axis=0)
    root_b = to_blender(positions[:, 0])
    loc = (root_b - rest_heads[0]) @ B[0]  # B0ᵀ · (p − head)
    return quats, loc


def skin_transforms(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray) -> np.ndarray:
    """Per-bone deformation matrices ``(T, 31, 4, 4)`` in Blender space taking the
    rest mesh to the posed one (what the Armature modifier applies)."""
    positions = np.asarray(positions, dtype=np.float64)
    T = positions.shape[0]
    rest_heads, _ = armature_rest(bone_vectors)
    rb = rot_to_blender(rotations)
    pb = to_blender(positions)
    heads = pb[:, _PAR].copy()
    heads[:, 0] = pb[:, 0]
    out = np.zeros((T, N_BONES, 4, 4))
    out[..., :3, :3] = rb
    out[..., :3, 3] = heads - np.einsum("tnab,nb->tna", rb, rest_heads)
    out[..., 3, 3] = 1.0
    return out


def body_arrays(body):
    """``(vertices (V, 3), faces (F, 3), indices (V, K), weights (V, K))`` of a
    :class:`~.skinning.Body`."""
    return (np.asarray(body.vertices, dtype=np.float64), np.asarray(body.faces),
            np.asarray(body.indices, dtype=np.int64), np.asarray(body.weights, dtype=np.float64))


# --------------------------------------------------------------------------- camera

def hip_forward(positions: np.ndarray) -> np.ndarray:
    """Horizontal facing ``(…, 3)`` (motion space) from the hip joints (SPEC §6)."""
    from .skeleton import HIPS

    lr = positions[..., HIPS[0], :] - positions[..., HIPS[1], :]
    f = np.cross(lr, np.array([0.0, 1.0, 0.0]))
    f[..., 1] = 0.0
    n = np.linalg.norm(f, axis=-1, keepdims=True)
    return np.where(n > 1e-9, f / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0]))


def frame_camera(points_b: np.ndarray, view_dir_b: np.ndarray, fov: float, aspect: float = 16 / 9,
                 margin: float = 1.15, elevation_deg: float = 12.0):
    """A camera looking at ``points_b (N, 3)`` (Blender space) from the side
    ``view_dir_b`` (horizontal, from the target towards the camera), so that the
    points' bounding sphere fills the field of view. Returns ``(location (3,),
    rotation (3, 3))``: camera-to-world, looking along its local −Z, +Y up."""
    pts = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(-1)]
    lo, hi = pts.min(0), pts.max(0)
    target = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.5)
    half = fov / 2 if aspect >= 1 else np.arctan(np.tan(fov / 2) * aspect)
    half_v = np.arctan(np.tan(fov / 2) / aspect) if aspect >= 1 else fov / 2
    dist = margin * radius / np.sin(min(half, half_v))
    v = np.asarray(view_dir_b, dtype=np.float64).copy()
    v[2] = 0.0
    v = v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-9 else np.array([0.0, -1.0, 0.0])
    el = np.deg2rad(elevation_deg)
    back = v * np.cos(el) + np.array([0.0, 0.0, np.sin(el)])
    loc = target + back * dist
    z = back  # camera looks along -Z, so +Z points from the target to the camera
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return loc, np.stack([x, y, z], axis=1)
