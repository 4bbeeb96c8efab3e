"""Scalar (Python float) kernels for the per-frame solvers (:mod:`.ik`,
:mod:`.foot_lock`, :mod:`.device_follow`): 3-vectors as 3-tuples, rotations as
row-major 9-tuples, and the two-bone IK on them (:func:`two_bone_s`, the scalar
twin of :func:`.ik.two_bone_ik`).

They work on Python floats because those solvers touch a handful of 3-vectors
a frame: numpy's per-call overhead (~1 µs) would dominate such tiny problems.
"""
from __future__ import annotations

from math import atan2, cos, sin, sqrt

I3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def rot_between_s(ux, uy, uz, vx, vy, vz):
    """Row-major 9-tuple of the minimal rotation taking u to v: the formula of
    :func:`.ik.rotation_between` (its batch form) on Python floats, for the
    frame loop (tests/test_kernels.py holds them equal)."""
    nu = sqrt(ux * ux + uy * uy + uz * uz)
    nv = sqrt(vx * vx + vy * vy + vz * vz)
    if nu < 1e-12 or nv < 1e-12:
        return I3
    ux, uy, uz = ux / nu, uy / nu, uz / nu
    vx, vy, vz = vx / nv, vy / nv, vz / nv
    c = ux * vx + uy * vy + uz * vz
    if 1.0 + c < 1e-12:
        if abs(ux) < 0.9:
            ax, ay, az = 0.0, uz, -uy  # u x (1,0,0)
        else:
            ax, ay, az = -uz, 0.0, ux  # u x (0,1,0)
        na = sqrt(ax * ax + ay * ay + az * az)
        ax, ay, az = ax / na, ay / na, az / na
        return (2 * ax * ax - 1, 2 * ax * ay, 2 * ax * az,
                2 * ay * ax, 2 * ay * ay - 1, 2 * ay * az,
                2 * az * ax, 2 * az * ay, 2 * az * az - 1)
    wx = uy * vz - uz * vy
    wy = uz * vx - ux * vz
    wz = ux * vy - uy * vx
    k = 1.0 / (1.0 + c)
    return (c + k * wx * wx, k * wx * wy - wz, k * wx * wz + wy,
            k * wy * wx + wz, c + k * wy * wy, k * wy * wz - wx,
            k * wz * wx - wy, k * wz * wy + wx, c + k * wz * wz)


def mat_vec(R, x, y, z):
    return (R[0] * x + R[1] * y + R[2] * z, R[3] * x + R[4] * y + R[5] * z,
            R[6] * x + R[7] * y + R[8] * z)


def mat_mul(A, B):
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def two_bone_s(hip, knee, ankle, target, pole):
    """Scalar :func:`two_bone_ik` on 3-sequences: ``(knee', ankle', R1, R2)``
    (points as 3-tuples, rotations as row-major 9-tuples)."""
    nk, na = two_bone_points_s(hip, knee, ankle, target, pole)
    return (nk, na) + minimal_turns(hip, knee, ankle, nk, na)


def minimal_turns(hip, knee, ankle, nk, na):
    """The minimal rotations taking the bones (hip→knee, knee→ankle) onto
    (hip→nk, nk→na): the upper bone's, then the lower one's after it."""
    ux, uy, uz = knee[0] - hip[0], knee[1] - hip[1], knee[2] - hip[2]
    lx, ly, lz = ankle[0] - knee[0], ankle[1] - knee[1], ankle[2] - knee[2]
    R1 = rot_between_s(ux, uy, uz, nk[0] - hip[0], nk[1] - hip[1], nk[2] - hip[2])
    rx, ry, rz = mat_vec(R1, lx, ly, lz)
    S = rot_between_s(rx, ry, rz, na[0] - nk[0], na[1] - nk[1], na[2] - nk[2])
    return R1, mat_mul(S, R1)


def two_bone_points_s(hip, knee, ankle, target, pole):
    """The new (knee, ankle) of :func:`two_bone_s`."""
    hx, hy, hz = hip
    kx, ky, kz = knee
    ax, ay, az = ankle
    ux, uy, uz = kx - hx, ky - hy, kz - hz
    lx, ly, lz = ax - kx, ay - ky, az - kz
    l1 = sqrt(ux * ux + uy * uy + uz * uz)
    l2 = sqrt(lx * lx + ly * ly + lz * lz)
    dx, dy, dz = target[0] - hx, target[1] - hy, target[2] - hz
    dist = sqrt(dx * dx + dy * dy + dz * dz)
    if dist > 1e-12:
        nx, ny, nz = dx / dist, dy / dist, dz / dist
    else:
        ox, oy, oz = ax - hx, ay - hy, az - hz
        on = sqrt(ox * ox + oy * oy + oz * oz)
        nx, ny, nz = (ox / on, oy / on, oz / on) if on > 1e-12 else (0.0, -1.0, 0.0)
    lo_, hi_ = abs(l1 - l2), l1 + l2
    D = lo_ if dist < lo_ else (hi_ if dist > hi_ else dist)
    a = (l1 * l1 - l2 * l2 + D * D) / (2.0 * D) if D > 1e-12 else 0.0
    h2 = l1 * l1 - a * a
    h = sqrt(h2) if h2 > 0.0 else 0.0
    # bend direction: pole, else old knee, else any perpendicular
    px, py, pz = pole[0] - hx, pole[1] - hy, pole[2] - hz
    s = px * nx + py * ny + pz * nz
    bx, by, bz = px - s * nx, py - s * ny, pz - s * nz
    bn = sqrt(bx * bx + by * by + bz * bz)
    if bn <= 1e-9:
        s = ux * nx + uy * ny + uz * nz
        bx, by, bz = ux - s * nx, uy - s * ny, uz - s * nz
        bn = sqrt(bx * bx + by * by + bz * bz)
        if bn <= 1e-9:
            ex, ey, ez = (1.0, 0.0, 0.0) if abs(nx) < 0.9 else (0.0, 0.0, 1.0)
            s = ex * nx + ey * ny + ez * nz
            bx, by, bz = ex - s * nx, ey - s * ny, ez - s * nz
            bn = sqrt(bx * bx + by * by + bz * bz)
    bx, by, bz = bx / bn, by / bn, bz / bn
    return ((hx + a * nx + h * bx, hy + a * ny + h * by, hz + a * nz + h * bz),
            (hx + D * nx, hy + D * ny, hz + D * nz))


