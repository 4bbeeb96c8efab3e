# SPDX-License-Identifier: GPL-3.0-or-later
"""``bpy.ops.dancing_points.render_preview``: a quick Workbench render of the
frame range to a PNG sequence or a video. Works in ``--background``; the
scene's render settings are restored afterwards."""

import os

import bpy
import numpy as np
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


def _output_files(render, f0, f1, file_format):
    """The files a render of frames ``f0..f1`` writes: one PNG per frame, or the video."""
    if file_format == 'FFMPEG':
        return [bpy.path.abspath(render.frame_path(frame=f0))]
    return [bpy.path.abspath(render.frame_path(frame=f)) for f in range(f0, f1 + 1)]


def _is_blank_png(path):
    """Whether a written PNG shows nothing: every pixel the same colour, up to
    the render's dithering noise (a few 8-bit steps)."""
    img = bpy.data.images.load(path, check_existing=False)
    try:
        px = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(px)
        px = px.reshape(-1, max(int(img.channels), 1))
    finally:
        bpy.data.images.remove(img)
    return len(px) == 0 or float(np.ptp(px, axis=0).max()) < 0.05


def _check_written(files, file_format):
    """None when every output file was written and the render shows something;
    else the problem, after removing the empty files this render left (a full
    disk leaves zero-byte images)."""
    missing = [f for f in files if not os.path.isfile(f)]
    empty = [f for f in files if os.path.isfile(f) and os.path.getsize(f) == 0]
    for f in empty:
        try:
            os.remove(f)
        except OSError:
            pass
    if missing or empty:
        what = "the video" if file_format == 'FFMPEG' else "{:d} of {:d} frames".format(
            len(missing) + len(empty), len(files))
        return "{:s} not written (disk full or folder not writable?): {:s}".format(
            what, (missing + empty)[0])
    if file_format == 'PNG' and _is_blank_png(files[len(files) // 2]):
        return "the rendered frames are blank ({:s}): nothing in front of the camera?".format(files[len(files) // 2])
    return None


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
            files = _output_files(r, f0, f1, self.file_format)
            problem = _check_written(files, self.file_format)
        except Exception as exc:
            self.report({'ERROR'}, "render failed: {:s}".format(operator_error_text(exc)))
            return {'CANCELLED'}
        finally:
            saved.restore()
        if problem:
            self.report({'ERROR'}, "render failed: {:s}".format(problem))
            return {'CANCELLED'}
        self.report({'INFO'}, "Rendered frames {:d}-{:d} to {:s}".format(f0, f1, files[0]))
        return {'FINISHED'}


classes = (DANCING_POINTS_OT_render_preview,)
register, unregister = bpy.utils.register_classes_factory(classes)
