# SPDX-License-Identifier: GPL-3.0-or-later
"""Import a take (``bpy.ops.dancing_points.import_take``, SPEC §8) and read it back.

A take in the scene is a collection "DP Take <name>" with three empties
(Head, LeftHand, RightHand) keyframed once per 30 Hz sample in Blender's Z-up
space: location, rotation (quaternion, device-to-world as in the file) and an
animated ``["dp_tracked"]`` flag (0 where the file had lost tracking; the
location and rotation then hold the last tracked value).

* ``.csv`` takes and CMU ``.amc`` files are read by the core (``formats.inputs.load_input``).
* ``.bvh`` and ``.fbx`` files go through Blender's own importers; the three
  points are then read off the imported rig, which is removed again:
  head point = head of bone ``Head``; hands = head of ``LeftFingerBase`` /
  ``RightFingerBase`` (the end of ``lwrist``) for the CMU-converted naming, else
  head of ``LeftHand`` / ``RightHand`` (the wrist; Mixamo and generic namings).
  Device rotations: the bone's world rotation relative to its rest pose
  (``Rpose · Rrestᵀ``, independent of bone roll), converted to motion space;
  the head device is that of bone ``Head`` composed with Ry(180°)
  (``take.take_from_tracked``: the device looks along −Z, the skull faces +Z),
  so a rig whose rest pose is the SPEC's (upright, facing +Z in the file's
  Y-up space: the CMU conversion, Mixamo's T-pose) gives SPEC §3 head
  quaternions exactly. When the rest pose is not that (e.g. an FBX whose rest
  pose is some frame of the dance, as Blender's FBX exporter writes an
  unskinned armature), each bone's facing is calibrated against the body
  (hips, else shoulders) over the clip instead, with a warning
  (``blender_math.rig_rotations``).

Synthesis reads the take back from the empties (:func:`take_from_collection`),
so keyframe edits made in Blender count.
"""

import os

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper, axis_conversion, orientation_helper

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import InputError, UserError, error_message
from ..dancing_points_addon.formats.files import regular_file
from ..dancing_points_addon.resample import resample_take
from ..dancing_points_addon.formats.naming import rig_side_bones, rig_tracked_bones
from ..dancing_points_addon.formats.inputs import check_take, load_input
from ..dancing_points_addon.formats.limits import check_duration, check_height, check_rate
from ..dancing_points_addon.formats.take import Take, take_from_tracked
from ..dancing_points_addon.formats.units import unit_scale_for_height
from . import compat
from .props import (DEVICE_OBJECT_NAMES, DEVICE_PROP, DEVICES, KIND_TAKE, TRACKED_PROP, device_objects)

FILE_TYPES = (".csv", ".bvh", ".fbx", ".amc")
NET_FPS = 30.0


# --------------------------------------------------------------------------- rig reading

def _snapshot():
    colls = ("objects", "meshes", "armatures", "actions", "materials", "images", "textures",
             "cameras", "lights", "collections", "node_groups")
    return {c: set(getattr(bpy.data, c)[:]) for c in colls}


def _remove_new(before, keep=()):
    new = []
    for c, old in before.items():
        new.extend(x for x in getattr(bpy.data, c)[:] if x not in old and x not in keep)
    if new:
        bpy.data.batch_remove(new)


def _scene_state(scene):
    r = scene.render
    return (r.fps, r.fps_base, scene.frame_start, scene.frame_end, scene.frame_current)


def _restore_scene_state(scene, state):
    r = scene.render
    r.fps, r.fps_base, scene.frame_start, scene.frame_end, frame = state
    scene.frame_set(frame)


