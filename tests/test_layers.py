"""The layering (README "Layout"): core (numpy + onnxruntime, no bpy) -> Blender
side (operators/, panels/) -> training and tools; no import cycles."""
import ast
import subprocess
import sys
from pathlib import Path

from conftest import ROOT

ROOT = Path(ROOT)
CORE = "dancing_points_addon"


def _modules(package):
    """``{module name: path}`` of every .py file of a top-level package."""
    out = {}
    for p in sorted((ROOT / package).rglob("*.py")):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(name, path):
    """Every module ``name`` imports, at any level of the file (``ast.walk``: the
    imports inside functions too; absolute names; relative imports resolved
    against the package)."""
    is_pkg = path.name == "__init__.py"
    package = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)  # "from pkg import module"
    return found


def _graph(packages):
    mods = {}
    for pkg in packages:
        mods.update(_modules(pkg))
    return {m: {d for d in _imports(m, p) if d in mods and d != m} for m, p in mods.items()}


def _cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _is_package_parent(a, b):
    """A package importing its own submodule (``pkg/__init__`` re-exports) is
    not a cycle of the code: only the submodule's own imports count."""
    return b.startswith(a + ".")


def test_imports_inside_functions_count(tmp_path):
    """An import inside a function (as a Blender callback defers one) is an edge too."""
    pkg = tmp_path / "operators"
    pkg.mkdir()
    (pkg / "a.py").write_text("def f():\n    if True:\n        from .b import x\n        from ..panels import c\n")
    assert {"operators.b", "panels.c"} <= _imports("operators.a", pkg / "a.py")


def test_no_import_cycles():
    """Neither in the core nor in the Blender side (operators/, panels/), training or tools,
    counting the imports inside functions."""
    graph = _graph([CORE, "operators", "panels", "training", "tools"])
    # a package's __init__ re-exporting its submodules is an edge down, never a cycle
    graph = {m: {d for d in deps if not _is_package_parent(m, d) and not _is_package_parent(d, m)}
             for m, deps in graph.items()}
    assert _cycles(graph) == []


OUTSIDE_CORE = ("bpy", "bpy_extras", "mathutils", "operators", "panels", "training", "tools", "torch")


def test_core_never_imports_the_blender_side_or_training():
    """Neither by an import statement nor by a module name in a string (as
    ``importlib.import_module("....operators.x")`` would)."""
    for name, path in _modules(CORE).items():
        bad = {d for d in _imports(name, path) if d.split(".")[0] in OUTSIDE_CORE}
        assert not bad, (name, sorted(bad))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                text = node.value.strip()
                assert not (" " not in text and any(text.startswith(m + ".") or ("." + m + ".") in text
                                                    for m in OUTSIDE_CORE[3:])), (name, text)


def test_every_core_module_imports_without_bpy():
    """Every module of the core (every .py file under it) imports in a Python
    where neither ``bpy`` nor the Blender side, training or torch can be imported."""
    code = (
        "import importlib, sys\n"
        "class NoBpy:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] in {OUTSIDE_CORE!r}:\n"
        "            raise ImportError(name + ' is not importable here')\n"
        "sys.meta_path.insert(0, NoBpy())\n"
        f"for n in {sorted(_modules(CORE))!r}:\n"
        "    importlib.import_module(n)\n"
        "assert 'bpy' not in sys.modules\n"
        "print('ok')\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split()[-1] == "ok"


def test_training_only_code_is_not_in_the_core():
    """Datasets, training metrics and developer tools live outside the extension's core."""
    names = set(_modules(CORE))
    for mod in ("dataset", "metrics", "build_extension"):
        assert not any(n.split(".")[-1] == mod for n in names), mod


# What the file layer may read: itself, the errors, the body's maths and the song's checks
# (never the synthesis: resampling, calibration, the networks, the runtime).
FORMATS_MAY_IMPORT = ("formats", "errors", "rotations", "skeleton", "audio")


def test_formats_import_nothing_of_the_synthesis():
    """``formats/`` is a leaf of the core: it reads and writes files, and any
    module above it (inputs, calibration, resampling, the runtime) may use it
    without a loop back."""
    core = _modules(CORE)
    for name, path in core.items():
        if not name.startswith(CORE + ".formats"):
            continue
        for dep in _imports(name, path):
            if dep in core and dep.startswith(CORE + "."):
                top = dep[len(CORE) + 1:].split(".")[0]
                assert top in FORMATS_MAY_IMPORT, (name, dep)


def test_no_core_module_over_500_lines():
    """A module of the core that grows past 500 lines is split by what its
    parts do (the frame's stages each have their own)."""
    long = {name: n for name, path in _modules(CORE).items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > 500}
    assert not long, long
