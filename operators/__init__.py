# SPDX-License-Identifier: GPL-3.0-or-later
"""Operators of the extension (``bpy.ops.dancing_points.*``, SPEC §8).

The import and synthesis operators are added here later; every operator class
goes into ``classes`` so that ``register``/``unregister`` pick it up.
"""

import bpy

classes = ()

register, unregister = bpy.utils.register_classes_factory(classes)
