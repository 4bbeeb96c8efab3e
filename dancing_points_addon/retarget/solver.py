"""The solver: :class:`Retargeter` turns the source dancer's motion into world
matrices of the target rig's bones (one cohesive class; foot locks in
``contacts``, hand holds between two dancers in ``holds``).

Rest-pose alignment (once per pair of rigs)
    For each mapped target bone, the segment it covers (its head to the head of
    the bone that continues the chain) is matched with the source segment of
    its chain: both get a frame from the segment direction and a secondary axis
    (the body's forward direction, or up for bones that point forward such as
    feet), and ``A = F_source · F_targetᵀ`` turns the target's reference pose
    into the source's rest pose. T-pose vs A-pose, bone rolls, bone axes and the
    rig's facing all end up in ``A``. A posed frame is then
    ``Q(t) = G(t) · A · Q_ref`` where ``G(t)`` is the source bone's world
    rotation relative to its rest (SPEC §2 global rotation), corrected by the
    smallest turn that puts the segment exactly on the source segment's
    direction (a target bone spanning several source bones).

Proportions
    Target positions come from forward kinematics of the target's own bone
    lengths. The pelvis (the midpoint of the hip joints) follows the source's,
    horizontally about the duet's centre (:func:`.source.duet_origin`) by the
    ratio of the head-point heights (the rigs' sizes), vertically above the
    floor by ``k`` = target leg length / source leg length (thigh + shin; each
    rig's ankle height above its floor kept). The ankles are put horizontally
    where the source's are relative to the pelvis, scaled by the height ratio
    (leg IK at the FK ankle's height), so the stride keeps the dancer's size.
    Planted feet are locked (:mod:`.contacts`). The head point and the wrists
    are then pulled to where the source's are relative to the pelvis, scaled by
    the ratio of the head-point heights: the spine and neck lean rigidly about
    the spine's base, the arms by two-bone IK (as far as they reach).

:class:`Retargeter` aligns the pair of rigs and solves each frame; the steps on
one frame's pose of the target rig (FK, feet, lean, reach) are its base,
:class:`~.steps.RigSteps`; what stands apart lives beside it (``contacts``,
``holds``, ``source``, ``mapping``, ``rig``).
"""
from __future__ import annotations

import numpy as np

