"""The steps on one frame's pose of the target rig, which
:class:`~.solver.Retargeter` takes in turn: forward kinematics and the
landmarks it reads (:meth:`RigSteps.fk`, :meth:`RigSteps.landmarks`), the feet
put and locked (:meth:`RigSteps.place_feet`, :meth:`RigSteps.lock_feet`), the
spine leaned towards a goal (:meth:`RigSteps.lean_to`) and the arms reaching
(:meth:`RigSteps.reach`). They read the pair of rigs' alignment, which the
solver sets up (see :mod:`.solver` for the method)."""
from __future__ import annotations

import numpy as np

from ..ik import rotation_between, smoothstep, two_bone_ik
from ..skeleton import JOINT_INDEX
from .contacts import foot_targets, reach_drop, smooth_max
from .mapping import ROOT_CHAIN, SIDES
from .rig import basis_from_pose
from .source import SRC_FWD, UP


class RigSteps:
    """The per-frame steps of :class:`~.solver.Retargeter` (its base: they read
    the alignment state its constructor makes)."""

    def fk(self, pose):
        """World matrices ``(T, B, 4, 4)`` of all target bones: mapped bones take
        their linear part from ``pose.lin``, every bone its head from its parent
        (reference offsets), unmapped bones their reference pose relative to the parent."""
        tgt = self.target
        W0 = tgt.ref_world
        T = pose.lin.shape[0]
        W = np.empty((T, len(tgt.names), 4, 4))
        mapped = self.seg
        inv0 = getattr(self, "_inv0", None)
        if inv0 is None:
            inv0 = self._inv0 = np.linalg.inv(W0)
        roots = set(self.groups[ROOT_CHAIN])
        for b in tgt.order:
            p = tgt.parents[b]
            if b in roots and b == self.root_bone:
                W[:, b] = np.eye(4)
                W[:, b, :3, :3] = pose.lin[:, b]
                W[:, b, :3, 3] = pose.root_head
                continue
            if p < 0:
                W[:, b] = W0[b]
            else:
                W[:, b] = W[:, p] @ (inv0[p] @ W0[b])
            if b in mapped:
                W[:, b, :3, :3] = pose.lin[:, b]
        return W

    def landmarks(self, W):
        """``{landmark: (T, 3)}`` of the target (world), the same names as
        :func:`.source.source_landmarks`: hip joints' midpoint, skull base, wrists, ankles, balls."""
        heads = W[..., :3, 3]
        out = {"hips": 0.5 * (heads[:, self._bones_of("lfemur")[0]] + heads[:, self._bones_of("rfemur")[0]])}
        for side in SIDES:
            wr = self._bones_of(side + "hand")
            if wr is not None:
                out[side + "wrist"] = heads[:, wr[0]]
            else:
                fa = self._bones_of(side + "radius")
                if fa is not None:
                    out[side + "wrist"] = self._end_world(W, fa[-1])
            foot = self._bones_of(side + "foot")
            if foot is not None:
                out[side + "ankle"] = heads[:, foot[0]]
            toe = self._bones_of(side + "toes")
            if toe is not None:
                out[side + "ball"] = heads[:, toe[0]]
            elif foot is not None:
                out[side + "ball"] = self._end_world(W, foot[-1])
        head = self._bones_of("head")
        if head is not None:
            out["head"] = heads[:, head[0]]
        return out

    def _end_world(self, W, b):
        """World position (T, 3) of bone ``b``'s segment end point."""
        chain = self.mapping[self.target.names[b]]
        end0 = self._end_point(b, self.groups[chain], chain)
        local = np.linalg.inv(self.target.ref_world[b]) @ np.append(end0, 1.0)
        return np.einsum("tij,j->ti", W[:, b], local)[:, :3]

    def _apply_delta(self, pose, bones, D, mask):
        for b in bones:
            pose.lin[mask, b] = D[mask] @ pose.lin[mask, b]
            pose.G[mask, b] = D[mask] @ pose.G[mask, b]

    # -- feet ---------------------------------------------------------------------
    def place_feet(self, pose, pts):
        """Put the ankles horizontally where the source's are relative to the
        pelvis, scaled by the height ratio (as the head and the wrists; the leg
        angles alone would scale the stride by the leg ratio): two-bone leg IK to
        that point at the FK ankle's height, the foot's orientation kept."""
        s = self.height_ratio
        heads = pose.W[..., :3, 3]
        for side in SIDES:
            thigh, shin, foot = (self._bones_of(side + n) for n in ("femur", "tibia", "foot"))
            if thigh is None or shin is None or foot is None:
                continue
            A = heads[:, foot[0]]
            target = A.copy()
            src = pts[:, JOINT_INDEX[side + "tibia"]]
            target[:, :2] = pose.anchor[:, :2] + s * (src[:, :2] - pose.src_anchor[:, :2])
            hip, knee = heads[:, thigh[0]], heads[:, shin[0]]
            fwd = np.einsum("tij,j->ti", pose.G[:, thigh[0]], self._Rw @ SRC_FWD)
            _, _, R1, R2 = two_bone_ik(hip, knee, A, target, knee + 0.1 * fwd)
            every = np.ones(len(A), dtype=bool)
            self._apply_delta(pose, thigh, R1, every)
            self._apply_delta(pose, shin, R2, every)  # (the foot's orientation is its own: kept)
        pose.W = self.fk(pose)

    def lock_feet(self, pose, contacts):
        """Lock the target's foot points where ``contacts (T, 4)`` (left ankle,
        left ball, right ankle, right ball) are on (:func:`foot_targets`): two-bone
        leg IK to the ankle target, the foot turned about the ankle to the foot
        target. Where a locked leg cannot reach its target, the pelvis is first
        lowered as much as needed (smoothly over a few frames)."""
        legs = self._leg_targets(pose, contacts)  # world targets: they stay where they are
        total = np.zeros(len(pose.root_head))
        for _ in range(3):  # the smoothed drop changes the hips' path a little: a few rounds
            heads = pose.W[..., :3, 3]
            drop = np.zeros(len(pose.root_head))
            for side, (_, ankle_t, act, L) in legs.items():
                hip = heads[:, self._bones_of(side + "femur")[0]]
                need = np.minimum(reach_drop(hip, ankle_t, 0.998 * L, self.max_drop * L),
                                  np.maximum(self.max_drop * L - total, 0.0))
                drop = np.maximum(drop, np.where(act, need, 0.0))
            if drop.max() < 1e-4:
                break
            drop = smooth_max(drop, self.blend_frames)
            total += drop
            pose.root_head = pose.root_head - drop[:, None] * UP
            pose.W = self.fk(pose)
        heads = pose.W[..., :3, 3]
        for side, (_, ankle_t, act, _) in legs.items():
            thigh, shin, foot = (self._bones_of(side + n) for n in ("femur", "tibia", "foot"))
            hip = heads[:, thigh[0]]
            toe = self._bones_of(side + "toes") or []
            A = heads[:, foot[0]]
            Fv = (heads[:, toe[0]] if toe else self._end_world(pose.W, foot[-1])) - A
            knee = heads[:, shin[0]]
            fwd = np.einsum("tij,j->ti", pose.G[:, thigh[0]], self._Rw @ SRC_FWD)
            _, _, R1, R2 = two_bone_ik(hip, knee, A, ankle_t, knee + 0.1 * fwd)
            R3 = rotation_between(Fv, pose.foot_vec[side])
            self._apply_delta(pose, thigh, R1, act)
            self._apply_delta(pose, shin, R2, act)
            self._apply_delta(pose, foot + list(toe), R3, act)
        pose.W = self.fk(pose)
        return pose

    def _leg_targets(self, pose, contacts):
        """``{side: (hip (T, 3), ankle target (T, 3), frames to solve (T,), leg length)}``;
        the foot vectors go to ``pose.foot_vec``."""
        W = pose.W
        heads = W[..., :3, 3]
        out = {}
        pose.foot_vec = {}
        ref = self.target.heads()
        for si, side in enumerate(SIDES):
            thigh, shin, foot = (self._bones_of(side + n) for n in ("femur", "tibia", "foot"))
            if thigh is None or shin is None or foot is None:
                continue
            toe = self._bones_of(side + "toes") or []
            A = heads[:, foot[0]]
            Bp = heads[:, toe[0]] if toe else self._end_world(W, foot[-1])
            floor_a = self.ground + (self.tgt_foot_height[side + "ankle"] or 0.0)
            floor_b = self.ground + (self.tgt_foot_height[side + "ball"] or 0.0)
            ankle_t, newF, act = foot_targets(A, Bp, contacts[:, 2 * si], contacts[:, 2 * si + 1], floor_a,
                                               floor_b, self.blend_frames, self.max_drift)
            if not act.any():
                continue
            L = float(np.linalg.norm(ref[shin[0]] - ref[thigh[0]]) + np.linalg.norm(ref[foot[0]] - ref[shin[0]]))
            out[side] = (heads[:, thigh[0]], ankle_t, act, L)
            pose.foot_vec[side] = newF
        return out

    def goal(self, pose, src_point):
        """Where a source point ``(T, 3)`` (world) goes on the target: horizontally
        relative to the pelvis, vertically above the floor, scaled by the ratio
        of the head-point heights."""
        s = self.height_ratio
        out = np.empty_like(src_point)
        out[:, :2] = pose.anchor[:, :2] + s * (src_point[:, :2] - pose.src_anchor[:, :2])
        out[:, 2] = self.ground + s * (src_point[:, 2] - pose.src_ground)
        return out

    # -- head ---------------------------------------------------------------------
    def lean_to(self, pose, goal):
        """Turn the spine and neck rigidly about the spine's base by the smallest
        rotation that aims the head point (skull base) at ``goal (T, 3)``."""
        spine = []
        for part in ("lowerback", "upperback", "thorax", "lowerneck", "upperneck"):
            for b in self._bones_of(part) or ():
                if b not in spine:
                    spine.append(b)
        head = self._bones_of("head")
        if not spine or head is None:
            return
        heads = pose.W[..., :3, 3]
        base = heads[:, spine[0]]
        D = rotation_between(heads[:, head[0]] - base, goal - base)
        self._apply_delta(pose, spine, D, np.ones(len(D), dtype=bool))

    # -- arms ---------------------------------------------------------------------
    def arm(self, side):
        """``(upper arm bones, forearm bones, hand bones or None)`` of ``side``."""
        fore = []
        for part in ("radius", "wrist"):
            for b in self._bones_of(side + part) or ():
                if b not in fore:
                    fore.append(b)
        return self._bones_of(side + "humerus"), fore or None, self._bones_of(side + "hand")

    def wrists(self, W):
        lm = self.landmarks(W)
        return np.stack([lm["lwrist"], lm["rwrist"]], axis=1)

    FOLDED, FOLDED_FADE = 0.2, 0.15  # × the arm's length: see :meth:`reach`

    def reach(self, pose, side, target, weight):
        """Move the wrist of ``side`` towards ``target (T, 3)`` by ``weight (T,)``
        with two-bone arm IK (elbow as the pole). Where the arm is too short, the
        clavicle first turns to bring the shoulder closer (as ``ik.EndEffectorIK``).
        Where the target is at the shoulder (under ``FOLDED`` of the arm's length
        from it, fading in over the next ``FOLDED_FADE``), the arm keeps its own
        rotations (the source's): the direction from the shoulder to such a target
        turns fast, and the folded arm would flip with it (a follower's hand on
        her own shoulder turned the avatar's forearm 100° in a frame)."""
        up, fa, _ = self.arm(side)
        if up is None or fa is None:
            return
        W = pose.W
        heads = W[..., :3, 3]
        sh, el = heads[:, up[0]], heads[:, fa[0]]
        wr = self.wrists(W)[:, SIDES.index(side)]
        arm = np.linalg.norm(el - sh, axis=-1) + np.linalg.norm(wr - el, axis=-1)
        near = np.linalg.norm(target - sh, axis=-1) / np.maximum(arm, 1e-12)
        weight = weight * smoothstep((near - self.FOLDED) / self.FOLDED_FADE)
        act = weight > 0
        if not act.any():
            return
        goal = wr + weight[:, None] * (target - wr)
        clav = self._bones_of(side + "clavicle")
        reach = 0.999 * arm
        dist = np.linalg.norm(goal - sh, axis=-1)
        far = act & (dist > reach)
        if clav is not None and far.any():
            tip = sh + (goal - sh) * (reach / np.maximum(dist, 1e-12))[:, None]
            _, _, Rc, _ = two_bone_ik(heads[:, clav[0]], sh, tip, goal, sh)
            self._apply_delta(pose, list(clav) + list(up) + list(fa), Rc, far)
            pose.W = W = self.fk(pose)
            heads = W[..., :3, 3]
            sh, el = heads[:, up[0]], heads[:, fa[0]]
            wr = self.wrists(W)[:, SIDES.index(side)]
        _, _, R1, R2 = two_bone_ik(sh, el, wr, goal, el)
        self._apply_delta(pose, up, R1, act)
        self._apply_delta(pose, fa, R2, act)

    # -- output -------------------------------------------------------------------
    def basis(self, W):
        """``matrix_basis (T, B, 4, 4)`` of every target bone for world matrices ``W``."""
        tgt = self.target
        pose = np.linalg.inv(tgt.matrix_world)[None, None] @ W
        return basis_from_pose(tgt.rest, tgt.parents, pose)
