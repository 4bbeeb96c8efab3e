# SPDX-License-Identifier: GPL-3.0-or-later
"""The source body of a take kept as a wire ghost in its collection (Keep
Source Body of ``bpy.ops.dancing_points.import_take``, :mod:`.take_io`): the
BVH/FBX rig the importer made (:func:`keep_ghost`), or a SPEC armature and body
for a CMU AMC file (:func:`build_amc_ghost`). Its objects carry ``["dp_ghost"]``
(:mod:`.method_view` shows or hides them).
"""

import bpy
import numpy as np

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.resample import NET_FPS
from . import compat
from .props import GHOST_PROP


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
    """The source rig kept by :func:`.take_rig.read_rig_take` (``ghost``) in the take
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


def remove_ghost(objs):
    from . import bake

    ids = []
    for obj in bake.alive(objs):
        ids.append(obj)
        if obj.data is not None:
            ids.append(obj.data)
        if obj.animation_data and obj.animation_data.action:
            ids.append(obj.animation_data.action)
    if ids:
        bpy.data.batch_remove(list(dict.fromkeys(ids)))