def _precheck(path, ext, input_fps=None):
    """Reject a malformed file with a one-line message before Blender's importer
    sees it (the core BVH parser names the line and checks the frame rate and
    duration; FBX: binary files only)."""
    regular_file(path, "a take file", missing="no such file")
    if ext == ".bvh":
        from ..dancing_points_addon.formats import bvh as core_bvh
        try:
            with np.errstate(all="ignore"):
                data = core_bvh.parse_bvh(path, input_fps=input_fps or None)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(path, f"cannot read BVH file ({type(exc).__name__}: {exc})") from None
        if rig_tracked_bones(data.names) is None:
            raise InputError(path, "cannot find the head and hand joints: expected the CMU-converted naming "
                                   "(Head, LeftHand, LeftFingerBase, ...) or Mixamo (mixamorig:Head, "
                                   "mixamorig:LeftHand, ...)")
    elif ext == ".fbx":
        try:
            with open(path, "rb") as fh:
                magic = fh.read(18)
        except OSError as exc:
            raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
        if magic != b"Kaydara FBX Binary":
            raise InputError(path, "not a binary FBX file (Blender's importer reads binary FBX only)")


def read_rig_take(context, path, ext, input_fps=0.0, axis_forward='-Z', axis_up='Y', units='AUTO',
                  ghost=None):
    """A BVH/FBX file through Blender's importer -> :class:`Take` (motion space).

    Everything the importer made is removed again and the scene's frame rate,
    range and current frame are restored, whatever happens; except, when
    ``ghost`` is a dict and the file was read, the source rig and its children
    (with their data, materials and actions), described in ``ghost``
    (``objects``, ``first_frame``, ``rate``, ``scale``) for :func:`keep_ghost`."""
    _precheck(path, ext, input_fps)
    scene = context.scene
    before = _snapshot()
    state = _scene_state(scene)
    keep = set()
    try:
        try:
            if ext == ".bvh":
                res = bpy.ops.import_anim.bvh(filepath=path, axis_forward=axis_forward, axis_up=axis_up,
                                              update_scene_fps=True, update_scene_duration=False,
                                              use_fps_scale=False, global_scale=1.0)
            else:
                res = bpy.ops.import_scene.fbx(filepath=path, use_anim=True, ignore_leaf_bones=False,
                                               automatic_bone_orientation=False)
        except RuntimeError as exc:  # the importer's own error report
            raise InputError(path, f"Blender's {ext[1:].upper()} importer failed: {compat.operator_error_text(exc)}") from None
        if 'FINISHED' not in res:
            raise InputError(path, f"Blender's {ext[1:].upper()} importer could not read the file")
        file_fps = scene.render.fps / scene.render.fps_base
        arms = [o for o in bpy.data.objects if o not in before["objects"] and o.type == 'ARMATURE']
        found = None
        for arm in arms:
            spec = rig_tracked_bones([b.name for b in arm.data.bones])
            if spec is not None:
                found = (arm, spec)
                break
        if found is None:
            raise InputError(path, "no armature with a Head bone and hand bones (expected the CMU-converted "
                                   "naming: Head, LeftHand, LeftFingerBase, ... or Mixamo: mixamorig:Head, "
                                   "mixamorig:LeftHand, ...)")
        arm, (point_bones, rot_bones, naming) = found
        side_bones = rig_side_bones([b.name for b in arm.data.bones])
        action = arm.animation_data.action if arm.animation_data else None
        if action is None:
            raise InputError(path, "the file has no animation")
        f0, f1 = (int(round(x)) for x in action.frame_range)
        if f1 - f0 + 1 < 2:
            raise InputError(path, f"only {f1 - f0 + 1} frame(s); a take needs at least 2")
        # The same bounds as the core readers, before a frame is evaluated.
        rate = (check_rate(path, input_fps) if input_fps and input_fps > 0 else
                check_rate(path, file_fps, what="the file's frame rate (set Input FPS to override it)"))
        check_duration(path, (f1 - f0) / rate, what=f"the animation ({f1 - f0 + 1} frames at {rate:g} fps)")
        frames = np.arange(f0, f1 + 1)
        # Rest pose (world, Blender space): bone frames, size, and whether it is the SPEC rest pose.
        mw = np.array(arm.matrix_world)
        bones = arm.data.bones

        def rest_point(name):
            return (mw @ np.array([*bones[name].head_local, 1.0]))[:3]

        rest_rot = np.stack([(mw @ np.array(bones[b].matrix_local))[:3, :3] for b in rot_bones])
        ends = np.array([[*bones[b].head_local, 1.0] for b in bones.keys()]
                        + [[*bones[b].tail_local, 1.0] for b in bones.keys()]) @ mw.T
        height = rest_point(point_bones[0])[2] - ends[:, 2].min()
        scale = unit_scale_for_height(height) if units == 'AUTO' else 1.0
        rest_ok = side_bones is not None and bm.rest_faces_spec(
            bm.to_motion(rest_point(side_bones[0])), bm.to_motion(rest_point(side_bones[1])),
            bm.to_motion(rest_point(point_bones[0])))
        if side_bones is None:
            side_bones = (point_bones[1], point_bones[2])  # only used if the rest pose is unusable
        T = len(frames)
        pts = np.empty((T, 5, 3))
        world = np.empty((T, 3, 3, 3))
        depsgraph = context.evaluated_depsgraph_get()
        names = tuple(point_bones) + tuple(side_bones)
        for i, f in enumerate(frames):
            scene.frame_set(int(f))
            ev = arm.evaluated_get(depsgraph)
            mw_t = np.array(ev.matrix_world)
            pb = ev.pose.bones
            for d, name in enumerate(names):
                pts[i, d] = (mw_t @ np.array([*pb[name].head, 1.0]))[:3]
            for d in range(3):
                world[i, d] = (mw_t @ np.array(pb[rot_bones[d]].matrix))[:3, :3]
        pts_m = bm.to_motion(pts * scale)
        # Bone frames (columns = local axes in world) to motion space: C^T · W.
        world_m = bm.C.T @ world
        rest_m = bm.C.T @ rest_rot
        rot = bm.rig_rotations(world_m, rest_m, pts_m[:, 3], pts_m[:, 4], rest_ok)
        time = (frames - frames[0]) / rate
        meta = {"source_naming": naming}
        take = take_from_tracked(time, pts_m[:, :3], rot[:, 0], rot[:, 1], rot[:, 2], meta, path)
        take.meta["source_fps"] = rate
        if not rest_ok:
            take.meta["rotation_estimate"] = "body"
        if ghost is not None:
            objs = [arm] + list(arm.children_recursive)
            ghost.update(objects=objs, first_frame=int(f0), rate=float(rate), scale=float(scale))
            for obj in objs:
                keep.add(obj)
                if obj.data is not None:
                    keep.add(obj.data)
                    keep.update(m for m in getattr(obj.data, "materials", ()) if m is not None)
                act = compat.assigned_action(obj)[0]
                if act is not None:
                    keep.add(act)
        return take
    finally:
        _remove_new(before, keep)
        _restore_scene_state(scene, state)


