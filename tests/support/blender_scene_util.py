"""Scene helpers for the add-on tests (``test_blender_addon.py``); not part of the add-on."""
from __future__ import annotations

import numpy as np

import bpy

from .ext_util import MODULE, enable_extension, import_from_extension

ID_COLLECTIONS = ("objects", "meshes", "armatures", "actions", "materials", "collections", "cameras",
                  "lights", "images")


def fresh_scene():
    """An empty scene, the extension still enabled (``read_homefile`` keeps the
    preferences; ``read_factory_settings`` would disable the add-on)."""
    enable_extension()
    bpy.ops.wm.read_homefile(use_empty=True)
    if MODULE not in bpy.context.preferences.addons:
        enable_extension()
    assert hasattr(bpy.ops.dancing_points, "import_take")
    return bpy.context.scene


def id_snapshot():
    """Names of every data-block of the kinds the add-on creates."""
    return {c: sorted(x.name for x in getattr(bpy.data, c)) for c in ID_COLLECTIONS}


def scene_state(scene=None):
    scene = scene or bpy.context.scene
    r = scene.render
    return (id_snapshot(), r.fps, r.fps_base, scene.frame_start, scene.frame_end, scene.frame_current,
            scene.camera.name if scene.camera else None)


def compat():
    return import_from_extension("operators.compat")


def props():
    return import_from_extension("operators.props")


def fcurve_keys(obj, data_path, index):
    """``(frames, values)`` of one F-Curve of ``obj``'s assigned action/slot."""
    c = compat()
    action, slot = c.assigned_action(obj)
    fc = c.find_fcurve(action, slot, data_path, index)
    assert fc is not None, (obj.name, data_path, index)
    f, v, _ = c.read_keys(fc)
    return f, v


def all_fcurves(obj):
    c = compat()
    action, slot = c.assigned_action(obj)
    return list(c.fcurves_of(action, slot))


def take_device_keys(coll):
    """``{device: (frames, loc (T, 3), quat (T, 4), tracked (T,))}`` of a take collection."""
    out = {}
    for dev, obj in props().device_objects(coll).items():
        frames, _ = fcurve_keys(obj, "location", 0)
        loc = np.stack([fcurve_keys(obj, "location", i)[1] for i in range(3)], axis=1)
        quat = np.stack([fcurve_keys(obj, "rotation_quaternion", i)[1] for i in range(4)], axis=1)
        tracked = fcurve_keys(obj, '["dp_tracked"]', 0)[1]
        out[dev] = (frames, loc, quat, tracked)
    return out


def posed_heads_tails(arm_obj, frames, names):
    """Evaluated bone heads and tails ``(F, B, 3)`` (world space) at ``frames``."""
    scene = bpy.context.scene
    heads = np.empty((len(frames), len(names), 3))
    tails = np.empty_like(heads)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for i, f in enumerate(frames):
        scene.frame_set(int(f))
        ev = arm_obj.evaluated_get(depsgraph)
        mw = np.array(ev.matrix_world)
        pb = ev.pose.bones
        for j, n in enumerate(names):
            heads[i, j] = (mw @ np.array([*pb[n].head, 1.0]))[:3]
            tails[i, j] = (mw @ np.array([*pb[n].tail, 1.0]))[:3]
    return heads, tails


