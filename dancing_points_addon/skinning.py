"""A smooth procedural mannequin and linear blend skinning, in numpy.

:func:`make_body` builds a default body — a smooth, proportioned mannequin —
around the rest pose of the SPEC §2 skeleton (the ASF T-pose in motion space,
root at the origin, facing +Z, left = +X, Y up):

1. *Shape*: an implicit surface, the signed distance field of round cones
   (limbs, neck, shoulders, thumbs; flattened ones for the mitten hands and
   the feet) and ellipsoids (pelvis, belly, chest, head) placed on the bones
   and sized from the skeleton's height (``_proportions``). Parts of one limb meet in a hard union
   (the round cones share their sphere at the joint: no seam, no bulge);
   different parts meet in a polynomial smooth union (no crease).
2. *Surface*: the field is sampled on a grid of 1.4 cm cells (for the
   reference skeleton, CMU subject 60; scaled with the skeleton, so every
   body has the same mesh, only sized) and polygonised by naive surface nets
   (one vertex per cell the surface crosses, one quad per grid edge it
   crosses, split along its shorter diagonal), after cells whose corners would
   make the surface non-manifold are resolved. Vertices are then relaxed
   (umbrella smoothing) and projected back onto the implicit surface (Newton
   steps): one closed, consistently outward-facing, 2-manifold genus-0 triangle
   mesh of about 11,500 vertices and 23,000 triangles.
3. *Weights*: every skinned bone has a "weight capsule", a round cone along
   its segment with the body's radius there; a vertex's weight for bone ``b``
   is a soft-min of the capsules' signed distances,
   ``exp(-(d_b - min_b d_b) / tau)``, kept for the 4 largest (minus the 5th,
   so weights stay continuous where the ranking changes), normalised and
   rounded to multiples of 1/1024 (rows still sum to exactly 1). Joints
   blend over a few centimetres; the skull is nearly rigid on ``head``. The
   hip joint and finger tip bones carry no weight (the pelvis moves with
   ``root``, the finger tips with ``hand``), nor does the thumb (the mitten's
   thumb moves with the palm, ``wrist``).

Deterministic; about 0.5 s per body on one core (cached per skeleton).

:func:`lbs` poses it with the per-bone rigid transforms of
:func:`dancing_points_addon.ik.bone_transforms`.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .errors import UserError
from .skeleton import rest_starts
from .skeleton import JOINT_INDEX, JOINT_NAMES

__all__ = ["Body", "make_body", "lbs", "lbs_frame", "bone_segment_distances", "BodyError",
           "weight_capsules"]

_J = JOINT_INDEX
N_BONES = len(JOINT_NAMES)
K_INFLUENCES = 4
WEIGHT_QUANTUM = 1.0 / 1024  # weights are multiples of this (few distinct values: fast vertex groups)
# The reference skeleton (CMU subject 60): ankle-to-head-bone-end height in rest pose, metres.
_REF_EXTENT = 1.51
_TAU = 0.02  # weight blend length (m, reference size)


class BodyError(UserError, ValueError):
    """Bone vectors a body cannot be built on (wrong shape, not finite, a limb of length 0)."""


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


# ---------------------------------------------------------------------------
# signed distance primitives (vectorised over points (N, 3))


def _sd_round_cone(p, a, b, r1, r2):
    """Exact signed distance to the round cone ``a (r1) → b (r2)`` (two spheres
    and the cone tangent to both)."""
    ba = b - a
    l2 = float(ba @ ba)
    rr = r1 - r2
    a2 = l2 - rr * rr
    il2 = 1.0 / l2
    pa = p - a
    y = pa @ ba
    z = y - l2
    x = pa * l2 - y[:, None] * ba
    x2 = np.einsum("ij,ij->i", x, x)
    y2 = y * y * l2
    z2 = z * z * l2
    k = np.sign(rr) * rr * rr * x2
    d_end = np.sqrt(x2 + z2) * il2 - r2
    d_start = np.sqrt(x2 + y2) * il2 - r1
    d_side = (np.sqrt(np.maximum(x2 * a2 * il2, 0.0)) + y * rr) * il2 - r1
    return np.where(np.sign(z) * a2 * z2 > k, d_end, np.where(np.sign(y) * a2 * y2 < k, d_start, d_side))


def _sd_ellipsoid(q, r):
    """Signed distance bound of an axis-aligned ellipsoid (local coordinates ``q``)."""
    k0 = np.linalg.norm(q / r, axis=1)
    k1 = np.linalg.norm(q / (r * r), axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


class _Prim:
    """One primitive: ``kind`` ``cone`` (``a``, ``b``, ``r1``, ``r2``) or
    ``ellipsoid`` (``centre``, ``size`` semi-axes along the rows of ``axes``, the
    local x, y, z in world space). A cone may be squashed: its local space is
    scaled by ``squash`` along the rows of ``axes`` (and the distance by the
    smallest factor), making its cross-sections ellipses."""

    def __init__(self, kind, blend, **kw):
        self.kind = kind
        self.blend = float(blend)  # smooth-union radius with what came before; 0 = hard union
        self.__dict__.update(kw)
        if kind == "cone":
            a, b = kw["a"], kw["b"]
            rmax = max(kw["r1"], kw["r2"]) * max(kw.get("squash", (1.0, 1.0, 1.0)))
            self.lo = np.minimum(a, b) - rmax
            self.hi = np.maximum(a, b) + rmax
        else:
            ext = float(np.max(kw["size"]))
            self.lo = kw["centre"] - ext
            self.hi = kw["centre"] + ext

    def sdf(self, p):
        if self.kind == "cone":
            sq = getattr(self, "squash", None)
            if sq is None:
                return _sd_round_cone(p, self.a, self.b, self.r1, self.r2)
            M = self.axes.T / np.asarray(sq)[None, :]  # world -> squashed local (columns)
            o = self.a
            return _sd_round_cone((p - o) @ M, np.zeros(3), (self.b - o) @ M, self.r1, self.r2) * min(sq)
        return _sd_ellipsoid((p - self.centre) @ self.axes.T, self.size)


def _smin(a, b, k):
    """Polynomial smooth minimum (``k`` = blend radius; ``k = 0``: the minimum)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _field(prims, p, margin=None):
    """The body's signed distance at points ``p (N, 3)``. With ``margin``, each
    primitive is evaluated only within ``margin`` of its bounding box (exact
    where the result is below ``margin`` minus the largest blend radius)."""
    f = np.full(len(p), 1.0)
    x, y, z = np.ascontiguousarray(p.T)
    for pr in prims:
        if margin is None:
            f = _smin(f, pr.sdf(p), pr.blend)
            continue
        lo, hi = pr.lo - margin, pr.hi + margin
        near = np.nonzero((x > lo[0]) & (x < hi[0]) & (y > lo[1]) & (y < hi[1]) & (z > lo[2]) & (z < hi[2]))[0]
        if len(near):
            f[near] = _smin(f[near], pr.sdf(p[near]), pr.blend)
    return f


