# SPDX-License-Identifier: GPL-3.0-or-later
"""What the retarget stores in the .blend: the bone mapping rows
(``Object.dp_retarget_map``), the panel's settings (``Scene.dp_retarget``) and
the names of the custom properties it sets on objects."""

import bpy
from bpy.props import BoolProperty, PointerProperty, StringProperty

from ..props import ROLE_PROP, ROLES

REF_PROP = "dp_reference_basis"  # on a target rig: its reference pose (matrix_basis, flattened)
SOURCE_PROP = "dp_retarget_source"  # on a retargeted rig: the DP armature it follows
TARGET_PROP = "dp_retarget_target"  # on a DP armature: the rig it was retargeted onto
CONVENTION_PROP = "dp_retarget_convention"  # on a target rig: how its stored mapping was made
# on an action the retarget made: its name then (renamed or copied, the action is the user's: never removed)
OUTPUT_PROP = "dp_retarget_output"
MAP_PROP = "dp_retarget_map"  # Object.dp_retarget_map: the bone mapping rows
RIG_PROPS = (REF_PROP, SOURCE_PROP, CONVENTION_PROP)  # the custom properties a retarget sets on a target rig


class DP_RetargetBoneMap(bpy.types.PropertyGroup):
    target: StringProperty(name="Target Bone", description="Bone of the target armature")
    source: StringProperty(name="Source", description="Dancing Points bone(s) it follows (SPEC §2 names, "
                                                      "'a+b' for a chain; empty: keeps its rest pose)")


def _is_armature(self, obj):
    return obj is not None and obj.type == 'ARMATURE'


def _is_dp_armature(self, obj):
    return _is_armature(self, obj) and obj.get(ROLE_PROP) in ROLES


class DP_RetargetSettings(bpy.types.PropertyGroup):
    leader_source: PointerProperty(name="Leader", type=bpy.types.Object, poll=_is_dp_armature,
                                   description="The baked leader armature (Dancing Points)")
    leader_target: PointerProperty(name="Leader Rig", type=bpy.types.Object, poll=_is_armature,
                                   description="Your armature that dances the leader's part")
    follower_source: PointerProperty(name="Follower", type=bpy.types.Object, poll=_is_dp_armature,
                                     description="The baked follower armature (Dancing Points)")
    follower_target: PointerProperty(name="Follower Rig", type=bpy.types.Object, poll=_is_armature,
                                     description="Your armature that dances the follower's part")
    foot_lock: BoolProperty(name="Foot Locking", default=True,
                            description="Keep the feet in contact on the target (leg IK)")
    close_hands: BoolProperty(name="Close Hands", default=True,
                              description="Hands that hold each other stay together (arm IK)")
    preset_path: StringProperty(name="Preset", subtype='FILE_PATH', default="//bone_map.json",
                                description="JSON file of a bone mapping")


def settings(context):
    """The scene's retarget settings (``Scene.dp_retarget``), or None."""
    return getattr(context.scene, "dp_retarget", None)
