# SPDX-License-Identifier: GPL-3.0-or-later
"""A batch worker in a ``bpy``-module process (Blender side, standalone).

``python -m dancing_points_addon batch --format blend|fbx`` (or ``--render``)
runs without the Blender binary: its workers are ``python
operators/batch_worker.py`` processes (``dancing_points_addon.batch.worker.worker_command``).
This script runs the core's worker loop (``worker_main``) with a converter that,
at the first take, imports ``bpy``, enables this checkout as the extension
``dancing_points`` (:func:`enable_extension_in_bpy`) and then converts each take
with the extension's ``operators.batch_cli.convert_job``.

Run as a program it imports nothing of the extension until then; imported as
``operators.batch_worker`` it gives :func:`enable_extension_in_bpy` to
``batch_cli``. Inside the Blender binary the workers are ``blender --background
--command dancing_points worker`` instead (``batch_cli.cli``).
"""

import contextlib
import os
import shutil
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)  # the checkout / extension folder
EXTENSION_ID = "dancing_points"
REPO_MODULE = "dp_batch"

_repo = {"dir": None}


def enable_extension_in_bpy() -> str:
    """In a ``bpy``-module process: the module name of this checkout enabled as the
    extension ``dancing_points`` (an existing one, else through a temporary user
    extension repository holding a link to the checkout, removed at exit)."""
    import atexit
    import bpy

    prefs = bpy.context.preferences
    prefs.use_preferences_save = False  # never write the user's preferences
    for addon in prefs.addons:
        if addon.module.split(".")[-1] == EXTENSION_ID:
            return addon.module
    if _repo["dir"] is None:
        d = tempfile.mkdtemp(prefix="dp_batch_ext_")
        os.symlink(ROOT, os.path.join(d, EXTENSION_ID), target_is_directory=True)
        repo = prefs.extensions.repos.new(name="Dancing Points batch", module=REPO_MODULE,
                                          custom_directory=d, source='USER')
        repo.enabled = True
        _repo["dir"] = d

        def cleanup():
            with contextlib.suppress(Exception):
                for r in bpy.context.preferences.extensions.repos:
                    if r.module == REPO_MODULE:
                        bpy.context.preferences.extensions.repos.remove(r)
                        break
            link = os.path.join(d, EXTENSION_ID)
            if os.path.islink(link):
                os.unlink(link)  # the link only, never the checkout
            shutil.rmtree(d, ignore_errors=True)

        atexit.register(cleanup)
    module = "bl_ext.{:s}.{:s}".format(REPO_MODULE, EXTENSION_ID)
    if prefs.addons.get(module) is None:
        res = bpy.ops.preferences.addon_enable(module=module)
        if res != {'FINISHED'} or prefs.addons.get(module) is None:
            raise RuntimeError("cannot enable the extension {:s} in bpy".format(module))
    return module


class BpyConverter:
    """The worker's converter for the jobs that need Blender: loaded at the first
    (``bpy`` imported, the extension enabled), then the extension's ``convert_job``."""

    def __init__(self, no_bpy_message):
        self.no_bpy_message = no_bpy_message
        self.convert = None

    def __call__(self, job, progress):
        if self.convert is None:
            self.convert = self._load()
        return self.convert(job, progress)

    def _load(self):
        try:
            import bpy  # noqa: F401
        except ImportError:
            raise RuntimeError(self.no_bpy_message) from None
        import importlib

        module = enable_extension_in_bpy()
        return importlib.import_module(module + ".operators.batch_cli").convert_job


def main() -> int:
    # The core from the checkout, and never this folder's modules as top-level ones.
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != HERE]
    sys.path.insert(0, ROOT)
    from dancing_points_addon.batch.worker import NO_BPY, worker_main

    return worker_main(bpy_converter=BpyConverter(NO_BPY))


if __name__ == "__main__":
    sys.exit(main())
