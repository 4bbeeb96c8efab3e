# SPDX-License-Identifier: GPL-3.0-or-later
"""Operators of the extension (``bpy.ops.dancing_points.*``, SPEC §8).

Thin translators between Blender and the bpy-free core (``dancing_points_addon``):

- ``dancing_points.import_take`` (``take_io``): a take (.csv), BVH, FBX or CMU
  AMC file -> a take collection with three keyframed empties
  (``take_collection``; BVH/FBX read by ``take_rig``, the source body kept by
  ``take_ghost``); File > Import menu entry and drag-and-drop (FileHandler).
- ``dancing_points.set_song`` / ``remove_take`` (``song``): the take's song as
  a sound strip lined up with it, its beats as timeline markers; removing a
  take removes them.
- ``dancing_points.synthesize`` (``synthesize``): the active take -> a baked
  duet (``bake``): leader and follower armatures with skinned bodies.
- ``dancing_points.render_preview`` (``render``): Workbench render of the range.
- ``dancing_points.live_start`` / ``live_stop`` (``live``): dance live from a
  VMC or OSC stream or Blender's VR session; Stop keeps the take.

``props`` holds the data stored in the .blend (``kinds``: whether a collection
is a take or a duet), ``compat`` the Blender-version shims (legacy vs slotted
actions, bulk keyframe I/O).
"""

from . import props, take_io, song, synthesize, render, retarget, batch_cli, method_view, stage, live

_modules = (props, song, take_io, synthesize, render, retarget, batch_cli, method_view, stage, live)


def register():
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()
