"""Pose recovery post-processing (paper, appendix "Motion recovery and visualization").

The networks predict, per frame, world joint positions ``(31, 3)`` (SPEC §2: the
*end* of each ASF bone) and global bone rotations ``(31, 3, 3)``
independently. This module turns them into what a user sees:

* :func:`bone_transforms` combines both into one rigid transform per bone (for
  skinning): bone ``n`` is rotated by ``R_n`` and placed at its start, the
  position of its parent joint (the root bone at ``positions[0]``).
* :class:`~.foot_lock.FootLocker` (in ``foot_lock``) removes residual foot sliding with the predicted foot
  contacts: a causal, streaming foot lock solved with two-bone leg IK.
* :class:`EndEffectorIK` (optional "hand/head IK") pulls the leader's head and
  wrists onto the tracked three-point signal, and the follower's wrists onto
  the leader's hands in a hold. Its arms swing about the shoulder and bend as
  a hinge (``arm="swing"``), so a forearm does not spin about itself when a
  target pulls the wrist across.
* :class:`ArmTurnLimit` (stateful) lets an arm bone turn at most so far a
  frame relative to the chest: where a hold's target passes the shoulder, the
  arm swings over in a few frames instead of flipping in one.

Every IK step edits positions and rotations *consistently*: when a bone's
direction changes by a rotation ``D``, its global rotation becomes ``D · R``.
Bone lengths of the input positions are preserved (except for the optional
spine stretch of :class:`EndEffectorIK`, see there).

The per-frame classes work on Python floats for the handful of 3-vectors they
touch (the kernels of :mod:`.scalar_kernels`): numpy's per-call overhead
(~1 µs) would dominate such tiny problems. :func:`two_bone_ik` is the
vectorised numpy version of their two-bone solver.
"""
from __future__ import annotations

from itertools import chain
from math import cos, isfinite, radians, sqrt

import numpy as np

from .representation import cross, vector_norm
from .scalar_kernels import (about, add3, align_s, angle_s, frame_s, mat_mul, minimal_turns, rot_between_s,
                             rot_scale, smooth01, sub3, transpose_s, two_bone_points_s, two_bone_s)
from .skeleton import JOINT_INDEX, PARENTS

__all__ = [
    "rotation_between", "two_bone_ik", "bone_transforms", "transforms_to_matrices", "EndEffectorIK", "smoothstep",
    "ArmTurnLimit",
]

_J = JOINT_INDEX


