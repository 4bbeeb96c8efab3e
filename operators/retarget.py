# SPDX-License-Identifier: GPL-3.0-or-later
"""Retarget the baked duet onto the animator's own characters.

- ``bpy.ops.dancing_points.retarget(source=..., target=...)``: the motion of a
  Dancing Points armature (leader or follower of a baked duet) becomes a NEW
  action on the target armature (one keyframe per frame, written in bulk);
  its meshes, rest pose and other actions are left as they are (an action that
  would be left without users gets a fake user so it is kept).
- ``bpy.ops.dancing_points.retarget_duet()``: both dancers at once (the hands
  that hold each other are closed symmetrically), from the panel's pickers.
- ``dancing_points.retarget_map_auto`` / ``_save`` / ``_load``: the bone
  mapping stored on the target armature (``Object.dp_retarget_map``), to
  inspect and edit in the panel, saved and loaded as JSON presets.
- :func:`retarget_duet_onto` (for the batch command) and :func:`load_rig_file`
  (a .blend, .glb/.gltf or .fbx with an armature).

All the maths is in ``dancing_points_addon.retarget``; this module moves data
between Blender and it. The target's reference pose (the pose it is shown in
when first retargeted: its T- or A-pose) is stored on the object
(``dp_reference_basis``) so that later runs align against the same pose.
"""

import os
import tempfile

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, IntProperty, PointerProperty, StringProperty

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon import retarget as rt
from ..dancing_points_addon.rotations import axis_angle_to_quat, euler_to_matrix, quat_to_axis_angle, quat_to_matrix
from ..dancing_points_addon.skeleton import JOINT_NAMES
from . import bake, compat
from .props import is_duet

REF_PROP = "dp_reference_basis"
SOURCE_PROP = "dp_retarget_source"  # on a retargeted rig: the DP armature it follows
TARGET_PROP = "dp_retarget_target"  # on a DP armature: the rig it was retargeted onto
ROLE_PROP = "dp_role"


class RetargetFailure(Exception):
    """One user-facing line."""


# --------------------------------------------------------------------------- data stored in the .blend

class DP_RetargetBoneMap(bpy.types.PropertyGroup):
    target: StringProperty(name="Target Bone", description="Bone of the target armature")
    source: StringProperty(name="Source", description="Dancing Points bone(s) it follows (SPEC §2 names, "
                                                      "'a+b' for a chain; empty: keeps its rest pose)")


def _is_armature(self, obj):
    return obj is not None and obj.type == 'ARMATURE'


def _is_dp_armature(self, obj):
    return _is_armature(self, obj) and obj.get(ROLE_PROP) in ("leader", "follower")


class DP_RetargetSettings(bpy.types.PropertyGroup):
    leader_source: PointerProperty(name="Leader", type=bpy.types.Object, poll=_is_dp_armature,
                                   description="The baked leader armature (Dancing Points)")
    leader_target: PointerProperty(name="Leader Rig", type=bpy.types.Object, poll=_is_armature,
                                   description="Your armature that dances the leader's part")
    follower_source: PointerProperty(name="Follower", type=bpy.types.Object, poll=_is_dp_armature,
                                     description="The baked follower armature (Dancing Points)")
    follower_target: PointerProperty(name="Follower Rig", type=bpy.types.Object, poll=_is_armature,
                                     description="Your armature that dances the follower's part")
    foot_lock: BoolProperty(name="Foot Locking", default=True,
                            description="Keep the feet in contact on the target (leg IK)")
    close_hands: BoolProperty(name="Close Hands", default=True,
                              description="Hands that hold each other stay together (arm IK)")
    preset_path: StringProperty(name="Preset", subtype='FILE_PATH', default="//bone_map.json",
                                description="JSON file of a bone mapping")


# --------------------------------------------------------------------------- reading rigs

def _mat(m):
    return np.array(m, dtype=np.float64)


