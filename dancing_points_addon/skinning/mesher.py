"""Polygonisation of the body's field (step 2 of the package): naive surface nets on a
grid, made manifold (:func:`surface_nets`), quads split along their shorter
diagonal (:func:`triangulate`), and the vertices relaxed and projected back onto
the implicit surface (:func:`relax_and_project`).
"""
from __future__ import annotations

import numpy as np

from .sdf import field


def _corner_offsets():
    return np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def _simple_configs():
    """``ok (256,)``: cell corner sign patterns (bit c = corner c inside) whose
    surface is one disc: no face with a checkerboard pattern, and the inside and
    the outside corners each connected along the cube's edges."""
    off = _corner_offsets()
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(off[a] - off[b]).sum() == 1]
    faces = []
    for ax in range(3):
        for v in (0, 1):
            cs = [c for c in range(8) if off[c][ax] == v]
            faces.append(cs)  # 4 corners; diagonals differ in both other bits
    ok = np.zeros(256, dtype=bool)
    for cfg in range(256):
        ins = [(cfg >> c) & 1 for c in range(8)]
        good = True
        for cs in faces:
            vals = [ins[c] for c in cs]
            # corners cs in bit order: the pairs (0, 3) and (1, 2) are diagonals
            if vals[0] == vals[3] and vals[1] == vals[2] and vals[0] != vals[1]:
                good = False
        for want in (0, 1):
            nodes = [c for c in range(8) if ins[c] == want]
            if not nodes:
                continue
            seen = {nodes[0]}
            stack = [nodes[0]]
            while stack:
                x = stack.pop()
                for a, b in edges:
                    for u, w in ((a, b), (b, a)):
                        if u == x and ins[w] == want and w not in seen:
                            seen.add(w)
                            stack.append(w)
            if len(seen) != len(nodes):
                good = False
        ok[cfg] = good
    return ok


_SIMPLE = _simple_configs()
_CORNERS = _corner_offsets()


def _cell_configs(inside):
    nx, ny, nz = inside.shape
    cfg = np.zeros((nx - 1, ny - 1, nz - 1), dtype=np.int32)
    for c, (dx, dy, dz) in enumerate(_CORNERS):
        cfg |= inside[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz].astype(np.int32) << c
    return cfg


def _make_simple(F, max_iter=64):
    """Resolve cells whose corner signs would make the surface non-manifold by
    moving their inside corner nearest the surface just outside (monotone: it ends)."""
    F = F.copy()
    tiny = 1e-9
    for _ in range(max_iter):
        inside = F < 0
        bad = np.argwhere(~_SIMPLE[_cell_configs(inside)])
        if not len(bad):
            return F
        corners = bad[:, None, :] + _CORNERS[None]  # (n, 8, 3)
        vals = F[corners[..., 0], corners[..., 1], corners[..., 2]]
        vals = np.where(vals < 0, -vals, np.inf)
        pick = np.argmin(vals, axis=1)
        c = corners[np.arange(len(bad)), pick]
        F[c[:, 0], c[:, 1], c[:, 2]] = tiny
    raise RuntimeError("the body's surface could not be made manifold")


