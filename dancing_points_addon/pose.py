"""Pose recovery (paper Appendix B): one rigid transform per bone from the
network's independently predicted joint positions and rotations.

The predicted positions give each bone's direction, the skeleton gives its
length; rotations are turned minimally so that ``R · rest bone vector`` lands
exactly on the recovered bone. The result is a consistent skeleton pose: bone
lengths exact, every bone's end on its joint, ready for skinning or baking.

:class:`LegJoints` puts a pose's legs back on the joints the CMU skeleton
has (hip joints rigid with the pelvis, each leg bone's twist limited): the
follower's legs, pulled towards the pose anchor's, need it.
"""
from __future__ import annotations

from itertools import chain
from math import atan2, cos, sin, sqrt

import numpy as np

from .ik import two_bone_ik
from .representation import dot3, norm, rot6d_to_matrix
from .scalar_kernels import mat_mul, two_bone_s
from .skeleton import HIPS, JOINT_INDEX, LOWER_BODY, PARENTS, joint_block, joint_rows

N = len(PARENTS)
# ANCESTORS[n, k] = 1 when bone k lies on the chain from the root to bone n (k != root)
ANCESTORS = np.zeros((N, N))
for _n in range(1, N):
    _k = _n
    while _k > 0:
        ANCESTORS[_n, _k] = 1.0
        _k = PARENTS[_k]
_PAR = np.maximum(PARENTS, 0)
_PARENT = PARENTS.tolist()
_EYE_COL = np.eye(3)[:, :, None]


def joints_from_rotations(root, rotations, bone_vectors) -> np.ndarray:
    """Forward kinematics: joint positions ``(…, 31, 3)`` of global bone
    rotations ``(…, 31, 3, 3)`` on a skeleton's rest ``bone_vectors (31, 3)``,
    the root at ``root (…, 3)``."""
    bones = (rotations @ bone_vectors[:, :, None])[..., 0]
    bones[..., 0, :] = 0.0
    return np.asarray(root)[..., None, :] + ANCESTORS @ bones


