# SPDX-License-Identifier: GPL-3.0-or-later
"""The three points of a BVH or FBX file through Blender's own importers
(:func:`read_rig_take`, for ``bpy.ops.dancing_points.import_take``,
:mod:`.take_io`); the imported rig is removed again.

Which bones and what their rotations mean: ``formats.rig_rest`` (the same
as the core BVH reader's). Points: the heads of the skull bone and the hand
bones (the wrists). Device rotations: the skull's and the forearm's end's
(the hand bone's parent: never the hand bone, which bends at the wrist),
each the bone's world rotation relative to its rest pose (``Rpose · Rrestᵀ``,
independent of bone roll), converted to motion space and corrected for the
rest pose (T- or A-pose, any facing) to SPEC §2's; the head device is that
of the skull composed with Ry(180°) (``take.take_from_tracked``). A rig
whose rest pose cannot be related to the SPEC's (say an armature exported
without its rest pose, where Blender writes the pose of the export frame)
gives its points without orientations: ``orientations=none``, the reason in
``orientations_problem``.
"""

import re

import bpy
import numpy as np

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import InputError
from ..dancing_points_addon.formats.files import regular_file
from ..dancing_points_addon.formats.naming import rig_tracked_bones
from ..dancing_points_addon.formats.rig_rest import rest_corrections, tracked_rig
from ..dancing_points_addon.formats.limits import check_duration, check_rate
from ..dancing_points_addon.formats.take import take_from_tracked
from ..dancing_points_addon.formats.units import unit_scale_for_height
from . import compat
from .bake import ROLE_LABEL
from .props import ROLE_PROP, ROLES

RIG_NAMES = ("a skull bone and hand bones: Head with LeftHand/RightHand as in Mixamo, Rokoko or the "
             "CMU-converted BVH; hand_l (Unreal), DEF-hand.L (Rigify), J_Bip_L_Hand (VRoid) or lhand (ASF)")
# The armatures of a baked duet by the role they dance (``bake.bake_duet``: "DP Leader", "DP Follower").
DP_ARMATURE_ROLES = {"DP " + label: role for role, label in ROLE_LABEL.items()}


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
            raise InputError(path, "cannot find the head and hand joints: expected " + RIG_NAMES)
    elif ext == ".fbx":
        try:
            with open(path, "rb") as fh:
                magic = fh.read(18)
        except OSError as exc:
            raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
        if magic != b"Kaydara FBX Binary":
            raise InputError(path, "not a binary FBX file (Blender's importer reads binary FBX only)")


def _file_name(obj, taken):
    """The name ``obj`` has in the file: Blender renames an imported object whose
    name an object of the scene already has (``Rig`` -> ``Rig.001``)."""
    m = re.fullmatch(r"(.+)\.\d{3,}", obj.name)
    return m.group(1) if m and m.group(1) in taken else obj.name


def _armature_role(obj, name):
    """The dance role an armature states: its :data:`~.props.ROLE_PROP`, else the
    name of a Dancing Points duet's armature (``DP Leader`` / ``DP Follower``, as
    an FBX export of a duet has them); None when it says none."""
    role = obj.get(ROLE_PROP)
    if role in ROLES:
        return role
    return DP_ARMATURE_ROLES.get(name)


def choose_armature(path, arms, taken=(), role=None, armature=""):
    """The armature of a file to read a take from, among the imported ``arms``:
    ``(object, rig_tracked_bones spec, name in the file, role it states)``.

    ``armature`` (a name as in the file) picks one. Otherwise, of the armatures
    with head and hand bones: the only one; else the only one whose stated role
    (:func:`_armature_role`) is ``role`` (None: the leader, a take's default
    role), so that a Dancing Points duet FBX gives the chosen dancer. Anything
    else is an :class:`InputError` naming the candidates and how to choose."""
    found = []
    for arm in sorted(arms, key=lambda o: o.name):
        spec = rig_tracked_bones([b.name for b in arm.data.bones])
        name = _file_name(arm, taken)
        found.append((arm, spec, name, _armature_role(arm, name)))
    cands = [f for f in found if f[1] is not None]
    listed = ", ".join(repr(f[2]) for f in cands)
    if armature:
        named = [f for f in found if armature in (f[2], f[0].name)]
        if not named:
            raise InputError(path, "no armature named {!r} in the file (armatures: {:s})".format(
                armature, ", ".join(repr(f[2]) for f in found) or "none"))
        if named[0][1] is None:
            raise InputError(path, "armature {!r} has no Head bone and hand bones (armatures with them: "
                                   "{:s})".format(armature, listed or "none"))
        return named[0]
    if not cands:
        raise InputError(path, "no armature with a Head bone and hand bones (expected " + RIG_NAMES + ")")
    if len(cands) == 1:
        return cands[0]
    want = role or "leader"
    same = [f for f in cands if f[3] == want]
    if len(same) == 1:
        return same[0]
    raise InputError(path, "{:d} armatures have a Head bone and hand bones ({:s}){:s}; name the one to read "
                           "in the import's Armature option, or keep only that one in the file".format(
                               len(cands), listed, " and none is the {:s}'s".format(want) if not same else
                               ", {:d} of them the {:s}'s".format(len(same), want)))


