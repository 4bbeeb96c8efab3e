"""A procedural low-poly body and linear blend skinning, in numpy.

:func:`make_body` builds a simple human body — "two people, not sticks" —
around the rest pose of the SPEC §2 skeleton (the ASF T-pose in motion space,
root at the origin, facing +Z, left = +X): tapered elliptic tubes along the
legs, arms, spine and neck, capped at their ends, an ellipsoid head and
rounded boxes for the hands and feet, merged into one triangle mesh. Each
part is skinned to a few nearby bones by inverse-distance weights to the bone
segments (top 4, normalised), which blends rings near a joint smoothly between
the two bones that meet there.

:func:`lbs` poses it with the per-bone rigid transforms of
:func:`dancing_points_addon.ik.bone_transforms`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .skeleton import rest_starts
from .skeleton import JOINT_INDEX, JOINT_NAMES

__all__ = ["Body", "make_body", "lbs", "lbs_frame", "bone_segment_distances"]

_J = JOINT_INDEX
N_BONES = len(JOINT_NAMES)


@dataclass
class Body:
    """A skinned mesh in rest pose (motion space, metres).

    ``vertices (V, 3)``, ``faces (F, 3)`` (triangles, counter-clockwise seen
    from outside), ``indices (V, k)`` bone indices and ``weights (V, k)`` their
    weights (rows sum to 1), ``rest_start (31, 3)`` the rest start of every
    bone (for :func:`dancing_points_addon.ik.bone_transforms`), ``part (V,)``
    the index of the part each vertex belongs to, named in ``part_names``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    indices: np.ndarray
    weights: np.ndarray
    rest_start: np.ndarray
    part: np.ndarray
    part_names: tuple

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    def dense_weights(self) -> np.ndarray:
        """Weights as a dense ``(V, 31)`` matrix."""
        W = np.zeros((len(self.vertices), N_BONES))
        np.add.at(W, (np.arange(len(W))[:, None], self.indices), self.weights)
        return W


# ---------------------------------------------------------------------------
# geometry


def _frame(axis: np.ndarray, front=np.array([0.0, 0.0, 1.0])):
    """Orthonormal (side, front) perpendicular to unit ``axis`` (front ~ +Z)."""
    f = front - np.dot(front, axis) * axis
    if np.linalg.norm(f) < 1e-6:
        f = np.array([0.0, 1.0, 0.0]) - axis[1] * axis
    f /= np.linalg.norm(f)
    s = np.cross(f, axis)  # side; (s, f, axis) is right-handed
    return s, f


def _superellipse(theta, exponent):
    c, s = np.cos(theta), np.sin(theta)
    e = 2.0 / exponent
    return np.sign(c) * np.abs(c) ** e, np.sign(s) * np.abs(s) ** e


