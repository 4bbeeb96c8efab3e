# SPDX-License-Identifier: GPL-3.0-or-later
"""``bpy.ops.dancing_points.render_preview``: a quick Workbench render of the
frame range to a PNG sequence or a video. Works in ``--background``; the
scene's render settings are restored afterwards.

The look (studio light, material colours, shadows, cavity, outlines) and the
burn-in (the take's name, the frame and the time, and with a song the beat's
count: Blender's render stamp) are set for the render only. A video has the
scene's song (AAC) when a take's song is in the sequencer. It renders through the DP Camera on the scene's
camera mode (follow / wide), or through the scene's own camera when that is
chosen (``stage.preview_camera``); the scene's camera is put back afterwards.
The user's objects marked ``["dp_hide_in_preview"]``
(``dancing_points.hide_in_previews``) are hidden for the render only."""

import os

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import stage
from .compat import operator_error_text


def _default_path(context):
    settings = getattr(context.scene, "dancing_points", None)
    return settings.preview_path if settings is not None and settings.preview_path else "//dancing_points_preview/"


class _Saved:
    """Attribute values to put back after the render."""

    def __init__(self):
        self.items = []

    def set(self, obj, attr, value):
        old = getattr(obj, attr)
        if not isinstance(old, str) and hasattr(old, "__len__"):
            old = tuple(old)  # a colour: a copy, not the live array
        self.items.append((obj, attr, old))
        setattr(obj, attr, value)

    def set_if(self, obj, attr, value):
        """:meth:`set` where this Blender version has ``attr``."""
        if hasattr(obj, attr):
            self.set(obj, attr, value)

    def restore(self):
        for obj, attr, value in reversed(self.items):
            try:
                setattr(obj, attr, value)
            except (AttributeError, TypeError, ValueError):
                pass


# Workbench settings of the preview's look (scene.display.shading).
LOOK = (("light", 'STUDIO'), ("color_type", 'MATERIAL'), ("show_shadows", True), ("shadow_intensity", 0.45),
        ("show_cavity", True), ("cavity_type", 'BOTH'), ("show_object_outline", True),
        ("object_outline_color", (0.05, 0.05, 0.05)), ("show_specular_highlight", True))
STAMP_OFF = ("use_stamp_date", "use_stamp_render_time", "use_stamp_camera", "use_stamp_lens",
             "use_stamp_scene", "use_stamp_filename", "use_stamp_marker", "use_stamp_memory",
             "use_stamp_hostname", "use_stamp_frame_range", "use_stamp_sequencer_strip")


def take_label(scene):
    """The name shown in the burn-in: the newest visible duet's take, else the scene's take."""
    duet = stage.newest_duet(scene)
    name = duet.dancing_points.take_name if duet is not None else ""
    if not name:
        settings = getattr(scene, "dancing_points", None)
        name = settings.take.name if settings is not None and settings.take is not None else scene.name
    return name[len("DP Take "):] if name.startswith("DP Take ") else name


def stamp_font_size(scene):
    """The burn-in's font size (pixels) for the render's size: 24 at 540 rows."""
    r = scene.render
    return max(8, int(round(r.resolution_y * r.resolution_percentage / 100.0 * 24 / 540)))


def set_audio(saved, scene, video):
    """A video gets the scene's song (AAC) when a take's song is in its sequencer;
    PNG frames stay silent."""
    from .song import has_song

    ff = scene.render.ffmpeg
    if video and has_song(scene):
        saved.set(ff, "audio_codec", 'AAC')
        saved.set_if(ff, "audio_channels", 'STEREO')
        saved.set_if(ff, "audio_mixrate", 48000)
        saved.set_if(ff, "audio_bitrate", 192)
        return True
    saved.set(ff, "audio_codec", 'NONE')
    return False


