import os
import pathlib
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
