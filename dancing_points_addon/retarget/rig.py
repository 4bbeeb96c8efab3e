"""The target rig as arrays: :class:`TargetRig` (bones, hierarchy, rest and
reference pose), Blender's ``matrix_basis`` <-> armature-space pose
(:func:`pose_from_basis`, :func:`basis_from_pose`) and the keyable channels of
a ``matrix_basis`` (:func:`channels`)."""
from __future__ import annotations

import numpy as np

from .. import blender_math as bm
from ..rotations import matrix_to_euler, matrix_to_quat, rotation_angle
from .mapping import RetargetError


def _depths(parents):
    d = np.zeros(len(parents), dtype=np.int64)
    for i in topological_order(parents):
        if parents[i] >= 0:
            d[i] = d[parents[i]] + 1
    return d


def topological_order(parents):
    """Bone indices with every parent before its children."""
    parents = [int(p) for p in parents]
    children = [[] for _ in parents]
    roots = []
    for i, p in enumerate(parents):
        (children[p] if p >= 0 else roots).append(i)
    out, stack = [], list(reversed(roots))
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(reversed(children[i]))
    if len(out) != len(parents):
        raise RetargetError("the rig's bone hierarchy has a cycle")
    return out


class TargetRig:
    """A target armature as arrays.

    ``names``, ``parents`` (index, -1 for roots), ``rest (B, 4, 4)``
    (``Bone.matrix_local``), ``lengths (B,)``, ``ref_basis (B, 4, 4)`` (the
    reference pose as ``matrix_basis``; default identity: the rest pose),
    ``matrix_world (4, 4)`` (the armature object's).
    """

    def __init__(self, names, parents, rest, lengths=None, ref_basis=None, matrix_world=None):
        self.names = list(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.parents = np.asarray(parents, dtype=np.int64)
        self.rest = np.asarray(rest, dtype=np.float64)
        B = len(self.names)
        self.lengths = np.ones(B) if lengths is None else np.asarray(lengths, dtype=np.float64)
        self.ref_basis = np.broadcast_to(np.eye(4), (B, 4, 4)).copy() if ref_basis is None \
            else np.asarray(ref_basis, dtype=np.float64)
        self.matrix_world = np.eye(4) if matrix_world is None else np.asarray(matrix_world, dtype=np.float64)
        self.order = topological_order(self.parents)
        self.depth = _depths(self.parents)
        self.ref_pose = pose_from_basis(self.rest, self.parents, self.ref_basis[None], self.order)[0]
        self.ref_world = self.matrix_world[None] @ self.ref_pose  # (B, 4, 4)

    def heads(self):
        return self.ref_world[:, :3, 3]

    def tails(self):
        y = np.zeros((len(self.names), 4))
        y[:, 1] = self.lengths
        y[:, 3] = 1.0
        return np.einsum("bij,bj->bi", self.ref_world, y)[:, :3]

    def ground(self) -> float:
        """World height of the rig's floor: the armature object's origin."""
        return float(self.matrix_world[2, 3])


def pose_from_basis(rest, parents, basis, order=None):
    """Armature-space pose matrices ``(T, B, 4, 4)`` from ``matrix_basis (T, B, 4, 4)``
    (Blender: ``pose = pose_parent · rest_parent⁻¹ · rest · basis``)."""
    rest = np.asarray(rest, dtype=np.float64)
    basis = np.asarray(basis, dtype=np.float64)
    order = topological_order(parents) if order is None else order
    out = np.empty(basis.shape)
    inv_rest = np.linalg.inv(rest)
    for b in order:
        p = parents[b]
        if p < 0:
            out[:, b] = rest[b] @ basis[:, b]
        else:
            out[:, b] = out[:, p] @ (inv_rest[p] @ rest[b]) @ basis[:, b]
    return out


def basis_from_pose(rest, parents, pose):
    """Inverse of :func:`pose_from_basis`."""
    rest = np.asarray(rest, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    inv_rest = np.linalg.inv(rest)
    inv_pose = np.linalg.inv(pose)
    out = np.empty(pose.shape)
    for b in range(pose.shape[1]):
        p = parents[b]
        if p < 0:
            out[:, b] = inv_rest[b] @ pose[:, b]
        else:
            out[:, b] = (inv_rest[b] @ rest[p]) @ inv_pose[:, p] @ pose[:, b]
    return out


def channels(basis, rotation_modes=None):
    """``(location (T, B, 3), rotation (T, B, 4) quaternions or Euler angles in
    the first 3, scale (T, B, 3))`` of ``matrix_basis (T, B, 4, 4)``.
    ``rotation_modes``: per bone 'QUATERNION' (default) or an Euler order."""
    basis = np.asarray(basis, dtype=np.float64)
    lin = basis[..., :3, :3]
    scale = np.linalg.norm(lin, axis=-2)
    rot = lin / np.where(scale > 1e-12, scale, 1.0)[..., None, :]
    rot = _nearest_rotation(rot)
    q = bm.continuous_quats(matrix_to_quat(rot))
    out_rot = q.copy()
    if rotation_modes is not None:
        for b, mode in enumerate(rotation_modes):
            if mode in ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"):
                e = np.unwrap(matrix_to_euler(rot[:, b], mode), axis=0)  # angles in the order's axis order
                for i, axis in enumerate(mode):  # Blender stores (x, y, z) whatever the order
                    out_rot[:, b, "XYZ".index(axis)] = e[:, i]
                out_rot[:, b, 3] = 0.0
    return basis[..., :3, 3].copy(), out_rot, scale


def _nearest_rotation(m):
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= d[..., None]
    return u @ vt


def rotation_steps_deg(W):
    """Frame-to-frame rotation angle (degrees) ``(T-1, B)`` of world matrices ``(T, B, 4, 4)``."""
    lin = np.asarray(W, dtype=np.float64)[..., :3, :3]
    lin = lin / np.linalg.norm(lin, axis=-2, keepdims=True)
    rel = np.swapaxes(lin[:-1], -1, -2) @ lin[1:]
    return np.degrees(rotation_angle(rel))
