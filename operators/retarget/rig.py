# SPDX-License-Identifier: GPL-3.0-or-later
"""Reading from Blender: a target armature as a ``TargetRig`` (with its
reference pose), the motion of a Dancing Points armature, and rig files
(.blend, .glb/.gltf, .fbx) imported into the scene."""

import os
import shutil
import tempfile

import bpy
import numpy as np

from ...dancing_points_addon import blender_math as bm
from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.retarget import RetargetError
from ...dancing_points_addon.skeleton import JOINT_NAMES
from .. import bake, compat
from .props import REF_PROP


def mat(m):
    """A Blender matrix as a float64 array."""
    return np.array(m, dtype=np.float64)


def _bone_arrays(obj):
    bones = obj.data.bones
    names = [b.name for b in bones]
    index = {n: i for i, n in enumerate(names)}
    parents = [index[b.parent.name] if b.parent is not None else -1 for b in bones]
    rest = np.stack([mat(b.matrix_local) for b in bones])
    lengths = np.array([b.length for b in bones])
    return names, parents, rest, lengths


def reference_basis(obj, store=True):
    """The target's reference pose as ``matrix_basis (B, 4, 4)``: the one stored on
    the object, else its current pose when it has no action (just imported), else
    its rest pose, but a scaled bone keeps its scale and offset (a glTF or FBX
    importer leaves a node's transform, a scale of 0.01 say, on a pose bone:
    without it such a rig's rest pose is 100 times its size). Stored on the
    object (``dp_reference_basis``) the first time."""
    names = [b.name for b in obj.data.bones]
    stored = obj.get(REF_PROP)
    if stored is not None:
        try:
            arr = np.array(list(stored), dtype=np.float64).reshape(-1, 4, 4)
            if arr.shape[0] == len(names):
                return arr
        except (TypeError, ValueError):
            pass
    action, _ = compat.assigned_action(obj)
    if action is None:
        arr = np.stack([mat(obj.pose.bones[n].matrix_basis) for n in names])
    else:
        arr = np.broadcast_to(np.eye(4), (len(names), 4, 4)).copy()
        for i, n in enumerate(names):  # an importer's node transform: a scaled bone's scale and offset
            pb = obj.pose.bones[n]
            if np.abs(np.array(pb.scale) - 1.0).max() > 1e-6:
                arr[i, [0, 1, 2], [0, 1, 2]] = tuple(pb.scale)
                arr[i, :3, 3] = tuple(pb.location)
    if store:
        obj[REF_PROP] = arr.reshape(-1).tolist()
    return arr


def target_rig(obj, store=True, deform_parents=False):
    """The target as a :class:`TargetRig`; with ``deform_parents`` (a generated
    Rigify rig solved on its DEF- bones), every DEF- bone under the DEF- bone it follows."""
    names, parents, rest, lengths = _bone_arrays(obj)
    if deform_parents:
        from ...dancing_points_addon.retarget.rigify import deform_parents as _deform_parents

        parents = _deform_parents(names, parents)
    return rt.TargetRig(names, parents, rest, lengths, reference_basis(obj, store), mat(obj.matrix_world))


def source_motion(arm_obj):
    """``(frames, positions (T, 31, 3), rotations (T, 31, 3, 3), bone_vectors, matrix_world)``
    of a Dancing Points armature, from its action's keys (SPEC motion space)."""
    bones = arm_obj.data.bones
    missing = [n for n in JOINT_NAMES if n not in bones]
    if missing:
        raise RetargetError("'{:s}' is not a Dancing Points armature (no bone {:s})".format(
            arm_obj.name, missing[0]))
    action, slot = compat.assigned_action(arm_obj)
    if action is None:
        raise RetargetError("'{:s}' has no animation to retarget".format(arm_obj.name))
    fc = compat.find_fcurve(action, slot, 'pose.bones["root"].location', 0)
    if fc is None:
        raise RetargetError("'{:s}' has no root motion keys".format(arm_obj.name))
    frames, _, _ = compat.read_keys(fc)
    if len(frames) < 2:
        raise RetargetError("'{:s}' has fewer than 2 keyframes".format(arm_obj.name))
    T = len(frames)
    quats = np.zeros((T, len(JOINT_NAMES), 4))
    quats[..., 0] = 1.0
    loc = np.zeros((T, 3))
    for n, name in enumerate(JOINT_NAMES):
        for i in range(4):
            f = compat.find_fcurve(action, slot, 'pose.bones["{:s}"].rotation_quaternion'.format(name), i)
            if f is not None:
                quats[:, n, i] = compat.sample_fcurve(f, frames)
    for i in range(3):
        f = compat.find_fcurve(action, slot, 'pose.bones["root"].location', i)
        if f is not None:
            loc[:, i] = compat.sample_fcurve(f, frames)
    rest_rot, rest_heads = bake.rest_frames(arm_obj)
    tails = np.stack([np.array(bones[n].tail_local) for n in JOINT_NAMES])
    bv = bm.to_motion(tails - rest_heads)
    bv[0] = 0.0
    pos, rot = rt.spec_pose_from_channels(quats, loc, rest_rot, rest_heads, bv)
    return frames, pos, rot, bv, mat(arm_obj.matrix_world)


