# SPDX-License-Identifier: GPL-3.0-or-later
"""The preview stage: one collection "DP Stage" in the scene with a checker
floor at the dancers' floor level, the "DP Camera" on its "DP Camera Rig"
(the rig follows the couple, turning slowly round it so that neither dancer
hides the other, or holds a fixed wide shot:
``Scene.dancing_points.camera_mode``), a sun when the scene
has no light, and a light world when the scene has none.

Made once and reused: every bake refits the floor and rekeys the camera on the
new duet. The user's own objects, materials, world and camera are never
changed: the DP Camera becomes the scene camera only when the scene had none
(or already uses it). Everything the stage made carries the ID property
``dp_stage`` (its role), and ``dancing_points.remove_stage`` removes it all.
The maths (camera path, floor level, checker) is in
``dancing_points_addon.camera_path``.
"""

import contextlib

import bpy
import numpy as np
from mathutils import Matrix

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon import camera_path as cp
from ..dancing_points_addon.skeleton import JOINT_NAMES
from . import compat
from .kinds import is_duet, is_take

STAGE_NAME = "DP Stage"
# value: "stage", "floor", "camera", "camera_rig", "sun", "world", "material", "action"
STAGE_PROP = "dp_stage"
FOLLOW_PROP = "dp_follow_action"
HIDE_PROP = "dp_hide_in_preview"  # on a user's object: Render Preview hides it (never deletes it)
OBSTACLES_PROP = "dp_obstacles"  # on the stage: the user's objects standing where the dancers dance
WIDE_PROP = "dp_wide_matrix"
ROT_PROP = "dp_follow_rotation"
FLOOR_MARGIN = 12.0  # m of floor around the couple's path (the horizon stays far)
FLOOR_COLOURS = ((0.80, 0.80, 0.80, 1.0), (0.60, 0.60, 0.62, 1.0))  # linear: light / dark squares
WORLD_COLOUR = (0.80, 0.82, 0.85)
FOOT_JOINTS = [JOINT_NAMES.index(n) for n in ("lfoot", "ltoes", "rfoot", "rtoes")]
VIEW_ANGLE_DEG = 60.0  # the camera's side: this far round from the leader's initial facing
LENS_MM = 35.0


def _role(id_block):
    try:
        return id_block.get(STAGE_PROP)
    except (AttributeError, ReferenceError):
        return None


def find_stage(scene):
    """The scene's stage collection, or None."""
    for coll in scene.collection.children_recursive:
        if _role(coll) == "stage":
            return coll
    return None


def stage_object(stage, role):
    if stage is None:
        return None
    return next((o for o in stage.objects if _role(o) == role), None)


def scene_fps(scene):
    return scene.render.fps / (scene.render.fps_base or 1.0)


def view_direction(leader_positions):
    """The horizontal side the camera looks from (Blender space): the leader's
    initial facing turned by ``VIEW_ANGLE_DEG``."""
    view = bm.to_blender(bm.hip_forward(np.asarray(leader_positions)[0]))
    c, s = np.cos(np.deg2rad(VIEW_ANGLE_DEG)), np.sin(np.deg2rad(VIEW_ANGLE_DEG))
    return np.array([c * view[0] - s * view[1], s * view[0] + c * view[1], 0.0])


def _aspect(scene):
    r = scene.render
    return (r.resolution_x * r.pixel_aspect_x) / max(r.resolution_y * r.pixel_aspect_y, 1e-9)


