# SPDX-License-Identifier: GPL-3.0-or-later
"""A camera that follows the couple (numpy only; the Blender side keys it).

The camera looks at the couple from a side that turns slowly with them
(:func:`visible_directions`: the side from which neither dancer hides the
other, turning no faster than ``max_turn`` degrees a second; or a fixed
``view_dir``), at a slight elevation. Its position in its own axes ``(a, b, e)`` (right,
up, back) is a zero-phase smoothed version of where it should be on each frame
(centred on the couple, at the distance where the couple fills ``fill`` of the
frame height, far enough for every point to be inside the frame with a
margin). A correction pass then checks every frame with a perspective
projection and, where a frame breaks one of the constraints

- every point inside the frame (``|x|, |y| <= margin`` in normalised device
  coordinates, −1..1),
- the couple's projected height >= ``min_fill`` of the frame height,
- the centre of the couple's projected bounding box within ``centre_limit``
  of the middle horizontally (``0.2`` = the middle fifth),

adds a local, widened correction to the wanted path and smooths again, until
no frame breaks them. Everything is smooth (a Gaussian of the wanted path), so
the camera's acceleration is bounded; :func:`follow_camera` reports it.

Conventions as ``blender_math.frame_camera``: Blender space (Z up), the
rotation's columns are the camera's x (right), y (up), z (back; it looks along
−z); ``fov`` is the angle of the larger image side (Blender's ``sensor_fit``
``AUTO``), ``aspect`` = width / height.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


WIDEN = 0.5  # a correction spreads over ±WIDEN·sigma frames
GAIN = 1.0


@dataclass
class CameraPath:
    locations: np.ndarray      # (T, 3) camera positions, Blender space
    rotations: np.ndarray      # (T, 3, 3) camera-to-world rotation of each frame
    max_accel: float           # m/s², the largest |second derivative| of the path
    max_speed: float           # m/s
    iterations: int            # correction passes used
    sigma: float               # the smoothing used in the end (frames)
    min_fill: float            # smallest projected couple height / frame height
    max_centre: float          # largest |centre| (NDC units: 1 = half the width)
    max_extent: float          # largest |x| or |y| of a point (NDC; <= 1: inside)
    max_turn_rate: float = 0.0   # deg/s, the view direction's fastest turn
    max_turn_accel: float = 0.0  # deg/s², its largest angular acceleration

    @property
    def rotation(self) -> np.ndarray:
        """The first frame's rotation (all of them, for a camera that does not turn)."""
        return self.rotations[0]


def view_rotation(view_dir, elevation_deg: float = 10.0) -> np.ndarray:
    """Camera-to-world rotation ``(3, 3)`` looking horizontally against
    ``view_dir`` (from the target towards the camera), tilted down by
    ``elevation_deg``; ``(T, 3, 3)`` for directions ``(T, 3)``."""
    v = np.array(view_dir, dtype=np.float64)
    v[..., 2] = 0.0
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    v = np.where(n > 1e-9, v / np.maximum(n, 1e-12), np.array([0.0, -1.0, 0.0]))
    el = np.deg2rad(elevation_deg)
    z = v * np.cos(el) + np.array([0.0, 0.0, np.sin(el)])
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _heading(v):
    return np.arctan2(v[..., 1], v[..., 0])


