# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-version shims (4.2 LTS -> 5.x) for actions and bulk keyframe I/O.

Actions: Blender 4.2/4.3 keep F-Curves directly on the action
(``action.fcurves``); 4.4 introduced slotted (layered) actions, where an ID is
animated by an action *and* a slot and the F-Curves live in the channelbag of
that slot in the action's first keyframe strip; 5.0 removed ``action.fcurves``.
:func:`new_action_for` / :func:`ensure_fcurves` hide the difference.

Keyframes are always written in bulk (``keyframe_points.add`` +
``foreach_set``), never with ``keyframe_insert`` in a loop.
"""

import bpy
import numpy as np

SLOTTED = bpy.app.version >= (4, 4, 0)


def _enum_value(struct, prop, item):
    return struct.bl_rna.properties[prop].enum_items[item].value


def new_action_for(id_block, name):
    """A NEW action named ``name`` (Blender suffixes it if taken) assigned to
    ``id_block``; returns ``(action, slot)`` (``slot`` is None before 4.4).
    The ID's previous action, if any, is left untouched in ``bpy.data``."""
    action = bpy.data.actions.new(name)
    ad = id_block.animation_data or id_block.animation_data_create()
    ad.action = action
    slot = None
    if SLOTTED:
        slot = ad.action_slot
        if slot is None:
            slot = action.slots.new(id_type=id_block.id_type, name=id_block.name)
            ad.action_slot = slot
    return action, slot


def plain_value(value):
    """An ID property's value as plain Python (an array or group property read
    from a data-block is a view of it, which a later assignment would change)."""
    for conv in ("to_dict", "to_list"):
        if hasattr(value, conv):
            return getattr(value, conv)()
    return value


def assigned_action(id_block):
    """``(action, slot)`` animating ``id_block`` or ``(None, None)``."""
    ad = id_block.animation_data
    if ad is None or ad.action is None:
        return None, None
    return ad.action, (ad.action_slot if SLOTTED else None)


def _channelbag(action, slot, create):
    if create:
        try:
            from bpy_extras.anim_utils import action_ensure_channelbag_for_slot  # 5.0+
            return action_ensure_channelbag_for_slot(action, slot)
        except ImportError:
            pass
        layer = action.layers[0] if len(action.layers) else action.layers.new("Layer")
        strip = layer.strips[0] if len(layer.strips) else layer.strips.new(type='KEYFRAME')
        return strip.channelbag(slot, ensure=True)
    for layer in action.layers:
        for strip in layer.strips:
            bag = strip.channelbag(slot)
            if bag is not None:
                return bag
    return None


def fcurves_of(action, slot):
    """The F-Curve collection of ``slot`` in ``action`` (legacy: all of the action), or ()."""
    if action is None:
        return ()
    if SLOTTED and slot is not None:
        bag = _channelbag(action, slot, create=False)
        return bag.fcurves if bag is not None else ()
    if hasattr(action, "fcurves"):
        return action.fcurves
    return ()


def find_fcurve(action, slot, data_path, index=0):
    for fc in fcurves_of(action, slot):
        if fc.data_path == data_path and fc.array_index == index:
            return fc
    return None


def ensure_fcurves(action, slot, data_path, index, group):
    """The F-Curve ``data_path[index]`` of ``slot`` in ``action`` (created in the
    group ``group`` when missing). Works with legacy and slotted actions."""
    if SLOTTED and slot is not None:
        bag = _channelbag(action, slot, create=True)
        fc = bag.fcurves.find(data_path, index=index)
        if fc is None:
            fc = bag.fcurves.new(data_path, index=index)
            if group:
                grp = bag.groups.get(group) if hasattr(bag.groups, "get") else None
                if grp is None:
                    grp = bag.groups.new(group)
                fc.group = grp
        return fc
    fc = action.fcurves.find(data_path, index=index)
    if fc is None:
        fc = action.fcurves.new(data_path, index=index, action_group=group or "")
    return fc


def write_keys(fc, frames, values, interpolation='LINEAR'):
    """Replace the keyframes of ``fc`` by ``(frames[i], values[i])``, in bulk."""
    frames = np.asarray(frames, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    n = len(frames)
    kp = fc.keyframe_points
    if len(kp):
        if hasattr(kp, "clear"):
            kp.clear()
        else:
            while len(kp):
                kp.remove(kp[len(kp) - 1], fast=True)
    kp.add(n)
    co = np.empty(2 * n, dtype=np.float32)
    co[0::2] = frames
    co[1::2] = values
    kp.foreach_set("co", co)
    ipo = _enum_value(bpy.types.Keyframe, "interpolation", interpolation)
    kp.foreach_set("interpolation", np.full(n, ipo, dtype=np.int32))
    fc.update()


def read_keys(fc):
    """``(frames, values, interpolation values)`` of the keyframes of ``fc``."""
    n = len(fc.keyframe_points)
    co = np.empty(2 * n, dtype=np.float32)
    fc.keyframe_points.foreach_get("co", co)
    ipo = np.empty(n, dtype=np.int32)
    fc.keyframe_points.foreach_get("interpolation", ipo)
    return co[0::2].astype(np.float64), co[1::2].astype(np.float64), ipo


def sample_fcurve(fc, frames):
    """Values of ``fc`` at ``frames`` (array). LINEAR and CONSTANT keys without
    modifiers are evaluated in numpy; anything else through ``fc.evaluate``."""
    frames = np.asarray(frames, dtype=np.float64)
    kf, kv, ipo = read_keys(fc)
    lin = _enum_value(bpy.types.Keyframe, "interpolation", 'LINEAR')
    const = _enum_value(bpy.types.Keyframe, "interpolation", 'CONSTANT')
    simple = (len(kf) > 0 and len(fc.modifiers) == 0 and fc.extrapolation == 'CONSTANT'
              and np.all(np.diff(kf) > 0))
    if simple and np.all(ipo[:-1] == lin):
        return np.interp(frames, kf, kv)
    if simple and np.all(ipo[:-1] == const):
        i = np.clip(np.searchsorted(kf, frames, side="right") - 1, 0, len(kf) - 1)
        return kv[i]
    return np.array([fc.evaluate(float(f)) for f in frames])


def operator_error_text(exc) -> str:
    """The one line of an error raised by a Blender operator (``RuntimeError:
    Error: ...``; for an operator written in Python, e.g. an importer or the FBX
    exporter, ``Error: Python: Traceback ...`` down to the exception's own line,
    then Blender 5's ``Location: .../bpy/ops.py:N``): its last non-empty line that
    is not a ``Location:`` line, without Blender's ``Error:`` prefix."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip() and not ln.strip().startswith("Location: ")]
    msg = lines[-1] if lines else type(exc).__name__
    for prefix in ("Error: ", "error: "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    return msg
