"""Contact-based foot locking: :class:`FootLocker`, a causal, streaming foot lock
solved with two-bone leg IK, one dancer at a time (paper, appendix "Motion
recovery and visualization"). It uses the scalar kernels of :mod:`.ik`.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import pi, sin, sqrt

import numpy as np

from .features import FPS
from .option_checks import check_range
from .scalar_kernels import I3, mat_vec, rot_between_s, rot_scale, smooth01, two_bone_s
from .skeleton import FEET, JOINT_INDEX

_J = JOINT_INDEX


@dataclass(frozen=True)
class KinematicOptions:
    """Kinematic contact evidence (:class:`KinematicContacts`): a foot point
    within ``height`` metres of its floor and slower than ``speed`` m/s counts
    as planted; its floor is the lowest height seen, rising ``floor_rise``
    metres a frame (2 cm: a point a few centimetres up crossed the line on a
    millimetre of input noise and locked a frame earlier or later;
    docs/experiments.md)."""

    height: float = 0.02
    speed: float = 1.5
    floor_rise: float = 0.001

    def __post_init__(self):
        check_range("KinematicOptions", "height", self.height, 0.0, low_open=True)
        check_range("KinematicOptions", "speed", self.speed, 0.0, low_open=True)
        check_range("KinematicOptions", "floor_rise", self.floor_rise, 0.0)


class KinematicContacts:
    """Contact evidence from the predicted motion itself (causal), one dancer:
    a foot point low above its floor (the lowest height seen lately, rising
    ``floor_rise`` a frame) and slow since the last frame counts as planted,
    whatever the network's contact output says (:class:`KinematicOptions`)."""

    def __init__(self, options: KinematicOptions = KinematicOptions()):
        self.o = options
        self.prev = None  # last frame's four foot points (plain floats)
        self.floor = None  # per foot point, its floor level as seen so far

    def __call__(self, pos) -> np.ndarray:
        """The four foot points' evidence (1 planted, 0 not) of the pose ``pos (31, 3)``."""
        feet = pos.take(FEET, axis=0).tolist()  # four points: plain floats cost less than arrays
        prev, self.prev = self.prev, feet
        floor = self.floor
        if floor is None:
            floor = [y for _, y, _ in feet]
        else:
            rise = self.o.floor_rise
            floor = [min(f + rise, y) for f, (_, y, _) in zip(floor, feet)]
        self.floor = floor
        if prev is None:
            return np.zeros(4)
        out = []
        height, fast = self.o.height, self.o.speed
        for (x, y, z), (px, _, pz), f in zip(feet, prev, floor):
            dx, dz = x - px, z - pz
            speed = sqrt(dx * dx + dz * dz) * FPS
            out.append(1.0 if y - f < height and speed < fast else 0.0)
        return np.array(out)


def _moved2(p, q):
    """Squared horizontal distance of two points (3-sequences)."""
    return (p[0] - q[0]) ** 2 + (p[2] - q[2]) ** 2


class _Side:
    __slots__ = ("on_a", "on_b", "armed_a", "armed_b", "lock_a", "lock_b",
                 "off_t", "off_f", "k", "rb", "lift", "prev", "clear", "need")

    def __init__(self):
        self.on_a = self.on_b = False
        self.armed_a = self.armed_b = True
        self.lock_a = self.lock_b = None  # lock points (3-tuples)
        self.off_t = (0.0, 0.0, 0.0)  # transition offset of the ankle target
        self.off_f = (0.0, 0.0, 0.0)  # transition offset of the foot vector
        self.k = 1 << 30  # frames since the last transition
        self.rb = None  # leg deltas (femur, tibia, foot) being blended out after a release
        self.lift = None  # (planted ankle height, step height, planted ball height) of the catch-up step
        self.prev = None  # last frame's output (ankle, ball) points
        self.clear = 0.0  # the swing clearance's current lift (m)
        self.need = 0.0  # how far the swing clearance raised the ankle on the last frame (m)


