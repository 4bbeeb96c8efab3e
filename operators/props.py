# SPDX-License-Identifier: GPL-3.0-or-later
"""Data the add-on stores in a .blend: take settings on the take's collection,
duet bookkeeping, and the scene's synthesis settings.

Everything lives in ID properties (``Collection.dancing_points``,
``Scene.dancing_points``), so it is saved with the file and survives the add-on
being disabled (as plain custom properties).
"""

import math

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..dancing_points_addon.errors import InputError
from ..dancing_points_addon.formats.limits import FLOOR_RANGE_M, HEIGHT_RANGE_M, check_height
from .kinds import KIND_DUET, KIND_NONE, KIND_TAKE, is_duet, is_take
from .stage import apply_camera_mode
# ID property on the three take empties naming the device they carry.
DEVICE_PROP = "dp_device"
# Animated ID property on the empties: 1 tracked, 0 lost (SPEC §3 lost tracking).
TRACKED_PROP = "dp_tracked"
ROLE_PROP = "dp_role"  # on a baked armature or body: "leader" or "follower"
GHOST_PROP = "dp_ghost"  # on the objects of a take's source body (take_ghost; method_view shows/hides them)
ROLES = ("leader", "follower")
DEVICES = ("head", "lhand", "rhand")
DEVICE_OBJECT_NAMES = {"head": "Head", "lhand": "LeftHand", "rhand": "RightHand"}


class DP_CollectionSettings(bpy.types.PropertyGroup):
    """Set on the collections the add-on makes: a take (three empties) or a duet."""

    kind: EnumProperty(
        name="Kind",
        items=((KIND_NONE, "None", "Not made by Dancing Points"),
               (KIND_TAKE, "Take", "A three-point take: Head, LeftHand, RightHand empties"),
               (KIND_DUET, "Duet", "A baked duet: leader and follower armatures")),
        default=KIND_NONE,
    )
    # -- take ------------------------------------------------------------------
    source: StringProperty(name="Source", description="File the take was imported from", subtype='FILE_PATH')
    source_type: StringProperty(name="Source Type", description="csv, amc, bvh or fbx")
    height: FloatProperty(
        name="Dancer Height",
        description="Standing height of the tracked dancer, for calibration ({:g} to {:g} m; 0: estimate it from "
                    "the take)".format(*HEIGHT_RANGE_M),
        default=0.0, min=0.0, max=HEIGHT_RANGE_M[1], soft_max=2.5, unit='LENGTH', precision=3,
    )
    role: EnumProperty(
        name="Role", default='leader',
        description="Whose three points the take holds (SPEC §3 role); the other dancer is synthesised",
        items=(('leader', "Leader", "The leader's points: the follower is synthesised"),
               ('follower', "Follower", "The follower's points: the leader is synthesised")),
    )
    orientations: StringProperty(
        name="Orientations", default="",
        description="'none': the file's rig gave its points but not their orientations (its rest pose could "
                    "not be related to the SPEC's); the synthesis does not follow the devices' orientations")
    head_turn: FloatVectorProperty(
        name="Head Turn", size=4, subtype='QUATERNION', default=(1.0, 0.0, 0.0, 0.0),
        description="A headset whose pose is turned from SPEC §3's (worn tilted, another sender's axes): the "
                    "constant rotation in its own axes, reported = true · turn (identity: none)")
    lhand_turn: FloatVectorProperty(
        name="Left Hand Turn", size=4, subtype='QUATERNION', default=(1.0, 0.0, 0.0, 0.0),
        description="A left controller in another convention (a raw controller pose, a wrist tracker): the "
                    "constant rotation in its own axes, reported = true · turn (identity: none)")
    rhand_turn: FloatVectorProperty(
        name="Right Hand Turn", size=4, subtype='QUATERNION', default=(1.0, 0.0, 0.0, 0.0),
        description="The right controller's turn, as the left's")
    orientations_used: StringProperty(
        name="Orientations Used", description="Which device orientations the last synthesis followed")
    devices: EnumProperty(
        name="Devices", default='joints',
        description="What the take's three poses are (SPEC §3 devices)",
        items=(('joints', "Joints", "The head and wrist points of a full-body motion"),
               ('openxr', "OpenXR", "A headset's view pose and two controllers' grip poses")),
    )
    use_floor_y: BoolProperty(name="Floor Given", default=False,
                              description="The real floor's height in the take is known (else: estimated when "
                                          "the height is given, else 0)")
    floor_y: FloatProperty(name="Floor Height", default=0.0, min=-FLOOR_RANGE_M, max=FLOOR_RANGE_M, soft_min=-0.5,
                           soft_max=0.5, unit='LENGTH', precision=3,
                           description="Height of the real floor in the take's frame, within ±{:g} m (a headset's "
                                       "floor calibration can be off by centimetres)".format(FLOOR_RANGE_M))
    # what the last synthesis used (read only: shown in the panel)
    height_used: FloatProperty(name="Height Used", default=0.0, unit='LENGTH', precision=3,
                               description="The tracked dancer's height the last synthesis used")
    height_source: StringProperty(name="Height Source", description="given, estimated or assumed")
    floor_used: FloatProperty(name="Floor Used", default=0.0, unit='LENGTH', precision=3,
                              description="The floor height the last synthesis used")
    floor_source: StringProperty(name="Floor Source", description="given, estimated or assumed")
    input_fps: FloatProperty(name="Input FPS", description="Frame rate override used at import (0: the file's)",
                             default=0.0, min=0.0)
    source_fps: FloatProperty(name="Source FPS", description="Frame rate of the imported file", default=0.0)
    fps: FloatProperty(name="Take FPS", description="Rate of the take's keyframes (the networks' 30 Hz)",
                       default=30.0)
    frame_start: IntProperty(name="Start Frame", description="Scene frame of the take's first sample", default=1)
    frame_step: FloatProperty(name="Frame Step", default=1.0, min=1e-3,
                              description="Scene frames between two samples (the scene's frame rate / 30: "
                                          "the take plays at its real speed in the scene's time)")
    n_frames: IntProperty(name="Frames", description="Number of samples of the take", default=0, min=0)
    t0: FloatProperty(name="Start Time", description="Time (s) of the take's first sample in the file", default=0.0)
    axis_forward: StringProperty(name="Forward", default='-Z')
    axis_up: StringProperty(name="Up", default='Y')
    # the song (SPEC §3 audio, audio_offset_s), as last placed by the import or Set Song (shown in the panel)
    audio: StringProperty(name="Song", subtype='FILE_PATH', description="The song the take was danced to")
    audio_offset: FloatProperty(name="Song Offset", default=0.0, unit='TIME_ABSOLUTE',
                                description="The time in the song (s) at the take's time 0")
    # -- duet ------------------------------------------------------------------
    take_name: StringProperty(name="Take", description="Name of the take collection this duet was baked from")
    version: IntProperty(name="Version", description="Bake number for its take (1, 2, ...)", default=0)


