import os
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared"))
SALSA = SHARED / "data" / "cmu_salsa"
SOLO = SHARED / "data" / "cmu_solo_dance"
ASSETS = SHARED / "assets"

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@pytest.fixture(scope="session")
def salsa_dir():
    if not SALSA.exists():
        pytest.fail(f"shared data not found at {SALSA} (set DP_SHARED)")
    return SALSA
