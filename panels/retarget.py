# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Retarget" sub-panel of the Dancing Points sidebar tab: two armature
pickers per dancer (the baked Dancing Points armature and your rig), the
options, and the bone mapping of the active armature (editable, saved and
loaded as JSON presets)."""

import bpy

from ..operators.props import ROLE_PROP
from .common import SubPanel, split_layout


class DP_UL_retarget_map(bpy.types.UIList):
    """One row per bone of the target: its name and the Dancing Points bone(s) it follows."""

    bl_idname = "DP_UL_retarget_map"

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0, flt_flag=0):
        row = layout.row(align=True)
        row.label(text=item.target, icon='BONE_DATA' if item.source else 'BLANK1')
        row.prop(item, "source", text="", emboss=True)


class VIEW3D_PT_dancing_points_retarget(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_retarget"
    bl_label = "Retarget"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        layout, s = split_layout(self.layout, context, "dp_retarget")
        if s is None:
            return
        for role, label in (("leader", "Leader"), ("follower", "Follower")):
            col = layout.column(align=True)
            col.label(text=label, icon='ARMATURE_DATA')
            col.prop(s, role + "_source", text="Dancer")
            col.prop(s, role + "_target", text="Your Rig")
            src, tgt = getattr(s, role + "_source"), getattr(s, role + "_target")
            row = col.row()
            row.enabled = src is not None and tgt is not None
            op = row.operator("dancing_points.retarget", text="Retarget " + label, icon='POSE_HLT')
            op.source = src.name if src is not None else ""
            op.target = tgt.name if tgt is not None else ""
            op.foot_lock = s.foot_lock
            op.close_hands = s.close_hands
        layout.prop(s, "foot_lock")
        layout.prop(s, "close_hands")
        row = layout.row()
        row.enabled = (s.leader_source is not None and s.leader_target is not None) or \
                      (s.follower_source is not None and s.follower_target is not None)
        row.operator("dancing_points.retarget_duet", text="Retarget Duet", icon='ARMATURE_DATA')
        # Bone mapping of the active armature (not a Dancing Points one).
        obj = context.active_object
        box = layout.box()
        if obj is None or obj.type != 'ARMATURE' or obj.get(ROLE_PROP):
            box.label(text="Select your rig to edit its bone mapping", icon='INFO')
            return
        box.label(text="Bone Map: " + obj.name, icon='GROUP_BONE')
        row = box.row(align=True)
        op = row.operator("dancing_points.retarget_map_auto", text="Auto", icon='AUTO')
        op.target = obj.name
        op = row.operator("dancing_points.retarget_map_load", text="Load", icon='FILE_FOLDER')
        op.target = obj.name
        op = row.operator("dancing_points.retarget_map_save", text="Save", icon='FILE_TICK')
        op.target = obj.name
        how = obj.get("dp_retarget_convention")
        if how == "structure":
            box.label(text="Mapped by structure: check the rows below", icon='ERROR')
        elif how:
            box.label(text="Convention: " + str(how), icon='CHECKMARK')
        if all(n in obj.data.bones for n in ("torso", "DEF-spine", "thigh_fk.L", "upper_arm_fk.L")):
            box.label(text="Rigify rig: solved on DEF- bones, its FK/IK controls are keyed", icon='INFO')
        box.prop(s, "preset_path")
        if len(obj.dp_retarget_map):
            box.template_list("DP_UL_retarget_map", "", obj, "dp_retarget_map", obj, "dp_retarget_map_index", rows=6)


classes = (DP_UL_retarget_map, VIEW3D_PT_dancing_points_retarget)