def surface_nets(F, origin, h):
    """Naive surface nets of the zero level set of grid values ``F`` (negative
    inside; corner ``(i, j, k)`` at ``origin + h · (i, j, k)``): ``(vertices (V, 3),
    quads (Q, 4))``, counter-clockwise seen from outside."""
    F = np.where(F == 0.0, 1e-12, F)
    F = _make_simple(F)
    nx, ny, nz = F.shape
    inside = F < 0
    if inside[[0, -1]].any() or inside[:, [0, -1]].any() or inside[:, :, [0, -1]].any():
        raise RuntimeError("the body's grid does not enclose it")
    cy, cz = ny - 1, nz - 1

    def cell(i, j, k):
        return (i * cy + j) * cz + k

    n_cells = (nx - 1) * cy * cz
    acc = np.zeros((n_cells, 3))
    cnt = np.zeros(n_cells)
    quads = []
    for ax in range(3):
        sl0 = [slice(None)] * 3
        sl1 = [slice(None)] * 3
        sl0[ax] = slice(0, -1)
        sl1[ax] = slice(1, None)
        s0, s1 = inside[tuple(sl0)], inside[tuple(sl1)]
        idx = np.argwhere(s0 != s1)  # (m, 3): the edge's lower corner
        if not len(idx):
            continue
        lo = idx.copy()
        hi = idx.copy()
        hi[:, ax] += 1
        f0 = F[lo[:, 0], lo[:, 1], lo[:, 2]]
        f1 = F[hi[:, 0], hi[:, 1], hi[:, 2]]
        t = f0 / (f0 - f1)
        p = origin + h * (lo + t[:, None] * (hi - lo))
        # the four cells around the edge, in counter-clockwise order seen from +axis
        u, v = (ax + 1) % 3, (ax + 2) % 3
        ring = []
        for du, dv in ((1, 1), (0, 1), (0, 0), (1, 0)):
            c = idx.copy()
            c[:, u] -= du
            c[:, v] -= dv
            ring.append(cell(c[:, 0], c[:, 1], c[:, 2]))
        ring = np.stack(ring, axis=1)
        cells = ring.ravel()
        for c in range(3):
            acc[:, c] += np.bincount(cells, weights=np.repeat(p[:, c], 4), minlength=n_cells)
        cnt += np.bincount(cells, minlength=n_cells)
        # inside at the lower end: the surface faces +axis; else reverse
        flip = ~inside[lo[:, 0], lo[:, 1], lo[:, 2]]
        ring[flip] = ring[flip][:, ::-1]
        quads.append(ring)
    quads = np.concatenate(quads)
    used = np.nonzero(cnt)[0]
    vid = np.full(n_cells, -1, dtype=np.int64)
    vid[used] = np.arange(len(used))
    V = acc[used] / cnt[used, None]
    Q = vid[quads]
    return V, Q


def triangulate(V, Q):
    """Split quads along their shorter diagonal."""
    d02 = np.linalg.norm(V[Q[:, 0]] - V[Q[:, 2]], axis=1)
    d13 = np.linalg.norm(V[Q[:, 1]] - V[Q[:, 3]], axis=1)
    a = d02 <= d13
    t1 = np.where(a[:, None], Q[:, [0, 1, 2]], Q[:, [0, 1, 3]])
    t2 = np.where(a[:, None], Q[:, [0, 2, 3]], Q[:, [1, 2, 3]])
    return np.concatenate([t1, t2])


def _neighbours(n, faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    key = np.unique(np.concatenate([e[:, 0] * n + e[:, 1], e[:, 1] * n + e[:, 0]]))
    a, b = key // n, key % n
    return a, b, np.bincount(a, minlength=n).astype(np.float64)


def relax_and_project(prims, V, faces, h, margin, iterations=4):
    """Umbrella smoothing (tangential relaxation) alternating with Newton steps
    onto the implicit surface."""
    a, b, deg = _neighbours(len(V), faces)
    eps = 0.25 * h
    n = len(V)
    offsets = np.concatenate([np.zeros((1, 3)), np.eye(3) * eps, -np.eye(3) * eps])
    for it in range(iterations):
        mean = np.stack([np.bincount(a, weights=V[b, c], minlength=n) for c in range(3)], 1) / deg[:, None]
        V = V + 0.5 * (mean - V)
        for _ in range(2 if it == iterations - 1 else 1):
            vals = field(prims, (V[None] + offsets[:, None]).reshape(-1, 3), margin).reshape(7, n)
            f = vals[0]
            g = ((vals[1:4] - vals[4:7]) / (2 * eps)).T
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 1e-6)
            step = (f / g2)[:, None] * g
            ln = np.linalg.norm(step, axis=1, keepdims=True)
            V = V - step * np.minimum(1.0, h / np.maximum(ln, 1e-12))  # at most a cell per step
    return V