from .. import blender_math as bm
from ..ik import rotation_between
from ..rotations import matrix_to_quat, quat_slerp, quat_to_matrix
from ..skeleton import FEET, JOINT_INDEX, JOINT_NAMES, PARENTS, rest_joints
from .contacts import detect_contacts, planted
from .mapping import ROOT_CHAIN, SIDES, parse_chain, validate_mapping
from .rig import TargetRig
from .steps import RigSteps
from .source import SRC_FWD, SRC_LEFT, UP, hip_midpoint, source_frame, source_world


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def _frame(d, s):
    """Rotation ``(3, 3)`` with columns (d, s⊥, d × s⊥)."""
    x = _unit(d)
    y = s - np.dot(s, x) * x
    y = _unit(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def _body_frame(left, up):
    """Columns (left, up, forward = left × up)."""
    x = _unit(left - np.dot(left, up) * up)
    return np.stack([x, up, np.cross(x, up)], axis=1)


class _Pose:
    """A retargeted clip: world linear parts of the mapped bones, the root head,
    the source-driven rotations G (for poles), and the world matrices."""

    def __init__(self, lin, root_head, G, W):
        self.lin, self.root_head, self.G, self.W = lin, root_head, G, W


class Retargeter(RigSteps):
    """Source (SPEC skeleton with ``bone_vectors``) -> ``target`` (:class:`TargetRig`)
    with ``mapping`` {target bone: source chain}. Alignment, proportions and the
    segment bookkeeping are computed here, once."""

    def __init__(self, bone_vectors, target: TargetRig, mapping: dict, foot_lock: bool = True,
                 blend_frames: int = 6, match_hands: bool = True, match_head: bool = True,
                 match_feet: bool = True, max_drift: float = 0.30, max_step_deg: float = 60.0, max_drop: float = 0.06,
                 rigid=()):
        """``rigid``: groups of target bone names (consecutive segments of one
        chain) that move as one bone: the segments of a limb that a rig bends only
        as a whole (a generated Rigify rig's ``DEF-forearm.L`` and
        ``DEF-forearm.L.001``, driven by one ``forearm_fk.L``), which would
        otherwise each follow their own part of the source's chain and bend
        where the rig's controls cannot."""
        self.target = target
        self.max_drift = float(max_drift)
        self.max_drop = float(max_drop)
        self.max_step_deg = float(max_step_deg)
        self.mapping = validate_mapping(mapping, target.names)
        self.foot_lock = bool(foot_lock)
        self.match_hands = bool(match_hands)
        self.match_head = bool(match_head)
        self.match_feet = bool(match_feet)
        self.blend_frames = max(int(blend_frames), 1)
        self.bv = np.asarray(bone_vectors, dtype=np.float64)
        self.src_rest = bm.to_blender(rest_joints(self.bv))  # (31, 3) source armature, Blender axes
        tgt = target
        heads = tgt.heads()
        # Groups of target bones sharing a chain, ordered root-most first.
        groups = {}
        for name, chain in self.mapping.items():
            groups.setdefault(chain, []).append(tgt.index[name])
        for chain in groups:
            groups[chain].sort(key=lambda b: (tgt.depth[b], b))
        self.groups = groups
        self.root_bone = groups[ROOT_CHAIN][0]
        # Which bone covers which source bone (for the IK chains and landmarks).
        self.by_source = {}
        for chain, bones in groups.items():
            for s in (parse_chain(chain) if chain != ROOT_CHAIN else [0]):
                self.by_source.setdefault(JOINT_NAMES[s], bones)
        # Target body frame from its reference pose.
        hip_l, hip_r = self._hip_joint(heads, "l"), self._hip_joint(heads, "r")
        self.tgt_body = _body_frame(hip_l - hip_r, UP)
        self.src_body = _body_frame(SRC_LEFT, UP)
        # Per mapped bone: source polyline, fractions, twist bone, alignment.
        self.seg = {}
        for chain, bones in groups.items():
            if chain == ROOT_CHAIN:
                b = bones[0]
                self.seg[b] = dict(chain=[0], f0=0.0, f1=0.0, twist=0,
                                   A=self.src_body @ self.tgt_body.T)
                for extra in bones[1:]:
                    self.seg[extra] = dict(self.seg[b])
                continue
            src = parse_chain(chain)
            pts_idx = [int(PARENTS[src[0]])] + src  # polyline vertices (joint ends)
            poly = self.src_rest[pts_idx]
            seglen = np.linalg.norm(np.diff(poly, axis=0), axis=-1)
            s_cum = np.concatenate([[0.0], np.cumsum(seglen)])
            s_cum = s_cum / max(s_cum[-1], 1e-12)
            ends = [self._end_point(b, bones, chain) for b in bones]
            lens = np.array([np.linalg.norm(e - heads[b]) for b, e in zip(bones, ends)])
            f = np.concatenate([[0.0], np.cumsum(lens)]) / max(lens.sum(), 1e-12)
            for i, b in enumerate(bones):
                f0, f1 = float(f[i]), float(f[i + 1])
                mid = 0.5 * (f0 + f1)
                k = int(np.clip(np.searchsorted(s_cum, mid, side="right") - 1, 0, len(src) - 1))
                d_src = interp_poly(poly[None], s_cum, f1)[0] - interp_poly(poly[None], s_cum, f0)[0]
                d_tgt = ends[i] - heads[b]
                if np.linalg.norm(d_src) < 1e-9 or np.linalg.norm(d_tgt) < 1e-9:
                    A = self.src_body @ self.tgt_body.T
                else:
                    ds, dt = _unit(d_src), _unit(d_tgt)
                    use_up = abs(np.dot(ds, SRC_FWD)) > 0.7 or abs(np.dot(dt, self.tgt_body[:, 2])) > 0.7
                    A = _frame(ds, UP if use_up else SRC_FWD) @ _frame(dt, UP if use_up else self.tgt_body[:, 2]).T
                self.seg[b] = dict(chain=pts_idx, s=s_cum, f0=f0, f1=f1, twist=src[k], A=A,
                                   d_rest=_unit(d_src))
            for group in rigid:  # segments moving as one: the span of the whole group, one twist
                members = [tgt.index[n] for n in group if n in tgt.index and tgt.index[n] in bones]
                if len(members) < 2:
                    continue
                f0, f1 = min(self.seg[b]["f0"] for b in members), max(self.seg[b]["f1"] for b in members)
                k = int(np.clip(np.searchsorted(s_cum, 0.5 * (f0 + f1), side="right") - 1, 0, len(src) - 1))
                d_src = interp_poly(poly[None], s_cum, f1)[0] - interp_poly(poly[None], s_cum, f0)[0]
                for b in members:
                    d_tgt = ends[bones.index(b)] - heads[b]
                    sg = self.seg[b]
                    if np.linalg.norm(d_src) > 1e-9 and np.linalg.norm(d_tgt) > 1e-9:
                        ds, dt = _unit(d_src), _unit(d_tgt)
                        use_up = abs(np.dot(ds, SRC_FWD)) > 0.7 or abs(np.dot(dt, self.tgt_body[:, 2])) > 0.7
                        sg["A"] = _frame(ds, UP if use_up else SRC_FWD) @ _frame(dt, UP if use_up else
                                                                                 self.tgt_body[:, 2]).T
                        sg["d_rest"] = ds
                    sg.update(f0=f0, f1=f1, twist=src[k])
        # Proportions: leg lengths (thigh + shin), ankle heights.
        lt = [self._leg_length_target(heads, s) for s in SIDES]
        ls = [self._src_leg(s) for s in SIDES]
        self.scale = float(np.mean(lt) / np.mean(ls))
        self.tgt_anchor0 = 0.5 * (hip_l + hip_r)
        ground = tgt.ground()
        self.ground = ground
        self.tgt_foot_height = {}
        for side in SIDES:
            a, b = self._foot_points_ref(heads, side)
            self.tgt_foot_height[side + "ankle"] = float(a[2] - ground) if a is not None else None
            self.tgt_foot_height[side + "ball"] = float(b[2] - ground) if b is not None else None
        self.height = self._rig_height(heads)

    # -- reference-pose helpers ------------------------------------------------
    def _src_leg(self, side):
        """Source thigh + shin length of ``side``."""
        return float(sum(np.linalg.norm(self.bv[JOINT_INDEX[side + n]]) for n in ("femur", "tibia")))

    def _bones_of(self, spec_name):
        return self.by_source.get(spec_name)

    def _hip_joint(self, heads, side):
        bones = self._bones_of(side + "femur")
        return heads[bones[0]]

    def _knee_bone(self, side):
        return self._bones_of(side + "tibia")[0]

    def _leg_length_target(self, heads, side):
        hip = heads[self._bones_of(side + "femur")[0]]
        knee = heads[self._knee_bone(side)]
        foot = self._bones_of(side + "foot")
        if foot is not None:
            ankle = heads[foot[0]]
        else:
            bones = self.groups[self.mapping[self.target.names[self._knee_bone(side)]]]
            ankle = self._end_point(bones[-1], bones, self.mapping[self.target.names[bones[-1]]])
        return float(np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee))

    def _foot_points_ref(self, heads, side):
        foot = self._bones_of(side + "foot")
        toe = self._bones_of(side + "toes")
        a = heads[foot[0]] if foot is not None else None
        if toe is not None:
            b = heads[toe[0]]
        elif foot is not None:
            b = self._end_point(foot[-1], foot, self.mapping[self.target.names[foot[-1]]])
        else:
            b = None
        return a, b

    def _rig_height(self, heads):
        """Height of the head point (the skull base, SPEC §2's tracked head: the
        head bone's start) above the floor, in the reference pose."""
        head = self._bones_of("head")
        if head is not None:
            return float(heads[head[0], 2] - self.ground)
        neck = self._bones_of("upperneck")
        b = neck[-1]
        return float(self._end_point(b, neck, self.mapping[self.target.names[b]])[2] - self.ground)

    def source_height(self, ankle_height):
        """The source's head-point height standing straight: ``ankle_height`` (its
        ankles' floor level) + leg length + rest height of the skull base above the hip joints."""
        r = self.src_rest
        hip = hip_midpoint(r)
        legs = np.mean([self._src_leg(s) for s in SIDES])
        return float(ankle_height + legs + r[JOINT_INDEX["upperneck"], 2] - hip[2])

    def _end_point(self, b, bones, chain):
        """World reference point where target bone ``b``'s segment ends."""
        tgt = self.target
        heads = tgt.heads()
        i = bones.index(b)
        if i + 1 < len(bones):
            return heads[bones[i + 1]]
        last = parse_chain(chain)[-1] if chain != ROOT_CHAIN else 0
        kids = [c for c in range(len(tgt.names)) if tgt.parents[c] == b]
        # a child (or deeper descendant) continuing the chain: prefer the lowest SPEC index
        best = None
        stack = list(kids)
        while stack:
            c = stack.pop()
            cname = tgt.names[c]
            if cname in self.mapping and self.mapping[cname] != ROOT_CHAIN:
                first = parse_chain(self.mapping[cname])[0]
                if PARENTS[first] == last and (best is None or first < best[0]):
                    best = (first, c)
            else:
                stack.extend(x for x in range(len(tgt.names)) if tgt.parents[x] == c)
        if best is not None:
            return heads[best[1]]
        if kids:
            axis = _unit(tgt.tails()[b] - heads[b])
            proj = [float(np.dot(heads[c] - heads[b], axis)) for c in kids]
            c = kids[int(np.argmax(proj))]
            if proj[int(np.argmax(proj))] > 1e-6:
                return heads[c]
        return tgt.tails()[b]

    # -- solving -----------------------------------------------------------------
    def solve(self, positions, rotations, source_matrix=None, contacts=None, fps=30.0, origin=None):
        """Retarget a clip: SPEC ``positions (T, 31, 3)`` and ``rotations (T, 31, 3, 3)``
        (motion space) of the source armature placed at ``source_matrix``.
        ``contacts (T, 4)`` (bool, SPEC §2 foot points) default to :func:`detect_contacts`.
        ``origin``: the world point (x, y) about which the root motion is scaled
        (default the world origin; for a duet, :func:`.source.duet_origin`, so that
        partners of different sizes keep their distance).
        Returns a pose object (world matrices in ``.W``)."""
        pts, G_src = source_world(positions, rotations, source_matrix)
        T = pts.shape[0]
        tgt = self.target
        W0 = tgt.ref_world
        lin0 = W0[:, :3, :3]
        Bn = len(tgt.names)
        lin = np.zeros((T, Bn, 3, 3))
        G = np.zeros((T, Bn, 3, 3))
        M, Rw = source_frame(source_matrix)
        for b, sg in self.seg.items():
            Gt = G_src[:, sg["twist"]]
            if b not in self.groups[ROOT_CHAIN]:
                a = interp_poly(pts[:, sg["chain"]], sg["s"], sg["f0"])
                e = interp_poly(pts[:, sg["chain"]], sg["s"], sg["f1"])
                cur = np.einsum("tij,j->ti", Gt, Rw @ sg["d_rest"])
                Gt = _no_flips(rotation_between(cur, e - a) @ Gt, Rw @ sg["d_rest"], e - a, self.max_step_deg)
            else:
                Gt = _no_flips(Gt, None, None, self.max_step_deg)
            G[:, b] = Gt
            lin[:, b] = Gt @ (Rw @ sg["A"]) @ lin0[b]
        # Pelvis anchor: midpoint of the hip joints, scaled.
        src_anchor = hip_midpoint(pts)
        src_ground = float(M[2, 3])
        ankles = pts[:, [JOINT_INDEX["ltibia"], JOINT_INDEX["rtibia"]], 2] - src_ground
        src_ankle_h = float(np.mean(np.percentile(ankles, 5, axis=0)))
        tgt_ankle_h = np.mean([h for k, h in self.tgt_foot_height.items() if k.endswith("ankle") and h is not None]
                              or [src_ankle_h * self.scale])
        k = self.scale
        self.src_height = self.source_height(src_ankle_h)
        self.height_ratio = self.height / self.src_height
        anchor = np.empty_like(src_anchor)
        o = np.zeros(2) if origin is None else np.asarray(origin, dtype=np.float64)[:2]
        # Horizontally by the height ratio (where the dancer is on the floor and
        # relative to the partner, as everything above the pelvis); vertically by
        # the leg length (how high a pelvis the legs carry).
        anchor[:, :2] = o + self.height_ratio * (src_anchor[:, :2] - o)
        anchor[:, 2] = self.ground + tgt_ankle_h + k * (src_anchor[:, 2] - src_ground - src_ankle_h)
        rb = self.root_bone
        R_root = lin[:, rb] @ np.linalg.inv(lin0[rb])  # rotation applied to the pelvis
        root_head = anchor + np.einsum("tij,j->ti", R_root, W0[rb, :3, 3] - self.tgt_anchor0)
        pose = _Pose(lin, root_head, G, None)
        pose.W = self.fk(pose)
        self._Rw = Rw
        pose.anchor, pose.src_anchor = anchor, src_anchor
        pose.src_ground = src_ground
        if self.match_feet:
            self.place_feet(pose, pts)
        if self.foot_lock:  # first: it may lower the pelvis
            if contacts is None:
                src_feet = pts[:, FEET]
                contacts = planted(detect_contacts(src_feet, fps), src_feet)
            self.lock_feet(pose, np.asarray(contacts, dtype=bool))
        if self.match_head:
            self.lean_to(pose, self.goal(pose, pts[:, JOINT_INDEX["upperneck"]]))
            pose.W = self.fk(pose)
        if self.match_hands:
            for side in SIDES:
                self.reach(pose, side, self.goal(pose, pts[:, JOINT_INDEX[side + "wrist"]]), np.ones(T))
            pose.W = self.fk(pose)
        return pose


