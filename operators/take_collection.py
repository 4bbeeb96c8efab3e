# SPDX-License-Identifier: GPL-3.0-or-later
"""A take in the scene (SPEC §8) and reading it back.

A take is a collection "DP Take <name>" with three empties (Head, LeftHand,
RightHand) keyframed once per 30 Hz sample in Blender's Z-up space: location,
rotation (quaternion, device-to-world as in the file) and an animated
``["dp_tracked"]`` flag (0 where the file had lost tracking; the location and
rotation then hold the last tracked value); beside the keys, the take's own
samples at full precision (:func:`store_samples`).

Synthesis reads the take back from the empties (:func:`take_from_collection`),
so keyframe edits made in Blender count.
"""

import bpy
import numpy as np

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import UserError
from ..dancing_points_addon.formats.devices import META_TURN_KEYS
from ..dancing_points_addon.formats.take import ORIENTATIONS_KEY, Take
from ..dancing_points_addon.resample import NET_FPS
from . import compat
from .kinds import KIND_TAKE
from .props import DEVICE_OBJECT_NAMES, DEVICE_PROP, DEVICES, GHOST_PROP, TRACKED_PROP, check_dancer, device_objects


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
        remove_collection(coll)
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
    a = np.array(compat.plain_value(raw), dtype=np.float64).reshape(T, 21)
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


def remove_collection(coll):
    ids = [coll]
    for obj in coll.all_objects:
        ids.append(obj)
        if obj.animation_data and obj.animation_data.action:
            ids.append(obj.animation_data.action)
        if obj.get(GHOST_PROP) and obj.data is not None:
            ids.append(obj.data)
    bpy.data.batch_remove(list(dict.fromkeys(ids)))


def _last_key(objs):
    """The last scene frame every keyed device empty is keyed to: of each, its
    last location or rotation key; of those, the earliest (None: none is keyed,
    e.g. all driven by constraints)."""
    ends = []
    for obj in objs.values():
        action, slot = compat.assigned_action(obj)
        own = [float(fc.range()[1]) for path, n in (("location", 3), ("rotation_quaternion", 4)) for i in range(n)
               for fc in (compat.find_fcurve(action, slot, path, i),) if fc is not None and len(fc.keyframe_points)]
        if own:
            ends.append(max(own))
    return min(ends) if ends else None


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
    check_dancer("take '{:s}'".format(coll.name), s.height, s.use_floor_y, s.floor_y)
    objs = device_objects(coll)
    missing = [DEVICE_OBJECT_NAMES[d] for d in DEVICES if d not in objs]
    if missing:
        raise UserError("take '{:s}' has no {:s} empty (objects carry a '{:s}' property)".format(
            coll.name, " or ".join(missing), DEVICE_PROP))
    T = int(s.n_frames)
    if T < 2:
        raise UserError("take '{:s}' has {:d} frame(s); a take needs at least 2".format(coll.name, T))
    frames = take_frames(coll)
    last = _last_key(objs)
    if last is not None and frames[-1] > last + 1e-3:
        keyed = int(np.sum(frames <= last + 1e-3))
        raise UserError("take '{:s}' has {:d} frames (its Frames setting), but its empties are keyed only up to "
                        "scene frame {:g}, {:d} of them: set Frames to {:d} or key the rest".format(
                            coll.name, T, last, keyed, keyed))
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
    if s.orientations:
        meta[ORIENTATIONS_KEY] = s.orientations
    for key in META_TURN_KEYS:
        q = tuple(float(v) for v in getattr(s, key))
        if max(abs(q[0] - 1.0), *map(abs, q[1:])) > 1e-9:  # not the identity
            meta[key] = ",".join(repr(v) for v in q)
    if s.height > 0:
        meta["height_m"] = float(s.height)
    if s.use_floor_y:
        meta["floor_y"] = float(s.floor_y)
    return Take(time, pos, quats, meta, s.source)
