# SPDX-License-Identifier: GPL-3.0-or-later
"""Add-on preferences of the Dancing Points extension."""

import bpy
from bpy.props import IntProperty, StringProperty

# For an extension ``__package__`` is the root package ("bl_ext.<repo>.dancing_points"),
# which is the key Blender uses for the add-on's preferences.
ADDON_ID = __package__


class DancingPointsPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    onnx_threads: IntProperty(
        name="ONNX Threads",
        description="Threads ONNX Runtime uses for synthesis (intra-op)",
        default=1,
        min=1,
        max=64,
    )
    model_dir: StringProperty(
        name="Model Folder",
        description="Folder with the synthesis networks (mapping.onnx, placement.onnx, contacts.onnx, "
                    "pose_anchor.onnx, hip_heading.onnx, tracker_leader.onnx, tracker_follower.onnx); "
                    "empty: the models bundled with the extension",
        subtype='DIR_PATH',
        default="",
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "onnx_threads")
        layout.prop(self, "model_dir")


def get_preferences(context=None):
    """This add-on's preferences, or None when it is not enabled."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences if addon is not None else None


classes = (DancingPointsPreferences,)

register, unregister = bpy.utils.register_classes_factory(classes)
