"""The repository checkout is a valid Blender extension that enables and disables cleanly.

Enabled in the ``bpy`` module as a real extension (see ext_util), and its manifest
checked with Blender's own ``blender --command extension validate``/``build`` code.
"""

import subprocess
import sys
import tomllib
import zipfile

import pytest

from support import ext_util
from support.ext_util import ROOT

bpy = pytest.importorskip("bpy")

PANEL = "VIEW3D_PT_dancing_points"

# What `blender --command extension ...` runs, reachable from the bpy module:
# the command is registered by the core add-on `bl_pkg` with bpy.utils.register_cli_command,
# and its handler is bl_pkg.bl_extension_cli.cli_extension_handler. It runs in a
# subprocess because blender_ext.main() installs a SIGINT handler.
_EXTENSION_CLI = (
    "import sys, bpy\n"
    "from bl_pkg.bl_extension_cli import cli_extension_handler\n"
    "sys.exit(cli_extension_handler(sys.argv[1:]))\n"
)


def extension_cli(*args):
    return subprocess.run(
        [sys.executable, "-c", _EXTENSION_CLI, *map(str, args)],
        capture_output=True, text=True, timeout=300,
    )


def _manifest():
    with open(ROOT / "blender_manifest.toml", "rb") as fh:
        return tomllib.load(fh)


def test_manifest_fields():
    m = _manifest()
    assert m["id"] == "dancing_points"
    assert m["type"] == "add-on"
    assert m["blender_version_min"] == "4.2.0"
    assert m["license"] == ["SPDX:GPL-3.0-or-later"]
    assert len(m["tagline"]) < 64


def test_blender_validates_manifest():
    r = extension_cli("validate", ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Success parsing TOML" in r.stdout


def test_blender_builds_package_without_dev_files(tmp_path):
    r = extension_cli("build", "--source-dir", ROOT, "--output-dir", tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    (archive,) = tmp_path.glob("dancing_points-*.zip")
    assert archive.name == "dancing_points-{:s}.zip".format(_manifest()["version"])
    with zipfile.ZipFile(archive) as zf:
        names = zf.namelist()
    for required in ("blender_manifest.toml", "__init__.py", "preferences.py",
                     "operators/__init__.py", "panels/__init__.py", "dancing_points_addon/__init__.py"):
        assert required in names
    excluded = ("training/", "tools/", "tests/", "benchmarks/", ".ci/", ".venv/", ".git", "docs/", "cache/", "out/")
    leaked = [n for n in names if n.startswith(excluded) or "__pycache__/" in n or n.endswith(".pyc")]
    assert not leaked, leaked
    # The core in the zip is the bpy-free runtime: no training-only module, no developer tool.
    for mod in ("dataset.py", "metrics.py", "build_extension.py"):
        assert not any(n.endswith("/" + mod) for n in names), mod
    # The built archive passes validation too.
    r = extension_cli("validate", archive)
    assert r.returncode == 0, r.stdout + r.stderr


def test_enable_as_extension(dp_extension):
    import addon_utils

    assert dp_extension == "bl_ext.{:s}.dancing_points".format(ext_util.REPO_MODULE)
    assert dp_extension in bpy.context.preferences.addons
    assert addon_utils.check(dp_extension) == (True, True)
    assert ext_util.enable_extension() == dp_extension  # idempotent

    mod = sys.modules[dp_extension]
    assert addon_utils.module_bl_info(mod)["version"] == tuple(int(x) for x in _manifest()["version"].split("."))

    panel = bpy.types.Panel.bl_rna_get_subclass_py(PANEL)
    assert panel is not None
    assert (panel.bl_space_type, panel.bl_region_type, panel.bl_category) == ("VIEW_3D", "UI", "Dancing Points")

    prefs = bpy.context.preferences.addons[dp_extension].preferences
    assert prefs.onnx_threads == 1
    prop = prefs.bl_rna.properties["onnx_threads"]
    assert (prop.hard_min, prop.hard_max) == (1, 64)


def test_core_importable_from_extension(dp_extension):
    core = ext_util.import_from_extension("dancing_points_addon")
    assert core.__name__ == dp_extension + ".dancing_points_addon"


def test_panel_draws(dp_extension):
    # A headless bpy has no window to draw in: call draw() with a stand-in layout
    # that records the labels.
    panel_cls = bpy.types.Panel.bl_rna_get_subclass_py(PANEL)

    class Layout:
        def __init__(self):
            self.labels = []

        def label(self, text="", **_):
            self.labels.append(text)

    class Fake:
        layout = Layout()

    panel_cls.draw(Fake, bpy.context)
    version = _manifest()["version"]
    assert any(version in t for t in Fake.layout.labels), Fake.layout.labels
    assert "Import a take: File > Import > Dancing Points take" in Fake.layout.labels


def test_disable_and_reenable_cleanly(dp_extension):
    ext_util.disable_extension()
    try:
        assert dp_extension not in bpy.context.preferences.addons
        assert bpy.types.Panel.bl_rna_get_subclass_py(PANEL) is None
        assert not hasattr(bpy.types, PANEL)
    finally:
        assert ext_util.enable_extension() == dp_extension
    assert bpy.types.Panel.bl_rna_get_subclass_py(PANEL) is not None


def test_build_extension_bundles_models_and_wheels(tmp_path):
    """``python -m tools.build_extension``: Blender's own build of the
    tracked files, with the ONNX Runtime and soundfile wheels of the platform (never numpy), the
    shipped models, and no training code, tests or data; each zip validated."""
    res = subprocess.run([sys.executable, "-m", "tools.build_extension", "-o", str(tmp_path),
                          "--platform", "linux-x64"], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout + res.stderr
    (archive,) = tmp_path.glob("dancing_points-*-linux_x64.zip")
    with zipfile.ZipFile(archive) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    for f in ("models/mapping.onnx", "models/placement.onnx", "models/contacts.onnx", "models/pose_anchor.onnx",
              "models/hip_heading.onnx", "models/tracker_leader.onnx", "models/tracker_follower.onnx",
              "dancing_points_addon/samples/sample_take.csv"):
        assert f in names
    wheels = [n for n in names if n.startswith("wheels/")]
    assert any(n.startswith("wheels/onnxruntime-") and "manylinux" in n for n in wheels), wheels
    assert not any(n.lower().startswith("wheels/numpy") for n in wheels)
    assert any(n.startswith("wheels/python_osc-1.10.2-") and n.endswith("-none-any.whl") for n in wheels), wheels
    # the songs' decoder: libsndfile in soundfile's platform wheel, with cffi's
    assert any(n.startswith("wheels/soundfile-0.14.0-") and "manylinux" in n for n in wheels), wheels
    assert any(n.startswith("wheels/cffi-") and "manylinux" in n for n in wheels), wheels
    assert sorted("wheels/" + w.split("/")[-1] for w in manifest["wheels"]) == sorted(wheels)
    leaked = [n for n in names if n.startswith(("training/", "tests/", "benchmarks/", ".ci/", "docs/", "cache/"))
              or n.lower().endswith((".amc", ".asf", ".glb", ".fbx", ".npz"))]
    assert not leaked, leaked
