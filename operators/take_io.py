# SPDX-License-Identifier: GPL-3.0-or-later
"""Import a take (``bpy.ops.dancing_points.import_take``, SPEC §8).

The file is read as a :class:`Take` (:func:`load_any`): ``.csv`` takes and CMU
``.amc`` files by the core (``inputs.load_input``), ``.bvh`` and
``.fbx`` files through Blender's own importers (:mod:`.take_rig`). The take
becomes a collection of three keyframed empties (:mod:`.take_collection`,
which also reads it back for synthesis); Keep Source Body adds the file's full
body as a wire ghost (:mod:`.take_ghost`).
"""

import os

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper, axis_conversion, orientation_helper

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import InputError, error_message
from ..dancing_points_addon.formats.devices import META_TURN_KEYS, parse_turn
from ..dancing_points_addon.formats.files import regular_file
from ..dancing_points_addon.inputs import check_take, load_input
from ..dancing_points_addon.formats.limits import check_height, check_rate
from ..dancing_points_addon.formats.rig_rest import rig_problem_line
from ..dancing_points_addon.formats.take import ORIENTATIONS_NONE, ORIENTATIONS_PROBLEM_KEY, take_orientations_usable
from ..dancing_points_addon.resample import NET_FPS, resample_take
from ..dancing_points_addon.audio import take_song
from .song import place_song, song_of, store_song
from .take_collection import remove_collection, build_take_collection
from .take_ghost import remove_ghost, build_amc_ghost, keep_ghost
from .take_rig import read_rig_take

FILE_TYPES = (".csv", ".bvh", ".fbx", ".amc")
# Blender's last scene frame (MAXFRAME); scenes start at frame 0 or later
MAX_FRAME = bpy.types.Scene.bl_rna.properties["frame_end"].hard_max


def load_any(context, path, input_fps=0.0, height=0.0, axis_forward='-Z', axis_up='Y', units='AUTO', ghost=None,
             role=None, armature=""):
    """Any supported file as a :class:`Take` (motion space, source rate);
    ``ghost``, ``role`` and ``armature`` (which armature of a file with several):
    see :func:`.take_rig.read_rig_take` (BVH/FBX only)."""
    path = bpy.path.abspath(path) if path else path
    if not path:
        raise InputError("<no file>", "no file given")
    ext = os.path.splitext(path)[1].lower()
    if ext not in FILE_TYPES:
        raise InputError(path, f"unsupported file type {ext or '(no extension)'!r} (expected "
                               f"{', '.join(FILE_TYPES)})")
    # The core's rules (those of the command line): the frame rate and height
    # ranges, regular files only, then ``check_take`` on whatever was read.
    fps = check_rate(path, input_fps) if input_fps and input_fps > 0 else None
    h = check_height(path, height) if height and height > 0 else None
    regular_file(path, "a take file", missing="no such file")
    if ext in (".bvh", ".fbx"):
        take = check_take(read_rig_take(context, path, ext, fps or 0.0, axis_forward, axis_up, units, ghost,
                                        role=role, armature=armature), path)
    else:
        take = load_input(path, input_fps=fps)  # check_take included
    if h is not None:
        take.meta["height_m"] = h
    return take


# --------------------------------------------------------------------------- operator

