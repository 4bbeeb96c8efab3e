# SPDX-License-Identifier: GPL-3.0-or-later
"""What every sub-panel of the Dancing Points sidebar tab shares."""


class SubPanel:
    """Mixin: a sub-panel of the "Dancing Points" tab (``VIEW3D_PT_dancing_points``)."""

    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Dancing Points"
    bl_parent_id = "VIEW3D_PT_dancing_points"


def split_layout(layout, context, settings="dancing_points"):
    """A sub-panel's layout in property-split style, and the scene's settings
    group ``settings`` (None when the add-on's properties are not registered)."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout, getattr(context.scene, settings, None)
