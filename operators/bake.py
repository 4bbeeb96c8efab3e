# SPDX-License-Identifier: GPL-3.0-or-later
"""Bake a synthesised duet (``duet.Duet``, SPEC §4) into the scene.

Per dancer: an armature ("DP Leader" / "DP Follower") with the 31 SPEC §2 bones
(bone ``n`` from its parent's joint to its own joint, so its tail is the SPEC
joint position; the root bone points up from the root joint), one NEW action
with a keyframe per 30 Hz frame written in bulk (quaternion rotation on every
bone, location on the root only), and a default body mesh skinned to it (vertex
groups named after the bones, Armature modifier). All the maths is in
``dancing_points_addon.blender_math``; this module only creates the data-blocks.

Every bake is a new version: a new collection "DP Duet <take>" with new
armatures and actions ("DP Leader <take> v2", ...); earlier duets of the same
take are hidden, never modified.
"""

import contextlib

import bpy
import numpy as np

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon import skinning
from ..dancing_points_addon.skeleton import JOINT_NAMES, PARENTS
from . import compat, stage
from .kinds import KIND_DUET, is_duet, is_take
from .props import ROLE_PROP

ROLES = ("leader", "follower")
ROLE_LABEL = {"leader": "Leader", "follower": "Follower"}
# Linear RGB: leader blue-ish, follower red-ish.
ROLE_COLOUR = {"leader": (0.10, 0.28, 0.85, 1.0), "follower": (0.85, 0.12, 0.08, 1.0)}


def make_body(bone_vectors):
    """The default body of a skeleton (the core's ``skinning.make_body``):
    ``(vertices (motion space), faces, indices, weights)``."""
    return bm.body_arrays(skinning.make_body(bone_vectors))


def alive(blocks):
    """Those of ``blocks`` (data-blocks) not yet freed."""
    out = []
    for x in blocks:
        try:
            x.name  # raises ReferenceError when already freed
            out.append(x)
        except ReferenceError:
            pass
    return out


class Created:
    """What a bake changes, so that a failed bake leaves the scene as it was:
    the data-blocks it made (removed again), the changes it made to what was
    there (``on_failure``: undone, last first) and the data-blocks it replaced
    (``retire``: removed only when the bake succeeds, :meth:`finish`)."""

    def __init__(self):
        self.ids = []
        self._undo = []
        self._retired = []

    def add(self, id_block):
        self.ids.append(id_block)
        return id_block

    def on_failure(self, fn):
        """Call ``fn()`` if the bake fails (before the new data-blocks go)."""
        self._undo.append(fn)

    def retire(self, id_block, if_unused=True):
        """``id_block`` was replaced: removed by :meth:`finish` (``if_unused``:
        only if nothing uses it then)."""
        self._retired.append((id_block, if_unused))

    def finish(self):
        """The bake succeeded: remove the replaced data-blocks."""
        unused = [x for x, if_unused in self._retired if alive([x]) and (not if_unused or x.users == 0)]
        if unused:
            bpy.data.batch_remove(unused)
        self.ids, self._undo, self._retired = [], [], []

    def remove_all(self):
        """The bake failed: undo its changes, then remove what it made."""
        for fn in reversed(self._undo):
            with contextlib.suppress(ReferenceError):
                fn()
        made = alive(self.ids)
        if made:
            bpy.data.batch_remove(made)
        self.ids, self._undo, self._retired = [], [], []


@contextlib.contextmanager
def user_mode_kept(context):
    """Around work that needs object mode: the active object back in the mode
    (edit, pose, sculpt, ...) it was in before, when it still exists."""
    view_layer = context.view_layer
    obj = view_layer.objects.active if view_layer is not None else None
    mode = obj.mode if obj is not None else 'OBJECT'
    try:
        yield
    finally:
        if obj is not None and mode != 'OBJECT':
            with contextlib.suppress(ReferenceError, RuntimeError):
                if view_layer.objects.active != obj:
                    view_layer.objects.active = obj
                if obj.mode != mode:
                    bpy.ops.object.mode_set(mode=mode)