def mesh_rest_and_weights(mesh_obj, bone_names):
    """Rest vertices ``(V, 3)`` (object space) and dense weights ``(V, B)`` read
    back from the vertex groups."""
    me = mesh_obj.data
    V = len(me.vertices)
    co = np.empty(3 * V, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    gi = {g.index: bone_names.index(g.name) for g in mesh_obj.vertex_groups if g.name in bone_names}
    w = np.zeros((V, len(bone_names)))
    for v in me.vertices:
        for g in v.groups:
            if g.group in gi:
                w[v.index, gi[g.group]] += g.weight
    return co.reshape(V, 3).astype(np.float64), w


def evaluated_vertices(mesh_obj, frame):
    """World-space vertices of the deformed mesh at ``frame``."""
    scene = bpy.context.scene
    scene.frame_set(int(frame))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    ev = mesh_obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        co = np.empty(3 * len(me.vertices), dtype=np.float32)
        me.vertices.foreach_get("co", co)
        mw = np.array(ev.matrix_world)
    finally:
        ev.to_mesh_clear()
    co = co.reshape(-1, 3).astype(np.float64)
    return co @ mw[:3, :3].T + mw[:3, 3]


def load_png(path):
    """``(H, W, 4)`` float pixels of an image file (bottom row first)."""
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = img.size
        px = np.empty(w * h * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    return px.reshape(h, w, 4)


class RecordingLayout:
    """A stand-in for ``UILayout`` in background mode: records every call and
    returns itself, so a panel's ``draw`` can run and be checked."""

    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        def f(*a, **k):
            self.calls.append((name, a, k))
            return self
        return f


def build_armature(name, bones, modes=('QUATERNION',), location=(0.0, 0.0, 0.0), rotation_z=0.0, body=True,
                   connect=lambda bone: True, box=0.03, no_box=()):
    """An armature object from ``bones`` = ``(name, parent, head, tail, roll)`` (metres,
    armature space), pose bones in the rotation ``modes`` in turn, the object at
    ``location`` turned by ``rotation_z``; with ``body``, a skinned box around every
    bone (rigid weights; ``box``: its half width; none for the bones in ``no_box``)
    parented to it. A bone starting at its parent's tail is connected unless
    ``connect(name)`` says no."""
    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode='EDIT')
    for bname, parent, h, t, roll in bones:
        eb = arm.edit_bones.new(bname)
        eb.head, eb.tail, eb.roll = h, t, roll
        if parent:
            eb.parent = arm.edit_bones[parent]
            eb.use_connect = bool(np.allclose(arm.edit_bones[parent].tail, h)) and connect(bname)
    bpy.ops.object.mode_set(mode='OBJECT')
    for i, pb in enumerate(obj.pose.bones):
        pb.rotation_mode = modes[i % len(modes)]
    obj.location = location
    obj.rotation_euler = (0.0, 0.0, rotation_z)
    if body:
        verts, faces, groups = [], [], []
        for bname, _, h, t, _ in bones:
            if bname in no_box:
                continue
            h, t = np.array(h, dtype=float), np.array(t, dtype=float)
            base = len(verts)
            for a in (h, t):
                for dx in (-box, box):
                    for dy in (-box, box):
                        verts.append(tuple(a + (dx, dy, 0.0)))
            faces += [tuple(base + i for i in f) for f in ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6),
                                                            (0, 2, 6, 4), (1, 5, 7, 3))]
            groups.append((bname, list(range(base, base + 8))))
        me = bpy.data.meshes.new(name + " Body")
        me.from_pydata(verts, [], faces)
        mesh = bpy.data.objects.new(name + " Body", me)
        bpy.context.scene.collection.objects.link(mesh)
        mesh.parent = obj
        for bname, idx in groups:
            mesh.vertex_groups.new(name=bname).add(idx, 1.0, 'REPLACE')
        mesh.modifiers.new("Armature", 'ARMATURE').object = obj
    return obj


def enable_rigify():
    """Enable Blender's bundled Rigify add-on (``rigify``, or its extension module);
    returns the module name, or None when it is not available."""
    import addon_utils

    for mod in ("rigify", "bl_ext.blender_org.rigify"):
        if any(m.__name__ == mod for m in addon_utils.modules()):
            if mod not in bpy.context.preferences.addons:
                bpy.ops.preferences.addon_enable(module=mod)
            return mod
    return None


def pose_channels(obj):
    """Every pose bone's channels (location, rotations, scale) as one array."""
    return np.array([list(pb.location) + list(pb.rotation_quaternion) + list(pb.rotation_euler)
                     + list(pb.rotation_axis_angle) + list(pb.scale) for pb in obj.pose.bones])