def _no_flips(G, d_rest, d, max_deg, hold=6):
    """World rotations ``G (T, 3, 3)`` without source glitches. A frame that turns
    more than ``max_deg`` from the previous output (a flip of the source's bone:
    1800 deg/s at 30 Hz) keeps the previous rotation, swung onto the bone's
    direction ``d (T, 3)`` (``d_rest`` at rest) when that is no jump itself (a
    twist flip). A jump that lasts more than ``hold`` frames is caught up with
    at half ``max_deg`` per frame."""
    if len(G) < 2:
        return G
    c = np.cos(np.deg2rad(max_deg))
    tr = np.trace(np.swapaxes(G[:-1], -1, -2) @ G[1:], axis1=-2, axis2=-1)
    if not np.any((tr - 1.0) / 2.0 < c):
        return G
    out = np.array(G)
    held = 0
    for t in range(1, len(G)):
        cos_a = np.clip((np.trace(out[t - 1].T @ G[t]) - 1.0) / 2.0, -1.0, 1.0)
        if cos_a >= c:
            held = 0
            continue
        held += 1
        if held <= hold:
            nxt = out[t - 1]
            if d is not None:  # a twist flip: keep the twist, follow the direction if that is no jump
                swing = rotation_between(nxt @ d_rest, d[t]) @ nxt
                if (np.trace(nxt.T @ swing) - 1.0) / 2.0 >= c:
                    nxt = swing
        else:  # a lasting jump: turn towards the source, max_deg / 2 per frame
            q0, q1 = matrix_to_quat(out[t - 1]), matrix_to_quat(G[t])
            if np.dot(q0, q1) < 0:
                q1 = -q1
            frac = 0.5 * np.deg2rad(max_deg) / np.arccos(cos_a)
            nxt = quat_to_matrix(quat_slerp(q0, q1, np.array(frac)))
        out[t] = nxt
    return out


def interp_poly(pts, s_cum, f):
    """Point at arc-length fraction ``f`` of polylines ``pts (T, K, 3)`` whose rest
    vertices sit at fractions ``s_cum (K,)``."""
    f = float(np.clip(f, 0.0, 1.0))
    K = pts.shape[1]
    k = int(np.clip(np.searchsorted(s_cum, f, side="right") - 1, 0, K - 2))
    span = s_cum[k + 1] - s_cum[k]
    u = 0.0 if span <= 1e-12 else (f - s_cum[k]) / span
    return pts[:, k] + u * (pts[:, k + 1] - pts[:, k])