@dataclass(frozen=True)
class FootLockOptions:
    """One dancer's foot lock (:class:`FootLocker`, where each option is
    explained). The tracked dancer's are :data:`TRACKED_FOOT_LOCK`; the
    synthesised partner's are ``FollowerOptions.foot_lock``."""

    on: float = 0.6  # a contact point plants above this probability
    off: float = 0.4  # and lifts below this one
    blend_frames: int = 8  # frames every mode change blends over
    max_drift: float = 0.15  # m: a lock lets go when its predicted point is this far from it
    pole_forward: float = 0.1  # m: the knee's pole, along the femur's +Z from the predicted knee
    step_height: float = 0.06  # m: a full release is a catch-up step at least this high
    step_scale: float = 0.3  # its height per metre the foot travels
    step_max: float = 0.12  # m: and at most this high
    step_frames: int | None = None  # frames of a catch-up step (None: blend_frames)
    clearance: float = 0.0  # m: a free foot moving fast is lifted this far off its floor (0: not)
    clear_speed: tuple = (0.3, 0.6)  # m/s: the lift starts at the first speed and is full from the second
    clear_rate: float = 0.25  # the lift changes by at most this share of the clearance a frame
    land_still: bool = False  # a foot that plants stays where it was on the last frame
    lift_ball: bool = False  # the whole foot leaves the floor in a step, its ball too

    def __post_init__(self):
        if not 0.0 <= self.off <= self.on <= 1.0:
            raise ValueError(f"FootLockOptions: need 0 <= off <= on <= 1, not off={self.off!r}, on={self.on!r}")
        bad = [n for n, v in (("blend_frames", self.blend_frames), ("step_frames", self.step_frames))
               if v is not None and not v >= 1]
        bad += [n for n in ("max_drift", "step_height", "step_scale", "step_max", "clearance", "clear_rate")
                if not getattr(self, n) >= 0.0]
        if bad or not self.step_height <= self.step_max or not 0.0 <= self.clear_speed[0] < self.clear_speed[1]:
            raise ValueError(f"FootLockOptions: {', '.join(bad) or 'step_height, step_max or clear_speed'} "
                             f"out of range in {self!r}")


# The tracked dancer's foot lock (chosen on val; figures in models/README.md). Against the
# defaults: a lock holds until its predicted point is 20 cm away, not 15; a release is a catch-up
# step 8-12 cm high that lifts the ball too; a free foot moving fast is lifted 5 cm off its floor
# (on bodies other than the training leader's his feet sit lower against the dancer's own floor).
TRACKED_FOOT_LOCK = FootLockOptions(max_drift=0.2, step_height=0.08, step_max=0.12, clearance=0.05, lift_ball=True)