def ensure_object_mode(context):
    """Leave edit/pose mode of the active object (operators that add or key objects need object mode)."""
    obj = context.view_layer.objects.active if context.view_layer else None
    if obj is not None and obj.mode != 'OBJECT':
        bpy.ops.object.mode_set(mode='OBJECT')


def build_armature(context, name, bone_vectors, collection, created):
    """An armature object in the SPEC rest pose of ``bone_vectors`` (at the origin)."""
    arm = created.add(bpy.data.armatures.new(name))
    obj = created.add(bpy.data.objects.new(name, arm))
    collection.objects.link(obj)
    heads, tails = bm.armature_rest(bone_vectors)
    view_layer = context.view_layer
    prev_active = view_layer.objects.active
    ensure_object_mode(context)
    view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode='EDIT')
    try:
        ebs = []
        for n, bname in enumerate(JOINT_NAMES):
            eb = arm.edit_bones.new(bname)
            eb.head = heads[n]
            eb.tail = tails[n]
            eb.roll = 0.0
            p = int(PARENTS[n])
            if p >= 0:
                eb.parent = ebs[p]
                # Connected where the bone starts at its parent's tail (not for the root's children).
                eb.use_connect = p > 0
            ebs.append(eb)
    finally:
        bpy.ops.object.mode_set(mode='OBJECT')
        view_layer.objects.active = prev_active
    arm.display_type = 'OCTAHEDRAL'
    obj.show_in_front = False
    for pb in obj.pose.bones:
        pb.rotation_mode = 'QUATERNION'
    return obj


def rest_frames(arm_obj):
    """``(rest rotations (31, 3, 3), rest heads (31, 3))`` of the armature's bones
    (``Bone.matrix_local``), in SPEC order."""
    bones = arm_obj.data.bones
    rot = np.empty((len(JOINT_NAMES), 3, 3))
    heads = np.empty((len(JOINT_NAMES), 3))
    for n, name in enumerate(JOINT_NAMES):
        m = np.array(bones[name].matrix_local)
        rot[n] = m[:3, :3]
        heads[n] = m[:3, 3]
    return rot, heads


def key_armature(arm_obj, action_name, positions, rotations, frame_start, frame_step=1.0):
    """A NEW action on ``arm_obj`` with one keyframe per sample (bulk writes),
    sample ``k`` on scene frame ``frame_start + k * frame_step``."""
    rest_rot, rest_heads = rest_frames(arm_obj)
    quats, loc = bm.pose_channels(positions, rotations, rest_rot, rest_heads)
    frames = frame_start + frame_step * np.arange(positions.shape[0], dtype=np.float64)
    action, slot = compat.new_action_for(arm_obj, action_name)
    for n, name in enumerate(JOINT_NAMES):
        path = 'pose.bones["{:s}"].'.format(name)
        for i in range(4):
            compat.write_keys(compat.ensure_fcurves(action, slot, path + "rotation_quaternion", i, name),
                              frames, quats[:, n, i])
        if n == 0:
            for i in range(3):
                compat.write_keys(compat.ensure_fcurves(action, slot, path + "location", i, name),
                                  frames, loc[:, i])
    return action


def material(name, colour, created):
    mat = created.add(bpy.data.materials.new(name))
    mat.diffuse_color = colour  # Workbench and the viewport's Material colour
    try:
        if mat.node_tree is None and hasattr(mat, "use_nodes"):
            mat.use_nodes = True
        nodes = mat.node_tree.nodes if mat.node_tree is not None else ()
        for node in nodes:
            if node.type == 'BSDF_PRINCIPLED':
                node.inputs["Base Color"].default_value = colour
                node.inputs["Roughness"].default_value = 0.6
    except (AttributeError, KeyError, TypeError):
        pass
    return mat


