"""Enable the repository checkout in the ``bpy`` module *as an extension*.

Blender 4.2+ loads extensions as ``bl_ext.<repo module>.<extension id>``. We make
a throw-away user extension repository (a temporary directory), put a symlink
``dancing_points`` -> the repository checkout in it, register that repository
with ``bpy`` and enable the add-on through ``bpy.ops.preferences.addon_enable``,
exactly the way Blender loads an installed extension (relative imports,
``__package__`` = ``bl_ext.<repo>.dancing_points``, add-on preferences keyed by it).

Reuse from any test::

    from support.ext_util import enable_extension, dp_extension   # fixture

    def test_something(dp_extension):          # dp_extension == module name
        import bpy
        bpy.ops.dancing_points....

``enable_extension()`` is idempotent within a process; the repository and the
temporary directory are removed at interpreter exit. User preferences are never
saved (``use_preferences_save`` is switched off first).
"""

import atexit
import importlib
import os
import pathlib
import shutil
import sys
import tempfile


ROOT = pathlib.Path(__file__).resolve().parents[2]
EXTENSION_ID = "dancing_points"
REPO_MODULE = "dancing_points_tests"
REPO_NAME = "Dancing Points tests"
MODULE = "bl_ext.{:s}.{:s}".format(REPO_MODULE, EXTENSION_ID)

_repo_dir = None


def _find_repo(bpy):
    for repo in bpy.context.preferences.extensions.repos:
        if repo.module == REPO_MODULE:
            return repo
    return None


def _ensure_repo():
    """Create (once) the temporary extension repository holding the checkout."""
    global _repo_dir
    import bpy

    prefs = bpy.context.preferences
    # Never write the developer's userpref.blend because of the test repository.
    prefs.use_preferences_save = False

    if _repo_dir is not None and _find_repo(bpy) is not None:
        return
    _repo_dir = tempfile.mkdtemp(prefix="dp_ext_repo_")
    os.symlink(str(ROOT), os.path.join(_repo_dir, EXTENSION_ID), target_is_directory=True)
    repo = prefs.extensions.repos.new(
        name=REPO_NAME,
        module=REPO_MODULE,
        custom_directory=_repo_dir,
        source='USER',
    )
    repo.enabled = True
    atexit.register(_cleanup)


def is_enabled():
    import bpy
    return bpy.context.preferences.addons.get(MODULE) is not None


def enable_extension():
    """Enable the checkout as the extension ``bl_ext.<repo>.dancing_points``; return that module name."""
    _ensure_repo()
    if not is_enabled():
        import bpy
        result = bpy.ops.preferences.addon_enable(module=MODULE)
        if result != {'FINISHED'} or not is_enabled():
            raise RuntimeError("could not enable {:s} (addon_enable returned {!r})".format(MODULE, result))
    return MODULE


def disable_extension():
    """Disable the extension (keeps the repository, so enable_extension() works again)."""
    if _repo_dir is None or not is_enabled():
        return
    import bpy
    result = bpy.ops.preferences.addon_disable(module=MODULE)
    if result != {'FINISHED'} or is_enabled():
        raise RuntimeError("could not disable {:s} (addon_disable returned {!r})".format(MODULE, result))


def import_from_extension(name=""):
    """Import ``bl_ext.<repo>.dancing_points[.name]`` (enabling the extension first)."""
    enable_extension()
    return importlib.import_module(MODULE + ("." + name if name else ""))


def _cleanup():
    global _repo_dir
    if _repo_dir is None:
        return
    try:
        import bpy
        repo = _find_repo(bpy)
        if repo is not None:
            # Removing the repository disables its add-ons (unregister runs).
            bpy.context.preferences.extensions.repos.remove(repo)
    except Exception as ex:  # at interpreter exit: report, never raise
        print("ext_util: cleanup failed: {!r}".format(ex), file=sys.stderr)
    link = os.path.join(_repo_dir, EXTENSION_ID)
    if os.path.islink(link):
        os.unlink(link)  # the link only, never the checkout it points to
    shutil.rmtree(_repo_dir, ignore_errors=True)
    _repo_dir = None