def _unit(v, fallback=(1.0, 0.0, 0.0)):
    """``v`` normalised; ``fallback`` where ``v`` is (nearly) zero."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.asarray(fallback, dtype=np.float64)


def _frame_rows(x_axis, y_hint):
    """Rows (x, y, z) of a right-handed frame with ``x`` along ``x_axis`` and
    ``y`` as close as possible to ``y_hint``."""
    x = _unit(x_axis)
    y = np.asarray(y_hint, dtype=np.float64) - (np.asarray(y_hint) @ x) * x
    if np.linalg.norm(y) < 1e-6:
        y = np.cross(x, [0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.cross(x, [1.0, 0.0, 0.0])
    y = _unit(y)
    return np.stack([x, y, np.cross(x, y)])


# ---------------------------------------------------------------------------
# the mannequin's proportions


def _check_bones(bone_vectors):
    try:
        bv = np.asarray(bone_vectors, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise BodyError(f"bone vectors are not numbers: {exc}") from None
    if bv.shape != (N_BONES, 3):
        raise BodyError(f"bone vectors must have shape ({N_BONES}, 3), got {bv.shape}")
    if not np.all(np.isfinite(bv)):
        raise BodyError("bone vectors are not all finite")
    lengths = np.linalg.norm(bv, axis=1)
    need = ("lfemur", "ltibia", "rfemur", "rtibia", "lhumerus", "lradius", "rhumerus", "rradius",
            "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head", "lclavicle", "rclavicle",
            "lwrist", "rwrist", "lfoot", "rfoot")
    short = [n for n in need if lengths[_J[n]] < 1e-3]
    if short:
        raise BodyError(f"cannot build a body on a skeleton with bones of length 0: {', '.join(short)}")
    return bv


def _stature_scale(start, end):
    """The skeleton's size relative to the reference (CMU subject 60)."""
    ankle = 0.5 * (end[_J["ltibia"], 1] + end[_J["rtibia"], 1])
    extent = end[_J["head"], 1] - ankle
    if not 0.3 < extent < 3.5:
        raise BodyError(f"the skeleton's rest pose is {extent:.2f} m from ankle to head; "
                        f"expected an upright T-pose (Y up), 0.3-3.5 m")
    return extent / _REF_EXTENT


