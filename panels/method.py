# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Method" sub-panel: what of the method is drawn beside a baked duet
(``operators.method_view``: input markers, predicted trajectories, foot
contacts, the source body's ghost) and whether it shows in final renders."""

import bpy

from .common import SubPanel, split_layout


class VIEW3D_PT_dancing_points_method(SubPanel, bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points_method"
    bl_label = "Method"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        layout, settings = split_layout(self.layout, context, "dancing_points_method")
        if settings is None:
            return
        col = layout.column(heading="Show")
        col.prop(settings, "show_inputs")
        col.prop(settings, "show_predictions")
        col.prop(settings, "show_contacts")
        col.prop(settings, "show_ghost")
        layout.prop(settings, "method_in_render")


classes = (VIEW3D_PT_dancing_points_method,)