GHOST_PROP = "dp_ghost"  # on the objects of a take's source body (operators/method_view.py shows/hides them)


def _retime_action(action, slot, first_frame, rate, frame_start, frame_step=1.0):
    """Move the keys of ``action`` from the file's frames (``first_frame`` at
    ``rate`` fps) onto the take's scene time: 30 Hz sample ``k`` on frame
    ``frame_start + k · frame_step`` (bulk)."""
    a = NET_FPS / rate * frame_step
    for fc in compat.fcurves_of(action, slot):
        n = len(fc.keyframe_points)
        if not n:
            continue
        for attr in ("co", "handle_left", "handle_right"):
            co = np.empty(2 * n, dtype=np.float32)
            fc.keyframe_points.foreach_get(attr, co)
            co[0::2] = frame_start + (co[0::2] - first_frame) * a
            fc.keyframe_points.foreach_set(attr, co)
        fc.update()


def _ghost_look(obj, coll):
    for c in list(obj.users_collection):
        c.objects.unlink(obj)
    coll.objects.link(obj)
    obj[GHOST_PROP] = True
    obj.display_type = 'WIRE'
    obj.show_in_front = False
    obj.hide_select = True


def keep_ghost(coll, ghost, frame_start, frame_step=1.0):
    """The source rig kept by :func:`read_rig_take` (``ghost``) in the take
    collection ``coll``: its keys on the take's frames, scaled by the take's unit
    scale (under an empty "Source Body"), drawn as a wire ghost."""
    objs = ghost["objects"]
    root = bpy.data.objects.new("Source Body", None)
    root.empty_display_size = 0.1
    _ghost_look(root, coll)
    s = ghost["scale"]
    root.scale = (s, s, s)
    for obj in objs:
        _ghost_look(obj, coll)
        if obj.parent is None:
            obj.parent = root  # world = S · its own transform (identity parent inverse)
        action, slot = compat.assigned_action(obj)
        if action is not None:
            _retime_action(action, slot, ghost["first_frame"], ghost["rate"], frame_start, frame_step)
    return [root] + objs


