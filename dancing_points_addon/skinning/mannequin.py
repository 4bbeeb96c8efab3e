"""The default body of a skeleton: :func:`make_body` builds the
mannequin (field, surface, weights) once per skeleton and caches it.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..skeleton import JOINT_INDEX, JOINT_NAMES, rest_starts
from .mesher import relax_and_project, surface_nets, triangulate
from .proportions import N_BONES, check_bones, proportions, stature_scale
from .sdf import smin
from .weights import skin_weights

_J = JOINT_INDEX
_TAU = 0.02  # weight blend length (m, reference size)


@dataclass
class Body:
    """A skinned mesh in rest pose (motion space, metres).

    ``vertices (V, 3)``, ``faces (F, 3)`` (triangles, counter-clockwise seen
    from outside), ``indices (V, k)`` bone indices and ``weights (V, k)`` their
    weights (rows sum to 1), ``rest_start (31, 3)`` the rest start of every
    bone (for :func:`dancing_points_addon.ik.bone_transforms`), ``part (V,)``
    the index of the part each vertex belongs to, named in ``part_names`` (for
    the mannequin: its highest-weight bone, ``part_names`` = the bone names).
    ``envelope (31,)``: the largest distance of a vertex from the segment of
    its highest-weight bone, per bone (0 for bones that are no vertex's first).
    """

    vertices: np.ndarray
    faces: np.ndarray
    indices: np.ndarray
    weights: np.ndarray
    rest_start: np.ndarray
    part: np.ndarray
    part_names: tuple
    envelope: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    def dense_weights(self) -> np.ndarray:
        """Weights as a dense ``(V, 31)`` matrix."""
        W = np.zeros((len(self.vertices), N_BONES))
        np.add.at(W, (np.arange(len(W))[:, None], self.indices), self.weights)
        return W


def _build(bv):
    start = rest_starts(bv)
    end = start + bv
    s = stature_scale(start, end)
    prims, caps = proportions(start, end, s)
    h = 0.014 * s  # grid cell
    lo = np.min([p.lo for p in prims], axis=0)
    hi = np.max([p.hi for p in prims], axis=0)
    pad = 3 * h
    origin = lo - pad
    shape = np.ceil((hi + pad - origin) / h).astype(int) + 1
    axes = [origin[c] + h * np.arange(shape[c]) for c in range(3)]
    F = np.full(tuple(shape), 1.0)
    kmax = max(p.blend for p in prims)
    for p in prims:
        m = kmax + 3 * h
        i0 = np.maximum(np.floor((p.lo - m - origin) / h).astype(int), 0)
        i1 = np.minimum(np.ceil((p.hi + m - origin) / h).astype(int) + 1, shape)
        X, Y, Z = np.meshgrid(axes[0][i0[0]:i1[0]], axes[1][i0[1]:i1[1]], axes[2][i0[2]:i1[2]], indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
        sub = F[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
        F[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]] = smin(sub.ravel(), p.sdf(pts), p.blend).reshape(sub.shape)
    V, Q = surface_nets(F, origin, h)
    faces = triangulate(V, Q)
    V = relax_and_project(prims, V, faces, h, margin=kmax + 3 * h)
    names = [n for n in JOINT_NAMES if n in caps]
    bones = np.array([_J[n] for n in names])
    ca = np.array([caps[n][0] for n in names])
    cb = np.array([caps[n][1] for n in names])
    idx, w = skin_weights(V, bones, ca, cb, np.array([caps[n][2] for n in names]),
                           np.array([caps[n][3] for n in names]), tau=_TAU * s)
    top = idx[:, 0]
    d = end[top] - start[top]
    t = np.clip(np.einsum("ij,ij->i", V - start[top], d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
    seg = np.linalg.norm(V - start[top] - t[:, None] * d, axis=1)
    envelope = np.zeros(N_BONES)
    np.maximum.at(envelope, top, seg)
    return V, faces.astype(np.int64), idx, w, start, top.astype(np.int64), envelope


@lru_cache(maxsize=8)
def _cached(key):
    bv = np.frombuffer(key, dtype=np.float64).reshape(N_BONES, 3)
    out = _build(bv)
    for x in out:
        x.setflags(write=False)
    return out


def make_body(bone_vectors: np.ndarray) -> Body:
    """The default body of a skeleton: a smooth mannequin around the rest pose
    of ``bone_vectors (31, 3)`` (motion space, metres), skinned to its bones.

    Sized by the skeleton's height (ankle to head); about 11,500 vertices and
    23,000 triangles (the count does not depend on the size: a skeleton ``k``
    times the size gets the same mesh ``k`` times the size). A closed,
    outward-facing, 2-manifold mesh of genus 0. Raises
    :class:`BodyError` for bone vectors it cannot build on. Deterministic;
    cached per skeleton (each call returns fresh arrays).
    """
    bv = check_bones(bone_vectors)
    V, F, idx, w, start, part, env = _cached(np.ascontiguousarray(bv).tobytes())
    return Body(V.copy(), F.copy(), idx.copy(), w.copy(), start.copy(), part.copy(), tuple(JOINT_NAMES),
                env.copy())
