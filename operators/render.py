# SPDX-License-Identifier: GPL-3.0-or-later
"""``bpy.ops.dancing_points.render_preview``: a quick Workbench render of the
frame range to a PNG sequence or a video. Works in ``--background``; the
scene's render settings are restored afterwards."""

import os

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from .compat import operator_error_text


def _default_path(context):
    settings = getattr(context.scene, "dancing_points", None)
    return settings.preview_path if settings is not None and settings.preview_path else "//dancing_points_preview/"


class _Saved:
    """Attribute values to put back after the render."""

    def __init__(self):
        self.items = []

    def set(self, obj, attr, value):
        self.items.append((obj, attr, getattr(obj, attr)))
        setattr(obj, attr, value)

    def restore(self):
        for obj, attr, value in reversed(self.items):
            try:
                setattr(obj, attr, value)
            except (AttributeError, TypeError, ValueError):
                pass


class DANCING_POINTS_OT_render_preview(bpy.types.Operator):
    """Render the frame range with Workbench to a PNG sequence or a video"""

    bl_idname = "dancing_points.render_preview"
    bl_label = "Render Preview"
    bl_options = {'REGISTER'}

    filepath: StringProperty(
        name="Output", subtype='FILE_PATH', options={'SKIP_SAVE'},
        description="Output path (a folder ending in '/' or a file prefix; empty: the panel's setting)",
    )
    file_format: EnumProperty(
        name="Format", default='PNG',
        items=(('PNG', "PNG Sequence", "One PNG image per frame"),
               ('FFMPEG', "Video", "An MPEG-4 (H.264) video")),
    )
    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's)")
    resolution_percentage: IntProperty(name="Resolution %", default=50, min=1, max=100, subtype='PERCENTAGE')

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        if scene.camera is None:
            self.report({'ERROR'}, "the scene has no camera (Synthesise adds one)")
            return {'CANCELLED'}
        path = self.filepath or _default_path(context)
        folder = os.path.dirname(bpy.path.abspath(path))
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as exc:
            self.report({'ERROR'}, "cannot create {:s}: {:s}".format(folder, exc.strerror or str(exc)))
            return {'CANCELLED'}
        f0 = self.frame_start if self.frame_start >= 0 else scene.frame_start
        f1 = self.frame_end if self.frame_end >= 0 else scene.frame_end
        if f1 < f0:
            self.report({'ERROR'}, "empty frame range {:d}..{:d}".format(f0, f1))
            return {'CANCELLED'}
        saved = _Saved()
        r = scene.render
        try:
            saved.set(r, "engine", 'BLENDER_WORKBENCH')
            shading = scene.display.shading
            saved.set(shading, "light", 'STUDIO')
            saved.set(shading, "color_type", 'MATERIAL')
            saved.set(r, "filepath", path)
            saved.set(r, "resolution_percentage", self.resolution_percentage)
            saved.set(r, "use_file_extension", True)
            saved.set(scene, "frame_start", f0)
            saved.set(scene, "frame_end", f1)
            img = r.image_settings
            if hasattr(img, "media_type"):
                saved.set(img, "media_type", 'VIDEO' if self.file_format == 'FFMPEG' else 'IMAGE')
            saved.set(img, "file_format", self.file_format)
            if self.file_format == 'FFMPEG':
                saved.set(r.ffmpeg, "format", 'MPEG4')
                saved.set(r.ffmpeg, "codec", 'H264')
                saved.set(img, "color_mode", 'RGB')
            else:
                saved.set(img, "color_mode", 'RGBA')
            frame = scene.frame_current
            try:
                bpy.ops.render.render(animation=True, scene=scene.name)
            finally:
                scene.frame_set(frame)
            out = bpy.path.abspath(r.frame_path(frame=f0))
        except Exception as exc:
            self.report({'ERROR'}, "render failed: {:s}".format(operator_error_text(exc)))
            return {'CANCELLED'}
        finally:
            saved.restore()
        self.report({'INFO'}, "Rendered frames {:d}-{:d} to {:s}".format(f0, f1, out))
        return {'FINISHED'}


classes = (DANCING_POINTS_OT_render_preview,)
register, unregister = bpy.utils.register_classes_factory(classes)