def build_amc_ghost(context, coll, path, input_fps, frame_start, frame_step=1.0):
    """The full body of a CMU AMC file as a wire ghost in the take collection:
    a SPEC armature (its 30 Hz samples keyed as the take's: from ``frame_start``,
    ``frame_step`` apart) with the default body."""
    from ..dancing_points_addon.formats.asf_amc import load_amc
    from ..dancing_points_addon.resample import resample_motion
    from . import bake

    motion = resample_motion(load_amc(path, fps=input_fps or None), NET_FPS)
    bv, pos, rot = bm.consistent_pose(motion.positions, motion.rotations)
    made = bake.Created()
    try:
        arm = bake.build_armature(context, "Source Body", bv, coll, made)
        made.add(bake.key_armature(arm, "DP Source Body " + coll.name, pos, rot, frame_start, frame_step))
        body = bake.build_body("Source Body Mesh", arm, bv, (0.7, 0.7, 0.7, 0.35), coll, made)
        for obj in (arm, body):
            _ghost_look(obj, coll)
        return [arm, body]
    except Exception:
        made.remove_all()
        raise


def load_any(context, path, input_fps=0.0, height=0.0, axis_forward='-Z', axis_up='Y', units='AUTO', ghost=None):
    """Any supported file as a :class:`Take` (motion space, source rate);
    ``ghost``: see :func:`read_rig_take` (BVH/FBX only)."""
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
        take = check_take(read_rig_take(context, path, ext, fps or 0.0, axis_forward, axis_up, units, ghost),
                          path)
    else:
        take = load_input(path, input_fps=fps)  # check_take included
    if h is not None:
        take.meta["height_m"] = h
    return take


# --------------------------------------------------------------------------- take <-> empties

