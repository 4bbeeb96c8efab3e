# SPDX-License-Identifier: GPL-3.0-or-later
"""Dancing Points: the Blender extension entry point.

Only registers and unregisters; the work lives in ``dancing_points_addon``
(bpy-free core), ``operators`` and ``panels``. Relative imports only: the
package name depends on the repository the extension is installed in
(``bl_ext.<repo>.dancing_points``).
"""

from . import preferences, operators, panels

_modules = (preferences, operators, panels)


def register():
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()