def bone_vectors_from_pose(positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Rest bone vectors ``(31, 3)`` of a skeleton from one consistent posed frame
    (``posed bone vector = R · rest bone vector``)."""
    vec = positions - positions[_PAR]
    vec[0] = 0.0
    return np.einsum("nba,nb->na", rotations, vec)


def _align(u, v):
    """Rotations ``(…, 3, 3)`` taking unit vectors ``u`` to ``v`` by the shortest arc,
    as two reflections: across the plane normal to ``u + v`` (u -> −v), then
    across the plane normal to ``v`` (−v -> v). Undefined only for ``u = −v``."""
    w = u + v
    ww = 2.0 / np.maximum(np.einsum("...i,...i->...", w, w), 1e-12)
    hw = np.eye(3) - (w[..., :, None] * w[..., None, :]) * ww[..., None, None]
    hv = np.eye(3) - 2.0 * (v[..., :, None] * v[..., None, :])
    return hv @ hw


class PoseRecovery:
    """:func:`recover_pose` for one skeleton, with its constants precomputed
    (the runtime calls it once per dancer and frame)."""

    def __init__(self, bone_vectors: np.ndarray):
        self.bone_vectors = np.asarray(bone_vectors, dtype=np.float64)
        self.lengths = norm(self.bone_vectors)
        self.rest_dir = self.bone_vectors / np.maximum(self.lengths[:, None], 1e-12)
        self._rest_col = self.rest_dir[:, :, None]

    def __call__(self, positions: np.ndarray, rotations: np.ndarray):
        if positions.ndim == 2:
            return self._one(positions, rotations)
        d = positions - positions[..., _PAR, :]
        n = norm(d)[..., None]
        # Direction from positions; a collapsed bone falls back on its rotation.
        rot_dir = (rotations @ self.rest_dir[:, :, None])[..., 0]
        dirs = np.where(n > 1e-6, d / np.maximum(n, 1e-12), rot_dir)
        dirs[..., 0, :] = 0.0
        out_pos = positions[..., :1, :] + ANCESTORS @ (dirs * self.lengths[:, None])
        out_rot = rotations.copy()
        out_rot[..., 1:, :, :] = _align(rot_dir[..., 1:, :], dirs[..., 1:, :]) @ rotations[..., 1:, :, :]
        return out_pos, out_rot

    def _one(self, positions, rotations):
        """:meth:`__call__` for one frame ``(31, 3)``, ``(31, 3, 3)``
        (:func:`_recover_rows`)."""
        p, r = _recover_rows(positions[None], rotations[None], self.lengths[None], self._rest_col[None])
        return p[0], r[0]


class Recoveries:
    """Each skeleton's :class:`PoseRecovery` (``recoveries``) of one pose per
    skeleton, all in one pass (the frame loop's two dancers): ``positions
    (D, 31, 3)``, ``rotations (D, 31, 3, 3)`` in, each pose's bits as its own
    skeleton's recovery gives them (:func:`_recover_rows`)."""

    def __init__(self, recoveries):
        self.recoveries = tuple(recoveries)
        self.lengths = np.stack([r.lengths for r in self.recoveries])
        self._rest_col = np.stack([r._rest_col for r in self.recoveries])

    def __call__(self, positions: np.ndarray, rotations: np.ndarray):
        return _recover_rows(positions, rotations, self.lengths, self._rest_col)


def _recover_rows(positions, rotations, lengths, rest_col):
    """:meth:`PoseRecovery.__call__` of poses ``(D, 31, 3)``, ``(D, 31, 3, 3)``,
    each on its own skeleton (``lengths (D, 31)``, rest directions as columns
    ``rest_col (D, 31, 3, 1)``): the same arithmetic on component-major rows
    ``(D, 3, 31)`` (fewer, cheaper numpy calls); each pose's matrix products
    stay the same BLAS calls on the same layouts, whatever ``D``."""
    p = np.ascontiguousarray(positions.transpose(0, 2, 1))
    d = p - p.take(_PAR, axis=2)  # (take: cheaper than fancy indexing)
    dc = d.swapaxes(0, 1)  # (component first, for dot3)
    n = np.sqrt(dot3(dc, dc))[:, None]
    rot_dir = np.ascontiguousarray((rotations @ rest_col)[..., 0].transpose(0, 2, 1))
    dirs = d / np.maximum(n, 1e-12)
    if not n[:, :, 1:].min() > 1e-6:  # a collapsed (or NaN) bone, rare: its rotation's direction
        dirs = np.where(n > 1e-6, dirs, rot_dir)
    dirs[:, :, 0] = 0.0
    out_pos = positions[:, :1] + ANCESTORS @ (dirs * lengths[:, None]).transpose(0, 2, 1)
    # _align(rot_dir, dirs): hv @ hw, both h = I − k·u uᵀ built at once from
    # rows (u, k) = (w, ww) and (v, 2), then laid out C-ordered (D, 30, 3, 3)
    # like the batched code's, so the products take the same BLAS path.
    u = np.empty((2, len(p), 3, N - 1))
    w = np.add(rot_dir[:, :, 1:], dirs[:, :, 1:], out=u[0])
    u[1] = dirs[:, :, 1:]
    outer = u[:, :, :, None] * u[:, :, None, :]  # (2, D, 3, 3, 30): u_i u_j
    wc = w.swapaxes(0, 1)
    outer[0] *= (2.0 / np.maximum(dot3(wc, wc), 1e-12))[:, None, None]
    outer[1] *= 2.0
    hv_hw = np.empty((2, len(p), N - 1, 3, 3))
    np.subtract(_EYE_COL, outer, out=hv_hw.transpose(0, 1, 3, 4, 2))
    out_rot = rotations.copy()
    out_rot[:, 1:] = hv_hw[1] @ hv_hw[0] @ rotations[:, 1:]
    return out_pos, out_rot


def recover_pose(positions: np.ndarray, rotations: np.ndarray, bone_vectors: np.ndarray):
    """Consistent pose ``(…, 31, 3)``, ``(…, 31, 3, 3)`` from network outputs."""
    return PoseRecovery(bone_vectors)(positions, rotations)


# Her legs' joints as the CMU skeleton has them (``LegJoints``): the hip joint
# bone has no degree of freedom (it turns with the pelvis), the shin and toes no
# twist (a hinge each); the thigh's and foot's twist is limited to the
# follower's range in the salsa train frames (0.1 to 99.9 percentiles: thigh
# -43..43 degrees, foot -32..44), rounded out.
LEG_CHAINS = (LOWER_BODY[:5].tolist(), LOWER_BODY[5:].tolist())  # hip joint, thigh, shin, foot, toes; left, right
LEG_TWIST_DEG = (0.0, 45.0, 0.0, 40.0, 0.0)  # per bone of a chain, both sides
_HIP_ROWS, _LEG_ROWS = joint_rows(HIPS), tuple(joint_block(c) for c in LEG_CHAINS)  # (slices: views)


class LegJoints:
    """Puts a pose's legs back on the joints the skeleton has (in place, per
    frame): each hip joint rigid with the pelvis (its leg moved with it) and
    each leg bone's twist about itself, relative to its parent, within
    ``LEG_TWIST_DEG``. A pose whose leg positions were pulled from outside
    (``PoseOptions.anchor``) is re-aligned by minimal rotations, and
    minimal rotations composed frame after frame let a bone's twist drift (her
    thigh 50 degrees off her pelvis at the median, 130 at the 99th percentile,
    on the sample take): the skin at her hips stretched."""

    def __init__(self, bone_vectors):
        bv = np.asarray(bone_vectors, dtype=np.float64)
        self.bone_vectors = bv
        self.rest_dir = (bv / np.maximum(norm(bv)[:, None], 1e-12)).tolist()
        self.limits = np.radians(LEG_TWIST_DEG).tolist()
        self._hip_vectors = bv[list(HIPS)]

    def __call__(self, positions, rotations):
        return self.twist(*self.hips(positions, rotations))

    def twist(self, positions, rotations, limits=None):
        """Each leg bone's twist within ``LEG_TWIST_DEG`` (or ``limits``, radians
        per bone of a chain; no joint moves)."""
        clamp_twist(rotations, self.rest_dir, LEG_CHAINS[0], LEG_CHAINS[1], self.limits if limits is None else limits)
        return positions, rotations

    def hips(self, positions, rotations):
        """Each hip joint rigid with the pelvis, its leg moved with it."""
        hips, (left, right) = _HIP_ROWS, _LEG_ROWS
        shift = positions[0] + self._hip_vectors @ rotations[0].T - positions[hips]
        positions[left] += shift[0]
        positions[right] += shift[1]
        rotations[hips] = rotations[0]
        return positions, rotations


def clamp_twist(rotations, rest_dir, left, right, limits):
    """Limit each bone's twist (its turn about its own axis, relative to its
    parent) to ``limits`` radians (one per position in the chains), in place;
    the bones' directions, and so the positions, do not change. ``left``,
    ``right``: two chains of bones, each bone after its parent. Per frame, on
    Python floats (a handful of 3 × 3 products: numpy's per-call cost would
    dominate)."""
    bones = (*left, *right)
    top = max(bones) + 1
    R = rotations.reshape(-1, 9)[:top].tolist()  # every bone up to the last (a parent comes before its child)
    changed = False
    for b, lim in zip(bones, (*limits, *limits)):
        P = R[_PARENT[b]]
        C = R[b]
        # M = Pᵀ C: its trace and antisymmetric part give the relative rotation's quaternion
        tr = (P[0] * C[0] + P[1] * C[1] + P[2] * C[2] + P[3] * C[3] + P[4] * C[4] + P[5] * C[5]
              + P[6] * C[6] + P[7] * C[7] + P[8] * C[8])
        m21 = P[2] * C[1] + P[5] * C[4] + P[8] * C[7] - (P[1] * C[2] + P[4] * C[5] + P[7] * C[8])
        m02 = P[0] * C[2] + P[3] * C[5] + P[6] * C[8] - (P[2] * C[0] + P[5] * C[3] + P[8] * C[6])
        m10 = P[1] * C[0] + P[4] * C[3] + P[7] * C[6] - (P[0] * C[1] + P[3] * C[4] + P[6] * C[7])
        w = 0.5 * sqrt(max(1.0 + tr, 1e-12))
        ax, ay, az = rest_dir[b]
        th = 2.0 * atan2((m21 * ax + m02 * ay + m10 * az) / (4.0 * w), w)
        d = min(max(th, -lim), lim) - th
        if d == 0.0:
            continue
        # C · (the rotation about a by d): Rodrigues, I + s K + (1 − c) K², K = [a]ₓ
        s, t = sin(d), 1.0 - cos(d)
        D = (1.0 + t * (ax * ax - 1.0), t * ax * ay - s * az, t * ax * az + s * ay,
             t * ax * ay + s * az, 1.0 + t * (ay * ay - 1.0), t * ay * az - s * ax,
             t * ax * az - s * ay, t * ay * az + s * ax, 1.0 + t * (az * az - 1.0))
        R[b] = (C[0] * D[0] + C[1] * D[3] + C[2] * D[6], C[0] * D[1] + C[1] * D[4] + C[2] * D[7],
                C[0] * D[2] + C[1] * D[5] + C[2] * D[8],
                C[3] * D[0] + C[4] * D[3] + C[5] * D[6], C[3] * D[1] + C[4] * D[4] + C[5] * D[7],
                C[3] * D[2] + C[4] * D[5] + C[5] * D[8],
                C[6] * D[0] + C[7] * D[3] + C[8] * D[6], C[6] * D[1] + C[7] * D[4] + C[8] * D[7],
                C[6] * D[2] + C[7] * D[5] + C[8] * D[8])
        changed = True
    if changed:  # the chains' rows back (unchanged ones as they were), through fromiter: cheaper than nested lists
        lo = min(bones)
        rotations[lo:top] = np.fromiter(chain.from_iterable(R[lo:top]), np.float64, 9 * (top - lo)).reshape(-1, 3, 3)
    return rotations


def move_keeping_feet(positions, rotations, shift):
    """The pose ``(31, 3)``, ``(31, 3, 3)`` moved by ``shift`` (3,) with its
    ankles left where they were: each leg's thigh and shin turned (two-bone IK
    from the hip) to reach its old ankle, the foot carried by what is left
    where that is out of reach. New arrays; every bone keeps its length."""
    old = positions
    positions = positions + np.asarray(shift, dtype=np.float64)
    rotations = rotations.copy()
    rows = rotations.reshape(-1, 9)
    for leg in _LEG_ROWS:  # on Python floats (two_bone_s): a handful of products; each leg read, written once
        (hip, k, a, foot, toes), (r_femur, r_tibia) = positions[leg].tolist(), rows[leg][1:3].tolist()
        knee, ankle, r1, r2 = two_bone_s(hip, k, a, old[leg.start + 2].tolist(), k)
        dx, dy, dz = ankle[0] - a[0], ankle[1] - a[1], ankle[2] - a[2]
        positions[leg.start + 1:leg.stop] = (knee, ankle, (foot[0] + dx, foot[1] + dy, foot[2] + dz),
                                             (toes[0] + dx, toes[1] + dy, toes[2] + dz))
        rows[leg.start + 1:leg.start + 3] = mat_mul(r1, r_femur), mat_mul(r2, r_tibia)
    return positions, rotations


# A foot point may sink at most this far below its floor level (its height
# standing, the contact network's ``floor_levels``) before its leg is bent to
# lift it: the feet never go through the floor.
FLOOR_MARGIN = 0.025


class FloorGuard:
    """Keep a pose's feet on or above the floor (in place, per frame): where
    the ankle, the ball or the toe tip of a leg is lower than its floor level
    (``levels``: ankle, ball, ankle, ball, as the contact points) less
    ``margin``, the leg's knee bends (two-bone IK from the hip) to lift the
    ankle by the deficit; the foot moves with it, unturned."""

    def __init__(self, levels, margin: float = FLOOR_MARGIN):
        lv = [float(v) - margin for v in levels]
        J = JOINT_INDEX
        self.legs = [((J[s + "hipjoint"], J[s + "femur"], J[s + "tibia"], J[s + "foot"], J[s + "toes"]),
                      (lv[2 * i], lv[2 * i + 1])) for i, s in enumerate("lr")]

    def __call__(self, positions, rotations):
        for (hip, femur, tibia, foot, toes), (la, lb) in self.legs:
            ya, yb, yt = positions[tibia, 1], positions[foot, 1], positions[toes, 1]
            lift = max(la - ya, lb - yb, lb - yt)
            if not lift > 0.0:
                continue
            ankle = positions[tibia]
            knee, new_ankle, r1, r2 = two_bone_ik(positions[hip], positions[femur], ankle, ankle + (0.0, lift, 0.0))
            move = new_ankle - ankle
            positions[femur], positions[tibia] = knee, new_ankle
            positions[[foot, toes]] += move
            rotations[femur] = r1 @ rotations[femur]
            rotations[tibia] = r2 @ rotations[tibia]
        return positions, rotations


class OutputSmoothing:
    """A causal low-pass on one dancer's output pose (its tracker state is
    left alone): each frame keeps the share ``keep`` of the last output, of
    the root's position and of every bone's rotation (the blend taken back to
    a rotation, Gram-Schmidt on its columns); the joints then follow from the
    skeleton (``bone_vectors``, forward kinematics), so the pose stays on it.
    A pose that stays, stays (a planted foot does not slide); motion lags by
    ``keep / (1 − keep)`` frames."""

    def __init__(self, keep: float, bone_vectors: np.ndarray):
        if not 0.0 <= keep < 1.0:
            raise ValueError(f"the smoothing's kept share must be within 0..1 (1 excluded), not {keep!r}")
        self.keep = float(keep)
        self.bone_vectors = np.asarray(bone_vectors, dtype=np.float64)
        self.reset()

    def reset(self):
        self._prev = None

    def __call__(self, positions, rotations):
        if self.keep == 0.0:
            return positions, rotations
        if self._prev is not None:
            a, b = self.keep, 1.0 - self.keep
            pp, pr = self._prev
            m = a * pr + b * rotations
            rotations = rot6d_to_matrix(np.concatenate([m[:, :, 0], m[:, :, 1]], axis=-1))  # columns 0, 1
            positions = joints_from_rotations(a * pp[0] + b * positions[0], rotations, self.bone_vectors)
        self._prev = (positions.copy(), rotations.copy())
        return positions, rotations