def _bone_arrays(obj):
    bones = obj.data.bones
    names = [b.name for b in bones]
    index = {n: i for i, n in enumerate(names)}
    parents = [index[b.parent.name] if b.parent is not None else -1 for b in bones]
    rest = np.stack([_mat(b.matrix_local) for b in bones])
    lengths = np.array([b.length for b in bones])
    return names, parents, rest, lengths


def reference_basis(obj, store=True):
    """The target's reference pose as ``matrix_basis (B, 4, 4)``: the one stored on
    the object, else its current pose when it has no action (just imported), else
    its rest pose. Stored on the object (``dp_reference_basis``) the first time."""
    names = [b.name for b in obj.data.bones]
    stored = obj.get(REF_PROP)
    if stored is not None:
        try:
            arr = np.array(list(stored), dtype=np.float64).reshape(-1, 4, 4)
            if arr.shape[0] == len(names):
                return arr
        except (TypeError, ValueError):
            pass
    action, _ = compat.assigned_action(obj)
    if action is None:
        arr = np.stack([_mat(obj.pose.bones[n].matrix_basis) for n in names])
    else:
        arr = np.broadcast_to(np.eye(4), (len(names), 4, 4)).copy()
    if store:
        obj[REF_PROP] = arr.reshape(-1).tolist()
    return arr


def target_rig(obj, store=True):
    names, parents, rest, lengths = _bone_arrays(obj)
    return rt.TargetRig(names, parents, rest, lengths, reference_basis(obj, store), _mat(obj.matrix_world))


def source_motion(arm_obj):
    """``(frames, positions (T, 31, 3), rotations (T, 31, 3, 3), bone_vectors, matrix_world)``
    of a Dancing Points armature, from its action's keys (SPEC motion space)."""
    bones = arm_obj.data.bones
    missing = [n for n in JOINT_NAMES if n not in bones]
    if missing:
        raise RetargetFailure("'{:s}' is not a Dancing Points armature (no bone {:s})".format(
            arm_obj.name, missing[0]))
    action, slot = compat.assigned_action(arm_obj)
    if action is None:
        raise RetargetFailure("'{:s}' has no animation to retarget".format(arm_obj.name))
    fc = compat.find_fcurve(action, slot, 'pose.bones["root"].location', 0)
    if fc is None:
        raise RetargetFailure("'{:s}' has no root motion keys".format(arm_obj.name))
    frames, _, _ = compat.read_keys(fc)
    if len(frames) < 2:
        raise RetargetFailure("'{:s}' has fewer than 2 keyframes".format(arm_obj.name))
    T = len(frames)
    quats = np.zeros((T, len(JOINT_NAMES), 4))
    quats[..., 0] = 1.0
    loc = np.zeros((T, 3))
    for n, name in enumerate(JOINT_NAMES):
        for i in range(4):
            f = compat.find_fcurve(action, slot, 'pose.bones["{:s}"].rotation_quaternion'.format(name), i)
            if f is not None:
                quats[:, n, i] = compat.sample_fcurve(f, frames)
    for i in range(3):
        f = compat.find_fcurve(action, slot, 'pose.bones["root"].location', i)
        if f is not None:
            loc[:, i] = compat.sample_fcurve(f, frames)
    rest_rot, rest_heads = bake.rest_frames(arm_obj)
    tails = np.stack([np.array(bones[n].tail_local) for n in JOINT_NAMES])
    bv = bm.to_motion(tails - rest_heads)
    bv[0] = 0.0
    pos, rot = rt.spec_pose_from_channels(quats, loc, rest_rot, rest_heads, bv)
    return frames, pos, rot, bv, _mat(arm_obj.matrix_world)


# --------------------------------------------------------------------------- mapping on the object

def stored_mapping(obj):
    return {item.target: item.source for item in getattr(obj, "dp_retarget_map", ()) if item.source}


