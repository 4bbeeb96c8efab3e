# SPDX-License-Identifier: GPL-3.0-or-later
"""The bone mapping stored on a target armature (``Object.dp_retarget_map``:
one row per bone), filled from a preset or guessed from the bone names."""

import os

import bpy

from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.retarget import RetargetError
from ...dancing_points_addon.retarget.structure import describe, structural_mapping
from .props import CONVENTION_PROP


def stored_mapping(obj):
    return {item.target: item.source for item in getattr(obj, "dp_retarget_map", ()) if item.source}


def set_mapping(obj, mapping):
    """Store ``mapping`` on ``obj``: one row per bone (unmapped bones with an empty source)."""
    coll = obj.dp_retarget_map
    coll.clear()
    for b in obj.data.bones:
        item = coll.add()
        item.target = b.name
        item.source = mapping.get(b.name, "")


def guess_mapping(obj):
    """``(mapping, how)``: by the bone names when a convention fits (``how``: its
    name), else by the rig's structure (``how``: ``"structure"``)."""
    names = [b.name for b in obj.data.bones]
    mapping, conv = rt.auto_mapping(names)
    if mapping:
        try:
            rt.validate_mapping(mapping, names)
            return mapping, conv
        except RetargetError:
            pass
    from .rig import target_rig

    mapping, _ = structural_mapping(target_rig(obj, store=False))
    return mapping, "structure"


def looks_like_file(preset):
    """Whether a preset names a file (a JSON or a path), not a built-in convention."""
    return preset.lower().endswith(".json") or preset.startswith("//") or os.sep in preset or "/" in preset


def preset_path(preset):
    """A preset file's absolute path; a ``//`` path is relative to the saved
    .blend file (:class:`RetargetError` while it has none: the file would land
    in whatever folder Blender was started from)."""
    if preset.startswith("//") and not bpy.data.filepath:
        raise RetargetError("'{:s}' is relative to the .blend file, which is not saved yet: save it first "
                            "or choose an absolute path".format(preset))
    return bpy.path.abspath(preset)


def mapping_for(obj, preset="", notes=None):
    """The mapping to use for ``obj``: a preset (file path or built-in name) when
    given, else the one stored on the object, else the automatic guess (stored):
    by the bone names, else by the rig's structure (then a line naming the mapped
    bones is appended to ``notes``, to check in the bone-map panel)."""
    names = [b.name for b in obj.data.bones]
    if preset:
        path = preset_path(preset)
        if os.path.isfile(path):
            data = rt.load_preset(path)
            mapping = {k: v for k, v in data["bones"].items() if k in names and v}
            if not mapping:  # a convention table: match names by convention
                mapping, _ = rt.auto_mapping(names, conventions={data["name"]: data}, convention=data["name"])
        elif looks_like_file(preset):
            raise RetargetError("bone map file not found: {:s}".format(path))
        else:
            mapping, _ = rt.auto_mapping(names, convention=preset)
        set_mapping(obj, mapping)
        return mapping
    mapping = stored_mapping(obj)
    if mapping:
        return mapping
    try:
        mapping, how = guess_mapping(obj)
    except RetargetError as exc:
        raise RetargetError("no bone naming convention recognised on '{:s}' (CMU/BVH, Mixamo, Rigify, VRM, "
                            "Unreal) and {:s}".format(obj.name, str(exc).replace(
                                "no bone naming convention recognised, and ", ""))) from None
    set_mapping(obj, mapping)
    obj[CONVENTION_PROP] = how
    if how == "structure" and notes is not None:
        notes.append("'{:s}': no naming convention recognised, bones mapped by structure (check them in the "
                     "Bone Map panel): {:s}".format(obj.name, describe(mapping)))
    return mapping