def uncovered_shares(leader_points, follower_points, headings):
    """``(T, K)``: the share of the farther dancer's box (the bounding box of his
    or her points in the image) that the nearer dancer's box leaves uncovered,
    seen from each horizontal heading ``(K,)`` (radians, the direction from the
    couple towards the camera; an orthographic view: the boxes' widths across
    the view and their heights). Points ``(T, N, 3)``, Blender space, NaN ignored."""
    th = np.asarray(headings, dtype=np.float64)
    across = np.stack([-np.sin(th), np.cos(th)], axis=1)  # the image's x axis, (K, 2)
    towards = np.stack([np.cos(th), np.sin(th)], axis=1)
    out = []
    with np.errstate(all="ignore"):
        for lo in range(0, len(leader_points), 256):  # (T, N, K) a chunk at a time: any length of take
            L = np.asarray(leader_points[lo:lo + 256], dtype=np.float64)
            Fo = np.asarray(follower_points[lo:lo + 256], dtype=np.float64)
            xl, xf = L[..., :2] @ across.T, Fo[..., :2] @ across.T
            nearer_l = np.nanmean(L[..., :2] @ towards.T, axis=1) > np.nanmean(Fo[..., :2] @ towards.T, axis=1)
            l0, l1, f0, f1 = np.nanmin(xl, 1), np.nanmax(xl, 1), np.nanmin(xf, 1), np.nanmax(xf, 1)
            zl0, zl1 = np.nanmin(L[..., 2], 1)[:, None], np.nanmax(L[..., 2], 1)[:, None]
            zf0, zf1 = np.nanmin(Fo[..., 2], 1)[:, None], np.nanmax(Fo[..., 2], 1)[:, None]
            ox = np.clip(np.minimum(l1, f1) - np.maximum(l0, f0), 0.0, None)
            oy = np.clip(np.minimum(zl1, zf1) - np.maximum(zl0, zf0), 0.0, None)
            far = np.where(nearer_l, (f1 - f0) * (zf1 - zf0), (l1 - l0) * (zl1 - zl0))
            u = 1.0 - ox * oy / np.maximum(far, 1e-9)
            out.append(np.where(np.isfinite(u), u, 1.0))
    return np.concatenate(out) if out else np.zeros((0, len(th)))


def visible_directions(leader_points, follower_points, view_dir, fps: float = 30.0, *, step_deg: float = 1.0,
                       turn_cost: float = 0.2, prior: float = 0.05, sigma_s: float = 1.0,
                       max_turn: float = 25.0):
    """Per frame a horizontal view direction ``(T, 3)`` (from the couple towards
    the camera, Blender space) from which neither dancer hides the other, turning
    slowly: a path over the headings ``step_deg`` apart, at most one step a
    frame, that minimises over the take the frames where less than 60 % of
    the farther dancer's box is uncovered (:func:`uncovered_shares`; a cost
    rising from 0 at 60 % uncovered to 1 at 40 %), plus ``turn_cost`` per step
    turned and ``prior`` (per half turn) for looking away from ``view_dir``
    (dynamic programming); then smoothed by a zero-phase Gaussian of
    ``sigma_s`` seconds, and more until it turns no faster than ``max_turn``
    degrees a second (so the angular acceleration is bounded too).
    Points ``(T, N, 3)`` of each dancer, Blender space, NaN ignored."""
    T = len(leader_points)
    K = max(int(round(360.0 / step_deg)), 4)
    th = np.arange(K) * (2.0 * np.pi / K)
    vd = np.asarray(view_dir, dtype=np.float64)
    h0 = float(_heading(vd))
    cost = np.clip((0.6 - uncovered_shares(leader_points, follower_points, th)) / 0.2, 0.0, 1.0)
    cost += prior * np.abs(np.angle(np.exp(1j * (th - h0)))) / np.pi
    if T == 0:
        return np.zeros((0, 3))
    total = cost[0].copy()
    back = np.empty((T, K), dtype=np.int64)
    moves = np.array([-1, 0, 1])
    ks = np.arange(K)
    for t in range(1, T):
        cand = np.stack([np.roll(total, m) + turn_cost * abs(m) for m in moves])  # cand[j, k]: from k - moves[j]
        j = cand.argmin(0)
        back[t] = (ks - moves[j]) % K
        total = cand[j, ks] + cost[t]
    k = int(total.argmin())
    idx = np.empty(T, dtype=np.int64)
    for t in range(T - 1, -1, -1):
        idx[t] = k
        k = back[t, k]
    theta = np.unwrap(th[idx])
    sig = sigma_s * fps
    theta = smooth(theta, sig)
    limit = np.deg2rad(max_turn) / fps
    for _ in range(60):
        if T < 2 or np.abs(np.diff(theta)).max() <= limit:
            break
        sig *= 1.3
        theta = smooth(theta, sig)
    return np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)