def build_take_collection(context, take30, name, frame_start=1, conv=bm.C, settings=None, frame_step=1.0):
    """The collection "DP Take <name>" with the three keyframed empties.

    ``take30``: a take at 30 Hz (motion space, or the file's axes with ``conv``
    the file -> Blender matrix). ``settings``: values for ``coll.dancing_points``.
    Sample ``k`` is keyed on scene frame ``frame_start + k * frame_step``
    (``frame_step`` = the scene's frame rate / 30: the take plays at its real
    speed in scene time)."""
    T = take30.n_frames
    frames = sample_frames(frame_start, frame_step, T)
    coll = bpy.data.collections.new("DP Take " + name)
    try:
        context.scene.collection.children.link(coll)
        s = coll.dancing_points
        s.kind = KIND_TAKE
        for k, v in (settings or {}).items():
            setattr(s, k, v)
        s.frame_start = int(frame_start)
        s.frame_step = float(frame_step)
        s.n_frames = T
        s.fps = NET_FPS
        s.t0 = float(take30.time[0])
        valid = take30.valid
        store_samples(coll, bm.to_motion(bm.to_blender(take30.positions, conv)),
                      bm.quat_to_motion(bm.quat_to_blender(take30.quats, conv)))
        objs = {}
        for d, dev in enumerate(DEVICES):
            obj = bpy.data.objects.new(DEVICE_OBJECT_NAMES[dev], None)
            obj.empty_display_type = 'SPHERE' if dev == "head" else 'ARROWS'
            obj.empty_display_size = 0.12 if dev == "head" else 0.08
            obj.rotation_mode = 'QUATERNION'
            obj[DEVICE_PROP] = dev
            obj[TRACKED_PROP] = 1.0
            coll.objects.link(obj)
            objs[dev] = obj
            ok = valid[:, d]
            loc = bm.fill_gaps(bm.to_blender(take30.positions[:, d], conv), ok)
            q = bm.fill_gaps(bm.quat_to_blender(take30.quats[:, d], conv), ok)
            q = bm.continuous_quats(q)
            obj.location = loc[0]
            obj.rotation_quaternion = q[0]
            action, slot = compat.new_action_for(obj, "DP {:s} {:s}".format(name, obj.name))
            group = DEVICE_OBJECT_NAMES[dev]
            for i in range(3):
                compat.write_keys(compat.ensure_fcurves(action, slot, "location", i, group), frames, loc[:, i])
            for i in range(4):
                compat.write_keys(compat.ensure_fcurves(action, slot, "rotation_quaternion", i, group),
                                  frames, q[:, i])
            compat.write_keys(compat.ensure_fcurves(action, slot, '["%s"]' % TRACKED_PROP, 0, group),
                              frames, ok.astype(np.float64), interpolation='CONSTANT')
        return coll, objs
    except Exception:
        _remove_collection(coll)
        raise


def sample_frames(frame_start, frame_step, n):
    """Scene frames ``(n,)`` of a take's 30 Hz samples."""
    return frame_start + float(frame_step) * np.arange(n, dtype=np.float64)


def take_frames(coll):
    """Scene frames of the samples of a take collection."""
    s = coll.dancing_points
    return sample_frames(s.frame_start, s.frame_step if s.frame_step > 0 else 1.0, int(s.n_frames))


SAMPLES_PROP = "dp_samples"  # the take's own 30 Hz samples, float64, motion space


def store_samples(coll, positions, quats):
    """Keep the take's 30 Hz samples at full precision beside its keyframes
    (which Blender stores as float32): synthesis reads them back while the
    empties still show them, so the bake is the command line's duet of the
    same file, not that of a take rounded to float32."""
    T = len(positions)
    coll[SAMPLES_PROP] = np.concatenate([np.asarray(positions, np.float64).reshape(T, 9),
                                         np.asarray(quats, np.float64).reshape(T, 12)], axis=1).ravel().tolist()


def stored_samples(coll, positions, quats, tol=1e-4):
    """The stored full-precision samples ``(positions, quats)`` when they still
    agree with the take read from the empties (``positions (T, 3, 3)``,
    ``quats (T, 3, 4)``, NaN where lost) within ``tol``; else None (the
    user edited the animation: the keyframes are the take)."""
    raw = coll.get(SAMPLES_PROP)
    T = len(positions)
    if raw is None or len(raw) != T * 21:
        return None
    a = np.array(raw.to_list() if hasattr(raw, "to_list") else raw, dtype=np.float64).reshape(T, 21)
    pos, q = a[:, :9].reshape(T, 3, 3), a[:, 9:].reshape(T, 3, 4)
    lost = ~np.isfinite(positions).all(-1)
    if not np.array_equal(lost, ~np.isfinite(pos).all(-1)):
        return None
    ok = ~lost
    if ok.any():
        if np.max(np.abs(pos[ok] - positions[ok])) > tol:
            return None
        dq = np.minimum(np.abs(q[ok] - quats[ok]).max(-1), np.abs(q[ok] + quats[ok]).max(-1))
        if np.max(dq) > tol:
            return None
    return pos, q


