"""Online duet synthesis: three points in, two full-body poses out, 30 times a second.

One loop serves the live preview and the offline bake: :meth:`Synthesizer.step`
takes one 30 Hz three-point frame (read as the calibration says) and returns
the leader's and the follower's pose for that frame, using no later input;
:meth:`Synthesizer.synthesize` calibrates and resamples a whole take and runs
the same frame over it.

Timing (see ``features``): the tracker state at step ``t`` holds each dancer's
pose at ``t − 1``; its future keys ``t − 1 + k`` are the current input (key 1)
and the mapping network's prediction from the input up to ``t`` (keys ≥ 2). The
follower's key 1 comes from the previous step's mapping.

What a user chooses is :class:`~.synthesis_options.SynthesisOptions`. The
stages a frame passes live beside this module: the input cleaned
(:mod:`.input_cleaning`), a tracker's state (:mod:`.dancer_state`), her
placement (:mod:`.follower`), her hips and holds (:mod:`.partner_pose`), the
foot lock (:mod:`.foot_lock`), pose recovery (:mod:`.pose`), the devices'
turns followed (:mod:`.device_follow`) and the duet (:mod:`.duet`).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import features as F
from .calibration import TRAIN_HEIGHT, Calibration, apply_calibration, calibrate, check_role, height_from_head
from .dancer_state import DancerState, set_poses, settle_step, tracker_step
from .device_follow import DeviceFollow, hand_flex
from .duet import Duet, DuetFrame, DuetFrames
from .input_cleaning import InputCleaner
from .keys import KEY_INDEX, KeySource
from .follower import OUT_SMOOTH, FollowerOptions, Placement, PulledRoot, Separation, check_partner_networks
from .partner_pose import HandHold, HipTwist, PartnerPose, hip_heading_from_probs
from .synthesis_options import SynthesisOptions
from .tracked_pose import TrackedOptions, TrackedPose
from .nets import contact_floor_levels, default_pose, load_nets, meta_json
from .pose import (LEG_TWIST_DEG, FloorGuard, LegJoints, OutputSmoothing, PoseRecovery, Recoveries,
                   bone_vectors_from_pose)
from .representation import compose_floats, hip_frame, to_local, to_world
from .rotations import quat_to_matrix
from .skeleton import JOINT_INDEX, LOWER_BODY, TRACKED, joint_rows

CALIBRATION_FRAMES = 30  # live, without a calibration: the height is estimated over the first second
DEFAULT_FLOOR_LEVELS = (0.07, 0.04, 0.07, 0.04)  # ankle, ball (m): without the contact network's levels


class _Read(NamedTuple):
    """What :meth:`Synthesizer._read` makes of one frame's devices."""

    tracked: np.ndarray  # (3, 3) the three points, cleaned, at the tracker's scale
    root: np.ndarray  # (4,) their root
    scale: float  # the tracker's scale
    x: np.ndarray | None  # (1, MAP_IN) the mapping's input (None: :meth:`Synthesizer.synthesize` makes a block's)
    devices: tuple | None  # the devices' rotations for DeviceFollow (None: not followed)


# What keeps each tracker's pose state on its root on any length of take (see
# :func:`~.dancer_state.settle_step`), by the tracker's dance role, tracked or synthesised:
# his head within 5 cm of his root, her pose re-centred on her root every frame.
RECENTRE_POSE = {"leader": 0.05, "follower": True}
# Frames :meth:`Synthesizer.synthesize` reads ahead of the frame loop (between
# lost devices) to run the networks on the input once for all of them.
READ_AHEAD = 256
_LOWER_BODY = joint_rows(LOWER_BODY)  # (a slice: a view)


