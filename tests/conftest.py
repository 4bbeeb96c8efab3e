import inspect
import os
import pathlib
import re
import signal
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared"))
SALSA = SHARED / "data" / "cmu_salsa"
SOLO = SHARED / "data" / "cmu_solo_dance"
ASSETS = SHARED / "assets"
# The shipped models (``$DP_MODEL_DIR`` overrides, e.g. to try freshly trained ones).
MODELS = os.environ.get("DP_MODEL_DIR") or str(ROOT / "models")

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# A suite started in the background of a non-interactive shell (``pytest … &``) inherits Ctrl-C
# ignored, and so would every process it starts: the tests that stop ``live`` or the command line
# with SIGINT need it delivered.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def dp_extension():
    """The extension enabled in ``bpy``; the value is its module name ``bl_ext.<repo>.dancing_points``."""
    from support.ext_util import enable_extension

    return enable_extension()


@pytest.fixture(scope="session")
def salsa_dir():
    if not SALSA.exists():
        pytest.fail(f"shared data not found at {SALSA} (set DP_SHARED)")
    return SALSA


# Blender 4.2-4.3's bpy module crashes (SIGSEGV) at interpreter exit once an
# add-on with Python property callbacks (``poll=``/``update=``) was unregistered
# while running (here: the atexit removal of the test extension repository), a
# Blender bug fixed by 4.4 (reproduced with a 10-line PropertyGroup, bpy 4.2.0
# and 4.2.23). On those versions the session ends by running the atexit
# handlers and leaving with pytest's own status, before the crashing teardown.
_EXIT_STATUS = [None]


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS[0] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    bpy = sys.modules.get("bpy")
    if bpy is None or _EXIT_STATUS[0] is None or bpy.app.version >= (4, 4, 0):
        return
    import atexit
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(_EXIT_STATUS[0])


# Markers (declared in pyproject.toml), assigned here by test module so that the
# test files carry none: ``blender`` for tests that need Blender's ``bpy`` module
# (they import it or enable the extension), ``slow`` for modules that take over
# about a minute on a 2-core machine. The quick subset: ``-m "not blender and not slow"``.
BLENDER_MODULES = {
    # every test of these needs bpy (a module-level importorskip, or Blender batch workers)
    "test_batch.py", "test_blender_addon.py", "test_extension.py", "test_fbx_input.py",
    "test_fk_blender.py", "test_live_blender.py", "test_preview.py", "test_retarget_sizes.py",
    "test_song_blender.py",
}
# Core modules with a Blender part: only the tests that ask for one of these
# fixtures, are skipped without bpy (a skipif naming bpy), or import bpy themselves.
BLENDER_FIXTURES = {
    "test_method_view.py": {"scene_duet"},
    "test_outputs_safety.py": set(),
    "test_readers_robust.py": {"blender"},
    "test_rig_orientations.py": {"rigs"},
    "test_retarget.py": {"scene"},
    "test_retarget_rigs.py": {"rigs"},
    "test_runtime.py": set(),
    "test_device_orientations.py": set(),
}
SLOW_MODULES = {
    # Blender's: whole scenes, renders and batch workers (test_retarget_sizes about 7.5 min)
    "test_batch.py", "test_blender_addon.py", "test_fbx_input.py", "test_live_blender.py",
    "test_preview.py", "test_retarget.py", "test_retarget_rigs.py", "test_retarget_sizes.py",
    "test_song_blender.py",
    # the core's, as timed on 2026-11-28 (2 cores shared with other runs): runtime 947 s,
    # cluster 268, noise 204, outputs_safety 192, roles 148, devices 127, live 122, training 116
    "test_cluster.py", "test_devices.py", "test_live.py", "test_noise.py", "test_outputs_safety.py",
    "test_roles.py", "test_runtime.py", "test_training.py",
}


def _needs_bpy(item, module: str) -> bool:
    if module in BLENDER_MODULES:
        return True
    if module not in BLENDER_FIXTURES:
        return False
    fixtures = set(getattr(item, "fixturenames", ()))
    if fixtures & (BLENDER_FIXTURES[module] | {"dp_extension"}):
        return True
    if any("bpy" in str(m.kwargs.get("reason", "")) for m in item.iter_markers("skipif")):
        return True
    try:
        source = inspect.getsource(item.function)
    except (AttributeError, OSError, TypeError):
        return False
    return re.search(r"import bpy\b|importorskip\(\"bpy\"\)", source) is not None


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.path.name
        if _needs_bpy(item, module):
            item.add_marker(pytest.mark.blender)
        if module in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