def smooth01(x):
    if x >= 1.0:
        return 1.0
    if x <= 0.0:
        return 0.0
    return x * x * (3.0 - 2.0 * x)


def rot_scale(D, w):
    """The rotation about the axis of ``D`` by ``w`` times its angle (9-tuples)."""
    vx, vy, vz = D[7] - D[5], D[2] - D[6], D[3] - D[1]  # 2 sin(θ) axis
    s2 = sqrt(vx * vx + vy * vy + vz * vz)
    c = 0.5 * (D[0] + D[4] + D[8] - 1.0)
    th = atan2(0.5 * s2, c)
    if th < 1e-12:
        return I3
    if s2 < 1e-9:  # a half turn: axis from the symmetric part
        m = max(range(3), key=lambda i: D[4 * i])
        col = (D[m] + (m == 0), D[3 + m] + (m == 1), D[6 + m] + (m == 2))
        n = sqrt(col[0] ** 2 + col[1] ** 2 + col[2] ** 2)
        x, y, z = col[0] / n, col[1] / n, col[2] / n
    else:
        x, y, z = vx / s2, vy / s2, vz / s2
    a = w * th
    ca, sa = cos(a), sin(a)
    t = 1.0 - ca
    return (ca + t * x * x, t * x * y - sa * z, t * x * z + sa * y,
            t * y * x + sa * z, ca + t * y * y, t * y * z - sa * x,
            t * z * x - sa * y, t * z * y + sa * x, ca + t * z * z)


def sub3(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def add3(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def about(p, piv, R, new_piv):
    """``new_piv + R (p − piv)``."""
    x, y, z = mat_vec(R, p[0] - piv[0], p[1] - piv[1], p[2] - piv[2])
    return (new_piv[0] + x, new_piv[1] + y, new_piv[2] + z)


def frame_s(ux, uy, uz, nx, ny, nz):
    """Rows of the orthonormal frame (u, n ⟂ u, u × n), or None when degenerate."""
    nu = sqrt(ux * ux + uy * uy + uz * uz)
    if nu < 1e-12:
        return None
    ux, uy, uz = ux / nu, uy / nu, uz / nu
    s = nx * ux + ny * uy + nz * uz
    nx, ny, nz = nx - s * ux, ny - s * uy, nz - s * uz
    nn = sqrt(nx * nx + ny * ny + nz * nz)
    if nn < 1e-12:
        return None
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    return (ux, uy, uz, nx, ny, nz, uy * nz - uz * ny, uz * nx - ux * nz, ux * ny - uy * nx)


def transpose_s(A):
    """The transpose of a 9-tuple matrix."""
    return (A[0], A[3], A[6], A[1], A[4], A[7], A[2], A[5], A[8])


def align_s(F0, F1):
    """The rotation taking frame ``F0`` onto ``F1`` (rows as from :func:`frame_s`): F1ᵀ F0."""
    return mat_mul(transpose_s(F1), F0)


def angle_s(D):
    """The angle (rad) of the rotation ``D`` (9-tuple)."""
    c = 0.5 * (D[0] + D[4] + D[8] - 1.0)
    s = 0.5 * sqrt((D[7] - D[5]) ** 2 + (D[2] - D[6]) ** 2 + (D[3] - D[1]) ** 2)
    return atan2(s, c)


def clip01(x):
    """``np.clip(x, 0.0, 1.0)`` of a float, to the bit (NaN kept, −0.0 to 0.0)."""
    if x > 0.0:
        return x if x < 1.0 else 1.0
    return x if x != x else 0.0


def segments_gap_s(p0, p1, q0, q1):
    """:func:`.representation.segments_gap` of one pair of segments on
    3-sequences, as a 3-tuple: the same products, sums (each dot product
    summed x, y, then z, as numpy sums three numbers) and clamps."""
    ux, uy, uz = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    vx, vy, vz = q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2]
    wx, wy, wz = p0[0] - q0[0], p0[1] - q0[1], p0[2] - q0[2]
    A = ux * ux + uy * uy + uz * uz
    B = ux * vx + uy * vy + uz * vz
    C = vx * vx + vy * vy + vz * vz
    D = ux * wx + uy * wy + uz * wz
    E = vx * wx + vy * wy + vz * wz
    den = A * C - B * B
    s = clip01((B * E - C * D) / max(den, 1e-12)) if den > 1e-12 else 0.0
    t = clip01((B * s + E) / max(C, 1e-12))
    s = clip01((B * t - D) / max(A, 1e-12))
    return ((p0[0] + s * ux) - (q0[0] + t * vx), (p0[1] + s * uy) - (q0[1] + t * vy),
            (p0[2] + s * uz) - (q0[2] + t * vz))
