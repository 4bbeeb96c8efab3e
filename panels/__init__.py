# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Dancing Points" tab of the 3D Viewport sidebar (N panel)."""

import os
import tomllib

import bpy

_MANIFEST = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "blender_manifest.toml")
_version = None


def addon_version():
    """The extension's version string, read once from blender_manifest.toml (the single source)."""
    global _version
    if _version is None:
        try:
            with open(_MANIFEST, "rb") as fh:
                _version = str(tomllib.load(fh)["version"])
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            _version = "unknown"
    return _version


class VIEW3D_PT_dancing_points(bpy.types.Panel):
    bl_idname = "VIEW3D_PT_dancing_points"
    bl_label = "Dancing Points"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Dancing Points"

    def draw(self, context):
        layout = self.layout
        layout.label(text="Version " + addon_version())
        layout.label(text="Import a take: File > Import > Dancing Points take")


classes = (VIEW3D_PT_dancing_points,)

register, unregister = bpy.utils.register_classes_factory(classes)