def plan(scene, leader_positions, follower_positions, sample_frames, fov):
    """Everything the stage needs, computed before anything is made: the scene
    frames, the follow path on them, the wide shot and the floor. Positions:
    motion space ``(T, 31, 3)``; ``sample_frames (T,)``: their scene frames."""
    lead = np.asarray(leader_positions, dtype=np.float64)
    foll = np.asarray(follower_positions, dtype=np.float64)
    pts = bm.to_blender(np.concatenate([lead, foll], axis=1))
    f0 = int(np.floor(sample_frames[0] + 1e-6))
    f1 = int(np.ceil(sample_frames[-1] - 1e-6))
    frames = np.arange(f0, max(f1, f0) + 1, dtype=np.float64)
    at_frames = cp.interpolate_frames(pts, sample_frames, frames)
    view = view_direction(lead)
    aspect = _aspect(scene)
    n = lead.shape[1]
    # the side it looks from turns slowly, so that neither dancer hides the other
    sides = cp.visible_directions(at_frames[:, :n], at_frames[:, n:], view, fps=scene_fps(scene))
    path = cp.follow_camera(at_frames, fov, aspect, sides, fps=scene_fps(scene))
    wide_loc, wide_rot = bm.frame_camera(pts[:: max(1, len(pts) // 200)].reshape(-1, 3), view, fov, aspect)
    floor_z = float(np.mean([cp.floor_level(p[:, FOOT_JOINTS, 1]) for p in (lead, foll)]))
    flat = pts.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(-1)]
    lo = np.minimum(flat.min(0), path.locations.min(0)) - FLOOR_MARGIN
    hi = np.maximum(flat.max(0), path.locations.max(0)) + FLOOR_MARGIN
    floor = cp.checker_floor(lo, hi, floor_z)
    return {"frames": frames, "path": path, "wide": (wide_loc, wide_rot), "floor_z": floor_z, "floor": floor}


def _new(created, block):
    if created is not None:
        created.add(block)
    return block


def _material(name, colour, created):
    mat = bpy.data.materials.get(name)
    if mat is None or _role(mat) != "material":
        mat = _new(created, bpy.data.materials.new(name))
        mat[STAGE_PROP] = "material"
    mat.diffuse_color = colour
    mat.roughness = 0.9
    return mat


def _floor(stage, floor, created):
    verts, quads, parity = floor
    mesh = _new(created, bpy.data.meshes.new("DP Floor"))
    mesh[STAGE_PROP] = "floor"
    mesh.from_pydata(verts.tolist(), [], quads.tolist())
    for i, colour in enumerate(FLOOR_COLOURS):
        mesh.materials.append(_material("DP Floor {:d}".format(i + 1), colour, created))
    mesh.polygons.foreach_set("material_index", parity.astype(np.int32))
    mesh.update()
    obj = stage_object(stage, "floor")
    if obj is None:
        obj = _new(created, bpy.data.objects.new("DP Floor", mesh))
        obj[STAGE_PROP] = "floor"
        stage.objects.link(obj)
    else:
        old = obj.data
        obj.data = mesh
        if old is not None:
            if created is None:
                if old.users == 0:
                    bpy.data.meshes.remove(old)
            else:  # kept until the bake has succeeded
                created.on_failure(lambda: setattr(obj, "data", old))
                created.retire(old)
    obj.hide_select = True
    return obj


def _camera(stage, created):
    """The "DP Camera Rig" empty (it carries the path) and the "DP Camera", its
    child at the rig's origin (a local offset the user gives it stays)."""
    rig = stage_object(stage, "camera_rig")
    if rig is None:
        rig = _new(created, bpy.data.objects.new("DP Camera Rig", None))
        rig[STAGE_PROP] = "camera_rig"
        rig.empty_display_type = 'PLAIN_AXES'
        rig.empty_display_size = 0.2
        stage.objects.link(rig)
    cam = stage_object(stage, "camera")
    if cam is None:
        data = _new(created, bpy.data.cameras.new("DP Camera"))
        data.lens = LENS_MM
        data.clip_end = 500.0
        data[STAGE_PROP] = "camera"
        cam = _new(created, bpy.data.objects.new("DP Camera", data))
        cam[STAGE_PROP] = "camera"
        stage.objects.link(cam)
    if cam.parent != rig:
        cam.parent = rig
        cam.matrix_parent_inverse.identity()
        cam.location = (0.0, 0.0, 0.0)
        cam.rotation_mode = 'QUATERNION'
        cam.rotation_quaternion = (1.0, 0.0, 0.0, 0.0)
    return rig, cam


def _key_follow(cam, frames, path, created):
    """A new "DP Camera Follow" action on the rig ``cam``: the path's location and
    rotation (quaternion) on every frame (bulk)."""
    old = bpy.data.actions.get(cam.get(FOLLOW_PROP, "")) if cam.get(FOLLOW_PROP) else None
    action, slot = compat.new_action_for(cam, "DP Camera Follow")
    _new(created, action)
    action[STAGE_PROP] = "action"
    action.use_fake_user = True  # kept while the wide shot is in use
    for i in range(3):
        compat.write_keys(compat.ensure_fcurves(action, slot, "location", i, "DP Camera"),
                          frames, path.locations[:, i])
    quats = bm.continuous_quats(bm.matrix_to_quat(path.rotations))
    for i in range(4):
        compat.write_keys(compat.ensure_fcurves(action, slot, "rotation_quaternion", i, "DP Camera"),
                          frames, quats[:, i])
    cam[FOLLOW_PROP] = action.name
    if old is not None and old != action and _role(old) == "action":
        if created is None:
            bpy.data.actions.remove(old)
        else:  # kept until the bake has succeeded (a failed one points the rig back at it)
            created.retire(old, if_unused=False)  # (a fake user keeps it)
    return action


def apply_camera_mode(scene):
    """Put the DP Camera (its rig) on the scene's ``camera_mode``: the follow
    action (also with the scene's own camera chosen), or the wide shot (fixed).
    Does nothing when the scene has no stage."""
    cam = stage_object(find_stage(scene), "camera_rig")
    if cam is None:
        return None
    settings = getattr(scene, "dancing_points", None)
    mode = settings.camera_mode if settings is not None else 'FOLLOW'
    action = bpy.data.actions.get(cam.get(FOLLOW_PROP, "")) if cam.get(FOLLOW_PROP) else None
    ad = cam.animation_data or cam.animation_data_create()
    if mode in ('FOLLOW', 'SCENE') and action is not None:
        rot = cam.get(ROT_PROP)
        if rot is not None:
            cam.rotation_mode = 'QUATERNION'
            cam.rotation_quaternion = list(rot)
        ad.action = action
        if compat.SLOTTED and ad.action_slot is None and len(action.slots):
            ad.action_slot = action.slots[0]
    else:
        ad.action = None
        wide = cam.get(WIDE_PROP)
        if wide is not None:
            cam.matrix_world = Matrix(np.asarray(list(wide), dtype=np.float64).reshape(4, 4).tolist())
    return mode


_STAGE_KEYS = ("dp_camera_max_accel", "dp_camera_max_speed", "dp_camera_max_turn_rate", "dp_floor_z")


_RIG_KEYS = (ROT_PROP, WIDE_PROP, FOLLOW_PROP)


def _props(block, keys):
    """The values of ``keys`` that ``block`` has, as plain Python."""
    return {} if block is None else {k: compat.plain_value(block[k]) for k in keys if k in block}


def _put_back(block, kept, keys):
    """``block``'s ``keys`` as :func:`_props` found them (those it did not have, removed)."""
    for k in keys:
        if k in kept:
            block[k] = kept[k]
        elif k in block:
            del block[k]


def _scene_restorer(scene, stage):
    """A function that puts back what :func:`ensure_stage` sets on the scene, the
    stage collection and an existing camera rig (its follow action too)."""
    frames, camera = (scene.frame_start, scene.frame_end), scene.camera
    keys = _STAGE_KEYS + (OBSTACLES_PROP,)
    kept = _props(stage, keys)
    rig = stage_object(stage, "camera_rig")
    if rig is not None:
        pose = (rig.location.copy(), rig.rotation_mode, rig.rotation_quaternion.copy())
        rig_kept = _props(rig, _RIG_KEYS)

    def restore():
        scene.frame_start, scene.frame_end = frames
        scene.camera = camera
        if stage is not None:
            _put_back(stage, kept, keys)
        if rig is not None:
            rig.location, rig.rotation_mode, rig.rotation_quaternion = pose
            _put_back(rig, rig_kept, _RIG_KEYS)
            apply_camera_mode(scene)  # the rig on its old follow action

    return restore


def ensure_stage(context, leader_positions, follower_positions, sample_frames, created=None):
    """Make or refit the scene's stage for a duet (motion-space positions
    ``(T, 31, 3)`` keyed at scene frames ``sample_frames``); sets the scene's
    frame range to the duet. Returns ``(stage collection, plan)``; data-blocks
    it makes are added to ``created`` (a ``bake.Created``)."""
    scene = context.scene
    stage = find_stage(scene)
    cam = stage_object(stage, "camera")
    fov = cam.data.angle if cam is not None and cam.type == 'CAMERA' else 2 * np.arctan(36.0 / 2 / LENS_MM)
    p = plan(scene, leader_positions, follower_positions, np.asarray(sample_frames, dtype=np.float64), fov)
    if stage is None:
        stage = _new(created, bpy.data.collections.new(STAGE_NAME))
        stage[STAGE_PROP] = "stage"
        scene.collection.children.link(stage)
    if created is not None:  # what a failed bake puts back
        created.on_failure(_scene_restorer(scene, stage))
    _floor(stage, p["floor"], created)
    rig, cam = _camera(stage, created)
    path = p["path"]
    rot = Matrix(path.rotations[0].tolist())
    rig.rotation_mode = 'QUATERNION'
    rig.rotation_quaternion = rot.to_quaternion()
    rig[ROT_PROP] = list(rig.rotation_quaternion)
    rig.location = path.locations[0].tolist()
    wide_loc, wide_rot = p["wide"]
    wide = np.eye(4)
    wide[:3, :3] = wide_rot
    wide[:3, 3] = wide_loc
    rig[WIDE_PROP] = wide.ravel().tolist()
    _key_follow(rig, p["frames"], path, created)
    apply_camera_mode(scene)
    if scene.camera is None or _role(scene.camera) == "camera":
        scene.camera = cam
    if not any(o.type == 'LIGHT' for o in scene.objects):
        sun_data = _new(created, bpy.data.lights.new("DP Sun", 'SUN'))
        sun_data.energy = 3.0
        sun_data[STAGE_PROP] = "sun"
        sun = _new(created, bpy.data.objects.new("DP Sun", sun_data))
        sun[STAGE_PROP] = "sun"
        sun.rotation_euler = (np.deg2rad(40.0), 0.0, np.deg2rad(30.0))
        stage.objects.link(sun)
    if scene.world is None:
        world = _new(created, bpy.data.worlds.new("DP World"))
        world[STAGE_PROP] = "world"
        world.color = WORLD_COLOUR
        scene.world = world
    scene.frame_start = int(p["frames"][0])
    scene.frame_end = int(p["frames"][-1])
    for k, v in zip(_STAGE_KEYS, (path.max_accel, path.max_speed, path.max_turn_rate, p["floor_z"])):
        stage[k] = v
    stage[OBSTACLES_PROP] = find_obstacles(scene, leader_positions, follower_positions)
    return stage, p


def preview_camera(scene):
    """The camera Render Preview renders through: the DP Camera (follow or wide)
    unless the scene's own camera is chosen (``camera_mode`` 'SCENE') or there is
    no stage; None when there is none."""
    settings = getattr(scene, "dancing_points", None)
    mode = settings.camera_mode if settings is not None else 'FOLLOW'
    cam = stage_object(find_stage(scene), "camera")
    if mode != 'SCENE' and cam is not None and cam.type == 'CAMERA':
        return cam
    return scene.camera


def _ours(obj):
    """Whether an object belongs to the add-on (a take, duet, stage or ghost), not the user."""
    if _role(obj) is not None or obj.get("dp_role") is not None or obj.get("dp_ghost") is not None:
        return True
    return any(_role(c) is not None or is_take(c) or is_duet(c) for c in obj.users_collection)


def _character(obj):
    """A body that dances itself (skinned to an armature, or parented to one): a
    retargeted character, not something in the dancers' way."""
    parent = obj.parent
    while parent is not None:
        if parent.type == 'ARMATURE':
            return True
        parent = parent.parent
    return any(m.type == 'ARMATURE' for m in getattr(obj, "modifiers", ()))


def find_obstacles(scene, leader_positions, follower_positions, margin=0.05):
    """The user's objects standing where the dancers dance: shown in renders,
    with a body (a mesh, curve, text...), and whose world bounding box (grown by
    ``margin`` m sideways) holds some joint of either dancer on some frame, at
    least ``margin`` below its top (motion-space positions ``(T, 31, 3)``; a floor
    under their feet is not in the way). Sorted by name."""
    pts = bm.to_blender(np.concatenate([np.asarray(leader_positions, dtype=np.float64),
                                        np.asarray(follower_positions, dtype=np.float64)], axis=1))
    pts = pts[:: max(1, len(pts) // 300)].reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(-1)]
    found = []
    for obj in scene.objects:
        if obj.type not in {'MESH', 'CURVE', 'SURFACE', 'META', 'FONT', 'VOLUME', 'POINTCLOUD', 'CURVES'}:
            continue
        if obj.hide_render or _ours(obj) or _character(obj):
            continue
        corners = np.array([list(c) + [1.0] for c in obj.bound_box]) @ np.array(obj.matrix_world).T
        lo, hi = corners[:, :3].min(0), corners[:, :3].max(0)
        lo[:2] -= margin
        hi[:2] += margin
        hi[2] -= margin
        if len(pts) and bool(np.all((pts >= lo) & (pts <= hi), axis=1).any()):
            found.append(obj.name)
    return sorted(found)


def obstacles(scene):
    """The objects of the stage's obstacle list that are still there and not yet
    hidden in previews."""
    stage = find_stage(scene)
    names = list(stage.get(OBSTACLES_PROP, [])) if stage is not None else []
    objs = [scene.objects.get(n) for n in names]
    return [o for o in objs if o is not None and not o.get(HIDE_PROP)]


def remove_stage(scene):
    """Remove the scene's stage and everything it made (the world only when it
    is the stage's). Returns whether there was one."""
    stage = find_stage(scene)
    if stage is None:
        return False
    ids = [stage]
    for obj in stage.all_objects:
        if _role(obj) is None:  # something the user put in it: keep it, in the scene
            if obj.name not in scene.collection.objects:
                scene.collection.objects.link(obj)
            continue
        ids.append(obj)
        if obj.data is not None:
            ids.append(obj.data)
            ids.extend(m for m in getattr(obj.data, "materials", ()) if m is not None and _role(m) == "material")
        name = obj.get(FOLLOW_PROP)
        if name and bpy.data.actions.get(name) is not None:
            ids.append(bpy.data.actions[name])
    if scene.camera is not None and _role(scene.camera) == "camera":
        scene.camera = None
    if scene.world is not None and _role(scene.world) == "world":
        ids.append(scene.world)
        scene.world = None
    bpy.data.batch_remove(list(dict.fromkeys(ids)))
    return True


@contextlib.contextmanager
def excluded(context):
    """The stage left out of the view layer for a while (an export of the duet
    alone: the FBX)."""
    stage = find_stage(context.scene)
    found = []

    def walk(lc):
        if lc.collection == stage:
            found.append(lc)
        for child in lc.children:
            walk(child)

    if stage is not None:
        walk(context.view_layer.layer_collection)
    states = [(lc, lc.exclude) for lc in found]
    try:
        for lc in found:
            lc.exclude = True
        yield stage
    finally:
        for lc, ex in states:
            lc.exclude = ex


def newest_duet(scene):
    """The newest visible duet collection of the scene (for the burn-in's take name)."""
    duets = [c for c in scene.collection.children_recursive if is_duet(c) and not c.hide_render]
    return max(duets, key=lambda c: c.dancing_points.version, default=None)


class DANCING_POINTS_OT_remove_stage(bpy.types.Operator):
    """Remove the DP Stage (floor, DP Camera, lights and world it made)"""

    bl_idname = "dancing_points.remove_stage"
    bl_label = "Remove Stage"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        if not remove_stage(context.scene):
            self.report({'ERROR'}, "the scene has no DP Stage")
            return {'CANCELLED'}
        self.report({'INFO'}, "Removed the DP Stage")
        return {'FINISHED'}


class DANCING_POINTS_OT_hide_in_previews(bpy.types.Operator):
    """Hide your objects that stand where the dancers dance in Render Preview (they are not deleted; F12 and the viewport still show them)"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "dancing_points.hide_in_previews"
    bl_label = "Hide in Previews"
    bl_options = {'REGISTER', 'UNDO'}

    names: bpy.props.StringProperty(
        name="Objects", options={'SKIP_SAVE'},
        description="Objects to hide, comma separated (empty: those found standing where the dancers dance)")
    hide: bpy.props.BoolProperty(name="Hide", default=True, options={'SKIP_SAVE'},
                                 description="Hide them in previews (off: show them again)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        if self.names:
            names = [n.strip() for n in self.names.split(",") if n.strip()]
            missing = [n for n in names if scene.objects.get(n) is None]
            if missing:
                self.report({'ERROR'}, "no object named '{:s}' in the scene".format(missing[0]))
                return {'CANCELLED'}
            objs = [scene.objects[n] for n in names]
        else:
            stage = find_stage(scene)
            objs = [scene.objects.get(n) for n in (stage.get(OBSTACLES_PROP, []) if stage is not None else [])]
            objs = [o for o in objs if o is not None]
        if not objs:
            self.report({'ERROR'}, "no object stands where the dancers dance")
            return {'CANCELLED'}
        for obj in objs:
            if self.hide:
                obj[HIDE_PROP] = True
            elif HIDE_PROP in obj:
                del obj[HIDE_PROP]
        self.report({'INFO'}, "{:s} in Render Preview: {:s}".format(
            "Hidden" if self.hide else "Shown again", ", ".join(o.name for o in objs)))
        return {'FINISHED'}


classes = (DANCING_POINTS_OT_remove_stage, DANCING_POINTS_OT_hide_in_previews)
register, unregister = bpy.utils.register_classes_factory(classes)