def turn_rates(rotations, fps: float = 30.0):
    """The view direction's largest angular speed (deg/s) and acceleration (deg/s²)
    over rotations ``(T, 3, 3)`` (about the vertical: the camera's heading)."""
    z = np.asarray(rotations)[:, :, 2]
    h = np.unwrap(np.arctan2(z[:, 1], z[:, 0]))
    if len(h) < 2:
        return 0.0, 0.0
    v = np.diff(h) * fps
    a = np.diff(v) * fps if len(v) > 1 else np.zeros(1)
    return float(np.rad2deg(np.abs(v).max())), float(np.rad2deg(np.abs(a).max()))


def half_tangents(fov: float, aspect: float):
    """``(tan of half the horizontal angle, tan of half the vertical angle)``."""
    t = np.tan(fov / 2)
    return (t, t / aspect) if aspect >= 1 else (t * aspect, t)


def project(points, locations, rotation, fov: float, aspect: float):
    """Normalised device coordinates ``(T, N, 2)`` (−1..1 across the frame, y up)
    and depth ``(T, N)`` of ``points (T, N, 3)`` seen by cameras at
    ``locations (T, 3)`` with ``rotation`` ``(3, 3)`` or one per frame ``(T, 3, 3)``."""
    tx, ty = half_tangents(fov, aspect)
    q = (np.asarray(points, np.float64) - np.asarray(locations, np.float64)[:, None]) @ np.asarray(rotation)
    depth = -q[..., 2]
    d = np.where(depth > 1e-9, depth, np.nan)
    return np.stack([q[..., 0] / (d * tx), q[..., 1] / (d * ty)], axis=-1), depth


def frame_metrics(ndc):
    """Per frame: the couple's projected height as a fraction of the frame
    height, the horizontal centre of its bounding box (NDC), and the largest
    ``|x|``/``|y|`` of any point (``> 1``: outside, ``NaN`` behind the camera)."""
    x, y = ndc[..., 0], ndc[..., 1]
    fill = (np.nanmax(y, axis=1) - np.nanmin(y, axis=1)) / 2
    centre = (np.nanmax(x, axis=1) + np.nanmin(x, axis=1)) / 2
    ext = np.max(np.abs(ndc), axis=(1, 2))  # NaN propagates: a point behind the camera
    return fill, centre, np.where(np.isfinite(ext), ext, np.inf)