def _tube(points, radii, n_around=16, per_metre=60.0, min_rings=2, caps=(True, True),
          cap_rings=3, exponent=2.0, front=np.array([0.0, 0.0, 1.0])):
    """A capped tube along a polyline.

    ``points (m, 3)``; ``radii (m, 2)`` semi-axes (side, front) at each point,
    interpolated linearly. Rings are spaced ``~1/per_metre`` apart (at least
    ``min_rings`` per segment); ``exponent`` > 2 squares the cross-section
    (a rounded box). Caps are elliptic domes of ``cap_rings`` rings closed by
    a pole vertex. Returns ``(vertices, faces)``.
    """
    points = np.asarray(points, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    seg = np.diff(points, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    # ring parameters along the polyline (segment index + fraction)
    centres, rads, axes = [], [], []
    for i in range(len(seg)):
        n = max(min_rings, int(np.ceil(seglen[i] * per_metre)))
        ts = np.linspace(0.0, 1.0, n + 1)[:-1] if i < len(seg) - 1 else np.linspace(0.0, 1.0, n + 1)
        for t in ts:
            centres.append(points[i] + t * seg[i])
            rads.append(radii[i] + t * (radii[i + 1] - radii[i]))
            d = seg[i] / seglen[i]
            # at the polyline's inner joints, the ring faces the bisector
            if t == 0.0 and i > 0:
                d = d + seg[i - 1] / seglen[i - 1]
                d /= np.linalg.norm(d)
            axes.append(d)
    centres, rads, axes = np.array(centres), np.array(rads), np.array(axes)
    theta = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    cx, cy = _superellipse(theta, exponent)
    # parallel-transport the cross-section frame along the tube (no twist)
    s0, f0 = _frame(axes[0], front)
    S, F = [s0], [f0]
    for k in range(1, len(axes)):
        f = F[-1] - np.dot(F[-1], axes[k]) * axes[k]
        f /= np.linalg.norm(f)
        S.append(np.cross(f, axes[k]))
        F.append(f)
    S, F = np.array(S), np.array(F)
    ring = (centres[:, None, :] + (rads[:, 0, None] * cx)[:, :, None] * S[:, None, :]
            + (rads[:, 1, None] * cy)[:, :, None] * F[:, None, :])  # (rings, around, 3)
    verts = [ring.reshape(-1, 3)]
    nr = len(centres)
    faces = []
    a = np.arange(n_around)
    b = (a + 1) % n_around
    for k in range(nr - 1):
        r0, r1 = k * n_around, (k + 1) * n_around
        faces.append(np.stack([r0 + a, r0 + b, r1 + b], 1))
        faces.append(np.stack([r0 + a, r1 + b, r1 + a], 1))
    count = nr * n_around
    for end, on in ((0, caps[0]), (1, caps[1])):
        if not on:
            continue
        k = 0 if end == 0 else nr - 1
        sign = -1.0 if end == 0 else 1.0
        depth = min(rads[k]) * sign
        prev = np.arange(k * n_around, (k + 1) * n_around)
        for c in range(1, cap_rings + 1):
            phi = 0.5 * np.pi * c / (cap_rings + 1)
            scale = np.cos(phi)
            pts = (centres[k] + axes[k] * depth * np.sin(phi)
                   + (rads[k, 0] * scale * cx)[:, None] * S[k] + (rads[k, 1] * scale * cy)[:, None] * F[k])
            cur = np.arange(count, count + n_around)
            verts.append(pts)
            count += n_around
            if end == 1:
                faces.append(np.stack([prev[a], prev[b], cur[b]], 1))
                faces.append(np.stack([prev[a], cur[b], cur[a]], 1))
            else:
                faces.append(np.stack([prev[a], cur[b], prev[b]], 1))
                faces.append(np.stack([prev[a], cur[a], cur[b]], 1))
            prev = cur
        pole = centres[k] + axes[k] * depth
        verts.append(pole[None])
        if end == 1:
            faces.append(np.stack([prev[a], prev[b], np.full(n_around, count)], 1))
        else:
            faces.append(np.stack([prev[a], np.full(n_around, count), prev[b]], 1))
        count += 1
    return np.concatenate(verts), np.concatenate(faces)


def _ellipsoid(centre, radii, frame, n_around=20, n_rings=12):
    """A UV ellipsoid; ``frame`` = (side, up, front) unit axes; ``radii`` along them."""
    s, u, f = frame
    theta = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    phis = np.linspace(0.0, np.pi, n_rings + 1)[1:-1]  # ring latitudes (no poles)
    verts = [centre - u * radii[1]]
    for phi in phis:
        y = -np.cos(phi)
        r = np.sin(phi)
        ring = (centre + u * radii[1] * y + (radii[0] * r * np.cos(theta))[:, None] * s
                + (radii[2] * r * np.sin(theta))[:, None] * f)
        verts.append(ring)
    verts.append(centre + u * radii[1])
    V = np.vstack([np.atleast_2d(v) for v in verts])
    a = np.arange(n_around)
    b = (a + 1) % n_around
    faces = [np.stack([np.zeros(n_around, int), 1 + b, 1 + a], 1)]
    for k in range(len(phis) - 1):
        r0, r1 = 1 + k * n_around, 1 + (k + 1) * n_around
        faces.append(np.stack([r0 + a, r0 + b, r1 + b], 1))
        faces.append(np.stack([r0 + a, r1 + b, r1 + a], 1))
    top = len(V) - 1
    r0 = 1 + (len(phis) - 1) * n_around
    faces.append(np.stack([r0 + a, r0 + b, np.full(n_around, top)], 1))
    return V, np.concatenate(faces)


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


def _skin_weights(verts, allowed, starts, ends, k=4, power=4.0, floor=0.01):
    """Top-``k`` inverse-distance weights to the allowed bone segments."""
    dist = bone_segment_distances(verts, starts, ends)
    w = np.where(allowed, 1.0 / np.maximum(dist, floor) ** power, 0.0)
    k = min(k, w.shape[1])
    idx = np.argpartition(-w, k - 1, axis=1)[:, :k]
    ww = np.take_along_axis(w, idx, axis=1)
    order = np.argsort(-ww, axis=1)
    idx = np.take_along_axis(idx, order, axis=1)
    ww = np.take_along_axis(ww, order, axis=1)
    ww = ww / np.sum(ww, axis=1, keepdims=True)
    # drop negligible influences (keeps the rows normalised)
    ww = np.where(ww < 1e-4, 0.0, ww)
    ww = ww / np.sum(ww, axis=1, keepdims=True)
    return idx.astype(np.int64), ww


# ---------------------------------------------------------------------------
# the body


def make_body(bone_vectors: np.ndarray, radius_scale: float = 1.0, n_around: int = 16,
              per_metre: float = 40.0) -> Body:
    """A low-poly human body around the rest pose of ``bone_vectors (31, 3)``.

    Radii (metres, × ``radius_scale``): thigh 7.5 → 5.5, shin 5 → 3.8, upper
    arm 4.5 → 3.8, forearm 3.6 → 2.8, torso an ellipse of semi-axes 13 × 9
    (waist 12 × 8.5, pelvis 14.5 × 10), neck 5.5, head an ellipsoid of
    8 × 10.5 × 9.5 on the ``head`` bone; rounded boxes for the hands and feet.
    About 5,500 vertices and 11,000 triangles with the defaults.
    """
    bv = np.asarray(bone_vectors, dtype=np.float64)
    rs = float(radius_scale)
    start = rest_starts(bv)
    end = start + bv
    j = _J
    parts = []  # (name, vertices, faces, allowed bone names)

    def tube(name, pts, radii, bones, **kw):
        kw.setdefault("n_around", n_around)
        kw.setdefault("per_metre", per_metre)
        v, f = _tube(pts, np.asarray(radii) * rs, **kw)
        parts.append((name, v, f, bones))

    up = np.array([0.0, 1.0, 0.0])
    for s in "lr":
        hip, knee, ankle = end[j[s + "hipjoint"]], end[j[s + "femur"]], end[j[s + "tibia"]]
        thigh_dir = (knee - hip) / np.linalg.norm(knee - hip)
        tube(s + "leg", [hip - thigh_dir * 0.06, hip, knee, ankle],
             [(0.08, 0.08), (0.075, 0.075), (0.052, 0.055), (0.038, 0.04)],
             [s + "hipjoint", s + "femur", s + "tibia"], n_around=n_around + 4)
        # foot: a rounded box from behind the heel to the toe tip, down to the sole
        ball, toe = end[j[s + "foot"]], end[j[s + "toes"]]
        sole = min(ball[1], toe[1]) - 0.02
        heel = np.array([ankle[0], 0.5 * (ankle[1] + sole), ankle[2] - 0.05])
        tip = np.array([toe[0], 0.5 * (toe[1] + 0.01 + sole), toe[2] + 0.015])
        mid = np.array([ball[0], 0.5 * (ankle[1] + sole) - 0.01, ball[2]])
        h_heel = 0.5 * (ankle[1] + 0.015 - sole)
        tube(s + "foot", [heel, mid, tip],
             [(0.04, h_heel), (0.048, 0.5 * (ball[1] + 0.02 - sole)), (0.04, 0.5 * (toe[1] + 0.01 - sole))],
             [s + "tibia", s + "foot", s + "toes"], exponent=4.0, front=up, per_metre=60.0)
        # arm: shoulder -> elbow -> wrist
        sh, el, wr = end[j[s + "clavicle"]], end[j[s + "humerus"]], end[j[s + "wrist"]]
        tube(s + "arm", [sh, el, wr], [(0.048, 0.048), (0.038, 0.04), (0.028, 0.03)],
             [s + "clavicle", s + "humerus", s + "radius", s + "wrist"])
        # shoulder girdle: neck base -> shoulder
        n0 = start[j[s + "clavicle"]]
        tube(s + "shoulder", [n0 + 0.3 * bv[j[s + "clavicle"]], sh],
             [(0.06, 0.06), (0.055, 0.055)],
             ["thorax", s + "clavicle", s + "humerus"], front=up)
        # hand: wrist -> knuckles -> finger tips (flat box)
        fingers = end[j[s + "fingers"]]
        hdir = (fingers - wr) / np.linalg.norm(fingers - wr)
        tube(s + "hand", [wr, end[j[s + "hand"]], fingers + hdir * 0.03],
             [(0.016, 0.045), (0.014, 0.048), (0.01, 0.04)],
             [s + "wrist", s + "hand", s + "fingers", s + "thumb"], exponent=3.0, n_around=12)
        thumb = end[j[s + "thumb"]]
        tdir = (thumb - wr) / np.linalg.norm(thumb - wr)
        tube(s + "thumb", [wr + 0.4 * (thumb - wr), thumb + 0.015 * tdir], [(0.012, 0.012), (0.009, 0.009)],
             [s + "wrist", s + "thumb"], n_around=8, per_metre=60.0)
    # torso: pelvis bottom -> root -> lowerback -> upperback -> thorax (neck base)
    root = start[0]
    sp = [end[j["lowerback"]], end[j["upperback"]], end[j["thorax"]]]
    tube("torso", [root - up * 0.12, root, sp[0], sp[1], sp[2]],
         [(0.13, 0.09), (0.145, 0.10), (0.12, 0.085), (0.13, 0.09), (0.11, 0.075)],
         ["root", "lhipjoint", "rhipjoint", "lowerback", "upperback", "thorax", "lclavicle", "rclavicle"],
         n_around=n_around + 12)
    # neck
    tube("neck", [sp[2] - up * 0.03, end[j["lowerneck"]], end[j["upperneck"]]],
         [(0.055, 0.055), (0.05, 0.05), (0.048, 0.048)],
         ["thorax", "lowerneck", "upperneck", "head"])
    # head: ellipsoid on the head bone, a little forward
    hb = bv[j["head"]]
    hu = hb / np.linalg.norm(hb)
    hs, hf = _frame(hu)
    centre = start[j["head"]] + 0.6 * hb + hf * 0.015
    v, f = _ellipsoid(centre, np.array([0.08, 0.105, 0.095]) * rs, (hs, hu, hf),
                      n_around=n_around + 8, n_rings=14)
    parts.append(("head", v, f, ["head"]))  # the skull is rigid; the neck blends into it

    verts, faces, allowed, part = [], [], [], []
    off = 0
    for p, (name, v, f, bones) in enumerate(parts):
        verts.append(v)
        faces.append(f + off)
        mask = np.zeros(N_BONES, dtype=bool)
        mask[[j[b] for b in bones]] = True
        allowed.append(np.broadcast_to(mask, (len(v), N_BONES)))
        part.append(np.full(len(v), p))
        off += len(v)
    verts = np.concatenate(verts)
    faces = np.concatenate(faces).astype(np.int64)
    allowed = np.concatenate(allowed)
    idx, w = _skin_weights(verts, allowed, start, end)
    return Body(verts, faces, idx, w, start, np.concatenate(part), tuple(p[0] for p in parts))


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
