# SPDX-License-Identifier: GPL-3.0-or-later
"""The method made visible: what the networks see and predict, drawn
in the scene beside a baked duet.

:func:`build_method_view` adds to the duet collection a child collection
"DP Method <take>" with objects that render in Workbench (and any engine):

- **predicted trajectories** ("DP Predictions"): a curve object (bevelled
  poly splines) with six splines, the mapping network's 1 s predicted future
  of both dancers' three tracked points at the current frame (the paper's
  figure; hers placed on the placement network's predicted roots, what her
  placement steers to), leader cyan, follower orange (bright: they read in a 960 x 540 render). The predictions of every
  frame are stored on the object as an ID property float array (saved in the
  .blend); a persistent ``frame_change_pre`` handler writes the current
  frame's into the spline points;
- **input markers** ("DP Input Head", ...): small spheres on the take's three
  empties (Copy Location constraints), the leader's three input points;
- **foot contacts** ("DP Contacts"): one mesh of eight flat discs (four foot
  points per dancer) 2 mm above the floor (the scene's "DP Stage" floor when
  there is one, else the lowest foot point of both dancers over the take);
  the same handler moves each disc under its foot
  and gives it its radius while the foot lock holds that point (the
  synthesis's lock states, ``Duet.planted``; a duet without them, e.g.
  synthesised without foot locking: contact probability ≥ 0.5), zero
  otherwise. One object, fixed topology: any length of take.

The source body of a take imported from BVH/FBX/AMC with "Keep Source Body"
(``take_ghost``, objects flagged ``["dp_ghost"]``) is shown or hidden with the
same settings (``Scene.dancing_points_method``: show_inputs,
show_predictions, show_contacts, show_ghost, method_in_render). With
``method_in_render`` off (the default) every such object has
``hide_render`` set: the final render shows only the dancers.
"""

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, PointerProperty

from ..dancing_points_addon import blender_math as bm
from ..dancing_points_addon.errors import UserError
from ..dancing_points_addon.features import FUTURE
from ..dancing_points_addon.skeleton import FEET
from .bake import Created, material
from .props import DEVICE_OBJECT_NAMES, DEVICES, GHOST_PROP, device_objects

METHOD_PROP = "dp_method"  # on a method object: "predictions", "inputs" or "contacts"
PRED_PROP = "dp_predictions"  # float32 (T, 2 dancers, 3 points, FUTURE, 3), Blender space
CONTACT_PROP = "dp_contact_marks"  # float32 (T, 8 discs, 4): centre (Blender space), in contact 0/1
FRAME_START_PROP = "dp_frame_start"
FRAME_STEP_PROP = "dp_frame_step"  # scene frames per 30 Hz sample (as the take's keys)
N_FRAMES_PROP = "dp_n_frames"
KINDS = ("predictions", "inputs", "contacts")

N_TRACKS = 6  # 2 dancers × 3 points
N_DISCS = 8  # 2 dancers × 4 foot points (SPEC §2 order)
DISC_SEGMENTS = 16
DISC_RADIUS = 0.045  # m
FLOOR_LIFT = 0.002  # m above the duet's floor
TUBE_RADIUS = 0.014  # m, the trajectories' bevel (reads at 960 x 540)
MARKER_RADIUS = 0.03  # m

LEADER = (0.10, 0.28, 0.85)
FOLLOWER = (0.85, 0.12, 0.08)


def _lighter(c, f=0.5):
    return tuple(x + (1.0 - x) * f for x in c) + (1.0,)


COLOURS = {"pred_leader": (0.0, 0.65, 1.0, 1.0), "pred_follower": (1.0, 0.35, 0.0, 1.0),  # cyan / orange
           "contact_leader": _lighter(LEADER, 0.25), "contact_follower": _lighter(FOLLOWER, 0.25),
           "input": (1.0, 0.95, 0.0, 1.0)}


# --------------------------------------------------------------------------- data (numpy)

def prediction_array(duet):
    """The duet's predictions as stored: float32 ``(T, 2, 3, FUTURE, 3)``, Blender space."""
    p = duet.predictions
    if p is None:
        raise UserError("the duet has no recorded predictions (synthesise with record_predictions=True)")
    p = np.asarray(p)
    if p.ndim != 5 or p.shape[1:] != (2, FUTURE, 3, 3) or len(p) != duet.n_frames:
        raise UserError("the duet's predictions have shape {!r}, expected ({:d}, 2, {:d}, 3, 3)".format(
            p.shape, duet.n_frames, FUTURE))
    return bm.to_blender(p.transpose(0, 1, 3, 2, 4)).astype(np.float32)