@orientation_helper(axis_forward='-Z', axis_up='Y')
class DANCING_POINTS_OT_import_take(bpy.types.Operator, ImportHelper):
    """Import a three-point take (.csv), or the head and hands of a BVH, FBX or CMU AMC motion, as a take"""

    bl_idname = "dancing_points.import_take"
    bl_label = "Import Dancing Points Take"
    bl_options = {'REGISTER', 'UNDO', 'PRESET'}

    filename_ext = ".csv"
    filter_glob: StringProperty(default="*.csv;*.bvh;*.fbx;*.amc", options={'HIDDEN'})

    frame_start: IntProperty(name="Start Frame", default=1, min=0, max=MAX_FRAME,
                             description="Scene frame of the take's first sample (the whole take must end by "
                                         "Blender's last frame, {:d})".format(MAX_FRAME))
    input_fps: FloatProperty(
        name="Input FPS", default=0.0, min=0.0, soft_max=240.0,
        description="Frame rate of the file's rows (0: from the file: its time column, BVH Frame Time, "
                    "FBX frame rate, AMC 60/120 Hz)",
    )
    height: FloatProperty(
        name="Dancer Height", default=0.0, min=0.0, soft_max=2.5, unit='LENGTH', precision=3,
        description="Standing height of the tracked dancer (0: the file's height_m, else estimated)",
    )
    role: EnumProperty(
        name="Role", default='FILE',
        description="Whose three points the take holds (SPEC §3 role); the other dancer is synthesised",
        items=(('FILE', "From File", "The take's role (a .csv's role=...; else the leader)"),
               ('leader', "Leader", "The leader's points: the follower is synthesised"),
               ('follower', "Follower", "The follower's points: the leader is synthesised")),
    )
    armature: StringProperty(
        name="Armature", default="",
        description="BVH/FBX with several armatures: the name of the one to read (empty: the only one with head "
                    "and hand bones, else the one dancing the take's Role, as in a Dancing Points duet FBX)",
    )
    devices: EnumProperty(
        name="Devices", default='FILE',
        description="What the take's three poses are (SPEC §3 devices)",
        items=(('FILE', "From File", "The take's devices (a .csv's devices=...; joints for a motion file)"),
               ('joints', "Joints", "The head and wrist points of a full-body motion"),
               ('openxr', "OpenXR", "A headset's view pose and two controllers' grip poses")),
    )
    units: EnumProperty(
        name="Units", default='AUTO',
        items=(('AUTO', "Automatic", "BVH/FBX: scale the rig to a human size (metres, CMU units, inches, "
                                     "centimetres, millimetres)"),
               ('FILE', "As Imported", "BVH/FBX: use the importer's units (1 unit = 1 m)")),
    )
    update_scene_fps: BoolProperty(name="Update Scene FPS", default=True,
                                   description="Set the scene to the take's 30 fps")
    update_scene_duration: BoolProperty(name="Update Scene Duration", default=True,
                                        description="Set the scene's frame range to the take")
    audio: StringProperty(name="Song", default="", subtype='FILE_PATH',
                          description="The song danced to (WAV, FLAC, OGG, MP3; empty: the take's audio, if any): "
                                      "a sound strip lined up with the take, and its beats as timeline markers")
    audio_offset: FloatProperty(name="Song Offset", default=0.0, min=-3600.0, max=3600.0, unit='TIME_ABSOLUTE',
                                description="The time in the song (s) at the take's time 0 (when not set: the "
                                            "take's audio_offset_s, else 0)")
    keep_source: BoolProperty(name="Keep Source Body", default=False,
                              description="BVH, FBX, AMC: keep the file's full body in the take as a wire "
                                          "ghost, to compare with the synthesised leader")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        for prop in ("frame_start", "input_fps", "role", "armature", "height", "devices", "units", "update_scene_fps",
                     "update_scene_duration", "audio", "audio_offset", "keep_source", "axis_forward", "axis_up"):
            layout.prop(self, prop)

    def invoke(self, context, event):
        if self.filepath and hasattr(self, "invoke_popup"):  # drag and drop (FileHandler)
            return self.invoke_popup(context)
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        try:
            coll = self.import_file(context)
        except Exception as exc:  # noqa: BLE001 - a user error or an unexpected failure: one line
            self.report({'ERROR'}, error_message(exc, "Dancing Points import failed"))
            return {'CANCELLED'}
        arm = getattr(self, "_source_armature", "")
        song = song_of(coll)
        self.report({'INFO'}, "Imported take '{:s}' ({:d} frames at 30 fps{:s}{:s})".format(
            coll.name, coll.dancing_points.n_frames, ", armature '{:s}'".format(arm) if arm else "",
            ", song '{:s}' at {:.1f} bpm".format(os.path.basename(song.path), song.tempo_bpm) if song else ""))
        return {'FINISHED'}

    def import_file(self, context):
        path = bpy.path.abspath(self.filepath)
        ext = os.path.splitext(path)[1].lower()
        ghost = {} if self.keep_source and ext in (".bvh", ".fbx") else None
        try:
            take = load_any(context, path, self.input_fps, self.height, self.axis_forward, self.axis_up,
                            self.units, ghost, role=None if self.role == 'FILE' else self.role,
                            armature=self.armature.strip())
            song = self._song(take, path)
            coll = self._make_take(context, path, ext, take, ghost)
            if song is not None:
                try:
                    place_song(context.scene, coll, song)
                    store_song(coll, song)
                except Exception:
                    remove_collection(coll)
                    raise
        except Exception:
            if ghost:  # the kept rig, when the take could not be made
                remove_ghost(ghost["objects"])
            raise
        return coll

    def _song(self, take, path):
        """The take's song, analysed: the operator's Song (an unreadable one fails the
        import) else the take's ``audio`` (an unreadable one is a warning)."""
        offset = self.audio_offset if self.properties.is_property_set("audio_offset") else None
        audio = bpy.path.abspath(self.audio) if self.audio else None
        warnings = []
        song = take_song(take, audio, offset, warn=warnings.append)
        for w in warnings:
            self.report({'WARNING'}, w)
        return song

    def _make_take(self, context, path, ext, take, ghost):
        conv = np.array(axis_conversion(from_forward=self.axis_forward, from_up=self.axis_up).to_3x3())
        source_fps = float(take.meta.pop("source_fps", 0.0))
        problem = take.meta.pop(ORIENTATIONS_PROBLEM_KEY, None)
        take.meta.pop("source_naming", None)
        self._source_armature = take.meta.pop("source_armature", "")  # said in the INFO line
        if not source_fps and take.n_frames > 1:
            source_fps = float((take.n_frames - 1) / max(take.time[-1] - take.time[0], 1e-9))
        take30 = resample_take(take, NET_FPS)
        if take30.n_frames < 2:
            raise InputError(path, "shorter than two 30 Hz frames")
        if ext in (".bvh", ".fbx"):
            conv = bm.C  # the rig was read in Blender's space already; it is motion space now
        name = os.path.splitext(os.path.basename(path))[0]
        devices = (take.meta.get("devices") or "joints") if self.devices == 'FILE' else self.devices
        if devices not in ("joints", "openxr"):
            raise InputError(path, f"unknown devices value {devices!r} (expected joints or openxr)")
        role = (take.meta.get("role") or "leader") if self.role == 'FILE' else self.role
        if role not in ("leader", "follower"):
            raise InputError(path, f"unknown role {role!r} (expected leader or follower)")
        settings = dict(source=path, source_type=ext[1:], height=float(take.height or 0.0),
                        input_fps=float(self.input_fps), source_fps=source_fps, devices=devices, role=role,
                        axis_forward=self.axis_forward, axis_up=self.axis_up,
                        orientations="" if take_orientations_usable(take.meta) else ORIENTATIONS_NONE)
        for key in META_TURN_KEYS:
            if take.meta.get(key) not in (None, ""):
                settings[key] = parse_turn(take.meta[key], key, path)
        if take.meta.get("floor_y") not in (None, ""):
            try:
                settings.update(use_floor_y=True, floor_y=float(take.meta["floor_y"]))
            except ValueError:
                raise InputError(path, f"floor_y is not a number: {take.meta['floor_y']!r}") from None
        scene = context.scene
        # Keys in scene time: one scene frame per sample when the scene is set to 30 fps, else
        # the scene's rate / 30 (a 24 fps project keeps its rate and the take its real speed).
        step = 1.0 if self.update_scene_fps else (scene.render.fps / (scene.render.fps_base or 1.0)) / NET_FPS
        span = int(np.ceil((take30.n_frames - 1) * step - 1e-6))  # scene frames from the first sample to the last
        if span > MAX_FRAME:
            raise InputError(path, "the take's {:d} frames span {:d} scene frames at this scene's rate, more than "
                                   "Blender's {:d}: import it at 30 fps (Update Scene FPS) or cut it".format(
                                       take30.n_frames, span + 1, MAX_FRAME + 1))
        if self.frame_start + span > MAX_FRAME:
            raise InputError(path, "the take's {:d} frames from Start Frame {:d} would end on frame {:d}, past "
                                   "Blender's last frame {:d}: set Start Frame to at most {:d}".format(
                                       take30.n_frames, self.frame_start, self.frame_start + span, MAX_FRAME,
                                       MAX_FRAME - span))
        coll, objs = build_take_collection(context, take30, name, self.frame_start, conv, settings, step)
        try:
            if ghost:
                keep_ghost(coll, ghost, self.frame_start, step)
            elif self.keep_source and ext == ".amc":
                build_amc_ghost(context, coll, path, float(self.input_fps), self.frame_start, step)
            if ghost or self.keep_source and ext == ".amc":
                from .method_view import apply_visibility
                apply_visibility(context.scene)  # the Method panel's settings (default: not in renders)
        except Exception:
            remove_collection(coll)
            raise
        scene = context.scene
        if self.update_scene_fps:
            scene.render.fps = int(NET_FPS)
            scene.render.fps_base = 1.0
        if self.update_scene_duration:
            scene.frame_start = self.frame_start
            scene.frame_end = self.frame_start + span
        scene.dancing_points.take = coll
        if problem:
            self.report({'WARNING'}, rig_problem_line(os.path.basename(path), problem))
        for obj in context.view_layer.objects:
            if obj.select_get():
                obj.select_set(False)
        head = objs["head"]
        if head.name in context.view_layer.objects:
            head.select_set(True)
            context.view_layer.objects.active = head
        return coll


class DANCING_POINTS_FH_import_take(bpy.types.FileHandler):
    bl_idname = "DANCING_POINTS_FH_import_take"
    bl_label = "Dancing Points take"
    bl_import_operator = "dancing_points.import_take"
    bl_file_extensions = ";".join(FILE_TYPES)

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type in ('VIEW_3D', 'OUTLINER')


def menu_func_import(self, context):
    self.layout.operator(DANCING_POINTS_OT_import_take.bl_idname,
                         text="Dancing Points take (.csv, .bvh, .fbx, .amc)")


classes = (DANCING_POINTS_OT_import_take, DANCING_POINTS_FH_import_take)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(menu_func_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_func_import)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
