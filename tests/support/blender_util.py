"""Small bpy helpers for the Blender cross-check tests (not part of the add-on)."""
from __future__ import annotations

import re

import bpy
import numpy as np
from mathutils import Euler, Matrix


def empty_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def asf_rest_starts(skel) -> np.ndarray:
    """Rest start of every ASF bone (skeleton order), summed independently of the core FK."""
    starts = np.zeros((len(skel.bones), 3))
    for j, bone in enumerate(skel.bones):
        p = skel.parents[j]
        if p < 0:
            starts[j] = skel.root_position
        else:
            pb = skel.bones[p]
            starts[j] = starts[p] + pb.direction * pb.length
    return starts


def build_asf_armature(skel, name="asf", root_tail=(0.0, 0.1, 0.0), roll=0.0):
    """An armature with one bone per ASF bone, in motion-space coordinates (the
    object at identity). Bone head = rest start, tail = start + bone vector;
    the zero-length root points along ``root_tail``. Children of non-root bones
    are connected (their head is the parent's tail)."""
    scene = bpy.context.scene
    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    bpy.ops.object.mode_set(mode="EDIT")
    starts = asf_rest_starts(skel)
    ebs = []
    for j, bone in enumerate(skel.bones):
        eb = arm.edit_bones.new(bone.name)
        eb.head = starts[j]
        if bone.length > 0:
            eb.tail = starts[j] + bone.direction * bone.length
        else:
            eb.tail = starts[j] + np.asarray(root_tail)
        eb.roll = roll * (j % 3 - 1)  # a few different rolls: the result must not depend on them
        p = skel.parents[j]
        if p >= 0:
            eb.parent = ebs[p]
            eb.use_connect = bool(skel.parents[p] >= 0)
        ebs.append(eb)
    bpy.ops.object.mode_set(mode="OBJECT")
    return obj


def asf_axes(asf_path) -> dict:
    """``{bone: C}``: each ASF ``axis a b c ORDER`` (and the root ``axis`` /
    ``orientation``) read straight from the file, as mathutils matrices (Euler:
    the first listed axis is applied first). Degrees assumed (CMU files)."""
    text = open(asf_path).read()
    out = {}
    root = re.search(r":root(.*?):bonedata", text, re.S).group(1)
    order = re.search(r"axis\s+(\w+)", root).group(1)
    ang = [float(v) for v in re.search(r"orientation\s+(\S+)\s+(\S+)\s+(\S+)", root).groups()]
    out["root"] = Euler([np.radians(a) for a in ang], order.upper()).to_matrix()
    for block in re.findall(r"\bbegin\b(.*?)\bend\b", text.split(":bonedata", 1)[1].split(":hierarchy")[0], re.S):
        name = re.search(r"name\s+(\S+)", block).group(1)
        m = re.search(r"axis\s+(\S+)\s+(\S+)\s+(\S+)\s+(\w+)", block)
        out[name] = Euler([np.radians(float(v)) for v in m.groups()[:3]], m.group(4).upper()).to_matrix()
    return out


def asf_local_matrix(c: Matrix, dofs, values) -> Matrix:
    """ASF local rotation ``C · E · C⁻¹`` of one bone for one frame (degrees), with
    mathutils; ``E`` composes the ``dof`` rotations, the first listed applied first."""
    e = Matrix.Identity(3)
    for d, v in zip(dofs, values):
        if d[0] == "r":
            e = Matrix.Rotation(np.radians(float(v)), 3, d[1].upper()) @ e
    return c @ e @ c.transposed()


def pose_points(obj, bone_names):
    """Armature-space heads and tails ``(J, 3)`` of the pose bones, current frame."""
    pb = obj.pose.bones
    heads = np.array([tuple(pb[n].head) for n in bone_names])
    tails = np.array([tuple(pb[n].tail) for n in bone_names])
    return heads, tails