def _proportions(start, end, s):
    """The mannequin's primitives (in smooth-union order) and weight capsules
    ``{bone: (a, b, r1, r2)}``. Lengths in metres at the reference size, × ``s``."""
    j = _J
    up = np.array([0.0, 1.0, 0.0])
    front = np.array([0.0, 0.0, 1.0])
    P = []
    caps = {}

    def cone(blend, a, b, r1, r2, **kw):
        P.append(_Prim("cone", blend, a=np.asarray(a, float), b=np.asarray(b, float), r1=r1 * s, r2=r2 * s, **kw))

    def ellipsoid(blend, centre, size, axes=np.eye(3)):
        P.append(_Prim("ellipsoid", blend, centre=np.asarray(centre, float), size=np.asarray(size) * s, axes=axes))

    root = start[j["root"]]
    hips = 0.5 * (end[j["lhipjoint"]] + end[j["rhipjoint"]])
    hip_half = 0.5 * abs(end[j["lhipjoint"], 0] - end[j["rhipjoint"], 0])
    neck0 = end[j["thorax"]]
    lb, ub = end[j["lowerback"]], end[j["upperback"]]
    # torso: pelvis, belly, rib cage: ellipsoids blended wide
    ellipsoid(0.0, [root[0], hips[1] + 0.03 * s, 0.5 * (root[2] + hips[2]) - 0.012 * s],
              [hip_half / s + 0.06, 0.13, 0.1])
    ellipsoid(0.09 * s, lb + np.array([0.0, -0.02, 0.01]) * s, [0.13, 0.15, 0.095])
    ellipsoid(0.08 * s, ub + np.array([0.0, 0.035, 0.018]) * s, [0.145, 0.145, 0.102])
    # neck and head
    cone(0.045 * s, neck0 - 0.02 * s * up, end[j["upperneck"]], 0.058, 0.05)
    hb = end[j["head"]] - start[j["head"]]
    hax = _frame_rows(np.cross(_unit(hb), front), _unit(hb))  # rows: side (+X), up, front
    ellipsoid(0.03 * s, start[j["head"]] + 0.55 * hb + hax[2] * 0.012 * s, [0.078, 0.108, 0.094], axes=hax)
    caps["lowerneck"] = (start[j["lowerneck"]], end[j["lowerneck"]], 0.058, 0.055)
    caps["upperneck"] = (start[j["upperneck"]], end[j["upperneck"]], 0.055, 0.05)
    caps["head"] = (start[j["head"]] + 0.4 * hb, end[j["head"]], 0.08, 0.08)
    caps["root"] = (root + 0.02 * s * up, np.array([root[0], hips[1] - 0.04 * s, 0.5 * (root[2] + hips[2])]),
                    0.12, 0.12)
    caps["lowerback"] = (start[j["lowerback"]], lb, 0.115, 0.12)
    caps["upperback"] = (start[j["upperback"]], ub, 0.12, 0.125)
    caps["thorax"] = (start[j["thorax"]], end[j["thorax"]], 0.125, 0.1)
    for side in "lr":
        n = lambda name: side + name  # noqa: E731
        clav0, sh = start[j[n("clavicle")]], end[j[n("clavicle")]]
        el, wr = end[j[n("humerus")]], end[j[n("radius")]]
        knuck, tips = end[j[n("wrist")]], end[j[n("fingers")]]
        thumb = end[j[n("thumb")]]
        hip, knee, ankle = end[j[n("hipjoint")]], end[j[n("femur")]], end[j[n("tibia")]]
        ball, toe = end[j[n("foot")]], end[j[n("toes")]]
        # shoulder (trapezius to deltoid), arm, forearm
        sh_in = clav0 + 0.3 * (sh - clav0)
        cone(0.045 * s, sh_in, sh, 0.058, 0.05)
        cone(0.0, sh, el, 0.05, 0.038)
        cone(0.0, el, wr, 0.038, 0.027)
        # hand: a mitten (a flat round cone) from the wrist to past the finger tips, and a thumb
        hdir = _unit(tips - wr)
        tip = tips + hdir * 0.02 * s
        hax = _frame_rows(hdir, thumb - wr)  # rows: along, towards the thumb, thickness
        cone(0.035 * s, wr + hdir * 0.025 * s, tip - hdir * 0.016 * s, 0.0195, 0.016, squash=(1.0, 2.1, 1.0),
             axes=hax)
        t0 = wr + 0.3 * (knuck - wr) + hax[1] * 0.02 * s
        cone(0.015 * s, t0, t0 + _unit(hdir + 0.6 * hax[1]) * 0.06 * s, 0.0145, 0.012)
        # leg: thigh, shin (one chain), foot (heel, ball, toes, instep)
        cone(0.05 * s, hip, knee, 0.085, 0.053)
        cone(0.0, knee, ankle, 0.053, 0.036)
        fwd = toe - ankle
        fwd[1] = 0.0
        fwd = _unit(fwd, front)
        side_ax = _unit(np.cross(up, fwd))
        fax = np.stack([side_ax, up, fwd])
        sole = min(ball[1], toe[1]) - 0.026 * s
        heel = np.array([ankle[0], sole + 0.03 * s, ankle[2]]) - fwd * 0.05 * s
        ballp = np.array([ball[0], sole + 0.024 * s, ball[2]])
        toep = np.array([toe[0], sole + 0.017 * s, toe[2]]) + fwd * 0.015 * s
        cone(0.035 * s, heel, ballp, 0.03, 0.024, squash=(1.3, 1.0, 1.0), axes=fax)
        cone(0.02 * s, ballp, toep, 0.024, 0.017, squash=(1.85, 1.0, 1.0), axes=fax)
        cone(0.025 * s, ankle - 0.005 * s * up, ballp + 0.008 * s * up, 0.033, 0.018, squash=(1.4, 1.0, 1.0),
             axes=fax)
        # weight capsules
        caps[n("clavicle")] = (clav0 + 0.35 * (sh - clav0), sh, 0.05, 0.05)
        caps[n("humerus")] = (sh, el, 0.05, 0.038)
        caps[n("radius")] = (el, wr, 0.038, 0.027)
        caps[n("wrist")] = (wr, knuck, 0.03, 0.028)
        caps[n("hand")] = (knuck, tip, 0.024, 0.02)
        caps[n("femur")] = (hip, knee, 0.085, 0.053)
        caps[n("tibia")] = (knee, ankle, 0.053, 0.036)
        caps[n("foot")] = (heel + fwd * 0.02 * s, ballp, 0.032, 0.026)
        caps[n("toes")] = (ballp, toep, 0.026, 0.018)
    caps = {b: (np.asarray(a, float), np.asarray(c, float), r1 * s, r2 * s) for b, (a, c, r1, r2) in caps.items()}
    return P, caps