def set_mapping(obj, mapping):
    """Store ``mapping`` on ``obj``: one row per bone (unmapped bones with an empty source)."""
    coll = obj.dp_retarget_map
    coll.clear()
    for b in obj.data.bones:
        item = coll.add()
        item.target = b.name
        item.source = mapping.get(b.name, "")


def mapping_for(obj, preset=""):
    """The mapping to use for ``obj``: a preset (file path or built-in name) when
    given, else the one stored on the object, else the automatic guess (stored)."""
    names = [b.name for b in obj.data.bones]
    if preset:
        path = bpy.path.abspath(preset)
        if os.path.isfile(path):
            data = rt.load_preset(path)
            mapping = {k: v for k, v in data["bones"].items() if k in names and v}
            if not mapping:  # a convention table: match names by convention
                mapping, _ = rt.auto_mapping(names, conventions={data["name"]: data}, convention=data["name"])
        else:
            mapping, _ = rt.auto_mapping(names, convention=preset)
        set_mapping(obj, mapping)
        return mapping
    mapping = stored_mapping(obj)
    if mapping:
        return mapping
    parents = [names.index(b.parent.name) if b.parent else -1 for b in obj.data.bones]
    mapping, conv = rt.auto_mapping(names, parents)
    if not mapping:
        raise RetargetFailure("no bone naming convention recognised on '{:s}' (CMU/BVH, Mixamo, Rigify DEF-, "
                              "Unreal): load a preset or fill in the mapping".format(obj.name))
    set_mapping(obj, mapping)
    return mapping


# --------------------------------------------------------------------------- writing keys

def _path(name, prop):
    return 'pose.bones["{:s}"].{:s}'.format(bpy.utils.escape_identifier(name), prop)


def key_rig(obj, basis, frames, action_name):
    """A NEW action on ``obj`` keying every bone's location, rotation (in the pose
    bone's own rotation mode) and scale from ``matrix_basis (T, B, 4, 4)``."""
    names = [b.name for b in obj.data.bones]
    modes = [obj.pose.bones[n].rotation_mode for n in names]
    loc, rot, scale = rt.channels(basis, modes)
    old, _ = compat.assigned_action(obj)
    if old is not None and old.users <= 1 and not old.use_fake_user:
        old.use_fake_user = True  # keep the rig's previous action when the new one replaces it
    action, slot = compat.new_action_for(obj, action_name)
    for b, name in enumerate(names):
        mode = modes[b]
        for i in range(3):
            compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, "location"), i, name),
                              frames, loc[:, b, i])
        if mode == 'QUATERNION':
            for i in range(4):
                compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, "rotation_quaternion"), i, name),
                                  frames, rot[:, b, i])
        elif mode == 'AXIS_ANGLE':
            aa = quat_to_axis_angle(rot[:, b])
            for i in range(4):
                compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, "rotation_axis_angle"), i, name),
                                  frames, aa[:, i])
        else:
            for i in range(3):
                compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, "rotation_euler"), i, name),
                                  frames, rot[:, b, i])
        for i in range(3):
            compat.write_keys(compat.ensure_fcurves(action, slot, _path(name, "scale"), i, name),
                              frames, scale[:, b, i])
    return action