def _is_take(self, coll):
    return is_take(coll)


def _camera_mode_update(self, context):
    apply_camera_mode(self.id_data)


class DP_SceneSettings(bpy.types.PropertyGroup):
    take: PointerProperty(
        name="Take", type=bpy.types.Collection, poll=_is_take,
        description="The take that Synthesise works on (default: the active object's take)",
    )
    foot_lock: BoolProperty(name="Foot Locking", default=True,
                            description="Pin feet in contact with the floor (contact-based IK)")
    follow_devices: BoolProperty(name="Follow Devices", default=True,
                                 description="Turn the tracked dancer's head and hands as the devices are turned")
    hand_ik: BoolProperty(name="Hand IK", default=True,
                          description="Put the leader's head and wrists exactly on the tracked points")
    preview_format: EnumProperty(
        name="Format", default='PNG',
        items=(('PNG', "PNG Sequence", "One PNG image per frame"),
               ('FFMPEG', "Video", "An MPEG-4 (H.264) video")),
    )
    preview_path: StringProperty(name="Output", subtype='FILE_PATH', default="//dancing_points_preview/",
                                 description="Where Render Preview writes its frames or video")
    camera_mode: EnumProperty(
        name="Camera", default='FOLLOW', update=_camera_mode_update,
        items=(('FOLLOW', "Follow", "Render Preview uses the DP Camera, which follows the couple, keeping "
                                    "both framed and in sight"),
               ('WIDE', "Wide", "Render Preview uses the DP Camera, still, framing the whole take"),
               ('SCENE', "Scene Camera", "Render Preview uses the scene's own camera (the DP Camera keeps "
                                         "following the couple)")),
    )
    burn_in: BoolProperty(name="Burn-in", default=True,
                          description="Render Preview stamps the take's name, the frame and the time")


classes = (DP_CollectionSettings, DP_SceneSettings)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Collection.dancing_points = PointerProperty(type=DP_CollectionSettings)
    bpy.types.Scene.dancing_points = PointerProperty(type=DP_SceneSettings)


def unregister():
    del bpy.types.Scene.dancing_points
    del bpy.types.Collection.dancing_points
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)


# --------------------------------------------------------------------------- checks

def check_dancer(where, height, use_floor_y, floor_y):
    """The take's or Live's *Dancer Height* (0: estimated) and *Floor Height*
    (when given) within the ranges the command line and the take reader allow
    (``--height``, ``--floor-y``); else an :class:`InputError` naming ``where``
    and the setting. The properties' own bounds do not suffice: a script, or a
    file saved before they existed, can hold any value."""
    h = float(height)
    if h != 0.0:
        check_height(where, h, what="Dancer Height")
    if use_floor_y:
        f = float(floor_y)
        if not (math.isfinite(f) and abs(f) <= FLOOR_RANGE_M):
            raise InputError(where, "Floor Height must be within ±{:g} m, got {:g}".format(FLOOR_RANGE_M, f))


# --------------------------------------------------------------------------- lookups

def device_objects(take_coll):
    """``{device: object}`` of the take's empties (by their ``dp_device`` property)."""
    out = {}
    for obj in take_coll.all_objects:
        dev = obj.get(DEVICE_PROP)
        if dev in DEVICES and dev not in out:
            out[dev] = obj
    return out


def take_of_object(obj):
    """The take collection an object belongs to: its own collection, or the take a
    duet it belongs to was baked from."""
    if obj is None:
        return None
    for coll in obj.users_collection:
        if is_take(coll):
            return coll
    for coll in obj.users_collection:
        if is_duet(coll):
            take = bpy.data.collections.get(coll.dancing_points.take_name)
            if is_take(take):
                return take
    return None


def active_take(context, name=""):
    """The take to work on: ``name`` if given, else the active object's, else the
    scene's ``dancing_points.take``, else the only take in the scene."""
    if name:
        coll = bpy.data.collections.get(name)
        return coll if is_take(coll) else None
    take = take_of_object(getattr(context, "active_object", None))
    if take is not None:
        return take
    scene = context.scene
    settings = getattr(scene, "dancing_points", None)
    if settings is not None and is_take(settings.take):
        return settings.take
    takes = [c for c in scene.collection.children_recursive if is_take(c)]
    return takes[0] if len(takes) == 1 else None