# ---------------------------------------------------------------------------
# vectorised helpers


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The minimal rotation ``(…, 3, 3)`` taking direction ``u`` to direction ``v``.

    ``R = c·I + [w]× + w wᵀ / (1 + c)`` with ``w = û × v̂``, ``c = û · v̂``.
    Opposite directions give a half turn about an axis perpendicular to ``u``;
    a zero vector gives the identity.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.shape != v.shape:
        u, v = np.broadcast_arrays(u, v)
    nu = vector_norm(u, keepdims=True)
    nv = vector_norm(v, keepdims=True)
    ok = (nu[..., 0] > 1e-12) & (nv[..., 0] > 1e-12)
    u = u / np.where(nu > 1e-12, nu, 1.0)
    v = v / np.where(nv > 1e-12, nv, 1.0)
    c = np.add.reduce(u * v, axis=-1)  # (np.sum's arithmetic)
    w = cross(u, v)
    opposite = 1.0 + c < 1e-12
    k = 1.0 / np.where(opposite, 1.0, 1.0 + c)
    R = k[..., None, None] * w[..., :, None] * w[..., None, :]
    R[..., 0, 0] += c
    R[..., 1, 1] += c
    R[..., 2, 2] += c
    R[..., 0, 1] -= w[..., 2]
    R[..., 0, 2] += w[..., 1]
    R[..., 1, 0] += w[..., 2]
    R[..., 1, 2] -= w[..., 0]
    R[..., 2, 0] -= w[..., 1]
    R[..., 2, 1] += w[..., 0]
    if opposite.any():
        # half turn about an axis perpendicular to u
        e = np.where(np.abs(u[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
        a = np.cross(u, e)
        with np.errstate(invalid="ignore"):  # (a zero u's row, not opposite, is not used)
            a /= vector_norm(a, keepdims=True)
        half = 2.0 * a[..., :, None] * a[..., None, :] - np.eye(3)
        R = np.where(opposite[..., None, None], half, R)
    return np.where(ok[..., None, None], R, np.eye(3))


def _perp_unit(d: np.ndarray, n: np.ndarray) -> tuple:
    """Component of ``d`` perpendicular to the unit ``n``, normalised; and its norm."""
    p = d - np.add.reduce(d * n, axis=-1, keepdims=True) * n  # (np.sum's arithmetic)
    pn = vector_norm(p, keepdims=True)
    return p / np.where(pn > 1e-12, pn, 1.0), pn[..., 0]


def two_bone_ik(hip, knee, ankle, target, pole=None):
    """Analytic two-bone IK, vectorised over any leading axes (all inputs ``(…, 3)``).

    Returns ``(knee', ankle', R_upper, R_lower)``:

    * the lengths ``|hip − knee|`` and ``|knee − ankle|`` are kept;
    * ``ankle'`` is at ``target`` when it is reachable, else as close as the
      chain allows on the line hip → target (straight leg when too far,
      folded when too near);
    * ``knee'`` lies in the plane of (hip, target, pole), on the pole's side
      (``pole`` defaults to the old knee; degenerate poles fall back to the old
      knee, then to any perpendicular);
    * ``R_upper`` takes the old upper direction ``knee − hip`` to the new one;
      ``R_lower`` takes the old lower direction ``ankle − knee`` to the new one
      and equals ``S · R_upper`` with ``S`` the minimal rotation that remains,
      so the lower bone's twist follows the upper one's. Update global bone
      rotations by left-multiplying: ``R_femur ← R_upper · R_femur``.
    """
    hip = np.asarray(hip, dtype=np.float64)
    knee = np.asarray(knee, dtype=np.float64)
    ankle = np.asarray(ankle, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    pole = knee if pole is None else np.asarray(pole, dtype=np.float64)
    if not hip.shape == knee.shape == ankle.shape == target.shape == pole.shape:
        hip, knee, ankle, target, pole = np.broadcast_arrays(hip, knee, ankle, target, pole)
    up = knee - hip
    lo = ankle - knee
    l1 = vector_norm(up)
    l2 = vector_norm(lo)
    d = target - hip
    dist = vector_norm(d)
    # direction hip -> target (fallback: the old ankle direction, then straight down)
    old = ankle - hip
    on = vector_norm(old)
    n = np.where((dist > 1e-12)[..., None], d / np.maximum(dist, 1e-300)[..., None],
                 np.where((on > 1e-12)[..., None], old / np.maximum(on, 1e-300)[..., None],
                          np.array([0.0, -1.0, 0.0])))
    D = np.clip(dist, np.abs(l1 - l2), l1 + l2)
    Dd = np.maximum(D, 1e-12)
    a = (l1 * l1 - l2 * l2 + D * D) / (2.0 * Dd)
    h = np.sqrt(np.maximum(l1 * l1 - a * a, 0.0))
    b, bn = _perp_unit(pole - hip, n)
    b2, bn2 = _perp_unit(up, n)
    b = np.where((bn > 1e-9)[..., None], b, b2)
    bad = (bn <= 1e-9) & (bn2 <= 1e-9)
    if bad.any():
        e = np.where(np.abs(n[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
        b3, _ = _perp_unit(e, n)
        b = np.where(bad[..., None], b3, b)
    new_knee = hip + a[..., None] * n + h[..., None] * b
    new_ankle = hip + D[..., None] * n
    R1 = rotation_between(up, new_knee - hip)
    S = rotation_between(np.einsum("...ij,...j->...i", R1, lo), new_ankle - new_knee)
    R2 = S @ R1
    return new_knee, new_ankle, R1, R2


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# ---------------------------------------------------------------------------
# rigid per-bone transforms (for skinning)


def bone_transforms(positions: np.ndarray, rotations: np.ndarray, rest_start: np.ndarray,
                    parents: np.ndarray = PARENTS):
    """Per-bone rigid transforms from predicted positions and rotations.

    ``positions (…, J, 3)``, ``rotations (…, J, 3, 3)``, ``rest_start (J, 3)``
    (:func:`~.skeleton.rest_starts`). Returns ``(R, t)`` with ``R = rotations`` and
    ``t (…, J, 3)`` such that a rest-pose point ``p`` of bone ``n`` goes to
    ``R_n p + t_n = R_n (p − rest_start_n) + start_n``, where ``start_n`` is the
    position of the parent joint (``positions[0]`` for the root).
    """
    positions = np.asarray(positions, dtype=np.float64)
    R = np.asarray(rotations, dtype=np.float64)
    idx = np.where(parents < 0, 0, parents)
    start = positions[..., idx, :]
    t = start - np.einsum("...jab,jb->...ja", R, np.asarray(rest_start, dtype=np.float64))
    return R, t


def transforms_to_matrices(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(R, t)`` to homogeneous ``(…, 4, 4)`` matrices."""
    M = np.zeros(R.shape[:-2] + (4, 4))
    M[..., :3, :3] = R
    M[..., :3, 3] = t
    M[..., 3, 3] = 1.0
    return M


# ---------------------------------------------------------------------------
# end-effector IK (head and wrists on the tracked points)


def _hinge_turns(sh, el, wr, nel, nwr, straight=0.05):
    """The turns of a two-bone arm as a hinge: each bone's rotation takes its
    old (direction, bend-plane normal) frame onto the new one, so the elbow's
    normal is carried over and the forearm's roll follows the upper arm's —
    a minimal rotation of the forearm alone is ill-defined when it has to turn
    by nearly half a turn, and flips. An arm (old or new) straighter than
    ``straight`` (sine of the elbow angle) turns by the minimal rotations
    (:func:`minimal_turns`)."""
    u, f = sub3(el, sh), sub3(wr, el)
    u2, f2 = sub3(nel, sh), sub3(nwr, nel)
    n = (u[1] * f[2] - u[2] * f[1], u[2] * f[0] - u[0] * f[2], u[0] * f[1] - u[1] * f[0])
    n2 = (u2[1] * f2[2] - u2[2] * f2[1], u2[2] * f2[0] - u2[0] * f2[2], u2[0] * f2[1] - u2[1] * f2[0])
    lu = sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2) * sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
    nn = sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
    nn2 = sqrt(n2[0] ** 2 + n2[1] ** 2 + n2[2] ** 2)
    if lu >= 1e-12 and nn >= straight * lu and nn2 >= straight * lu:
        Fu, Fu2 = frame_s(*u, *n), frame_s(*u2, *n2)
        Fl, Fl2 = frame_s(*f, *n), frame_s(*f2, *n2)
        if Fu is not None and Fu2 is not None and Fl is not None and Fl2 is not None:
            return align_s(Fu, Fu2), align_s(Fl, Fl2)
    return minimal_turns(sh, el, wr, nel, nwr)


class EndEffectorIK:
    """Pull the tracked points (SPEC §2: end of ``upperneck``, ``lwrist``,
    ``rwrist``) onto target positions, frame by frame (stateless).

    Order: the head first (it may move the shoulders), then each arm.

    *Head.* The neck piece (``lowerneck`` + ``upperneck``) turns rigidly about
    its base (the end of ``thorax``) by the minimal rotation that aims its end
    at the head target. Optionally (``lean`` in [0, 1], default 0) a fraction
    of that aim is first taken by a rigid lean of the whole upper body about
    the root. What is left lies along the neck (the target is nearer or
    farther than the neck reaches): it is taken up by stretching/compressing
    the spine — the ends of ``lowerback``, ``upperback`` and ``thorax`` move by
    1/3, 2/3 and 3/3 of it and everything above translates with the thorax —
    limited to ``max_stretch`` metres, so each spine bone's length changes by
    at most a third of that; every other bone keeps its length. The ``head``
    bone keeps its predicted global orientation (the head device measures it)
    and follows the neck's end.

    *Arms.* Two-bone IK from the shoulder (end of ``*clavicle``) over the elbow
    (end of ``*humerus``) to the wrist (end of ``*wrist``); the forearm is
    ``*radius`` and ``*wrist`` as one rigid piece, the pole the predicted
    elbow (``arm="pole"``, the default). With ``arm="swing"`` the whole arm
    first swings about the shoulder towards the target and the bones then
    turn as a hinge, keeping the arm's bend plane (see ``_swing_hinge``): the
    pole method turns the forearm by its own minimal rotation, which flips
    when the forearm has to turn by nearly half a turn (a hand hold pulling the
    wrist across). When the target is beyond ``reach`` × the arm's length, the
    clavicle first turns about its start (two-bone IK of the clavicle and the
    stretched arm) to bring the shoulder closer. The hand, fingers and thumb
    move rigidly with the forearm.

    A target containing NaN (lost tracking) leaves that chain unchanged.
    """

    _FIRST = _J["lowerback"]  # joints lowerback..rthumb (11..30) are the upper body

    def __init__(self, lean: float = 0.0, max_stretch: float = 0.08, reach: float = 0.999,
                 arm: str = "pole"):
        if arm not in ("pole", "swing"):
            raise ValueError(f"EndEffectorIK: arm must be 'pole' or 'swing', not {arm!r}")
        self.arm = arm
        self.lean = float(lean)
        self.max_stretch = float(max_stretch)
        self.reach = float(reach)
        o = self._FIRST
        j = {n: i - o for n, i in _J.items() if i >= o}  # local indices into the upper body
        self._j = j
        self._above_thorax = [i for i in range(31 - o)
                              if i not in (j["lowerback"], j["upperback"], j["thorax"])]
        self._arms = [(j[s + "clavicle"], j[s + "humerus"],
                       (j[s + "radius"], j[s + "wrist"], j[s + "hand"], j[s + "fingers"], j[s + "thumb"]))
                      for s in "lr"]

    def step(self, positions, rotations, targets):
        """``positions (31, 3)``, ``rotations (31, 3, 3)``, ``targets (3, 3)``:
        world positions of the head (end of upperneck), left wrist, right wrist.
        Returns new ``(positions, rotations)`` arrays."""
        P = np.array(positions, dtype=np.float64)
        R = np.array(rotations, dtype=np.float64)
        tg = np.asarray(targets, dtype=np.float64).tolist()
        ok = [isfinite(x) and isfinite(y) and isfinite(z) for x, y, z in tg]
        if not any(ok):
            return P, R
        o = self._FIRST
        pts = P[o:].tolist()
        delta = {}
        if ok[0]:
            self._solve_head(pts, P[0].tolist(), delta, tg[0])
        for side in (0, 1):
            if ok[1 + side]:
                self._solve_arm(pts, delta, self._arms[side], tg[1 + side])
        # back to arrays (fromiter: cheaper than numpy parsing nested sequences)
        P[o:] = np.fromiter(chain.from_iterable(pts), np.float64, 3 * len(pts)).reshape(-1, 3)
        if delta:
            bones = [b + o for b in delta]
            D = np.fromiter(chain.from_iterable(delta.values()), np.float64, 9 * len(delta)).reshape(-1, 3, 3)
            R[bones] = np.matmul(D, R.take(bones, axis=0))
        return P, R

    @staticmethod
    def _compose(delta, b, D):
        """Left-multiply bone ``b``'s accumulated delta by ``D``."""
        old = delta.get(b)
        delta[b] = D if old is None else mat_mul(D, old)

    def _solve_head(self, pts, root, delta, target):
        j = self._j
        LB, UB, TH, LN, UN, HD = (j["lowerback"], j["upperback"], j["thorax"],
                                  j["lowerneck"], j["upperneck"], j["head"])
        if self.lean > 0.0:
            Q = rot_between_s(*sub3(pts[UN], root), *sub3(target, root))
            if self.lean < 1.0:
                Q = rot_scale(Q, self.lean)
            head_vec = sub3(pts[HD], pts[UN])
            for i in range(len(pts)):
                pts[i] = about(pts[i], root, Q, root)
                if i != HD:
                    delta[i] = Q
            pts[HD] = add3(pts[UN], head_vec)
        n0, ln, un, hd = pts[TH], pts[LN], pts[UN], pts[HD]
        D = rot_between_s(*sub3(un, n0), *sub3(target, n0))
        ln2 = about(ln, n0, D, n0)
        un2 = about(un, n0, D, n0)
        ex, ey, ez = sub3(target, un2)
        en = sqrt(ex * ex + ey * ey + ez * ez)
        if en > self.max_stretch:
            f = self.max_stretch / en
            ex, ey, ez = ex * f, ey * f, ez * f
        self._compose(delta, LN, D)
        self._compose(delta, UN, D)
        if en > 1e-12:
            # the rest of the error lies along the neck: stretch the spine
            if ex or ey or ez:  # (nothing to move with max_stretch=0)
                for i in self._above_thorax:
                    p = pts[i]
                    pts[i] = (p[0] + ex, p[1] + ey, p[2] + ez)
            lb, ub, th = pts[LB], pts[UB], pts[TH]
            lb2 = (lb[0] + ex / 3.0, lb[1] + ey / 3.0, lb[2] + ez / 3.0)
            ub2 = (ub[0] + 2.0 * ex / 3.0, ub[1] + 2.0 * ey / 3.0, ub[2] + 2.0 * ez / 3.0)
            th2 = (th[0] + ex, th[1] + ey, th[2] + ez)
            self._compose(delta, LB, rot_between_s(*sub3(lb, root), *sub3(lb2, root)))
            self._compose(delta, UB, rot_between_s(*sub3(ub, lb), *sub3(ub2, lb2)))
            self._compose(delta, TH, rot_between_s(*sub3(th, ub), *sub3(th2, ub2)))
            pts[LB], pts[UB], pts[TH] = lb2, ub2, th2
        e = (ex, ey, ez)
        pts[LN] = add3(ln2, e)
        pts[UN] = add3(un2, e)
        pts[HD] = add3(pts[UN], sub3(hd, un))

    SWING_LO, SWING_HI = 0.2, 0.4
    SWING_COS_ON, SWING_COS_OFF = cos(radians(120.0)), cos(radians(160.0))

    @classmethod
    def _swing_hinge(cls, sh, el, wr, target):
        """Swing the whole arm about the shoulder by a fraction of the minimal
        rotation aiming its shoulder→wrist line at the target — all of it when
        the wrist is at least 40 % of the arm from the shoulder and the swing
        is at most 120°; none when the wrist is under 20 % (a folded arm,
        where that line's direction is ill-defined) or the swing 160° or more
        (where its axis is) — then two-bone IK from the swung arm with its
        elbow as the pole, each bone turning as a hinge (:func:`_hinge_turns`)."""
        u, f, w = sub3(el, sh), sub3(wr, el), sub3(wr, sh)
        arm = sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2) + sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
        wn = sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
        beta = smooth01((wn / max(arm, 1e-12) - cls.SWING_LO) / (cls.SWING_HI - cls.SWING_LO))
        d = sub3(target, sh)
        dn = sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        if beta > 0.0 and dn > 1e-12:
            # a swing of nearly half a turn has an ill-defined axis: fade it out
            c = (w[0] * d[0] + w[1] * d[1] + w[2] * d[2]) / (wn * dn)
            beta *= smooth01((c - cls.SWING_COS_OFF) / (cls.SWING_COS_ON - cls.SWING_COS_OFF))
        if beta > 0.0:
            Q = rot_between_s(*w, *d)
            if beta < 1.0:
                Q = rot_scale(Q, beta)
            el = about(el, sh, Q, sh)
            wr = about(wr, sh, Q, sh)
        nel, nwr = two_bone_points_s(sh, el, wr, target, el)
        R1, R2 = _hinge_turns(sh, el, wr, nel, nwr)
        if beta > 0.0:
            R1, R2 = mat_mul(R1, Q), mat_mul(R2, Q)
        return nel, nwr, R1, R2

    def _solve_arm(self, pts, delta, arm, target):
        clav, hum, rigid = arm
        n0 = pts[self._j["thorax"]]
        sh, el, wr = pts[clav], pts[hum], pts[rigid[1]]
        l1 = sqrt((el[0] - sh[0]) ** 2 + (el[1] - sh[1]) ** 2 + (el[2] - sh[2]) ** 2)
        l2 = sqrt((wr[0] - el[0]) ** 2 + (wr[1] - el[1]) ** 2 + (wr[2] - el[2]) ** 2)
        reach = self.reach * (l1 + l2)
        d = sub3(target, sh)
        dist = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if dist > reach:
            # turn the clavicle so that the shoulder comes within reach: two-bone
            # IK of (clavicle, straight arm of length `reach`) from the clavicle
            # start to the target, the old shoulder as pole
            f = reach / dist
            tip = (sh[0] + d[0] * f, sh[1] + d[1] * f, sh[2] + d[2] * f)
            nsh, _, Rc, _ = two_bone_s(n0, sh, tip, target, sh)
            for i in (hum,) + rigid:
                pts[i] = about(pts[i], sh, Rc, nsh)
                self._compose(delta, i, Rc)
            self._compose(delta, clav, Rc)
            pts[clav] = sh = nsh
            el, wr = pts[hum], pts[rigid[1]]
        if self.arm == "swing":
            nel, nwr, R1, R2 = self._swing_hinge(sh, el, wr, target)
        else:
            nel, nwr, R1, R2 = two_bone_s(sh, el, wr, target, el)
        for i in rigid:
            pts[i] = about(pts[i], el, R2, nel)
            self._compose(delta, i, R2)
        pts[rigid[1]] = nwr  # exact (the rigid move puts it there up to rounding)
        pts[hum] = nel
        self._compose(delta, hum, R1)


class ArmTurnLimit:
    """Each arm's upper arm and forearm turn by at most ``max_turn`` degrees a
    frame relative to the thorax (stateful, per dancer; call :meth:`reset` at a
    take's start).

    A hand hold's target passing close to the shoulder swings the shoulder→
    target line through large angles in a frame, and any stateless two-bone
    solution then jumps between the arm's two ways of folding (a 130° forearm
    turn in one frame). This limit is the arm's speed, not a clamp on where it
    goes: a bone that would turn farther turns ``max_turn`` towards the new
    pose along the shortest rotation, and reaches it a few frames later (the
    hold's wrist lags its target meanwhile). The default, 30°, is the fastest
    relative turn of any arm bone in the salsa train frames (both dancers: 99.99th
    percentile 23–27°, the largest 30–44°), so real-speed arm motion passes
    untouched. ``engaged`` counts the frames on which it acted."""

    def __init__(self, max_turn: float = 30.0):
        self.max = radians(float(max_turn))
        self._th = _J["thorax"]
        self._arms = [(_J[s + "clavicle"], _J[s + "humerus"],
                       (_J[s + "radius"], _J[s + "wrist"], _J[s + "hand"], _J[s + "fingers"], _J[s + "thumb"]))
                      for s in "lr"]
        self.reset()

    def reset(self):
        self._prev = [None, None]
        self.engaged = 0

    def step(self, positions, rotations):
        """``positions (31, 3)``, ``rotations (31, 3, 3)`` (world); returns them,
        edited in place where a bone turned too fast."""
        C = tuple(rotations[self._th].ravel().tolist())
        Ct = transpose_s(C)
        lim = self.max
        acted = False
        for side, (clav, hum, rigid) in enumerate(self._arms):
            Rh = tuple(rotations[hum].ravel().tolist())
            Rf = tuple(rotations[rigid[0]].ravel().tolist())
            rh, rf = mat_mul(Ct, Rh), mat_mul(Ct, Rf)
            prev = self._prev[side]
            if prev is not None:
                ph, pf = prev
                D = mat_mul(rh, transpose_s(ph))
                th = angle_s(D)
                if th > lim:  # the upper arm (and the forearm with it) turns lim towards its new pose
                    rh2 = mat_mul(rot_scale(D, lim / th), ph)
                    E = mat_mul(C, mat_mul(rh2, mat_mul(transpose_s(rh), Ct)))
                    self._turn(positions, rotations, (hum,) + rigid, E, positions[clav].tolist())
                    rh, rf = rh2, mat_mul(Ct, mat_mul(E, Rf))
                    acted = True
                D = mat_mul(rf, transpose_s(pf))
                th = angle_s(D)
                if th > lim:  # the forearm turns lim towards its new pose about the elbow
                    rf2 = mat_mul(rot_scale(D, lim / th), pf)
                    E = mat_mul(C, mat_mul(rf2, mat_mul(transpose_s(rf), Ct)))
                    self._turn(positions, rotations, rigid, E, positions[hum].tolist())
                    rf = rf2
                    acted = True
            self._prev[side] = (rh, rf)
        self.engaged += acted
        return positions, rotations

    @staticmethod
    def _turn(positions, rotations, bones, E, piv):
        """Turn ``bones`` (their end points and rotations) by ``E`` about ``piv``."""
        Em = np.array(E).reshape(3, 3)
        idx = list(bones)
        positions[idx] = (positions[idx] - piv) @ Em.T + piv
        rotations[idx] = np.matmul(Em, rotations[idx])