def build_body(name, arm_obj, bone_vectors, colour, collection, created):
    """The default body mesh, skinned to ``arm_obj`` (vertex groups + Armature modifier)."""
    verts, faces, idx, wts = make_body(bone_vectors)
    verts_b = bm.to_blender(verts)
    mesh = created.add(bpy.data.meshes.new(name))
    mesh.from_pydata(verts_b.tolist(), [], np.asarray(faces, dtype=np.int64).tolist())
    mesh.update()
    try:
        mesh.shade_smooth()
    except AttributeError:  # before 4.1
        mesh.polygons.foreach_set("use_smooth", np.ones(len(mesh.polygons), dtype=bool))
    mesh.materials.append(material(name, colour, created))
    obj = created.add(bpy.data.objects.new(name, mesh))
    collection.objects.link(obj)
    obj.parent = arm_obj
    groups = [obj.vertex_groups.new(name=b) for b in JOINT_NAMES]
    for b in range(len(JOINT_NAMES)):
        rows, cols = np.nonzero((idx == b) & (wts > 0))
        if not len(rows):
            continue
        w = wts[rows, cols]
        for value in np.unique(w):
            groups[b].add(rows[w == value].tolist(), float(value), 'ADD')
    mod = obj.modifiers.new("Armature", 'ARMATURE')
    mod.object = arm_obj
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    return obj


def _next_version(take_name):
    versions = [c.dancing_points.version for c in bpy.data.collections
                if is_duet(c) and c.dancing_points.take_name == take_name]
    return max(versions, default=0) + 1


def _hide_previous(take_name, keep, created):
    for c in bpy.data.collections:
        if c != keep and is_duet(c) and c.dancing_points.take_name == take_name:
            created.on_failure(lambda c=c, v=c.hide_viewport, r=c.hide_render: _set_hidden(c, v, r))
            c.hide_viewport = True
            c.hide_render = True


def _set_hidden(coll, viewport, render):
    coll.hide_viewport = viewport
    coll.hide_render = render


def frame_step_for(context, take_name):
    """Scene frames per 30 Hz sample: the take's (its empties' keys, in scene
    time), else the scene's frame rate / 30."""
    take = bpy.data.collections.get(take_name)
    if is_take(take) and take.dancing_points.frame_step > 0:
        return float(take.dancing_points.frame_step)
    return stage.scene_fps(context.scene) / 30.0


def bake_duet(context, duet, take_name, frame_start=1, frame_step=None):
    """Bake ``duet`` (motion space, SPEC §4) as a new duet collection; returns it.

    Sample ``k`` is keyed on scene frame ``frame_start + k * frame_step``
    (default: :func:`frame_step_for` the take), so the duet plays at its real
    speed at any scene frame rate. The stage (``stage.ensure_stage``: floor,
    DP Camera, light, world) is made or refitted and the scene's frame range
    set to the duet.

    The poses are first made rigid (``blender_math.consistent_pose``: constant
    bone vectors, each bone's end = its parent's end + R · rest vector), which
    leaves a pose the runtime already made consistent unchanged."""
    created = Created()
    scene = context.scene
    if frame_step is None:
        frame_step = frame_step_for(context, take_name)
    try:
        version = _next_version(take_name)
        short = take_name[len("DP Take "):] if take_name.startswith("DP Take ") else take_name
        coll = created.add(bpy.data.collections.new("DP Duet " + short))
        scene.collection.children.link(coll)
        coll.dancing_points.kind = KIND_DUET
        coll.dancing_points.take_name = take_name
        coll.dancing_points.version = version
        coll.dancing_points.role = getattr(duet, "tracked_role", "leader")  # whose points were tracked
        rigs = {}
        consistent = {}
        for role in ROLES:
            label = ROLE_LABEL[role]
            pos = getattr(duet, role + "_positions")
            rot = getattr(duet, role + "_rotations")
            bv, pos, rot = bm.consistent_pose(pos, rot)
            arm = build_armature(context, "DP " + label, bv, coll, created)
            action = key_armature(arm, "DP {:s} {:s} v{:d}".format(label, short, version), pos, rot, frame_start,
                                  frame_step)
            created.add(action)
            body = build_body("DP {:s} Body".format(label), arm, bv, ROLE_COLOUR[role], coll, created)
            arm[ROLE_PROP] = role
            body[ROLE_PROP] = role
            rigs[role] = (arm, body)
            consistent[role] = pos
        _hide_previous(take_name, coll, created)
        frames = frame_start + frame_step * np.arange(duet.n_frames, dtype=np.float64)
        stage.ensure_stage(context, consistent["leader"], consistent["follower"], frames, created)
    except BaseException:
        created.remove_all()
        raise
    created.finish()
    return coll, rigs
