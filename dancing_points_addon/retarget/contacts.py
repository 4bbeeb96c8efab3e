"""Foot contacts of the source and the foot locks on the target.

Foot points planted on the source (SPEC §6 contact: < 6 cm above their floor
level and slower than 0.30 m/s, :func:`detect_contacts`; and within 2 cm of
where the contact began, :func:`planted`) are locked on the target with
two-bone leg IK (:func:`..ik.two_bone_ik`, ``Retargeter.lock_feet``) where they
were on the contact's first frame (never below the target's own floor level,
:func:`foot_targets`); the lock fades out over a few frames after the contact
(as a safety net, a lock is also released when the unlocked point drifts more
than 30 cm away from it). Where a locked leg is too short for its lock, the
pelvis is lowered (by at most 6 % of the leg length, :func:`reach_drop`,
smoothed by :func:`smooth_max`).
"""
from __future__ import annotations

import numpy as np

from ..ik import smoothstep
from ..representation import CONTACT_HEIGHT, CONTACT_SPEED, floor_levels, foot_speeds
from .source import UP


def detect_contacts(points, fps=30.0, up=2, height=CONTACT_HEIGHT, speed=CONTACT_SPEED, floor=None):
    """Contacts ``(T, K)`` of foot points ``(T, K, 3)`` by the SPEC §6 rule
    (:func:`~.representation.contact_labels`: < ``height`` above the point's
    floor level, 5th percentile of its height or ``floor``; slower than
    ``speed`` m/s), with the speed relaxed to the slower of the two steps
    around a frame, so a planted foot's first and last frames count.
    ``up``: the up axis (2 for Blender space)."""
    p = np.asarray(points, dtype=np.float64)
    h = p[..., up]
    lvl = floor_levels(h) if floor is None else np.asarray(floor, dtype=np.float64)
    v = foot_speeds(p, fps)
    if len(p) > 2:
        v[1:-1] = np.minimum(v[1:-1], v[2:])  # either neighbouring step slow
    return (h - lvl < height) & (v < speed)


def planted(contacts, points, tol=0.02):
    """Contacts ``(T, K)`` reduced to where each point is planted: a contact run
    ends (for the rest of it) once the point ``(T, K, 3)`` has moved more than
    ``tol`` (m, horizontally) from where the run began — a foot pivoting on the
    other point or gliding along the floor is low and slow, but not planted."""
    c = np.array(contacts, dtype=bool)
    p = np.asarray(points, dtype=np.float64)
    for k in range(c.shape[1]):
        t = 0
        while t < len(c):
            if not c[t, k]:
                t += 1
                continue
            s = t
            while t < len(c) and c[t, k]:
                t += 1
            moved = np.linalg.norm(p[s:t, k, :2] - p[s, k, :2], axis=-1) > tol
            if moved.any():
                c[s + int(np.argmax(moved)):t, k] = False
    return c


def reach_drop(hip, target, reach, most):
    """How far ``(T,)`` the hip must go down (at most ``most``) for ``target`` to
    lie within ``reach`` of it: 0 where it already does, and where lowering the
    hip cannot help (the target horizontally out of reach)."""
    d = target - hip
    h2 = np.sum(d[:, :2] ** 2, axis=-1)
    v = -d[:, 2]  # how far the target lies below the hip
    fit = np.sqrt(np.maximum(reach * reach - h2, 0.0))
    return np.where(h2 < reach * reach, np.clip(v - fit, 0.0, most), 0.0)


def smooth_max(x, w):
    """A smooth envelope of ``x (T,)`` that is at least ``x`` everywhere: the
    running maximum over ±w frames, then its running mean over ±w frames."""
    T = len(x)
    pad = np.pad(x, w, mode="edge")
    mx = np.max(np.stack([pad[j:j + T] for j in range(2 * w + 1)]), axis=0)
    pad = np.pad(mx, w, mode="edge")
    return np.mean(np.stack([pad[j:j + T] for j in range(2 * w + 1)]), axis=0)