def floor_height(duet):
    """The duet's floor (motion-space height): the lowest foot point of both dancers."""
    return float(min(duet.leader_positions[:, FEET, 1].min(), duet.follower_positions[:, FEET, 1].min()))


def contact_array(duet, floor=None):
    """Per frame the eight discs (leader's four foot points, then the follower's):
    float32 ``(T, 8, 4)``: centre (Blender space, 2 mm above ``floor``, default
    :func:`floor_height`), 1 where the foot lock holds the point (``duet.planted``;
    without it, where the contact probability is at least 0.5) else 0."""
    floor = (floor_height(duet) if floor is None else float(floor)) + FLOOR_LIFT
    T = duet.n_frames
    out = np.empty((T, N_DISCS, 4), dtype=np.float32)
    planted = duet.planted
    for d, role in enumerate(("leader", "follower")):
        feet = np.array(getattr(duet, role + "_positions")[:, FEET], dtype=np.float64)
        feet[..., 1] = floor
        out[:, 4 * d:4 * d + 4, :3] = bm.to_blender(feet)
        out[:, 4 * d:4 * d + 4, 3] = (planted[:, d] if planted is not None
                                      else np.asarray(getattr(duet, role + "_contacts")) >= 0.5)
    return out


_RING = np.stack([np.cos(np.linspace(0, 2 * np.pi, DISC_SEGMENTS, endpoint=False)),
                  np.sin(np.linspace(0, 2 * np.pi, DISC_SEGMENTS, endpoint=False)),
                  np.zeros(DISC_SEGMENTS)], axis=1)


def disc_vertices(marks):
    """Vertices ``(8 · DISC_SEGMENTS, 3)`` of the discs of one frame's ``marks (8, 4)``:
    a disc of radius 0 (no area) where the foot is not in contact."""
    marks = np.asarray(marks, dtype=np.float64).reshape(N_DISCS, 4)
    r = DISC_RADIUS * (marks[:, 3] >= 0.5)
    return (marks[:, None, :3] + _RING[None] * r[:, None, None]).reshape(-1, 3)


# --------------------------------------------------------------------------- the frame handler

def _frame_index(obj, frame):
    """The sample shown at scene ``frame`` (the nearest), or None outside the take."""
    step = float(obj.get(FRAME_STEP_PROP, 1.0)) or 1.0
    t = int(round((float(frame) - float(obj.get(FRAME_START_PROP, 1))) / step))
    n = int(obj.get(N_FRAMES_PROP, 0))
    return t if 0 <= t < n else None


def _stored_frame(obj, prop, t, size):
    data = obj.get(prop)
    if data is None or t is None or len(data) < (t + 1) * size:
        return None
    return np.array(data[t * size:(t + 1) * size], dtype=np.float64)


def update_predictions(obj, frame):
    """Write frame ``frame``'s predictions into the curve's splines (outside the
    take: every point at the first one, nothing to see)."""
    size = N_TRACKS * FUTURE * 3
    vals = _stored_frame(obj, PRED_PROP, _frame_index(obj, frame), size)
    splines = obj.data.splines
    if len(splines) != N_TRACKS:
        return False
    co = np.ones((N_TRACKS, FUTURE, 4))
    if vals is None:
        co[..., :3] = 0.0
    else:
        co[..., :3] = vals.reshape(N_TRACKS, FUTURE, 3)
    for k, sp in enumerate(splines):
        if len(sp.points) != FUTURE:
            return False
        sp.points.foreach_set("co", co[k].ravel())
    obj.data.update_tag()
    return True


def update_contacts(obj, frame):
    """Discs under the feet in contact at ``frame`` (all of radius 0 outside the take)."""
    marks = _stored_frame(obj, CONTACT_PROP, _frame_index(obj, frame), N_DISCS * 4)
    me = obj.data
    if len(me.vertices) != N_DISCS * DISC_SEGMENTS:
        return False
    if marks is None:
        verts = np.zeros((N_DISCS * DISC_SEGMENTS, 3))
    else:
        verts = disc_vertices(marks)
    me.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    me.update()
    return True


_UPDATERS = {"predictions": update_predictions, "contacts": update_contacts}


def update_scene(scene, frame=None):
    """Bring every method object of ``scene`` to ``frame`` (default: the current
    one). Objects removed, renamed or with damaged data are skipped."""
    frame = scene.frame_current if frame is None else frame
    n = 0
    for obj in scene.objects:
        fn = _UPDATERS.get(obj.get(METHOD_PROP))
        if fn is None:
            continue
        try:
            n += bool(fn(obj, frame))
        except (AttributeError, ReferenceError, TypeError, ValueError, KeyError):
            continue
    return n


@persistent
def _on_frame_change(scene, depsgraph=None):
    try:
        update_scene(scene)
    except (AttributeError, ReferenceError):  # a scene being freed: nothing to do
        pass