def _import_error(path, exc):
    """The importer's error as one line naming the file."""
    return RetargetError("{:s}: {:s}".format(path, compat.operator_error_text(exc)))


def load_rig_file(path, context=None):
    """Import the armature of a .blend, .glb/.gltf or .fbx file into the scene;
    returns the armature object (the one with the most bones). glTF files that
    need ``EXT_meshopt_compression`` are decoded first (Blender's importer cannot)."""
    from ...dancing_points_addon.formats import gltf_meshopt

    context = context or bpy.context
    path = os.path.abspath(bpy.path.abspath(path))
    if not os.path.isfile(path):
        raise RetargetError("no such file: {:s}".format(path))
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".blend", ".glb", ".gltf", ".fbx"):
        raise RetargetError("unsupported rig file type '{:s}' (.blend, .glb, .gltf, .fbx)".format(ext))
    before = {kind: set(getattr(bpy.data, kind)) for kind in _IMPORTED}
    try:
        arms = _import_rig_file(path, ext, context, gltf_meshopt)
        if not arms:
            raise RetargetError("{:s} has no armature".format(path))
    except BaseException:  # nothing of the file is left in the scene
        new = [x for kind in _IMPORTED for x in getattr(bpy.data, kind) if x not in before[kind]]
        if new:
            bpy.data.batch_remove(new)
        raise
    return max(arms, key=lambda o: len(o.data.bones))


# what importing a rig file may add to the blend data
_IMPORTED = ("objects", "collections", "meshes", "armatures", "materials", "images", "textures", "actions",
             "node_groups", "cameras", "lights")


def _import_rig_file(path, ext, context, gltf_meshopt):
    """Import ``path`` (a supported ``ext``); the armatures it added."""
    before = set(bpy.data.objects)
    if ext == ".blend":
        try:
            with bpy.data.libraries.load(path, link=False) as (src, dst):
                dst.objects = list(src.objects)
        except (OSError, RuntimeError) as exc:
            raise _import_error(path, exc) from None
        coll = bpy.data.collections.new(os.path.splitext(os.path.basename(path))[0])
        context.scene.collection.children.link(coll)
        # bone shapes (a Rigify rig's WGT- widgets) come along but are not put in the scene
        shapes = {pb.custom_shape for o in dst.objects if o is not None and o.type == 'ARMATURE'
                  for pb in o.pose.bones if pb.custom_shape is not None}
        for o in dst.objects:
            if o is not None and o not in shapes:
                coll.objects.link(o)
    elif ext in (".glb", ".gltf"):
        src = path
        tmpdir = None
        try:
            try:
                if ext == ".glb" and gltf_meshopt.needs_decompression(path):
                    tmpdir = tempfile.mkdtemp(prefix="dp_glb_")
                    src = gltf_meshopt.decompress_glb(path, os.path.join(tmpdir, os.path.basename(path)))
            except (ValueError, IndexError, KeyError, OSError) as exc:
                raise RetargetError("{:s}: cannot decode its compressed meshes ({:s}); is the file "
                                    "complete?".format(path, str(exc) or type(exc).__name__)) from None
            bpy.ops.import_scene.gltf(filepath=src)
        except RuntimeError as exc:
            raise _import_error(path, exc) from None
        finally:
            if tmpdir is not None:
                shutil.rmtree(tmpdir, ignore_errors=True)
    elif ext == ".fbx":
        try:
            bpy.ops.import_scene.fbx(filepath=path)
        except RuntimeError as exc:
            raise _import_error(path, exc) from None
    return [o for o in bpy.data.objects if o not in before and o.type == 'ARMATURE']