def foot_targets(A, B, on_a, on_b, floor_a, floor_b, blend, max_drift=0.30):
    """Ankle targets ``(T, 3)``, foot vectors ``(T, 3)`` (ankle -> ball) and the
    frames to solve ``(T,)`` of one foot, from its unlocked ankle and ball
    ``A``, ``B (T, 3)`` and their contacts ``on_a``, ``on_b (T,)``.

    A point locks where it actually is when its contact starts (derived from the
    other point's lock when that one is already locked, so nothing jumps;
    otherwise lifted to its floor level if it is below it) and holds to the end
    of the contact. Then the offset between the lock and the unlocked point (on the
    last locked frame) fades out over ``blend`` frames: the foot moves on with
    the motion. A lock is
    released early when the unlocked point drifts farther than ``max_drift`` (m,
    horizontally) from it; that point then stays free until its contact ends.
    A locked ball has priority: the ankle turns about it (heel lifts);
    otherwise the ankle leads and the ball follows the foot's own orientation,
    pulled to its lock."""
    T = len(A)
    Fv = B - A
    flen = np.linalg.norm(Fv, axis=-1)
    ankle_t = A.copy()
    foot = Fv.copy()
    act = np.zeros(T, dtype=bool)
    pts = {"a": A, "b": B}
    # per point: lock point, frames since release (0: locked), armed, offset at release
    st = {"a": [None, 0, True, None], "b": [None, 0, True, None]}
    fade = [float(smoothstep(1.0 - j / (blend + 1))) for j in range(1, blend + 1)]

    def weight(k):
        p, j = st[k][0], st[k][1]
        if p is None:
            return 0.0
        return 1.0 if j == 0 else (fade[j - 1] if j <= blend else 0.0)

    def lock(k, t):
        p, j, _, off = st[k]
        return p if j == 0 else pts[k][t] + off

    for t in range(T):
        for k, on in (("a", on_a[t]), ("b", on_b[t])):
            p, j, armed, off = st[k]
            pt = pts[k][t]
            if p is not None and j == 0:  # locked: end of contact, or drifted away
                if not on or np.hypot(*(pt[:2] - p[:2])) > max_drift:
                    # fade out the lock's offset from the unlocked point as it was while
                    # locked (the last locked frame), not the lift-off's motion
                    st[k] = [p, 1, not on, p - pts[k][max(t - 1, 0)]]
            elif p is not None:  # fading out
                st[k] = [p, j + 1, armed or not on, off] if j < blend else [None, 0, armed or not on, None]
            else:
                st[k][2] = armed or not on
        starts = [k for k, on in (("a", on_a[t]), ("b", on_b[t])) if on and st[k][2] and not (
            st[k][0] is not None and st[k][1] == 0)]
        wa, wb = weight("a"), weight("b")
        for k in sorted(starts):  # the ankle first
            # Where the point actually is: derived from the other point's lock when
            # that one leads the foot (as it is: no jump), else its own position,
            # lifted to its floor level if it is below.
            if k == "a":
                if "b" not in starts and wb == 1.0:  # the ball leads
                    p = st["b"][0] - Fv[t]
                elif "b" in starts:  # both at once: the foot as it is, lifted out of the floor
                    p = A[t] + max(0.0, floor_a - A[t, 2], floor_b - B[t, 2]) * UP
                else:
                    p = A[t].copy()
                    p[2] = max(p[2], floor_a)
            else:
                if "a" in starts:  # both at once: the ball at the foot's length from the ankle's lock
                    p = st["a"][0] + Fv[t]
                elif wa > 0.0:  # the ankle leads
                    p = A[t] + wa * (lock("a", t) - A[t]) + Fv[t]
                else:
                    p = B[t].copy()
                    p[2] = max(p[2], floor_b)
            st[k] = [p, 0, True, None]
        wa, wb = weight("a"), weight("b")
        if wa == 0.0 and wb == 0.0:
            continue
        act[t] = True
        la = lock("a", t) if wa > 0 else A[t]
        if wb == 1.0:
            lb = st["b"][0]
            d = (1.0 - wa) * Fv[t] + wa * (lb - la)
            d = d / max(np.linalg.norm(d), 1e-12) * flen[t]
            ankle_t[t], foot[t] = lb - d, d
        else:
            at = A[t] + wa * (la - A[t])
            bt = at + Fv[t]
            if wb > 0.0:
                bt = bt + wb * (lock("b", t) - bt)
            d = bt - at
            ankle_t[t], foot[t] = at, d / max(np.linalg.norm(d), 1e-12) * flen[t]
    return ankle_t, foot, act