def keyed_world(obj, ret, frames):
    """World matrices ``(T, B, 4, 4)`` of a rig keyed by :func:`key_rig`, read back
    from its action (numpy forward kinematics, no scene evaluation)."""
    action, slot = compat.assigned_action(obj)
    names = [b.name for b in obj.data.bones]
    T, B = len(frames), len(names)
    basis = np.broadcast_to(np.eye(4), (T, B, 4, 4)).copy()
    for b, name in enumerate(names):
        pb = obj.pose.bones[name]

        def get(prop, i, default):
            fc = compat.find_fcurve(action, slot, _path(name, prop), i)
            return compat.sample_fcurve(fc, frames) if fc is not None else np.full(T, default)

        loc = np.stack([get("location", i, pb.location[i]) for i in range(3)], -1)
        scl = np.stack([get("scale", i, pb.scale[i]) for i in range(3)], -1)
        if pb.rotation_mode == 'QUATERNION':
            R = quat_to_matrix(np.stack([get("rotation_quaternion", i, pb.rotation_quaternion[i])
                                         for i in range(4)], -1))
        elif pb.rotation_mode == 'AXIS_ANGLE':
            R = quat_to_matrix(axis_angle_to_quat(np.stack([get("rotation_axis_angle", i, pb.rotation_axis_angle[i])
                                                            for i in range(4)], -1)))
        else:
            xyz = np.stack([get("rotation_euler", i, pb.rotation_euler[i]) for i in range(3)], -1)
            R = euler_to_matrix(xyz[:, ["XYZ".index(a) for a in pb.rotation_mode]], pb.rotation_mode)
        basis[:, b, :3, :3] = R * scl[:, None, :]
        basis[:, b, :3, 3] = loc
    pose = rt.pose_from_basis(ret.target.rest, ret.target.parents, basis, ret.target.order)
    return _mat(obj.matrix_world)[None, None] @ pose


# --------------------------------------------------------------------------- retargeting

class _Job:
    """One dancer: its DP armature, the target rig and the solved pose."""

    def __init__(self, source, target, preset="", foot_lock=True, origin=None):
        if source is None or source.type != 'ARMATURE':
            raise RetargetFailure("the source must be a Dancing Points armature")
        if target is None or target.type != 'ARMATURE':
            raise RetargetFailure("the target must be an armature")
        if source == target:
            raise RetargetFailure("source and target are the same armature")
        self.source, self.target = source, target
        bpy.context.view_layer.update()  # up-to-date matrix_world of objects moved since the last evaluation
        self.frames, self.pos, self.rot, bv, self.src_matrix = source_motion(source)
        try:
            mapping = mapping_for(target, preset)
            self.ret = rt.Retargeter(bv, target_rig(target), mapping, foot_lock=foot_lock)
        except rt.RetargetError as exc:
            raise RetargetFailure("{:s}: {:s}".format(target.name, str(exc))) from None
        if origin is None:
            origin = _duet_origin(source)
        self.pose = self.ret.solve(self.pos, self.rot, self.src_matrix, fps=_fps(), origin=origin)

    def src_wrists(self):
        pts, _ = rt.source_world(self.pos, self.rot, self.src_matrix)
        lm = rt.source_landmarks(pts)
        return np.stack([lm["lwrist"], lm["rwrist"]], axis=1)

    def key(self):
        basis = self.ret.basis(self.pose.W)
        name = "DP {:s} {:s}".format(self.target.name, self.source.name)
        action = key_rig(self.target, basis, self.frames, name)
        self.target[SOURCE_PROP] = self.source.name
        self.source[TARGET_PROP] = self.target.name
        action[SOURCE_PROP] = self.source.name
        return action


def _duet_origin(*sources):
    """Centre of the duet of ``sources`` (DP armatures; the partner of a single one
    is found in its duet collection) about which root motion is scaled."""
    if len(sources) == 1:
        partner = _partner_of(sources[0])
        sources = sources + ((partner,) if partner is not None else ())
    pts = []
    for src in sources:
        try:
            _, pos, rot, _, mat = source_motion(src)
        except RetargetFailure:
            continue
        pts.append(rt.source_world(pos, rot, mat)[0])
    return rt.duet_origin(*pts) if pts else None


def _fps():
    scene = bpy.context.scene
    return scene.render.fps / scene.render.fps_base if scene is not None else 30.0


def _partner_of(source):
    """The other DP armature of ``source``'s duet collection, or None."""
    role = source.get(ROLE_PROP)
    for coll in source.users_collection:
        if is_duet(coll):
            for o in coll.objects:
                if o != source and o.type == 'ARMATURE' and o.get(ROLE_PROP) in ("leader", "follower") \
                        and o.get(ROLE_PROP) != role:
                    return o
    return None


