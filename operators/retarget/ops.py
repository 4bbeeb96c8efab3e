# SPDX-License-Identifier: GPL-3.0-or-later
"""The retarget operators: one dancer, the duet, and the bone map's auto /
save / load. Each reports a failure as one line (``errors.error_message``)."""

import os

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.retarget import RetargetError
from ...dancing_points_addon.errors import error_message
from ..kinds import is_duet
from .jobs import hide_duet_bodies, retarget_duet_onto, retarget_one, retarget_pair
from ...dancing_points_addon.retarget.structure import describe, structural_mapping
from .mapping import CONVENTION_PROP, guess_mapping, mapping_for, preset_path, set_mapping, stored_mapping
from .rig import target_rig
from .props import settings


class _RetargetOperator:
    """``execute`` runs ``run(context)``, which returns the line to report when
    done; any failure is reported as one line and cancels."""

    def execute(self, context):
        try:
            done = self.run(context)
        except Exception as exc:
            self.report({'ERROR'}, error_message(exc, "retarget failed"))
            return {'CANCELLED'}
        self.report({'INFO'}, done)
        return {'FINISHED'}


class DANCING_POINTS_OT_retarget(_RetargetOperator, bpy.types.Operator):
    """Bake a dancer of the duet onto your own armature as a new action"""

    bl_idname = "dancing_points.retarget"
    bl_label = "Retarget Dancer"
    bl_options = {'REGISTER', 'UNDO'}

    source: StringProperty(name="Source", description="Dancing Points armature (leader or follower)")
    target: StringProperty(name="Target", description="Armature that receives the motion")
    preset: StringProperty(name="Preset", subtype='FILE_PATH', options={'SKIP_SAVE'},
                           description="Bone mapping preset (a .json file or a built-in name: mixamo, rigify, "
                                       "rigify_metarig, vrm0, vrm1, unreal, cmu_bvh); empty: the mapping stored "
                                       "on the target, else automatic (by names, else by structure)")
    foot_lock: BoolProperty(name="Foot Locking", default=True)
    close_hands: BoolProperty(name="Close Hands", default=True)

    def run(self, context):
        src = bpy.data.objects.get(self.source)
        tgt = bpy.data.objects.get(self.target)
        if src is None or tgt is None:
            raise RetargetError("no object named '{:s}'".format(self.source if src is None else self.target))
        info = retarget_one(context, src, tgt, self.preset, self.foot_lock, self.close_hands)
        for k in ("note", "warning"):
            if k in info:
                self.report({'WARNING'}, info[k])
        return "Retargeted '{:s}' onto '{:s}': action '{:s}', {:d} frames, scale {:.3f}{:s}".format(
            src.name, tgt.name, info["action"].name, info["frames"], info["scale"],
            " (Rigify controls keyed, limbs in FK)" if info.get("controls") else "")


def _named(name):
    """The object named ``name`` (a name given but not found is an error, not a dancer skipped)."""
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise RetargetError("no object named '{:s}'".format(name))
    return obj


class DANCING_POINTS_OT_retarget_duet(_RetargetOperator, bpy.types.Operator):
    """Bake both dancers onto the armatures picked in the panel (hands that hold each other stay together)"""

    bl_idname = "dancing_points.retarget_duet"
    bl_label = "Retarget Duet"
    bl_options = {'REGISTER', 'UNDO'}

    leader_target: StringProperty(name="Leader Rig", options={'SKIP_SAVE'})
    follower_target: StringProperty(name="Follower Rig", options={'SKIP_SAVE'})
    duet: StringProperty(name="Duet", description="Duet collection (empty: the panel's sources)",
                         options={'SKIP_SAVE'})
    hide_bodies: BoolProperty(name="Hide Default Bodies", default=True)

    def run(self, context):
        s = settings(context)
        lt, ft = (_named(name) if name else (getattr(s, field) if s else None)
                  for name, field in ((self.leader_target, "leader_target"),
                                      (self.follower_target, "follower_target")))
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
                raise RetargetError("pick a source and a target armature for at least one dancer")
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
        n = sum(1 for v in out.values() if isinstance(v, dict) and "action" in v)
        for v in out.values():
            if isinstance(v, dict) and "note" in v:
                self.report({'WARNING'}, v["note"])
        return "Retargeted {:d} dancer(s)".format(n)