class Synthesizer:
    """Holds the ONNX sessions (:data:`~.nets.MODEL_FILES`) and the rollout state.

    ``options``: a :class:`SynthesisOptions`; ``nets``: already loaded networks
    (default: :func:`~.nets.load_nets` of ``options.models``); ``follower``: the
    follower's placement state, torso separation and hand holds
    (:class:`~.follower.FollowerOptions`; None: no partner model, her root
    pulled towards the raw prediction: :class:`~.follower.PulledRoot`);
    ``tracked``: the tracked dancer's (:class:`~.tracked_pose.TrackedOptions`).
    Both dancers' next tracker step starts
    from the consistent skeleton pose of this one (pose recovery). The contact
    network (``nets["contacts"]``, on the mapping's input) times the follower's
    steps: her foot lock reads its probabilities (``FollowerOptions.foot_lock``),
    and they are her output contacts (with foot locking off, her tracker's are).
    ``record_predictions``: keep each step's mapping prediction
    (:attr:`last_prediction`, :attr:`Duet.predictions`) to show the method; it
    changes no output.
    """

    def __init__(self, options: SynthesisOptions | None = None, nets: dict | None = None,
                 follower: FollowerOptions | None = FollowerOptions(), record_predictions: bool = False,
                 tracked: TrackedOptions = TrackedOptions(),
                 keys: KeySource | None = None):
        options = options or SynthesisOptions()
        self.options = options
        self.keys = keys if keys is not None else KeySource()
        self.record_predictions = bool(record_predictions)
        self.last_prediction = None  # (2, FUTURE, 3, 3) float32 world, output scale (when recorded)
        self.height = None if options.height in (None, "auto", "") else float(options.height)
        self.calibration = None  # set by :meth:`synthesize` (or :meth:`set_calibration` for a live loop)
        self.foot_lock = options.foot_lock
        self.hand_ik = options.hand_ik
        self.follower_options = follower
        self.tracked_options = tracked
        # Rigid skeleton: the neck may turn but the spine may not stretch, so a
        # baked armature (fixed bone lengths) shows exactly this pose.
        self.ik_options = {"max_stretch": 0.0, "arm": "swing"}
        self._given_nets = nets is not None
        role = check_role(options.role or "leader")
        self._build(nets if nets is not None else load_nets(options.models, options.threads, role), role)

    def _build(self, nets: dict, role: str) -> None:
        """Everything that comes from the networks of a tracked ``role``: the
        two slots ("leader": the tracked dancer, "follower": the synthesised
        partner) are the dance roles for a leader's take and exchanged for a
        follower's (:attr:`role`; the outputs are put back in dance roles)."""
        self.nets = nets
        self.role = role
        follower = self.follower_options
        cal = meta_json(nets["mapping"], "calibration") or {}
        self.train_height = float(cal.get("height_m", TRAIN_HEIGHT))  # the tracked slot's dancer
        self.default_pose = {"tracked": default_pose(nets["leader"]), "partner": default_pose(nets["follower"])}
        # Each slot's rest skeleton (the tracked dancer's, the partner's), from its (FK-consistent) default pose.
        self.bone_vectors = {r: bone_vectors_from_pose(F.pose_positions(p), F.pose_rotations(p))
                             for r, p in self.default_pose.items()}
        self.cleaner = InputCleaner(F.pose_positions(self.default_pose["tracked"])[TRACKED],
                                    self.tracked_options.returns)
        self._recovery = Recoveries([PoseRecovery(self.bone_vectors[r]) for r in ("tracked", "partner")])
        # each dancer's floor level per foot point (training scale), from the contact network
        contacts = nets.get("contacts")
        self.floor_levels = None if contacts is None else contact_floor_levels(getattr(contacts, "meta", {}) or {})
        fo = follower
        check_partner_networks(fo, nets, self.foot_lock, self.floor_levels)
        self._net_steps = bool(self.foot_lock and fo is not None)  # her steps timed by the contact network
        self._anchor = float(fo.pose.anchor) if fo is not None else 0.0  # her legs pulled to the pose anchor's
        self._placement_net = fo is not None  # her roots from the placement network
        # the follower's arm lengths (shoulder to wrist), for hand holds
        levels = self.floor_levels or {r: DEFAULT_FLOOR_LEVELS for r in ("leader", "follower")}
        self._floor_guards = (FloorGuard(levels["leader"]), FloorGuard(levels["follower"]))
        bl = np.linalg.norm(self.bone_vectors["partner"], axis=-1)
        self._partner_arms = np.array([bl[JOINT_INDEX[s + "humerus"]] + bl[JOINT_INDEX[s + "radius"]]
                                   + bl[JOINT_INDEX[s + "wrist"]] for s in "lr"])
        self.reset()

    @property
    def partner_role(self) -> str:
        """The synthesised partner's dance role (the other one of :attr:`role`)."""
        return "leader" if self.role == "follower" else "follower"

    def set_role(self, role: str) -> None:
        """Track a dancer of ``role`` (SPEC §3 ``role``): the networks made for it
        (:func:`~.nets.load_nets`), from a fresh state."""
        role = check_role(role)
        if role == self.role:
            return
        if self._given_nets:
            raise ValueError(f"this synthesizer was given the networks of a {self.role}'s take; "
                             f"a {role}'s take needs its own")
        self._build(load_nets(self.options.models, self.options.threads, role), role)

    # -- state -----------------------------------------------------------------
    def reset(self):
        self.t = 0
        self._reads = 0  # frames read (:meth:`_read`), ahead of :attr:`t` within a block of :meth:`synthesize`
        self.hist_roots = np.zeros((F.PAST, 4))
        self.hist_tracked = np.zeros((F.PAST, 3, 3))
        self.tracked = DancerState(self.nets["leader"], self.default_pose["tracked"])
        self.partner = DancerState(self.nets["follower"], self.default_pose["partner"])
        self.prev_partner = None  # (root, tracked_local) predicted for frame t
        self.cleaner.reset()
        self.prev_tracked_pred = None  # the mapping's prediction of the next frame (root, tracked local)
        self._head_heights = []
        self._calibration = None
        devices = self.calibration.devices if self.calibration is not None else "joints"
        self._follow = None
        # which devices' orientations the tracked dancer follows (those that carry one)
        self._followed = self.calibration.followed if self.calibration is not None else (True, True, True)
        if self.options.follow_devices and any(self._followed):
            self._follow = DeviceFollow(self.bone_vectors["tracked"], "hand" if devices == "openxr" else "wrist",
                                        self.tracked_options.devices,
                                        hand_flex=hand_flex(F.pose_rotations(self.default_pose["tracked"])))
        self._lockers = None
        self._effector = None
        fo = self.follower_options
        # her root: a placement state, or (no partner model: the ablation) pulled to the raw prediction
        self._placement = Placement(fo.placement) if fo is not None else PulledRoot()
        self._separation = Separation(fo.placement.min_distance) if fo is not None else None
        self._hold = HandHold(fo.holds) if fo is not None and fo.holds.enabled else None
        self._partner_target = None  # (offset from the leader, world root) this frame
        self._contact_p = None  # the contact network's probabilities this frame (leader 4, follower 4)
        self._partner_effector = None
        if self.foot_lock or self.hand_ik:
            from . import ik
            if self.foot_lock:
                from .foot_lock import FootLocker, FootLockOptions
                to = self.tracked_options
                floor = None if self.floor_levels is None else [f + to.lock_floor
                                                                for f in self.floor_levels["leader"]]
                self._lockers = (FootLocker(to.foot_lock, floor),
                                 FootLocker(fo.foot_lock if fo is not None else FootLockOptions()))
                if self._net_steps and fo.steps.lock_floor >= 0:  # her locks go on her floor (the train split's)
                    self._lockers[1].floor = [f + fo.steps.lock_floor for f in self.floor_levels["follower"]]
            if self.hand_ik:
                self._effector = ik.EndEffectorIK(**self.ik_options)
        if self._hold is not None:
            from . import ik
            self._partner_effector = ik.EndEffectorIK(**self.ik_options)
        self._arm_limit = None
        if fo is not None and fo.pose.arm_turn > 0:
            from . import ik
            self._arm_limit = ik.ArmTurnLimit(fo.pose.arm_turn)
        self._hip_twist = HipTwist(fo.hips) if fo is not None and fo.hips.share > 0 else None
        self._out_smooth = None
        if fo is not None:
            keep = OUT_SMOOTH[self.partner_role] if fo.pose.out_smooth is None else fo.pose.out_smooth
            if keep:
                self._out_smooth = OutputSmoothing(keep, self.bone_vectors["partner"])
        # her legs kept on the skeleton's joints where the anchor pulls them (``pose.LegJoints``)
        self._leg_joints = LegJoints(self.bone_vectors["partner"]) if self._anchor > 0.0 else None
        # her output's thighs: their twist within ``out_thigh_twist`` (the other leg bones' as her state's)
        out_twist = float(fo.pose.out_thigh_twist) if fo is not None else 0.0
        self._out_twist = None
        if out_twist > 0.0:
            limits = list(LEG_TWIST_DEG)
            limits[1] = out_twist  # the thigh (a chain: hip joint, thigh, shin, foot, toes)
            self._out_twist = np.radians(limits).tolist()
            self._leg_joints = self._leg_joints or LegJoints(self.bone_vectors["partner"])
        lockers = self._lockers or (None, None)
        self._tracked_pose = TrackedPose(lockers[0], self._floor_guards[0], self._effector, self._follow,
                                         self.tracked_options)
        self._partner_pose = PartnerPose(lockers[1], self._floor_guards[1], self._partner_effector, self._net_steps,
                                    self._out_twist, self._leg_joints)
        self.keys.reset(self)

    def set_calibration(self, calibration: Calibration | None) -> None:
        """Read the devices of :meth:`step` as ``calibration`` says (devices, height,
        floor; :func:`~.calibration.calibrate`) from a fresh state; None: §2 points
        on a floor at y = 0, the height as the options give it."""
        self.calibration = calibration
        self.reset()

    def scale(self) -> float:
        """Tracker scale: training height over the user's (paper §7 calibration).
        The calibration's height when there is one (:meth:`synthesize` makes
        it, from the whole take), else the options' height; else (a live loop
        without either) the heads seen so far, fixed after the first second so
        that the output skeleton keeps its size."""
        if self.calibration is not None:
            return self.train_height / self.calibration.height
        if self.height is not None:
            return self.train_height / self.height
        if self._calibration is not None:
            return self._calibration
        if self._head_heights:
            s = self.train_height / height_from_head(self._head_heights)
            if len(self._head_heights) >= CALIBRATION_FRAMES:
                self._calibration = s
            return s
        return 1.0

    def role_bone_vectors(self) -> dict:
        """Each dancer's skeleton at the networks' scale, by dance role (``leader``, ``follower``)."""
        slot = {self.role: "tracked", self.partner_role: "partner"}
        return {r: self.bone_vectors[slot[r]] for r in ("leader", "follower")}

    def output_bone_vectors(self) -> dict:
        """Each dancer's skeleton at the output's scale (what the poses are made of), by dance role."""
        return {r: bv / self.scale() for r, bv in self.role_bone_vectors().items()}

    # -- one frame -------------------------------------------------------------
    def step(self, positions, quats, valid=(True, True, True)):
        """One 30 Hz frame: the three points ``positions (3, 3)``, ``quats (3, 4)``
        (w, x, y, z) and ``valid (3,)`` tracking flags, read as
        :attr:`calibration` says (§2 points above a floor at y = 0:
        :func:`~.calibration.apply_calibration` of the rows, then resampled).
        Returns (leader, follower) :class:`DuetFrame` in the take's frame. The
        one per-frame entry: a live loop that reads each row as it comes,
        resamples and calls this makes the frames :meth:`synthesize` makes of
        the same rows (which runs the same stages, the input's networks on
        blocks of frames at once)."""
        a, b = self._frame(positions, quats, valid)
        c = self.calibration
        if c is not None and c.floor_y:
            a.positions[:, 1] += c.floor_y
            b.positions[:, 1] += c.floor_y
        return (b, a) if self.role == "follower" else (a, b)

    def _frame(self, positions, quats, valid):
        """:meth:`step` on §2 points above a floor at y = 0."""
        read = self._read(positions, quats, valid)
        return self._advance(read, self._input_nets(read.x, read.root[None]))

    def _read(self, positions, quats, valid, mapping: bool = True) -> _Read:
        """The input side of a frame: the devices cleaned (:class:`~.input_cleaning.InputCleaner`), at
        the tracker's scale, into the input history, and the mapping's input.
        It needs the networks' outputs of the last frame only when a device is
        lost (the cleaner fills it from the mapping's prediction), so
        :meth:`synthesize` reads the frames between losses ahead and runs the
        networks on the input (:meth:`_input_nets`) once for all of them."""
        tracked, head_rot, root = self.cleaner.clean(positions, quats, valid, self.prev_tracked_pred,
                                                     1.0 / self.scale())
        devices = None
        if self._follow is not None:  # what the devices measure this frame, for the head and hands to follow
            use = self._followed
            devices = (head_rot if valid[0] and use[0] else None,
                       *(quat_to_matrix(quats[i]) if valid[i] and use[i] else None for i in (1, 2)))
        if valid[0] and self.calibration is None and self.height is None:
            self._head_heights.append(tracked[0, 1])
        s = self.scale()
        tracked_s = tracked
        if s != 1.0:  # (×1 changes nothing: skipped)
            tracked_s = tracked * s
            root = root * np.array([s, s, 1.0, 1.0])  # scaling about the origin keeps the heading
        if self._reads == 0:
            self.hist_roots[:] = root
            self.hist_tracked[:] = tracked_s
        else:
            self.hist_roots[:-1] = self.hist_roots[1:]  # (numpy copes with the overlap)
            self.hist_tracked[:-1] = self.hist_tracked[1:]
            self.hist_roots[-1] = root
            self.hist_tracked[-1] = tracked_s
        self._reads += 1
        x = F.mapping_input(self.hist_roots[None], self.hist_tracked[None]) if mapping else None
        return _Read(tracked_s, root, s, x, devices)

    def _input_nets(self, x, roots) -> dict:
        """The networks that read the mapping's input only, on ``x (B, MAP_IN)``
        of frames whose tracked roots are ``roots (B, 4)``: the mapping (her
        roots the placement network's), decoded per dancer into world roots
        and tracked points (``tracked_roots``, ``tracked_points``,
        ``partner_roots``, ``partner_points``), and as the options need them
        the contacts, the pose anchor and the hip heading (each ``(B, …)``; a
        batch gives each row the bits a batch of one does)."""
        nets = self.nets
        y = nets["mapping"](x)
        if self._placement_net:  # her predicted roots from the placement network
            y = F.splice_follower_roots(y, nets["placement"](x))
        (t_roots, t_tr), (p_roots, p_tr) = F.decode_mapping(y, roots)
        out = {"tracked_roots": t_roots, "tracked_points": t_tr, "partner_roots": p_roots, "partner_points": p_tr}
        if self._net_steps:
            out["contacts"] = nets["contacts"](x)
        if self._anchor > 0.0:
            out["anchor"] = nets["anchor"](x)
        if self._hip_twist is not None:
            out["hip"] = nets["hip"](x)
        return out

    def _advance(self, read: _Read, outs: dict):
        """The rest of a frame (:meth:`_read` gave its input, ``outs`` the
        networks on it, rows of one frame): both dancers one step on."""
        root, s, tracked_s = read.root, read.scale, read.tracked
        if read.devices is not None:
            self._tracked_pose.devices = read.devices
        if self.t == 0:
            self.tracked.place(root)
        if self._net_steps:
            p = outs["contacts"][0].astype(np.float64)
            b = self.follower_options.steps.contact_smooth
            if b > 0.0 and self._contact_p is not None:
                p = b * self._contact_p + (1.0 - b) * p
            self._contact_p = p
        t_roots, t_tr = outs["tracked_roots"][0], outs["tracked_points"][0]
        p_roots, p_tr = outs["partner_roots"][0], outs["partner_points"][0]
        self.prev_tracked_pred = (t_roots[0], t_tr[0])
        if self.record_predictions:  # the mapping's output (her roots the placement network's), world, output scale
            pred = to_world(np.stack([t_tr, p_tr]), np.stack([t_roots, p_roots]))
            pred = pred if self.role == "leader" else pred[::-1]  # (by dance role)
            self.last_prediction = (pred if s == 1.0 else pred * (1.0 / s)).astype(np.float32)
        placement = self._placement
        p_roots, p_tr = placement.smooth(p_roots, p_tr)
        self._tracked_root = root
        self._partner_target = placement.target(root, t_roots, p_roots)
        if self.t == 0:
            self.partner.place(self._partner_target[1])
            self.prev_partner = (p_roots[0], p_tr[0])
        cur_local = to_local(tracked_s, root)
        keys = self.keys.tracked(self, root, cur_local, t_roots, t_tr)
        tk_roots, tk_tr = keys if keys is not None else self._tracked_keys(root, cur_local, t_roots, t_tr)
        keys = self.keys.partner(self, p_roots, p_tr, t_roots, t_tr)
        pk_roots, pk_tr = keys if keys is not None else self._partner_keys(p_roots, p_tr, t_roots, t_tr)
        self.prev_partner = (p_roots[0], p_tr[0])
        goal = placement.goal(self._partner_target, pk_roots)
        dancers = (self.tracked, self.partner)
        rel, pos, rot, con = tracker_step(dancers, np.array([tk_roots, pk_roots]), np.array([tk_tr, pk_tr]))
        prev = self.partner.root.tolist()  # her new root: her tracker's proposal (root_compose's), placed
        partner_root = np.array(placement.step(prev, compose_floats(prev, rel[1].tolist()), goal))
        pos, rot, con = settle_step(dancers, (root, partner_root), pos, rot, con,
                                    (RECENTRE_POSE[self.role], RECENTRE_POSE[self.partner_role]))
        tc, pc = con
        if self._anchor > 0.0:  # her lower body pulled towards the pose anchor's
            legs = outs["anchor"][0].astype(np.float64).reshape(-1, 3)
            pp = pos[1]
            pp[_LOWER_BODY] += self._anchor * (to_world(legs, hip_frame(pp)) - pp[_LOWER_BODY])
        if self._separation is not None:
            dx, dz = self._separation.push(pos[0], pos[1])
            if dx or dz:  # her body and her root state move together
                pos[1, :, 0] += dx
                pos[1, :, 2] += dz
                self.partner.root = self.partner.root + np.array([dx, dz, 0.0, 0.0])
        pos, rot = self._recovery(pos, rot)  # both dancers' poses at once
        rigid = list(zip(pos, rot))  # (views: what changes them in place changes these)
        if self._anchor > 0.0:  # her legs' twist within the skeleton's (the anchor pulls their joints)
            self._leg_joints.twist(*rigid[1])
        set_poses(dancers, pos, rot, con)  # the next step starts from the consistent skeleton pose
        self.tracked.keep_footing(self.tracked_options.footing)  # his state back on its feet if it drifted off
        if self._anchor > 0.0:  # her output's hip joints turn with her pelvis (her state's need not)
            self._leg_joints.hips(*rigid[1])
        if self._hip_twist is not None:  # her hips towards where the hip-heading network says she faces
            self._hip_twist.step(*rigid[1], hip_heading_from_probs(outs["hip"][0], root))
        tp, tr = self._recover(self._tracked_pose, *rigid[0], tc, tracked_s)
        holds = None if self._hold is None else self._hold.wrist_targets(tp, rigid[1][0], t_tr, p_tr, t_roots,
                                                                         p_roots, self._partner_arms)
        pp, pr = self._recover(self._partner_pose, *rigid[1], pc, holds)
        if self._arm_limit is not None:  # her arms no faster than a real dancer's
            pp, pr = self._arm_limit.step(pp, pr)
        if self._out_smooth is not None:
            pp, pr = self._out_smooth(pp, pr)
        if self._net_steps:  # her contacts are what timed her steps
            pc = self._contact_p[4:]
        self.t += 1
        if s != 1.0:
            tp, pp = tp * (1.0 / s), pp * (1.0 / s)
        a, b = DuetFrame(tp, tr, tc), DuetFrame(pp, pr, pc)
        self.keys.observe(self, a, b)
        return a, b

    def planted(self) -> list | None:
        """Which foot points the foot lock held on the last frame, per dancer
        (leader, follower), in ``contacts`` order (left ankle, left ball, right
        ankle, right ball); None without foot locking."""
        if self._lockers is None:
            return None
        out = [[lock is not None for side in locker.locks for lock in side] for locker in self._lockers]
        return out if self.role == "leader" else out[::-1]

    def _recover(self, stage, pos, rot, contacts, targets):
        """One dancer's pose after pose recovery (Appendix B: a consistent
        skeleton pose) through its stage (:class:`~.tracked_pose.TrackedPose`,
        :class:`~.partner_pose.PartnerPose`): feet, floor, IK."""
        return stage(pos, rot, contacts, targets, self._contact_p)

    def _tracked_keys(self, root, cur_local, t_roots, t_tr):
        """Leader's key inputs: the current input frame, then the mapping's prediction."""
        return (np.concatenate([root[None], t_roots.take(KEY_INDEX, axis=0)]),
                np.concatenate([cur_local[None], t_tr.take(KEY_INDEX, axis=0)]))

    def _partner_keys(self, p_roots, p_tr, t_roots, t_tr):
        """The partner's key inputs: last step's prediction of frame t, then this
        step's; the key roots as her placement makes them (the predicted
        trajectory's shape from her own root, eased towards her target:
        ``follower.Placement``; without the partner model the prediction's own)."""
        tracked = np.concatenate([self.prev_partner[1][None], p_tr.take(KEY_INDEX, axis=0)])
        roots = self._placement.key_roots(self.partner.root.tolist(), self.prev_partner[0], p_roots, t_roots,
                                          self._tracked_root, self._partner_target[0], KEY_INDEX)
        return roots, tracked

    # -- a whole take ----------------------------------------------------------
    def calibrate(self, take) -> Calibration:
        """The calibration of ``take`` under this synthesizer's options
        (:func:`~.calibration.calibrate`)."""
        o = self.options
        return calibrate(take, height=self.height, floor_y=o.floor_y, devices=o.devices, offsets=o.offsets,
                         head_offset=o.head_offset, hand_offset=o.hand_offset, role=o.role,
                         head_turn=o.head_turn, hand_turn=o.hand_turn)

    def synthesize(self, take, progress=None) -> Duet:
        """Calibrate ``take`` (its devices, the dancer's height, the floor:
        :meth:`calibrate`), resample it to 30 Hz and run the frame loop over
        it from a fresh state; the duet is in the take's frame."""
        from .resample import resample_take

        calib = self.calibrate(take)
        self.set_role(calib.role)
        tk = resample_take(apply_calibration(take, calib), F.FPS)
        self.set_calibration(calib)
        T = tk.n_frames
        valid = tk.valid
        frames = DuetFrames(T, predictions=self.record_predictions, planted=self._lockers is not None)
        t = 0
        while t < T:
            # the frames up to the next lost device read ahead, the input's networks run on them at once
            end = t + 1
            while end < min(t + READ_AHEAD, T) and valid[end].all():
                end += 1
            reads = [self._read(tk.positions[t], tk.quats[t], valid[t], False)]
            first = self.hist_roots.copy(), self.hist_tracked.copy()  # the first frame's window, then each next
            reads += [self._read(tk.positions[k], tk.quats[k], valid[k], False) for k in range(t + 1, end)]
            x = F.mapping_inputs(*first, np.array([r.root for r in reads[1:]]).reshape(-1, 4),
                                 np.array([r.tracked for r in reads[1:]]).reshape(-1, 3, 3))
            outs = self._input_nets(x, np.array([r.root for r in reads]))
            for i, read in enumerate(reads):
                a, b = self._advance(read, {k: v[i:i + 1] for k, v in outs.items()})
                frames.put(t, a, b, self.last_prediction, self.planted())
                if progress is not None and (t % 30 == 0 or t == T - 1):
                    if progress(t + 1, T) is False:
                        raise KeyboardInterrupt("cancelled")
                t += 1
        return frames.duet(tk.time, self.role, calib.floor_y, bone_vectors=self.output_bone_vectors(),
                           calibration=calib)