def retarget_one(context, source, target, preset="", foot_lock=True, close_hands=True):
    """Retarget ``source`` (a DP armature) onto ``target``; the hands close onto the
    partner's rig when the partner dancer was already retargeted. Returns a dict of figures."""
    bake.ensure_object_mode(context)
    job = _Job(source, target, preset, foot_lock)
    info = {"scale": job.ret.scale, "frames": len(job.frames)}
    partner = _partner_of(source) if close_hands else None
    prig = bpy.data.objects.get(partner.get(TARGET_PROP, "")) if partner is not None else None
    if prig is not None and prig.type == 'ARMATURE' and prig != target \
            and prig.get(SOURCE_PROP) == partner.name and stored_mapping(prig):
        try:
            pframes, ppos, prot, pbv, pmat = source_motion(partner)
            if len(pframes) == len(job.frames) and np.allclose(pframes, job.frames):
                pret = rt.Retargeter(pbv, target_rig(prig, store=False), stored_mapping(prig), foot_lock=False)
                pw = pret.wrists(keyed_world(prig, pret, job.frames))
                pts, _ = rt.source_world(ppos, prot, pmat)
                lm = rt.source_landmarks(pts)
                src_b = np.stack([lm["lwrist"], lm["rwrist"]], axis=1)
                before, after = rt.close_hands(job.ret, job.pose, job.src_wrists(), src_b, wrists_b=pw)
                info["hand_gap_before"], info["hand_gap_after"] = before, after
        except (RetargetFailure, rt.RetargetError) as exc:
            info["warning"] = "hands not closed: {:s}".format(str(exc))
    info["action"] = job.key()
    info["pose"] = job.pose
    info["retargeter"] = job.ret
    return info


def retarget_pair(context, pairs, preset=("", ""), foot_lock=True, close_hands=True):
    """Retarget ``pairs`` = ((leader DP armature, rig), (follower DP armature, rig))
    jointly (hands closed symmetrically). Returns ``{role: info}``."""
    bake.ensure_object_mode(context)
    origin = _duet_origin(*[s for s, _ in pairs]) if len(pairs) == 2 else None
    jobs = [_Job(s, t, p, foot_lock, origin) for (s, t), p in zip(pairs, preset)]
    out = {}
    if close_hands and len(jobs) == 2 and len(jobs[0].frames) == len(jobs[1].frames):
        a, b = jobs
        before, after = rt.close_hands(a.ret, a.pose, a.src_wrists(), b.src_wrists(), b.ret, b.pose)
        out["hand_gap_before"], out["hand_gap_after"] = before, after
    for job, role in zip(jobs, ("leader", "follower")):
        out[role] = {"action": job.key(), "scale": job.ret.scale, "pose": job.pose, "retargeter": job.ret,
                     "frames": job.frames}
    return out


def duet_armatures(duet_collection):
    """``{role: DP armature}`` of a duet collection."""
    out = {}
    for o in duet_collection.objects:
        if o.type == 'ARMATURE' and o.get(ROLE_PROP) in ("leader", "follower"):
            out.setdefault(o[ROLE_PROP], o)
    return out


def retarget_duet_onto(leader_rig_obj, follower_rig_obj, duet_collection, context=None, foot_lock=True,
                       close_hands=True, hide_bodies=True):
    """Retarget the duet in ``duet_collection`` (made by ``dancing_points.synthesize``)
    onto two armature objects (either may be None to skip that dancer). With
    ``hide_bodies`` the duet's default bodies are hidden in renders and the
    viewport. Returns ``{role: {"action", "scale", ...}}``; raises
    :class:`RetargetFailure` with a one-line message."""
    context = context or bpy.context
    if duet_collection is None or not is_duet(duet_collection):
        raise RetargetFailure("not a Dancing Points duet collection")
    arms = duet_armatures(duet_collection)
    pairs = [(arms.get(role), rig) for role, rig in (("leader", leader_rig_obj), ("follower", follower_rig_obj))
             if rig is not None]
    if not pairs:
        raise RetargetFailure("no rig to retarget onto")
    for src, rig in pairs:
        if src is None:
            raise RetargetFailure("the duet has no armature for a dancer")
    if len(pairs) == 2:
        out = retarget_pair(context, pairs, foot_lock=foot_lock, close_hands=close_hands)
    else:
        src, rig = pairs[0]
        out = {src[ROLE_PROP]: retarget_one(context, src, rig, foot_lock=foot_lock, close_hands=close_hands)}
    if hide_bodies:
        hide_duet_bodies(duet_collection)
    return out