def _remove_collection(coll):
    ids = [coll]
    for obj in coll.all_objects:
        ids.append(obj)
        if obj.animation_data and obj.animation_data.action:
            ids.append(obj.animation_data.action)
        if obj.get(GHOST_PROP) and obj.data is not None:
            ids.append(obj.data)
    bpy.data.batch_remove(list(dict.fromkeys(ids)))


def _remove_ghost(objs):
    ids = []
    for obj in objs:
        try:
            obj.name  # raises ReferenceError when already removed
            ids.append(obj)
            if obj.data is not None:
                ids.append(obj.data)
            if obj.animation_data and obj.animation_data.action:
                ids.append(obj.animation_data.action)
        except ReferenceError:
            continue
    if ids:
        bpy.data.batch_remove(list(dict.fromkeys(ids)))


def _device_world(obj, context, frames):
    """Location (T, 3), quaternion (T, 4) and tracked flag (T,) of a device empty
    at ``frames``, Blender space."""
    T = len(frames)
    needs_eval = (obj.parent is not None or len(obj.constraints) > 0 or obj.rotation_mode != 'QUATERNION'
                  or (obj.animation_data is not None and len(obj.animation_data.drivers) > 0))
    action, slot = compat.assigned_action(obj)
    tracked = np.full(T, float(obj.get(TRACKED_PROP, 1.0)))
    fc = compat.find_fcurve(action, slot, '["%s"]' % TRACKED_PROP, 0)
    if fc is not None and len(fc.keyframe_points):
        tracked = compat.sample_fcurve(fc, frames)
    if needs_eval:
        scene = context.scene
        cur = scene.frame_current
        loc = np.empty((T, 3))
        quat = np.empty((T, 4))
        try:
            depsgraph = context.evaluated_depsgraph_get()
            for i, f in enumerate(frames):
                whole = int(np.floor(f + 1e-9))
                scene.frame_set(whole, subframe=float(f - whole))
                m = obj.evaluated_get(depsgraph).matrix_world
                loc[i] = m.to_translation()
                quat[i] = m.to_quaternion()
        finally:
            scene.frame_set(cur)
        return loc, quat, tracked
    loc = np.tile(np.array(obj.location), (T, 1))
    quat = np.tile(np.array(obj.rotation_quaternion), (T, 1))
    for i in range(3):
        fc = compat.find_fcurve(action, slot, "location", i)
        if fc is not None and len(fc.keyframe_points):
            loc[:, i] = compat.sample_fcurve(fc, frames)
    for i in range(4):
        fc = compat.find_fcurve(action, slot, "rotation_quaternion", i)
        if fc is not None and len(fc.keyframe_points):
            quat[:, i] = compat.sample_fcurve(fc, frames)
    return loc, quat, tracked


def take_from_collection(context, coll):
    """The take held by a take collection, read from its empties' animation:
    a 30 Hz :class:`Take` in motion space (Blender Z up -> Y up)."""
    s = coll.dancing_points
    objs = device_objects(coll)
    missing = [DEVICE_OBJECT_NAMES[d] for d in DEVICES if d not in objs]
    if missing:
        raise UserError("take '{:s}' has no {:s} empty (objects carry a '{:s}' property)".format(
            coll.name, " or ".join(missing), DEVICE_PROP))
    T = int(s.n_frames)
    if T < 2:
        raise UserError("take '{:s}' has {:d} frame(s); a take needs at least 2".format(coll.name, T))
    frames = take_frames(coll)
    pos = np.empty((T, 3, 3))
    quats = np.empty((T, 3, 4))
    for d, dev in enumerate(DEVICES):
        loc, q, tracked = _device_world(objs[dev], context, frames)
        q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
        lost = tracked < 0.5
        pos[:, d] = bm.to_motion(loc)
        quats[:, d] = bm.quat_to_motion(q)
        pos[lost, d] = np.nan
        quats[lost, d] = np.nan
    if not np.isfinite(pos).all(-1).any():
        raise UserError("take '{:s}' has no tracked samples".format(coll.name))
    exact = stored_samples(coll, pos, quats)
    if exact is not None:
        pos, quats = exact
    time = s.t0 + np.arange(T) / float(s.fps or NET_FPS)
    meta = {"devices": s.devices, "role": s.role}
    if s.height > 0:
        meta["height_m"] = float(s.height)
    if s.use_floor_y:
        meta["floor_y"] = float(s.floor_y)
    return Take(time, pos, quats, meta, s.source)


