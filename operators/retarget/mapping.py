# SPDX-License-Identifier: GPL-3.0-or-later
"""The bone mapping stored on a target armature (``Object.dp_retarget_map``:
one row per bone), filled from a preset or guessed from the bone names."""

import os

import bpy

from ...dancing_points_addon import retarget as rt
from ...dancing_points_addon.retarget import RetargetError


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


def mapping_for(obj, preset=""):
    """The mapping to use for ``obj``: a preset (file path or built-in name) when
    given, else the one stored on the object, else the automatic guess (stored)."""
    names = [b.name for b in obj.data.bones]
    if preset:
        path = bpy.path.abspath(preset)
        if os.path.isfile(path):
            data = rt.load_preset(path)
            mapping = {k: v for k, v in data["bones"].items() if k in names and v}
            if not mapping:  # a convention table: match names by convention
                mapping, _ = rt.auto_mapping(names, conventions={data["name"]: data}, convention=data["name"])
        else:
            mapping, _ = rt.auto_mapping(names, convention=preset)
        set_mapping(obj, mapping)
        return mapping
    mapping = stored_mapping(obj)
    if mapping:
        return mapping
    mapping, _ = rt.auto_mapping(names)
    if not mapping:
        raise RetargetError("no bone naming convention recognised on '{:s}' (CMU/BVH, Mixamo, Rigify DEF-, "
                              "Unreal): load a preset or fill in the mapping".format(obj.name))
    set_mapping(obj, mapping)
    return mapping