def hide_duet_bodies(duet_collection, hide=True):
    """Hide (or show) the duet's default bodies in the viewport and renders (the
    armatures stay: they drive the retargeted rigs' source data)."""
    for o in duet_collection.objects:
        if o.type == 'MESH' and o.get(ROLE_PROP) in ("leader", "follower"):
            o.hide_render = hide
            o.hide_viewport = hide


def load_rig_file(path, context=None):
    """Import the armature of a .blend, .glb/.gltf or .fbx file into the scene;
    returns the armature object (the one with the most bones). glTF files that
    need ``EXT_meshopt_compression`` are decoded first (Blender's importer cannot)."""
    from ..dancing_points_addon import gltf_meshopt

    context = context or bpy.context
    path = os.path.abspath(bpy.path.abspath(path))
    if not os.path.isfile(path):
        raise RetargetFailure("no such file: {:s}".format(path))
    ext = os.path.splitext(path)[1].lower()
    before = set(bpy.data.objects)
    if ext == ".blend":
        with bpy.data.libraries.load(path, link=False) as (src, dst):
            dst.objects = list(src.objects)
        coll = bpy.data.collections.new(os.path.splitext(os.path.basename(path))[0])
        context.scene.collection.children.link(coll)
        for o in dst.objects:
            if o is not None:
                coll.objects.link(o)
    elif ext in (".glb", ".gltf"):
        src = path
        tmpdir = None
        if ext == ".glb" and gltf_meshopt.needs_decompression(path):
            tmpdir = tempfile.mkdtemp(prefix="dp_glb_")
            src = gltf_meshopt.decompress_glb(path, os.path.join(tmpdir, os.path.basename(path)))
        try:
            bpy.ops.import_scene.gltf(filepath=src)
        except RuntimeError as exc:
            raise RetargetFailure("{:s}: {:s}".format(path, str(exc).strip().splitlines()[-1])) from None
        finally:
            if tmpdir is not None:
                import shutil
                shutil.rmtree(tmpdir, ignore_errors=True)
    elif ext == ".fbx":
        try:
            bpy.ops.import_scene.fbx(filepath=path)
        except RuntimeError as exc:
            raise RetargetFailure("{:s}: {:s}".format(path, str(exc).strip().splitlines()[-1])) from None
    else:
        raise RetargetFailure("unsupported rig file type '{:s}' (.blend, .glb, .gltf, .fbx)".format(ext))
    arms = [o for o in bpy.data.objects if o not in before and o.type == 'ARMATURE']
    if not arms:
        raise RetargetFailure("{:s} has no armature".format(path))
    return max(arms, key=lambda o: len(o.data.bones))


# --------------------------------------------------------------------------- operators

def _one_line(exc):
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if not isinstance(exc, (RetargetFailure, rt.RetargetError)):
        msg = "retarget failed: {:s}: {:s}".format(type(exc).__name__, msg)
    return msg


def _settings(context):
    return getattr(context.scene, "dp_retarget", None)