def weight_capsules(bone_vectors):
    """The weight capsules of the mannequin of ``bone_vectors``: ``(bones (B,),
    a (B, 3), b (B, 3), r1 (B,), r2 (B,))`` — a round cone per skinned bone
    (bone indices ``bones``), in rest pose."""
    bv = _check_bones(bone_vectors)
    start = rest_starts(bv)
    end = start + bv
    _, caps = _proportions(start, end, _stature_scale(start, end))
    names = [n for n in JOINT_NAMES if n in caps]
    return (np.array([_J[n] for n in names]), np.array([caps[n][0] for n in names]),
            np.array([caps[n][1] for n in names]), np.array([caps[n][2] for n in names]),
            np.array([caps[n][3] for n in names]))


# ---------------------------------------------------------------------------
# polygonisation: naive surface nets on a grid, made manifold


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


def _surface_nets(F, origin, h):
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


def _triangulate(V, Q):
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


def _relax_and_project(prims, V, faces, h, margin, iterations=4):
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
            vals = _field(prims, (V[None] + offsets[:, None]).reshape(-1, 3), margin).reshape(7, n)
            f = vals[0]
            g = ((vals[1:4] - vals[4:7]) / (2 * eps)).T
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 1e-6)
            step = (f / g2)[:, None] * g
            ln = np.linalg.norm(step, axis=1, keepdims=True)
            V = V - step * np.minimum(1.0, h / np.maximum(ln, 1e-12))  # at most a cell per step
    return V


# ---------------------------------------------------------------------------
# weights


