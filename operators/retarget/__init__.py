# SPDX-License-Identifier: GPL-3.0-or-later
"""Retarget the baked duet onto the animator's own characters.

- ``bpy.ops.dancing_points.retarget(source=..., target=...)``: the motion of a
  Dancing Points armature (leader or follower of a baked duet) becomes a NEW
  action on the target armature (one keyframe per frame, written in bulk);
  its meshes, rest pose and other actions are left as they are (an action that
  would be left without users gets a fake user so it is kept), but for the
  rig's previous output of the retarget, removed when nothing else uses it.
  A retarget that fails leaves the rig as it was (action, pose, bone map,
  custom properties).
- ``bpy.ops.dancing_points.retarget_duet()``: both dancers at once (the hands
  that hold each other are closed symmetrically), from the panel's pickers.
- ``dancing_points.retarget_map_auto`` / ``_save`` / ``_load``: the bone
  mapping stored on the target armature (``Object.dp_retarget_map``), to
  inspect and edit in the panel, saved and loaded as JSON presets.
- :func:`retarget_duet_onto` (for the batch command) and :func:`load_rig_file`
  (a .blend, .glb/.gltf or .fbx with an armature).

All the maths is in ``dancing_points_addon.retarget``; this package moves data
between Blender and it: ``props`` (what is stored in the .blend), ``rig``
(reading rigs, source motion and rig files), ``mapping`` (the bone mapping on
the object), ``keying`` (writing keys), ``jobs`` (retargeting one dancer, a
pair, a duet collection) and ``ops`` (the operators). The target's reference
pose (the pose it is shown in when first retargeted: its T- or A-pose) is
stored on the object (``dp_reference_basis``) so that later runs align against
the same pose.
"""

import bpy
from bpy.props import CollectionProperty, IntProperty, PointerProperty

from . import ops
from .jobs import duet_armatures, hide_duet_bodies, retarget_duet_onto
from .props import DP_RetargetBoneMap, DP_RetargetSettings
from .rig import load_rig_file, source_motion

# what the batch, the docs' script and the tests use
__all__ = ["duet_armatures", "hide_duet_bodies", "load_rig_file", "retarget_duet_onto", "source_motion",
           "register", "unregister"]

classes = (DP_RetargetBoneMap, DP_RetargetSettings) + ops.classes


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.dp_retarget_map = CollectionProperty(type=DP_RetargetBoneMap)
    bpy.types.Object.dp_retarget_map_index = IntProperty(name="Bone", default=0, min=0)
    bpy.types.Scene.dp_retarget = PointerProperty(type=DP_RetargetSettings)


def unregister():
    del bpy.types.Scene.dp_retarget
    del bpy.types.Object.dp_retarget_map_index
    del bpy.types.Object.dp_retarget_map
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