@persistent
def _on_load(*_args):
    for scene in bpy.data.scenes:
        try:
            update_scene(scene)
        except (AttributeError, ReferenceError):
            pass


# --------------------------------------------------------------------------- visibility

def _settings(scene):
    return getattr(scene, "dancing_points_method", None)


def object_kind(obj):
    """"predictions", "inputs", "contacts", "ghost" or None."""
    if obj.get(GHOST_PROP):
        return "ghost"
    kind = obj.get(METHOD_PROP)
    return kind if kind in KINDS else None


def apply_visibility(scene):
    """Show/hide the method objects and ghosts of ``scene`` after its settings;
    ``hide_render`` unless ``method_in_render``. Returns the number of objects set."""
    s = _settings(scene)
    show = {"inputs": True, "predictions": True, "contacts": True, "ghost": True}
    in_render = False
    if s is not None:
        show = {"inputs": s.show_inputs, "predictions": s.show_predictions, "contacts": s.show_contacts,
                "ghost": s.show_ghost}
        in_render = s.method_in_render
    n = 0
    for obj in scene.objects:
        kind = object_kind(obj)
        if kind is None:
            continue
        on = bool(show[kind])
        if obj.hide_viewport != (not on):
            obj.hide_viewport = not on
        if obj.hide_render != (not (on and in_render)):
            obj.hide_render = not (on and in_render)
        n += 1
    return n


def _on_setting(self, context):
    scene = getattr(context, "scene", None)
    if scene is not None:
        apply_visibility(scene)


class DP_MethodSettings(bpy.types.PropertyGroup):
    """What of the method is shown (``Scene.dancing_points_method``)."""

    show_inputs: BoolProperty(name="Input Points", default=True, update=_on_setting,
                              description="Markers on the leader's three input points (the take's empties)")
    show_predictions: BoolProperty(name="Predicted Trajectories", default=True, update=_on_setting,
                                   description="The mapping network's predicted next second of both "
                                               "dancers' head and wrists at the current frame")
    show_contacts: BoolProperty(name="Foot Contacts", default=True, update=_on_setting,
                                description="Marks on the floor under the foot points the foot lock holds")
    show_ghost: BoolProperty(name="Source Body", default=True, update=_on_setting,
                             description="The full-body source of a take imported from BVH, FBX or AMC "
                                         "(when kept at import), as a translucent ghost")
    method_in_render: BoolProperty(name="Show in Renders", default=False, update=_on_setting,
                                   description="Render the method objects too (off: only in the viewport)")


# --------------------------------------------------------------------------- building

def _tag(obj, kind, frame_start, n_frames, frame_step):
    obj[METHOD_PROP] = kind
    obj[FRAME_START_PROP] = float(frame_start)
    obj[FRAME_STEP_PROP] = float(frame_step)
    obj[N_FRAMES_PROP] = int(n_frames)


def _build_predictions(coll, short, data, frame_start, frame_step, made):
    cu = made.add(bpy.data.curves.new("DP Predictions " + short, 'CURVE'))
    cu.dimensions = '3D'
    cu.bevel_depth = TUBE_RADIUS
    cu.bevel_resolution = 1
    cu.use_fill_caps = False
    cu.materials.append(material("DP Predicted Leader", COLOURS["pred_leader"], made))
    cu.materials.append(material("DP Predicted Follower", COLOURS["pred_follower"], made))
    for k in range(N_TRACKS):
        sp = cu.splines.new('POLY')
        sp.points.add(FUTURE - 1)
        sp.material_index = k // 3
    obj = made.add(bpy.data.objects.new("DP Predictions " + short, cu))
    coll.objects.link(obj)
    obj.show_in_front = True  # the viewport shows the head's path inside the head
    _tag(obj, "predictions", frame_start, len(data), frame_step)
    obj[PRED_PROP] = np.ascontiguousarray(data, dtype=np.float32).ravel()
    return obj


