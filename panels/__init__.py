# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Dancing Points" tab of the 3D Viewport sidebar (N panel)."""

import os
import tomllib

import bpy

from . import live, method, retarget
from .common import SubPanel, split_layout

_MANIFEST = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "blender_manifest.toml")
_version = None


def addon_version():
    """The extension's version string, read once from blender_manifest.toml (the single source)."""
    global _version
    if _version is None:
        try:
            with open(_MANIFEST, "rb") as fh:
                _version = str(tomllib.load(fh)["version"])
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            _version = "unknown"
    return _version


class VIEW3D_PT_dancing_points(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points"
    bl_label = "Dancing Points"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Dancing Points"

    def draw(self, context):
        # Labels only: the controls are in the sub-panels below.
        layout = self.layout
        layout.label(text="Version " + addon_version())
        layout.label(text="Import a take: File > Import > Dancing Points take")


def _active_take(context):
    from ..operators.props import active_take
    return active_take(context)


class VIEW3D_PT_dancing_points_take(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_take"
    bl_label = "Take"

    def draw(self, context):
        layout, settings = split_layout(self.layout, context)
        layout.operator("dancing_points.import_take", text="Import Take...", icon='IMPORT')
        if settings is None:
            return
        layout.prop(settings, "take")
        take = _active_take(context)
        if take is None:
            layout.label(text="No active take", icon='INFO')
            return
        s = take.dancing_points
        col = layout.column(align=True)
        col.label(text=take.name, icon='OUTLINER_COLLECTION')
        col.label(text="{:d} frames at {:g} fps from frame {:d}".format(s.n_frames, s.fps, s.frame_start))
        layout.prop(s, "role")
        layout.prop(s, "devices")
        layout.prop(s, "height")
        row = layout.row(heading="Floor")
        row.prop(s, "use_floor_y", text="")
        sub = row.row()
        sub.active = s.use_floor_y
        sub.prop(s, "floor_y", text="")
        if s.height_source:  # what the last synthesis used
            col = layout.column(align=True)
            col.label(text="Height {:.2f} m ({:s})".format(s.height_used, s.height_source), icon='INFO')
            col.label(text="Floor at {:+.3f} m ({:s})".format(s.floor_used, s.floor_source))
            if s.orientations_used:
                col.label(text=s.orientations_used, icon='ERROR')
        from ..operators.song import song_of
        song = song_of(take)
        col = layout.column(align=True)
        if song is not None:
            col.label(text=os.path.basename(song.path), icon='SOUND')
            col.label(text="{:.1f} bpm, {:d} beats, offset {:.3f} s".format(song.tempo_bpm, len(song.beats),
                                                                            song.offset_s))
        op = col.operator("dancing_points.set_song", text="Change Song..." if song else "Set Song...",
                          icon='SOUND')
        op.take = take.name
        layout.operator("dancing_points.remove_take", text="Remove Take", icon='TRASH').take = take.name


class VIEW3D_PT_dancing_points_turns(SubPanel, bpy.types.Panel):
    """The active take's device turns: devices that report another convention than SPEC §3's."""

    bl_idname = "VIEW3D_PT_dancing_points_turns"
    bl_label = "Device Turns"
    bl_parent_id = "VIEW3D_PT_dancing_points_take"  # under the Take panel
    bl_options = {'DEFAULT_CLOSED'}

    @classmethod
    def poll(cls, context):
        return _active_take(context) is not None

    def draw(self, context):
        layout = self.layout
        s = _active_take(context).dancing_points
        layout.label(text="reported = true · turn, in the device's axes")
        for key in ("head_turn", "lhand_turn", "rhand_turn"):
            layout.prop(s, key)


class VIEW3D_PT_dancing_points_synthesis(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_synthesis"
    bl_label = "Synthesis"

    def draw(self, context):
        layout, settings = split_layout(self.layout, context)
        if settings is None:
            return
        layout.prop(settings, "foot_lock")
        layout.prop(settings, "hand_ik")
        layout.prop(settings, "follow_devices")
        row = layout.row()
        row.enabled = _active_take(context) is not None
        op = row.operator("dancing_points.synthesize", text="Synthesise Duet", icon='ARMATURE_DATA')
        op.foot_lock = settings.foot_lock
        op.hand_ik = settings.hand_ik
        op.follow_devices = settings.follow_devices


class VIEW3D_PT_dancing_points_preview(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_preview"
    bl_label = "Preview"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        layout, settings = split_layout(self.layout, context)
        if settings is None:
            return
        layout.prop(settings, "preview_path")
        layout.prop(settings, "preview_format")
        layout.prop(settings, "camera_mode")
        layout.prop(settings, "burn_in")
        from ..operators import stage
        in_the_way = stage.obstacles(context.scene)
        if in_the_way:
            box = layout.box()
            names = ", ".join(o.name for o in in_the_way)
            box.label(text="{:s} stands where they dance".format(names), icon='INFO')
            box.operator("dancing_points.hide_in_previews", icon='HIDE_ON')
        row = layout.row()
        row.enabled = stage.preview_camera(context.scene) is not None
        op = row.operator("dancing_points.render_preview", text="Render Preview", icon='RENDER_ANIMATION')
        op.filepath = settings.preview_path
        op.file_format = settings.preview_format
        op.burn_in = settings.burn_in
        layout.operator("dancing_points.remove_stage", text="Remove Stage", icon='TRASH')


classes = (VIEW3D_PT_dancing_points, VIEW3D_PT_dancing_points_take, VIEW3D_PT_dancing_points_turns,
           VIEW3D_PT_dancing_points_synthesis, VIEW3D_PT_dancing_points_preview)

classes += retarget.classes
classes += method.classes
classes += live.classes
register, unregister = bpy.utils.register_classes_factory(classes)