# --------------------------------------------------------------------------- operator

@orientation_helper(axis_forward='-Z', axis_up='Y')
class DANCING_POINTS_OT_import_take(bpy.types.Operator, ImportHelper):
    """Import a three-point take (.csv), or the head and hands of a BVH, FBX or CMU AMC motion, as a take"""

    bl_idname = "dancing_points.import_take"
    bl_label = "Import Dancing Points Take"
    bl_options = {'REGISTER', 'UNDO', 'PRESET'}

    filename_ext = ".csv"
    filter_glob: StringProperty(default="*.csv;*.bvh;*.fbx;*.amc", options={'HIDDEN'})

    frame_start: IntProperty(name="Start Frame", description="Scene frame of the take's first sample", default=1)
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
    keep_source: BoolProperty(name="Keep Source Body", default=False,
                              description="BVH, FBX, AMC: keep the file's full body in the take as a wire "
                                          "ghost, to compare with the synthesised leader")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        for prop in ("frame_start", "input_fps", "role", "height", "devices", "units", "update_scene_fps",
                     "update_scene_duration", "keep_source", "axis_forward", "axis_up"):
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
        self.report({'INFO'}, "Imported take '{:s}' ({:d} frames at 30 fps)".format(
            coll.name, coll.dancing_points.n_frames))
        return {'FINISHED'}

    def import_file(self, context):
        path = bpy.path.abspath(self.filepath)
        ext = os.path.splitext(path)[1].lower()
        ghost = {} if self.keep_source and ext in (".bvh", ".fbx") else None
        try:
            take = load_any(context, path, self.input_fps, self.height, self.axis_forward, self.axis_up,
                            self.units, ghost)
            coll = self._make_take(context, path, ext, take, ghost)
        except Exception:
            if ghost:  # the kept rig, when the take could not be made
                _remove_ghost(ghost["objects"])
            raise
        return coll

    def _make_take(self, context, path, ext, take, ghost):
        conv = np.array(axis_conversion(from_forward=self.axis_forward, from_up=self.axis_up).to_3x3())
        source_fps = float(take.meta.pop("source_fps", 0.0))
        estimated = take.meta.pop("rotation_estimate", None) is not None
        take.meta.pop("source_naming", None)
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
                        axis_forward=self.axis_forward, axis_up=self.axis_up)
        if take.meta.get("floor_y") not in (None, ""):
            try:
                settings.update(use_floor_y=True, floor_y=float(take.meta["floor_y"]))
            except ValueError:
                raise InputError(path, f"floor_y is not a number: {take.meta['floor_y']!r}") from None
        scene = context.scene
        # Keys in scene time: one scene frame per sample when the scene is set to 30 fps, else
        # the scene's rate / 30 (a 24 fps project keeps its rate and the take its real speed).
        step = 1.0 if self.update_scene_fps else (scene.render.fps / (scene.render.fps_base or 1.0)) / NET_FPS
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
            _remove_collection(coll)
            raise
        scene = context.scene
        if self.update_scene_fps:
            scene.render.fps = int(NET_FPS)
            scene.render.fps_base = 1.0
        if self.update_scene_duration:
            scene.frame_start = self.frame_start
            scene.frame_end = self.frame_start + int(np.ceil((take30.n_frames - 1) * step - 1e-6))
        scene.dancing_points.take = coll
        if estimated:
            self.report({'WARNING'}, "{:s}: the rig's rest pose is not a T-pose facing forward; the head "
                                     "orientation was estimated from the hips".format(os.path.basename(path)))
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