def _preset_file(context, filepath):
    """The preset file of a bone-map operator: its own, else the panel's."""
    s = settings(context)
    return filepath or (s.preset_path if s else "")


def _target_from(context, name):
    obj = bpy.data.objects.get(name) if name else getattr(context, "active_object", None)
    if obj is None or obj.type != 'ARMATURE':
        raise RetargetError("no target armature ('{:s}')".format(name or "the active object"))
    return obj


class DANCING_POINTS_OT_retarget_map_auto(_RetargetOperator, bpy.types.Operator):
    """Fill the target armature's bone mapping from its bone names"""

    bl_idname = "dancing_points.retarget_map_auto"
    bl_label = "Auto Map Bones"
    bl_options = {'REGISTER', 'UNDO'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    convention: EnumProperty(
        name="Convention", default='AUTO',
        items=(('AUTO', "Automatic", "Detect from the bone names, else map by the rig's structure"),
               ('mixamo', "Mixamo", ""), ('rigify', "Rigify (generated rig, DEF-)", ""),
               ('rigify_metarig', "Rigify Meta-Rig", ""), ('vrm0', "VRM (VRoid J_Bip_)", ""),
               ('vrm1', "VRM 1.0 Humanoid", ""), ('unreal', "Unreal", ""), ('cmu_bvh', "CMU / BVH", ""),
               ('cmu_asf', "CMU ASF", ""),
               ('STRUCTURE', "By Structure", "Find pelvis, legs, spine and arms from the hierarchy and rest pose")))

    def run(self, context):
        obj = _target_from(context, self.target)
        names = [b.name for b in obj.data.bones]
        if self.convention == 'AUTO':
            mapping, conv = guess_mapping(obj)
        elif self.convention == 'STRUCTURE':
            mapping, _ = structural_mapping(target_rig(obj, store=False))
            conv = "structure"
        else:
            mapping, conv = rt.auto_mapping(names, convention=self.convention)
        set_mapping(obj, mapping)
        obj[CONVENTION_PROP] = conv or ""
        if conv == "structure":
            self.report({'WARNING'}, "Mapped by structure, check: " + describe(mapping))
        return "{:d} of {:d} bones mapped ({:s})".format(len(mapping), len(names), conv or "none")


class DANCING_POINTS_OT_retarget_map_save(_RetargetOperator, bpy.types.Operator):
    """Save the target armature's bone mapping as a JSON preset"""

    bl_idname = "dancing_points.retarget_map_save"
    bl_label = "Save Bone Map"
    bl_options = {'REGISTER'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    filepath: StringProperty(name="File", subtype='FILE_PATH', options={'SKIP_SAVE'})

    def run(self, context):
        obj = _target_from(context, self.target)
        preset = _preset_file(context, self.filepath)
        if not preset:
            raise RetargetError("no file name")
        path = preset_path(preset)
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        rt.save_preset(path, stored_mapping(obj), name=obj.name)
        return "Saved the bone map of '{:s}' to {:s}".format(obj.name, path)


class DANCING_POINTS_OT_retarget_map_load(_RetargetOperator, bpy.types.Operator):
    """Load a bone mapping preset (JSON) onto the target armature"""

    bl_idname = "dancing_points.retarget_map_load"
    bl_label = "Load Bone Map"
    bl_options = {'REGISTER', 'UNDO'}

    target: StringProperty(name="Target", options={'SKIP_SAVE'})
    filepath: StringProperty(name="File", subtype='FILE_PATH', options={'SKIP_SAVE'})

    def run(self, context):
        obj = _target_from(context, self.target)
        mapping = mapping_for(obj, _preset_file(context, self.filepath))
        return "{:d} bones mapped on '{:s}'".format(len(mapping), obj.name)


classes = (DANCING_POINTS_OT_retarget, DANCING_POINTS_OT_retarget_duet, DANCING_POINTS_OT_retarget_map_auto,
           DANCING_POINTS_OT_retarget_map_save, DANCING_POINTS_OT_retarget_map_load)