def bone_segment_distances(points: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Distances ``(V, B)`` from points ``(V, 3)`` to segments ``starts → ends (B, 3)``."""
    d = ends - starts
    L2 = np.sum(d * d, axis=1)
    rel = points[:, None, :] - starts[None]
    t = np.einsum("vbk,bk->vb", rel, d) / np.where(L2 > 0, L2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    closest = starts[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1)


def _quantize_rows(w, q):
    """Weights rounded to multiples of ``q`` with rows still summing to 1 (largest remainders)."""
    n = int(round(1.0 / q))
    x = w * n
    base = np.floor(x)
    short = (n - base.sum(1)).astype(np.int64)
    order = np.argsort(-(x - base), axis=1, kind="stable")
    rank = np.argsort(order, axis=1, kind="stable")
    base = base + (rank < short[:, None])
    return base / n


def _skin_weights(verts, bones, a, b, r1, r2, tau, k=K_INFLUENCES):
    """Soft-min weights of the weight capsules: ``(indices (V, k), weights (V, k))``."""
    d = np.stack([_sd_round_cone(verts, a[i], b[i], r1[i], r2[i]) for i in range(len(bones))], axis=1)
    w = np.exp(-(d - d.min(1, keepdims=True)) / tau)
    order = np.argsort(-w, axis=1, kind="stable")[:, :k + 1]
    ww = np.take_along_axis(w, order, axis=1)
    ww = np.maximum(ww[:, :k] - ww[:, k:k + 1], 0.0)  # continuous where the 4th and 5th swap
    ww = ww / ww.sum(1, keepdims=True)
    ww = np.where(ww < 2e-3, 0.0, ww)
    ww = _quantize_rows(ww / ww.sum(1, keepdims=True), WEIGHT_QUANTUM)
    idx = bones[order[:, :k]]
    # bones of weight 0 point at the first bone (harmless, and tidy)
    idx = np.where(ww > 0, idx, idx[:, :1])
    return idx.astype(np.int64), ww


# ---------------------------------------------------------------------------
# the body


def _build(bv):
    start = rest_starts(bv)
    end = start + bv
    s = _stature_scale(start, end)
    prims, caps = _proportions(start, end, s)
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
        F[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]] = _smin(sub.ravel(), p.sdf(pts), p.blend).reshape(sub.shape)
    V, Q = _surface_nets(F, origin, h)
    faces = _triangulate(V, Q)
    V = _relax_and_project(prims, V, faces, h, margin=kmax + 3 * h)
    names = [n for n in JOINT_NAMES if n in caps]
    bones = np.array([_J[n] for n in names])
    ca = np.array([caps[n][0] for n in names])
    cb = np.array([caps[n][1] for n in names])
    idx, w = _skin_weights(V, bones, ca, cb, np.array([caps[n][2] for n in names]),
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
    bv = _check_bones(bone_vectors)
    V, F, idx, w, start, part, env = _cached(np.ascontiguousarray(bv).tobytes())
    return Body(V.copy(), F.copy(), idx.copy(), w.copy(), start.copy(), part.copy(), tuple(JOINT_NAMES),
                env.copy())

# ---------------------------------------------------------------------------
# linear blend skinning


def _split(transforms):
    if isinstance(transforms, tuple):
        R, t = transforms
        return np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    M = np.asarray(transforms, dtype=np.float64)
    return M[..., :3, :3], M[..., :3, 3]


def lbs(body: Body, transforms, chunk: int = 64) -> np.ndarray:
    """Linear blend skinning: posed vertices ``(T, V, 3)``.

    ``transforms``: ``(R (T, 31, 3, 3), t (T, 31, 3))`` from
    :func:`dancing_points_addon.ik.bone_transforms`, or homogeneous matrices
    ``(T, 31, 4, 4)``. ``v' = Σ_b w_vb (R_b v + t_b)``, evaluated as
    ``(Σ_b w_vb R_b) v + Σ_b w_vb t_b`` with the dense weight matrix (one
    BLAS product per chunk of ``chunk`` frames).
    """
    R, t = _split(transforms)
    single = R.ndim == 3
    if single:
        R, t = R[None], t[None]
    W = body.dense_weights()
    V = body.vertices
    T = R.shape[0]
    out = np.empty((T, len(V), 3))
    for a in range(0, T, chunk):
        b = min(a + chunk, T)
        M = np.matmul(W, R[a:b].reshape(b - a, N_BONES, 9)).reshape(b - a, len(V), 3, 3)
        out[a:b] = np.einsum("tvij,vj->tvi", M, V) + np.matmul(W, t[a:b])
    return out[0] if single else out


def lbs_frame(body: Body, transforms) -> np.ndarray:
    """One frame: ``transforms`` of one frame (``(R (31,3,3), t (31,3))`` or
    ``(31, 4, 4)``) → posed vertices ``(V, 3)``. Uses the sparse weights."""
    R, t = _split(transforms)
    Rv = R[body.indices]  # (V, k, 3, 3)
    p = np.einsum("vkij,vj->vki", Rv, body.vertices) + t[body.indices]
    return np.einsum("vk,vki->vi", body.weights, p)