def set_look(saved, scene, burn_in):
    shading = scene.display.shading
    for attr, value in LOOK:
        saved.set_if(shading, attr, value)
    # one anti-aliasing pass (FXAA): 4x faster than the default 8 samples, plenty for a preview
    saved.set_if(scene.display, "render_aa", 'FXAA')
    r = scene.render
    saved.set_if(r, "use_stamp", bool(burn_in))
    if burn_in:
        saved.set_if(r, "use_stamp_note", True)
        saved.set_if(r, "stamp_note_text", take_label(scene))
        saved.set_if(r, "use_stamp_frame", True)
        saved.set_if(r, "use_stamp_time", True)
        for attr in STAMP_OFF:
            saved.set_if(r, attr, False)
        from .song import has_song
        if has_song(scene):  # the dancers' count: the name of the last beat marker ("Marker 5")
            saved.set_if(r, "use_stamp_marker", True)
        saved.set_if(r, "stamp_font_size", stamp_font_size(scene))
        saved.set_if(r, "stamp_foreground", (1.0, 1.0, 1.0, 1.0))
        saved.set_if(r, "stamp_background", (0.0, 0.0, 0.0, 0.55))



def _output_files(render, f0, f1, file_format):
    """The files a render of frames ``f0..f1`` writes: one PNG per frame, or the video."""
    if file_format == 'FFMPEG':
        return [bpy.path.abspath(render.frame_path(frame=f0))]
    return [bpy.path.abspath(render.frame_path(frame=f)) for f in range(f0, f1 + 1)]


def _is_blank_png(path, margin_rows=0):
    """Whether a written PNG shows nothing: every pixel the same colour, up to
    the render's dithering noise (a few 8-bit steps); ``margin_rows`` rows at
    the top and bottom (the burn-in's) are not looked at."""
    img = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = img.size
        px = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(px)
        px = px.reshape(h, w, -1)
    finally:
        bpy.data.images.remove(img)
    if 0 < 2 * margin_rows < h:
        px = px[margin_rows:h - margin_rows]
    px = px.reshape(-1, px.shape[-1])
    return len(px) == 0 or float(np.ptp(px, axis=0).max()) < 0.05


def _check_written(files, file_format, margin_rows=0):
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
    if file_format == 'PNG' and _is_blank_png(files[len(files) // 2], margin_rows):
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
    burn_in: BoolProperty(name="Burn-in", default=True,
                          description="Stamp the take's name, the frame and the time on the frames")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        camera = stage.preview_camera(scene)
        if camera is None:
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
            stage.apply_camera_mode(scene)
            if scene.camera != camera:
                saved.set(scene, "camera", camera)
            for obj in scene.objects:  # the user's objects hidden in previews: for this render only
                if obj.get(stage.HIDE_PROP) and not obj.hide_render:
                    saved.set(obj, "hide_render", True)
            saved.set(r, "engine", 'BLENDER_WORKBENCH')
            saved.set(r, "filepath", path)
            saved.set(r, "resolution_percentage", self.resolution_percentage)
            set_look(saved, scene, self.burn_in)
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
            with_song = set_audio(saved, scene, self.file_format == 'FFMPEG')
            frame = scene.frame_current
            try:
                bpy.ops.render.render(animation=True, scene=scene.name)
            finally:
                scene.frame_set(frame)
            files = _output_files(r, f0, f1, self.file_format)
            problem = _check_written(files, self.file_format,
                                     2 * stamp_font_size(scene) if self.burn_in else 0)
        except Exception as exc:
            self.report({'ERROR'}, "render failed: {:s}".format(operator_error_text(exc)))
            return {'CANCELLED'}
        finally:
            saved.restore()
        if problem:
            self.report({'ERROR'}, "render failed: {:s}".format(problem))
            return {'CANCELLED'}
        self.report({'INFO'}, "Rendered frames {:d}-{:d} through '{:s}' to {:s}{:s}".format(
            f0, f1, camera.name, files[0], " with the song" if with_song else ""))
        return {'FINISHED'}


classes = (DANCING_POINTS_OT_render_preview,)
register, unregister = bpy.utils.register_classes_factory(classes)