def read_rig_take(context, path, ext, input_fps=0.0, axis_forward='-Z', axis_up='Y', units='AUTO',
                  ghost=None, role=None, armature=""):
    """A BVH/FBX file through Blender's importer -> :class:`Take` (motion space).

    The armature read is :func:`choose_armature`'s (``role``: the take's role
    when given, ``armature``: a name as in the file); its name in the file is
    ``meta['source_armature']``, and when no ``role`` is given, the role it
    states (a duet FBX's ``DP Leader`` / ``DP Follower``) is ``meta['role']``.

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
            why = compat.operator_error_text(exc)
            raise InputError(path, f"Blender's {ext[1:].upper()} importer failed: {why}") from None
        if 'FINISHED' not in res:
            raise InputError(path, f"Blender's {ext[1:].upper()} importer could not read the file")
        file_fps = scene.render.fps / scene.render.fps_base
        arms = [o for o in bpy.data.objects if o not in before["objects"] and o.type == 'ARMATURE']
        taken = {o.name for o in before["objects"]}
        arm, _, arm_name, arm_role = choose_armature(path, arms, taken, role, armature)
        bones = arm.data.bones
        names = [b.name for b in bones]
        where = {n: i for i, n in enumerate(names)}
        parents = [where[b.parent.name] if b.parent is not None else -1 for b in bones]
        rig = tracked_rig(names, parents)
        point_bones = [names[i] for i in rig.points]
        rot_bones = [names[rig.points[0] if i is None else i] for i in rig.rotations]
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
        # Rest pose (world, Blender space): bone frames, heads (how it relates to the SPEC's), size.
        mw = np.array(arm.matrix_world)
        rest_rot = np.stack([(mw @ np.array(bones[b].matrix_local))[:3, :3] for b in rot_bones])
        heads = np.array([[*b.head_local, 1.0] for b in bones]) @ mw.T
        ends = np.concatenate([heads, np.array([[*b.tail_local, 1.0] for b in bones]) @ mw.T])
        height = heads[rig.points[0], 2] - ends[:, 2].min()
        scale = unit_scale_for_height(height) if units == 'AUTO' else 1.0
        Q, problem = rest_corrections(bm.to_motion(heads[:, :3]), parents, rig)
        T = len(frames)
        pts = np.empty((T, 3, 3))
        world = np.empty((T, 3, 3, 3))
        depsgraph = context.evaluated_depsgraph_get()
        for i, f in enumerate(frames):
            scene.frame_set(int(f))
            ev = arm.evaluated_get(depsgraph)
            mw_t = np.array(ev.matrix_world)
            pb = ev.pose.bones
            for d in range(3):
                pts[i, d] = (mw_t @ np.array([*pb[point_bones[d]].head, 1.0]))[:3]
                world[i, d] = (mw_t @ np.array(pb[rot_bones[d]].matrix))[:3, :3]
        pts_m = bm.to_motion(pts * scale)
        # Bone frames (columns = local axes in world) to motion space: C^T · W; relative to the
        # rest pose: W · W_restᵀ (bone rolls cancel); to the SPEC rest pose: · Q.
        world = world / np.linalg.norm(world, axis=-2, keepdims=True)
        rest_rot = rest_rot / np.linalg.norm(rest_rot, axis=-2, keepdims=True)
        rot = (bm.C.T @ world) @ np.swapaxes(bm.C.T @ rest_rot, -1, -2)[None]
        if Q is not None:
            rot = rot @ Q[None]
        time = (frames - frames[0]) / rate
        meta = {"source_naming": rig.naming, "source_armature": arm_name}
        if role is None and arm_role is not None:  # the file says whose dance it is (a duet FBX's armature)
            meta["role"] = arm_role
        take = take_from_tracked(time, pts_m, rot[:, 0], rot[:, 1], rot[:, 2], meta, path, problem)
        take.meta["source_fps"] = rate
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