class DANCING_POINTS_OT_retarget(bpy.types.Operator):
    """Bake a dancer of the duet onto your own armature as a new action"""

    bl_idname = "dancing_points.retarget"
    bl_label = "Retarget Dancer"
    bl_options = {'REGISTER', 'UNDO'}

    source: StringProperty(name="Source", description="Dancing Points armature (leader or follower)")
    target: StringProperty(name="Target", description="Armature that receives the motion")
    preset: StringProperty(name="Preset", subtype='FILE_PATH', options={'SKIP_SAVE'},
                           description="Bone mapping preset (a .json file or a built-in name: mixamo, rigify, "
                                       "unreal, cmu_bvh); empty: the mapping stored on the target, else automatic")
    foot_lock: BoolProperty(name="Foot Locking", default=True)
    close_hands: BoolProperty(name="Close Hands", default=True)

    def execute(self, context):
        src = bpy.data.objects.get(self.source)
        tgt = bpy.data.objects.get(self.target)
        if src is None or tgt is None:
            self.report({'ERROR'}, "no object named '{:s}'".format(self.source if src is None else self.target))
            return {'CANCELLED'}
        try:
            info = retarget_one(context, src, tgt, self.preset, self.foot_lock, self.close_hands)
        except Exception as exc:
            self.report({'ERROR'}, _one_line(exc))
            return {'CANCELLED'}
        if "warning" in info:
            self.report({'WARNING'}, info["warning"])
        self.report({'INFO'}, "Retargeted '{:s}' onto '{:s}': action '{:s}', {:d} frames, scale {:.3f}".format(
            src.name, tgt.name, info["action"].name, info["frames"], info["scale"]))
        return {'FINISHED'}


class DANCING_POINTS_OT_retarget_duet(bpy.types.Operator):
    """Bake both dancers onto the armatures picked in the panel (hands that hold each other stay together)"""

    bl_idname = "dancing_points.retarget_duet"
    bl_label = "Retarget Duet"
    bl_options = {'REGISTER', 'UNDO'}

    leader_target: StringProperty(name="Leader Rig", options={'SKIP_SAVE'})
    follower_target: StringProperty(name="Follower Rig", options={'SKIP_SAVE'})
    duet: StringProperty(name="Duet", description="Duet collection (empty: the panel's sources)",
                         options={'SKIP_SAVE'})
    hide_bodies: BoolProperty(name="Hide Default Bodies", default=True)

    def execute(self, context):
        s = _settings(context)
        try:
            lt = bpy.data.objects.get(self.leader_target) if self.leader_target else (s.leader_target if s else None)
            ft = bpy.data.objects.get(self.follower_target) if self.follower_target else \
                (s.follower_target if s else None)
            foot_lock = s.foot_lock if s else True
            close = s.close_hands if s else True
            if self.duet:
                coll = bpy.data.collections.get(self.duet)
                out = retarget_duet_onto(lt, ft, coll, context, foot_lock, close, self.hide_bodies)
            else:
                ls = s.leader_source if s else None
                fs = s.follower_source if s else None
                pairs = [(a, b) for a, b in ((ls, lt), (fs, ft)) if a is not None and b is not None]
                if not pairs:
                    raise RetargetFailure("pick a source and a target armature for at least one dancer")
                if len(pairs) == 2:
                    out = retarget_pair(context, pairs, foot_lock=foot_lock, close_hands=close)
                else:
                    out = {"one": retarget_one(context, pairs[0][0], pairs[0][1], foot_lock=foot_lock,
                                               close_hands=close)}
                if self.hide_bodies:
                    for src, _ in pairs:
                        for coll in src.users_collection:
                            if is_duet(coll):
                                hide_duet_bodies(coll)
        except Exception as exc:
            self.report({'ERROR'}, _one_line(exc))
            return {'CANCELLED'}
        n = sum(1 for v in out.values() if isinstance(v, dict) and "action" in v)
        self.report({'INFO'}, "Retargeted {:d} dancer(s)".format(n))
        return {'FINISHED'}


def _preset_file(context, filepath):
    """The preset file of a bone-map operator: its own, else the panel's."""
    s = _settings(context)
    return filepath or (s.preset_path if s else "")