def smooth(x, sigma: float):
    """Zero-phase Gaussian smoothing of ``x (T, …)`` along time (``sigma`` in
    frames), the ends held (edge padding: the camera starts and ends at rest)."""
    x = np.asarray(x, dtype=np.float64)
    if sigma <= 0 or len(x) < 2:
        return x.copy()
    r = int(np.ceil(4 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)])
    flat = pad.reshape(len(pad), -1)
    out = np.empty((len(x), flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.convolve(flat[:, j], k, mode="valid")
    return out.reshape(x.shape)


def _widen(d, r: int):
    """Spread a correction over ``±r`` frames (the largest of either sign), so
    that smoothing keeps most of it."""
    if r <= 0 or not np.any(d):
        return d
    T = len(d)
    pad = np.concatenate([np.zeros(r), d, np.zeros(r)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * r + 1)[:T]
    mx, mn = win.max(1), win.min(1)
    return np.where(mx > 0, mx, 0.0) + np.where(mn < 0, mn, 0.0)


def _fill_gaps(points):
    """Frames with no finite point take the nearest earlier (else later) frame's points."""
    ok = np.isfinite(points).all(-1)
    good = ok.any(1)
    if good.all():
        return points, ok
    if not good.any():
        raise ValueError("no finite point to frame")
    idx = np.where(good, np.arange(len(good)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.flatnonzero(good)[0])
    return points[idx], ok[idx]


def follow_camera(points, fov: float, aspect: float, view_dir, fps: float = 30.0, *,
                  elevation_deg: float = 10.0, fill: float = 0.68, min_fill: float = 0.55,
                  margin: float = 0.88, centre_limit: float = 0.2, sigma_s: float = 1.0,
                  max_iter: int = 40) -> CameraPath:
    """A camera path following ``points (T, N, 3)`` (Blender space; both
    dancers' joints, NaN where unknown) at ``fps`` frames per second, looking
    against ``view_dir``: one direction ``(3,)`` for the whole take, or one per
    frame ``(T, 3)`` (:func:`visible_directions`).

    ``fill``: the wanted projected height of the couple (fraction of the frame
    height); ``min_fill``, ``margin``, ``centre_limit``: the constraints every
    frame meets (see the module); ``sigma_s``: the smoothing (seconds).
    Raises ``ValueError`` when there is nothing to frame."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[-1] != 3 or len(P) == 0:
        raise ValueError("points must be (T, N, 3) with T >= 1")
    P, ok = _fill_gaps(P)
    vd = np.asarray(view_dir, dtype=np.float64)
    if vd.ndim == 2 and len(vd) != len(P):
        raise ValueError("view_dir must be (3,) or one direction per frame")
    R = np.ascontiguousarray(np.broadcast_to(view_rotation(vd, elevation_deg), (len(P), 3, 3)))
    tx, ty = half_tangents(fov, aspect)
    Q = P @ R  # camera-aligned coordinates (u right, v up, w back)
    Q = np.where(ok[..., None], Q, np.nan)
    u, v, w = Q[..., 0], Q[..., 1], Q[..., 2]
    T = len(Q)
    # What each frame wants: centred, the couple at ``fill`` of the frame height.
    a0 = (np.nanmax(u, 1) + np.nanmin(u, 1)) / 2
    b0 = (np.nanmax(v, 1) + np.nanmin(v, 1)) / 2
    wc = (np.nanmax(w, 1) + np.nanmin(w, 1)) / 2
    height = np.nanmax(v, 1) - np.nanmin(v, 1)
    e_fill = wc + np.maximum(height, 0.3) / (2 * fill * ty)
    m_in = margin - 0.04  # aim inside the margin, so smoothing rarely breaks it

    def e_inside(a, b):
        need = np.maximum(np.abs(u - a[:, None]) / (m_in * tx), np.abs(v - b[:, None]) / (m_in * ty))
        return np.nanmax(w + need, 1)

    e0 = np.maximum(e_fill, e_inside(a0, b0))
    want = np.stack([a0, b0, e0], axis=1)

    def check(cam):
        locs = np.einsum("tij,tj->ti", R, cam)
        ndc, _ = project(P, locs, R, fov, aspect)
        ndc = np.where(ok[..., None], ndc, np.nan)
        with np.errstate(all="ignore"):
            return locs, frame_metrics(ndc)

    def corrections(cam, fl, cx, ext):
        a, b, e = cam[:, 0], cam[:, 1], cam[:, 2]
        d = np.zeros_like(want)
        # Too close: a point outside the margin -> back off to where all are inside.
        bad_in = ext > margin - 0.01
        d[:, 2] = np.where(bad_in, np.maximum(e_inside(a, b) - e, 0.0) + 0.02, 0.0)
        # Too far: the couple smaller than min_fill -> come closer (the size scales with 1/depth).
        bad_fill = (fl < min_fill + 0.02) & ~bad_in
        dist = e - wc
        d[:, 2] = np.where(bad_fill, dist * (np.nan_to_num(fl) / (min_fill + 0.05) - 1.0), d[:, 2])
        # Off centre: shift sideways.
        bad_c = np.abs(np.nan_to_num(cx)) > centre_limit - 0.02
        d[:, 0] = np.where(bad_c, (np.nan_to_num(cx) - np.sign(cx) * (centre_limit - 0.06)) * dist * tx, 0.0)
        return d, bool(bad_in.any() or bad_fill.any() or bad_c.any())

    # Constraints first, smoothness second: when the correction passes cannot
    # meet them at this smoothing (a jump no smooth path follows), smooth less.
    sig = max(sigma_s * fps, 0.0)
    it = 0
    while True:
        off = np.zeros_like(want)
        r = int(np.ceil(WIDEN * sig))
        for _ in range(max_iter):
            it += 1
            cam = smooth(want + off, sig)
            locs, (fl, cx, ext) = check(cam)
            d, bad = corrections(cam, fl, cx, ext)
            if not bad:
                break
            for j in range(3):
                off[:, j] += GAIN * _widen(d[:, j], r)
        if not bad or sig == 0.0:
            break
        sig = sig / 2 if sig > 1.0 else 0.0
    locs, (fl, cx, ext) = check(cam)
    dt = 1.0 / fps
    vel = np.diff(locs, axis=0) / dt if T > 1 else np.zeros((1, 3))
    acc = np.diff(locs, 2, axis=0) / dt ** 2 if T > 2 else np.zeros((1, 3))
    rate, turn_acc = turn_rates(R, fps)
    return CameraPath(locs, R, float(np.linalg.norm(acc, axis=1).max()),
                      float(np.linalg.norm(vel, axis=1).max()), it, float(sig), float(np.nanmin(fl)),
                      float(np.nanmax(np.abs(cx))), float(np.max(ext)), rate, turn_acc)


def interpolate_frames(values, sample_frames, frames):
    """``values (T, …)`` given at ``sample_frames (T,)`` (increasing), linearly
    interpolated at ``frames (F,)`` (held beyond the ends)."""
    values = np.asarray(values, dtype=np.float64)
    sample_frames = np.asarray(sample_frames, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.float64)
    if len(values) == 1:
        return np.repeat(values, len(frames), 0)
    i = np.clip(np.searchsorted(sample_frames, frames, side="right") - 1, 0, len(values) - 2)
    t = np.clip((frames - sample_frames[i]) / (sample_frames[i + 1] - sample_frames[i]), 0.0, 1.0)
    t = t.reshape((-1,) + (1,) * (values.ndim - 1))
    return values[i] * (1 - t) + values[i + 1] * t


def floor_level(foot_heights, sole: float = 0.025) -> float:
    """The floor height under the dancers: the 25th percentile of each frame's
    lowest foot joint ``foot_heights (T, K)`` (NaN ignored), less the sole's
    thickness below the joints."""
    h = np.asarray(foot_heights, dtype=np.float64)
    low = np.nanmin(np.where(np.isfinite(h), h, np.inf), axis=1)
    low = low[np.isfinite(low)]
    if not len(low):
        return 0.0
    return float(np.percentile(low, 25) - sole)


def checker_floor(lo, hi, z: float, square: float = 1.0):
    """A checkerboard floor covering ``lo..hi`` (two ``(x, y)`` corners, snapped
    outwards to whole squares) at height ``z``: ``(vertices (V, 3), quads
    (F, 4), material index (F,) alternating 0/1)``."""
    lo = np.floor(np.asarray(lo, dtype=np.float64)[:2] / square) * square
    hi = np.ceil(np.asarray(hi, dtype=np.float64)[:2] / square) * square
    nx = max(int(round((hi[0] - lo[0]) / square)), 1)
    ny = max(int(round((hi[1] - lo[1]) / square)), 1)
    xs = lo[0] + square * np.arange(nx + 1)
    ys = lo[1] + square * np.arange(ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    verts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, float(z))], axis=1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v = lambda a, b: a * (ny + 1) + b  # noqa: E731
    quads = np.stack([v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1)], axis=1)
    # parity of the world square index, so the pattern does not move with the extent
    parity = ((np.round(xs[i] / square) + np.round(ys[j] / square)) % 2).astype(np.int64)
    return verts, quads, parity