def _build_contacts(coll, short, marks, frame_start, frame_step, made):
    me = made.add(bpy.data.meshes.new("DP Contacts " + short))
    faces = np.arange(N_DISCS * DISC_SEGMENTS).reshape(N_DISCS, DISC_SEGMENTS)
    me.from_pydata(np.zeros((N_DISCS * DISC_SEGMENTS, 3)).tolist(), [], faces.tolist())
    me.materials.append(material("DP Contact Leader", COLOURS["contact_leader"], made))
    me.materials.append(material("DP Contact Follower", COLOURS["contact_follower"], made))
    me.polygons.foreach_set("material_index", (np.arange(N_DISCS) // 4).astype(np.int32))
    me.update()
    obj = made.add(bpy.data.objects.new("DP Contacts " + short, me))
    coll.objects.link(obj)
    _tag(obj, "contacts", frame_start, len(marks), frame_step)
    obj[CONTACT_PROP] = np.ascontiguousarray(marks, dtype=np.float32).ravel()
    return obj


def _sphere_mesh(name, made):
    import bmesh

    me = made.add(bpy.data.meshes.new(name))
    b = bmesh.new()
    try:
        bmesh.ops.create_icosphere(b, subdivisions=2, radius=MARKER_RADIUS)
        b.to_mesh(me)
    finally:
        b.free()
    try:
        me.shade_smooth()
    except AttributeError:
        me.polygons.foreach_set("use_smooth", np.ones(len(me.polygons), dtype=bool))
    return me


def _build_markers(coll, short, take_coll, frame_start, frame_step, n_frames, made):
    objs = device_objects(take_coll) if take_coll is not None else {}
    if not objs:
        return []
    me = _sphere_mesh("DP Input Marker " + short, made)
    me.materials.append(material("DP Input", COLOURS["input"], made))
    out = []
    for dev in DEVICES:
        empty = objs.get(dev)
        if empty is None:
            continue
        obj = made.add(bpy.data.objects.new("DP Input {:s} {:s}".format(DEVICE_OBJECT_NAMES[dev], short), me))
        coll.objects.link(obj)
        obj.show_in_front = True
        con = obj.constraints.new('COPY_LOCATION')
        con.target = empty
        _tag(obj, "inputs", frame_start, n_frames, frame_step)
        obj["dp_marks"] = dev  # the device it marks (never DEVICE_PROP: it is no take empty)
        out.append(obj)
    return out


def method_collection(duet_coll):
    """The duet's "DP Method" child collection, or None."""
    for c in duet_coll.children:
        if c.get(METHOD_PROP) == "collection":
            return c
    return None


def stage_floor(scene):
    """The floor height (Blender Z) of the scene's "DP Stage" (``operators.stage``), or None."""
    for coll in scene.collection.children_recursive:
        if coll.get("dp_stage") == "stage" and coll.get("dp_floor_z") is not None:
            return float(coll["dp_floor_z"])
    return None


def build_method_view(context, duet_coll, duet, take_coll=None, frame_start=1, frame_step=None):
    """Add the method objects of ``duet`` (a :class:`~.duet.Duet` with
    predictions) to ``duet_coll``; ``take_coll``: the take whose empties carry the
    input markers; sample ``k`` shows on scene frame ``frame_start + k ·
    frame_step`` (default: the take's step, else 1). Returns the new collection
    "DP Method <take>". On failure nothing is left behind."""
    if frame_step is None:
        frame_step = float(getattr(getattr(take_coll, "dancing_points", None), "frame_step", 1.0) or 1.0)
    preds = prediction_array(duet)
    marks = contact_array(duet, stage_floor(context.scene))
    made = Created()
    name = duet_coll.name
    short = name[len("DP Duet "):] if name.startswith("DP Duet ") else name
    try:
        coll = made.add(bpy.data.collections.new("DP Method " + short))
        duet_coll.children.link(coll)
        coll[METHOD_PROP] = "collection"
        _build_predictions(coll, short, preds, frame_start, frame_step, made)
        _build_contacts(coll, short, marks, frame_start, frame_step, made)
        _build_markers(coll, short, take_coll, frame_start, frame_step, duet.n_frames, made)
        apply_visibility(context.scene)
        update_scene(context.scene)
        return coll
    except Exception:
        made.remove_all()
        raise


def remove_method_view(coll):
    """Remove a "DP Method" collection with its objects, their data and materials."""
    ids = {coll}
    for obj in coll.all_objects:
        ids.add(obj)
        if obj.data is not None:
            ids.add(obj.data)
            ids.update(m for m in getattr(obj.data, "materials", ()) if m is not None)
    bpy.data.batch_remove(list(ids))


# --------------------------------------------------------------------------- registration

def _remove_handlers():
    for handlers, fn in ((bpy.app.handlers.frame_change_pre, _on_frame_change),
                         (bpy.app.handlers.load_post, _on_load)):
        for h in list(handlers):
            if h is fn or (getattr(h, "__name__", None) == fn.__name__
                           and getattr(h, "__module__", None) == fn.__module__):
                handlers.remove(h)


classes = (DP_MethodSettings,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.dancing_points_method = PointerProperty(type=DP_MethodSettings)
    _remove_handlers()
    bpy.app.handlers.frame_change_pre.append(_on_frame_change)
    bpy.app.handlers.load_post.append(_on_load)


def unregister():
    _remove_handlers()
    del bpy.types.Scene.dancing_points_method
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
