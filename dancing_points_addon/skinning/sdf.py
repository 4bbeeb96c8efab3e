"""The body's implicit surface (step 1 of the package): exact signed distances of
round cones and ellipsoids, vectorised over points ``(N, 3)``, a polynomial
smooth union, and the field of a list of primitives (:func:`field`).
"""
from __future__ import annotations

import numpy as np


def sd_round_cone(p, a, b, r1, r2):
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


class Prim:
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
                return sd_round_cone(p, self.a, self.b, self.r1, self.r2)
            M = self.axes.T / np.asarray(sq)[None, :]  # world -> squashed local (columns)
            o = self.a
            return sd_round_cone((p - o) @ M, np.zeros(3), (self.b - o) @ M, self.r1, self.r2) * min(sq)
        return _sd_ellipsoid((p - self.centre) @ self.axes.T, self.size)


def smin(a, b, k):
    """Polynomial smooth minimum (``k`` = blend radius; ``k = 0``: the minimum)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def field(prims, p, margin=None):
    """The body's signed distance at points ``p (N, 3)``. With ``margin``, each
    primitive is evaluated only within ``margin`` of its bounding box (exact
    where the result is below ``margin`` minus the largest blend radius)."""
    f = np.full(len(p), 1.0)
    x, y, z = np.ascontiguousarray(p.T)
    for pr in prims:
        if margin is None:
            f = smin(f, pr.sdf(p), pr.blend)
            continue
        lo, hi = pr.lo - margin, pr.hi + margin
        near = np.nonzero((x > lo[0]) & (x < hi[0]) & (y > lo[1]) & (y < hi[1]) & (z > lo[2]) & (z < hi[2]))[0]
        if len(near):
            f[near] = smin(f[near], pr.sdf(p[near]), pr.blend)
    return f


def unit(v, fallback=(1.0, 0.0, 0.0)):
    """``v`` normalised; ``fallback`` where ``v`` is (nearly) zero."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.asarray(fallback, dtype=np.float64)


def frame_rows(x_axis, y_hint):
    """Rows (x, y, z) of a right-handed frame with ``x`` along ``x_axis`` and
    ``y`` as close as possible to ``y_hint``."""
    x = unit(x_axis)
    y = np.asarray(y_hint, dtype=np.float64) - (np.asarray(y_hint) @ x) * x
    if np.linalg.norm(y) < 1e-6:
        y = np.cross(x, [0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.cross(x, [1.0, 0.0, 0.0])
    y = unit(y)
    return np.stack([x, y, np.cross(x, y)])