class FootLocker:
    """Causal, streaming foot locking with two-bone leg IK (one dancer).

    Call :meth:`step` once per frame, in order; :meth:`reset` between takes.

    Per side and per contact point (ankle, ball) a hysteresis switch turns on
    when the contact probability exceeds ``on`` and off when it falls below
    ``off``. A point locks at its current *output* world position when its
    switch turns on (its height clamped to at most ``floor[i]`` when floor
    heights of the four contact points are given; never raised). The side's
    mode follows from which points are locked:

    ======== ============================= ====================================
    locked   ankle target (IK)             foot (lfoot, ltoes) orientation
    ======== ============================= ====================================
    none     predicted ankle               predicted
    ankle    ankle lock point              predicted (translated to the ankle)
    ball     ball lock − (ball − ankle)    predicted (the ball stays put)
    both     ankle lock point              predicted, turned about the ankle
                                           so the ball aims at its lock point
    ======== ============================= ====================================

    The leg (hip = end of ``*hipjoint``, knee = end of ``*femur``, ankle = end
    of ``*tibia``) is solved with :func:`two_bone_ik`, the knee pole being the
    predicted knee pushed ``pole_forward`` metres along the femur's local +Z
    axis (the direction a CMU knee bends towards; this keeps the knee plane
    well defined when the predicted leg is straight but the lock needs it
    bent); the foot's end points move rigidly with the ankle.

    No pops: every mode change starts a blend of ``blend_frames`` frames
    (smoothstep weights). Between locked modes (e.g. heel lifts while the ball
    stays) the jump of the ankle target and foot vector is added as an offset
    that fades out. On a full release (no point locked any more) the leg's
    last IK rotations (femur, tibia, foot) are applied to the prediction and
    scaled back to identity about their axes, so the knee swings back
    smoothly even when the locked leg was stretched straight and the
    prediction is bent.
    A full release is a catch-up *step*, not a slide: while the leg blends
    back, the ankle is kept at least ``step_height · sin(π k / N)`` above its
    planted height (k frames since the release, N = ``step_frames``, by default
    ``blend_frames``; ``step_height`` grows with the
    distance to travel: ``clamp(step_scale · d, step_height, step_max)``), so
    the foot leaves the floor on the first frame and lands on the last,
    instead of skating along it; no point locks while the step is in the air.
    A lock whose predicted point drifts farther than ``max_drift`` (m) from it
    is released; that point can lock again when its contact probability has
    fallen below ``off`` or the release blend is over.
    When the lock point is out of the leg's reach the leg is stretched
    straight towards it (the ankle then misses the lock by the shortfall).

    ``options``: a :class:`FootLockOptions`. Off by default (the partner uses
    them all, see ``FollowerOptions.foot_lock``; the tracked dancer
    ``clearance`` and ``lift_ball``, see :data:`TRACKED_FOOT_LOCK`):
    ``land_still``: a free foot that
    locks stays where it was on the last frame instead of carrying that
    frame's motion into the lock; ``clearance`` (m): a free foot moving
    faster than ``clear_speed[0]`` m/s is lifted off its floor, fully from
    ``clear_speed[1]``, the lift changing by at most ``clear_rate × clearance``
    a frame (see :meth:`_swing`).
    """

    def __init__(self, options: FootLockOptions = FootLockOptions(), floor=None):
        o = options
        self.options = o
        self.on = float(o.on)
        self.off = float(o.off)
        self.blend_frames = max(int(o.blend_frames), 1)
        # the catch-up step's length (frames; None: ``blend_frames``)
        self.step_frames = self.blend_frames if o.step_frames is None else max(int(o.step_frames), 1)
        self.max_drift = float(o.max_drift)
        self.pole_forward = float(o.pole_forward)
        self.step_height, self.step_scale, self.step_max = float(o.step_height), float(o.step_scale), float(o.step_max)
        self.clearance = float(o.clearance)
        self.land_still = bool(o.land_still)
        self.clear_speed = (float(o.clear_speed[0]), float(o.clear_speed[1]))
        self.lift_ball = bool(o.lift_ball)
        self.clear_rate = float(o.clear_rate)  # the swing clearance's lift changes by at most this share a frame
        # each side's last output (ankle, ball) is kept for the options that need its speed
        self._keep_prev = self.clearance > 0.0 or self.land_still
        self.floor = None if floor is None else [float(x) for x in np.asarray(floor).reshape(4)]
        j = _J
        # rows gathered per frame: hip, knee, ankle, ball, toe (left, then right)
        self._rows = np.array([j["lhipjoint"], j["lfemur"], j["ltibia"], j["lfoot"], j["ltoes"],
                               j["rhipjoint"], j["rfemur"], j["rtibia"], j["rfoot"], j["rtoes"]])
        self._femurs = np.array([j["lfemur"], j["rfemur"]])
        # output positions (knee, ankle, ball, toe) = rotations (femur, tibia, foot, toes)
        self._gather = (self._rows[:, None] * 3 + np.arange(3)).ravel()
        self._gather_fwd = (self._femurs[:, None] * 9 + np.array([2, 5, 8])).ravel()
        # scatter indices per (left, right) kind: 0 untouched, 2 femur+tibia rotations,
        # 4 femur+tibia+foot+toes rotations (positions: knee, ankle, ball, toe)
        self._scatter = {}
        legs = [[j[s + "femur"], j[s + "tibia"], j[s + "foot"], j[s + "toes"]] for s in "lr"]
        for kl in (0, 2, 4):
            for kr in (0, 2, 4):
                pj = (legs[0] if kl else []) + (legs[1] if kr else [])
                rj = legs[0][:kl] + legs[1][:kr]
                pflat = (np.array(pj, dtype=np.int64)[:, None] * 3 + np.arange(3)).ravel()
                self._scatter[(kl, kr)] = (pflat, np.array(rj, dtype=np.int64))
        self.reset()

    def reset(self):
        self._sides = (_Side(), _Side())

    @property
    def locks(self):
        """``[(ankle_lock, ball_lock), (…)]`` of the left and right side (3-tuples or None)."""
        return [(s.lock_a, s.lock_b) for s in self._sides]

    @staticmethod
    def _mode(la, lb, a, fx, fy, fz):
        """Raw (unblended) ankle target and foot vector of a lock configuration."""
        if la is not None:
            if lb is not None:
                return la, (lb[0] - la[0], lb[1] - la[1], lb[2] - la[2])
            return la, (fx, fy, fz)
        if lb is not None:
            return (lb[0] - fx, lb[1] - fy, lb[2] - fz), (fx, fy, fz)
        return (a[0], a[1], a[2]), (fx, fy, fz)

    @staticmethod
    def _fk(rows, D1, D2, D3):
        """Leg points (knee, ankle, ball, toe) with deltas applied to the prediction."""
        hip, knee, a, b, toe = rows
        u = mat_vec(D1, knee[0] - hip[0], knee[1] - hip[1], knee[2] - hip[2])
        nk = (hip[0] + u[0], hip[1] + u[1], hip[2] + u[2])
        v = mat_vec(D2, a[0] - knee[0], a[1] - knee[1], a[2] - knee[2])
        na = (nk[0] + v[0], nk[1] + v[1], nk[2] + v[2])
        f = mat_vec(D3, b[0] - a[0], b[1] - a[1], b[2] - a[2])
        g = mat_vec(D3, toe[0] - a[0], toe[1] - a[1], toe[2] - a[2])
        return nk, na, (na[0] + f[0], na[1] + f[1], na[2] + f[2]), (na[0] + g[0], na[1] + g[1], na[2] + g[2])

    def _side(self, st: _Side, rows, ca: float, cb: float, fa, fb, fwd):
        hip, knee, a, b, toe = rows
        fx, fy, fz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        N = self.blend_frames  # a lock's blend
        NS = self.step_frames  # a release's catch-up step
        # hysteresis switches
        if st.on_a:
            if ca < self.off:
                st.on_a = False
        elif ca > self.on:
            st.on_a = True
        # a drift-released point may lock again once its release blend is over
        # (a sliding prediction with a steady contact then gets re-planted): the
        # catch-up step when the whole side is free, the lock's blend otherwise
        if not st.on_a or (st.lock_a is None and st.k >= (NS if st.lock_b is None else N)):
            st.armed_a = True
        if st.on_b:
            if cb < self.off:
                st.on_b = False
        elif cb > self.on:
            st.on_b = True
        if not st.on_b or (st.lock_b is None and st.k >= (NS if st.lock_a is None else N)):
            st.armed_b = True

        la, lb = st.lock_a, st.lock_b
        new_a, new_b = la, lb
        md2 = self.max_drift * self.max_drift
        if la is not None:
            if not st.on_a:
                new_a = None
            elif (a[0] - la[0]) ** 2 + (a[1] - la[1]) ** 2 + (a[2] - la[2]) ** 2 > md2:
                new_a = None
                st.armed_a = False
        if lb is not None:
            if not st.on_b:
                new_b = None
            elif (b[0] - lb[0]) ** 2 + (b[1] - lb[1]) ** 2 + (b[2] - lb[2]) ** 2 > md2:
                new_b = None
                st.armed_b = False
        # no new lock while a catch-up step is in the air: the foot lands first
        stepping = la is None and lb is None and st.lift is not None and st.k < NS
        engage_a = new_a is None and st.on_a and st.armed_a and not stepping
        engage_b = new_b is None and st.on_b and st.armed_b and not stepping
        free_old = la is None and lb is None
        if free_old and st.k >= NS and not (engage_a or engage_b):
            return self._swing(st, rows, fa, fb, fwd)  # free and settled: the prediction (lifted when fast)

        if engage_a or engage_b or new_a is not la or new_b is not lb:
            # a transition: the current output under the old mode is the
            # continuity reference
            Nw = NS if free_old else N
            w = 1.0 - smooth01(st.k / Nw) if st.k < Nw else 0.0
            if free_old:
                if w > 0.0 and st.rb is not None:
                    D1, D2, D3 = (rot_scale(D, w) for D in st.rb)
                    _, T_old, bo, _ = self._fk(rows, D1, D2, D3)
                    F_old = (bo[0] - T_old[0], bo[1] - T_old[1], bo[2] - T_old[2])
                elif self.land_still and st.prev is not None:
                    # a free foot that plants stays where it was on the last frame
                    # (it does not slide the last frame's motion into the lock)
                    pa, pb = st.prev
                    T_old, F_old = tuple(pa), (pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2])
                else:  # (raised by the swing clearance on the last frame, if it was)
                    T_old, F_old = (a[0], a[1] + st.need, a[2]), (fx, fy, fz)
            else:
                T_old, F_old = self._mode(la, lb, a, fx, fy, fz)
                ot, of = st.off_t, st.off_f
                T_old = (T_old[0] + w * ot[0], T_old[1] + w * ot[1], T_old[2] + w * ot[2])
                F_old = (F_old[0] + w * of[0], F_old[1] + w * of[1], F_old[2] + w * of[2])
            if engage_a:
                y = T_old[1] if fa is None else min(T_old[1], fa)
                new_a = (T_old[0], y, T_old[2])
            if engage_b:
                # the output ball: ankle target + foot vector of the predicted length
                fn = sqrt(fx * fx + fy * fy + fz * fz)
                Fn = sqrt(F_old[0] ** 2 + F_old[1] ** 2 + F_old[2] ** 2)
                s = fn / Fn if Fn > 1e-12 else 1.0
                bx, by, bz = T_old[0] + s * F_old[0], T_old[1] + s * F_old[1], T_old[2] + s * F_old[2]
                new_b = (bx, by if fb is None else min(by, fb), bz)
            st.lock_a, st.lock_b = new_a, new_b
            if new_a is not None or new_b is not None:
                st.lift = None
                st.clear = 0.0  # the next swing's clearance rises from the floor
            st.k = 0
            if new_a is None and new_b is None:
                # full release: the old mode's IK on this frame (so the output
                # is continuous), then its deltas blend out in rotation space
                pts, st.rb = self._solve(rows, T_old, F_old, fwd)
                d = sqrt((T_old[0] - a[0]) ** 2 + (T_old[2] - a[2]) ** 2)
                h = min(max(self.step_scale * d, self.step_height), self.step_max)
                # (planted ankle height, step height, the ball's height on this frame)
                st.lift = (T_old[1], h, pts[2][1]) if h > 0.0 else None
            else:
                st.rb = None
                T, F = self._mode(new_a, new_b, a, fx, fy, fz)
                st.off_t = (T_old[0] - T[0], T_old[1] - T[1], T_old[2] - T[2])
                st.off_f = (F_old[0] - F[0], F_old[1] - F[1], F_old[2] - F[2])

        if new_a is None and new_b is None:
            # free, blending the last IK deltas out (rotation space)
            if st.rb is None or st.k >= NS:
                st.k = max(N, NS)
                return None
            st.k += 1
            w = 1.0 - smooth01((st.k - 1) / NS)
            D1, D2, D3 = (rot_scale(D, w) for D in st.rb)
            pts = self._fk(rows, D1, D2, D3)
            if st.lift is not None:
                lift = st.lift[1] * sin(pi * st.k / NS)
                y = st.lift[0] + lift
                na, nb = pts[1], pts[2]
                if self.lift_ball:  # the whole foot leaves the floor: its ball too, however it is turned
                    y = na[1] + max(y - na[1], st.lift[2] + lift - nb[1])
                if na[1] < y:  # lift the ankle (the foot keeps its blended orientation)
                    T = (na[0], y, na[2])
                    pts, (R1, R2, R3) = self._solve(rows, T, (nb[0] - na[0], nb[1] - na[1], nb[2] - na[2]), fwd)
                    return pts, (R1, R2, R3)
            return pts, (D1, D2, D3)

        T, F = self._mode(new_a, new_b, a, fx, fy, fz)
        if st.k < N:
            w = 1.0 - smooth01(st.k / N)
            ot, of = st.off_t, st.off_f
            T = (T[0] + w * ot[0], T[1] + w * ot[1], T[2] + w * ot[2])
            F = (F[0] + w * of[0], F[1] + w * of[1], F[2] + w * of[2])
            st.k += 1

        return self._solve(rows, T, F, fwd)

    def _swing(self, st: _Side, rows, fa, fb, fwd):
        """A free foot (no lock, no catch-up step): the prediction, but a foot
        moving fast is off the floor. Its ankle is lifted so that both foot
        points are ``clearance`` above their floor levels at full speed
        (``clear_speed[1]`` m/s and over), none at ``clear_speed[0]`` and under
        (smoothstep between; the speed is the horizontal one since the last
        output); the lift changes by at most ``clear_rate · clearance`` a frame. None:
        the prediction passes through."""
        c = self.clearance
        st.need = 0.0
        if c <= 0.0 or fa is None or fb is None or st.prev is None:
            st.clear = 0.0
            return None
        a, b = rows[2], rows[3]
        v = FPS * sqrt(max(_moved2(a, st.prev[0]), _moved2(b, st.prev[1])))
        v0, v1 = self.clear_speed
        goal = c * smooth01((v - v0) / max(v1 - v0, 1e-9))
        r = self.clear_rate * c
        h = st.clear + min(max(goal - st.clear, -r), r)
        st.clear = h
        need = max(fa + h - a[1], fb + h - b[1])
        if h <= 0.0 or need <= 0.0:
            return None
        st.need = need
        return self._solve(rows, (a[0], a[1] + need, a[2]), (b[0] - a[0], b[1] - a[1], b[2] - a[2]), fwd)

    def _solve(self, rows, T, F, fwd):
        """Leg IK to the ankle target ``T`` and foot vector ``F``: the new
        (knee, ankle, ball, toe) and deltas (femur, tibia, foot)."""
        hip, knee, a, b, toe = rows
        fx, fy, fz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        pf = self.pole_forward
        pole = (knee[0] + pf * fwd[0], knee[1] + pf * fwd[1], knee[2] + pf * fwd[2])
        nk, na, R1, R2 = two_bone_s(hip, knee, a, T, pole)
        if F[0] == fx and F[1] == fy and F[2] == fz:
            R3 = I3
            ball = (na[0] + fx, na[1] + fy, na[2] + fz)
            toe_ = (na[0] + toe[0] - a[0], na[1] + toe[1] - a[1], na[2] + toe[2] - a[2])
        else:
            R3 = rot_between_s(fx, fy, fz, F[0], F[1], F[2])
            bb = mat_vec(R3, fx, fy, fz)
            tt = mat_vec(R3, toe[0] - a[0], toe[1] - a[1], toe[2] - a[2])
            ball = (na[0] + bb[0], na[1] + bb[1], na[2] + bb[2])
            toe_ = (na[0] + tt[0], na[1] + tt[1], na[2] + tt[2])
        return (nk, na, ball, toe_), (R1, R2, R3)

    def step(self, positions, rotations, contacts):
        """One frame: ``positions (31, 3)``, ``rotations (31, 3, 3)``, ``contacts (4,)``
        (probabilities of left ankle, left ball, right ankle, right ball).
        Returns new ``(positions, rotations)`` arrays (the inputs are not modified)."""
        P = np.array(positions, dtype=np.float64)
        R = np.array(rotations, dtype=np.float64)
        c = np.asarray(contacts, dtype=np.float64).tolist()
        g = P.reshape(-1)[self._gather].tolist()
        fwd = R.reshape(-1)[self._gather_fwd].tolist()  # knee-forward axes (femur local +Z)
        fl = self.floor or (None, None, None, None)
        res_l = self._side(self._sides[0], (g[0:3], g[3:6], g[6:9], g[9:12], g[12:15]),
                           c[0], c[1], fl[0], fl[1], fwd[0:3])
        res_r = self._side(self._sides[1], (g[15:18], g[18:21], g[21:24], g[24:27], g[27:30]),
                           c[2], c[3], fl[2], fl[3], fwd[3:6])
        if self._keep_prev:
            for side, res, o in ((self._sides[0], res_l, 0), (self._sides[1], res_r, 15)):
                side.prev = (g[o + 6:o + 9], g[o + 9:o + 12]) if res is None else (res[0][1], res[0][2])
        if res_l is None and res_r is None:
            return P, R
        pts, rots, key = (), (), ()
        for side, res in ((0, res_l), (1, res_r)):
            if res is None:
                key += (0,)
                continue
            k, n, b_, t_ = res[0]
            pts += k + n + b_ + t_
            R1, R2, R3 = res[1]
            if R3 is I3:
                rots += R1 + R2
                key += (2,)
            else:
                rots += R1 + R2 + R3 + R3
                key += (4,)
        pidx, ridx = self._scatter[key]
        P.reshape(-1)[pidx] = pts
        R[ridx] = np.matmul(np.array(rots).reshape(-1, 3, 3), R[ridx])
        return P, R

    def run(self, positions, rotations, contacts):
        """Convenience: :meth:`step` over a whole clip ``(T, …)`` (causal)."""
        outP = np.empty(np.shape(positions))
        outR = np.empty(np.shape(rotations))
        for t in range(len(outP)):
            outP[t], outR[t] = self.step(positions[t], rotations[t], contacts[t])
        return outP, outR