def _target_from(context, name):
    obj = bpy.data.objects.get(name) if name else getattr(context, "active_object", None)
    if obj is None or obj.type != 'ARMATURE':
        raise RetargetFailure("no target armature ('{:s}')".format(name or "the active object"))
    return obj


class DANCING_POINTS_OT_retarget_map_auto(bpy.types.Operator):
    """Fill the target armature's bone mapping from its bone names"""

    bl_idname = "dancing_points.retarget_map_auto"
    bl_label = "Auto Map Bones"
    bl_options = {'REGISTER', 'UNDO'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    convention: EnumProperty(
        name="Convention", default='AUTO',
        items=(('AUTO', "Automatic", "Detect from the bone names"), ('mixamo', "Mixamo", ""),
               ('rigify', "Rigify DEF-", ""), ('unreal', "Unreal", ""), ('cmu_bvh', "CMU / BVH", ""),
               ('cmu_asf', "CMU ASF", "")))

    def execute(self, context):
        try:
            obj = _target_from(context, self.target)
            names = [b.name for b in obj.data.bones]
            mapping, conv = rt.auto_mapping(names, convention=None if self.convention == 'AUTO' else self.convention)
        except Exception as exc:
            self.report({'ERROR'}, _one_line(exc))
            return {'CANCELLED'}
        set_mapping(obj, mapping)
        self.report({'INFO'}, "{:d} of {:d} bones mapped ({:s})".format(len(mapping), len(names), conv or "none"))
        return {'FINISHED'}


class DANCING_POINTS_OT_retarget_map_save(bpy.types.Operator):
    """Save the target armature's bone mapping as a JSON preset"""

    bl_idname = "dancing_points.retarget_map_save"
    bl_label = "Save Bone Map"
    bl_options = {'REGISTER'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    filepath: StringProperty(name="File", subtype='FILE_PATH', options={'SKIP_SAVE'})

    def execute(self, context):
        try:
            obj = _target_from(context, self.target)
            path = bpy.path.abspath(_preset_file(context, self.filepath))
            if not path:
                raise RetargetFailure("no file name")
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            rt.save_preset(path, stored_mapping(obj), name=obj.name)
        except Exception as exc:
            self.report({'ERROR'}, _one_line(exc))
            return {'CANCELLED'}
        self.report({'INFO'}, "Saved the bone map of '{:s}' to {:s}".format(obj.name, path))
        return {'FINISHED'}


class DANCING_POINTS_OT_retarget_map_load(bpy.types.Operator):
    """Load a bone mapping preset (JSON) onto the target armature"""

    bl_idname = "dancing_points.retarget_map_load"
    bl_label = "Load Bone Map"
    bl_options = {'REGISTER', 'UNDO'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    filepath: StringProperty(name="File", subtype='FILE_PATH', options={'SKIP_SAVE'})

    def execute(self, context):
        try:
            obj = _target_from(context, self.target)
            mapping = mapping_for(obj, _preset_file(context, self.filepath))
        except Exception as exc:
            self.report({'ERROR'}, _one_line(exc))
            return {'CANCELLED'}
        self.report({'INFO'}, "{:d} bones mapped on '{:s}'".format(len(mapping), obj.name))
        return {'FINISHED'}


classes = (DP_RetargetBoneMap, DP_RetargetSettings, DANCING_POINTS_OT_retarget, DANCING_POINTS_OT_retarget_duet,
           DANCING_POINTS_OT_retarget_map_auto, DANCING_POINTS_OT_retarget_map_save,
           DANCING_POINTS_OT_retarget_map_load)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.dp_retarget_map = CollectionProperty(type=DP_RetargetBoneMap)
    bpy.types.Object.dp_retarget_map_index = IntProperty(name="Bone", default=0, min=0)
    bpy.types.Scene.dp_retarget = PointerProperty(type=DP_RetargetSettings)


def unregister():
    del bpy.types.Scene.dp_retarget
    del bpy.types.Object.dp_retarget_map_index
    del bpy.types.Object.dp_retarget_map
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
