"""Who a cluster's worker must be (:mod:`.cluster`): the client's :func:`identity`
(project version, a hash of the extension's Python files, a hash of the
models' bytes), and :func:`check_worker`, a worker's test of it before any work.
"""
from __future__ import annotations

import hashlib
import os
import sys

from ..errors import UserError
from .worker import ROOT

# What identifies the code a worker runs: the extension's Python files (where present) and its manifest.
CODE_PARTS = ("dancing_points_addon", "operators", "panels", "__init__.py", "preferences.py")
MANIFEST = "blender_manifest.toml"


def project_version(root=ROOT) -> str:
    try:
        with open(os.path.join(root, MANIFEST), encoding="utf-8") as f:
            for line in f:
                key, _, value = line.partition("=")
                if key.strip() == "version":
                    return value.strip().strip('"\'')
    except OSError:
        pass
    return "unknown"


def code_hash(root=ROOT) -> str:
    """SHA-256 of the extension's Python files (relative names and bytes, sorted)."""
    files = []
    for part in CODE_PARTS:
        path = os.path.join(root, part)
        if os.path.isfile(path):
            files.append(part)
        elif os.path.isdir(path):
            for dirpath, dirnames, filenames in os.walk(path):
                dirnames[:] = sorted(d for d in dirnames if not d.startswith((".", "__pycache__")))
                files.extend(os.path.relpath(os.path.join(dirpath, n), root).replace(os.sep, "/")
                             for n in filenames if n.endswith(".py"))
    h = hashlib.sha256()
    for rel in sorted(files):
        with open(os.path.join(root, rel), "rb") as f:
            data = f.read()
        h.update(rel.encode("utf-8") + b"\0" + str(len(data)).encode() + b"\0" + data)
    return h.hexdigest()


_MODEL_HASHES: dict = {}


def models_hash(model_dir) -> str:
    """SHA-256 of a models folder's network files (cached per file size and time)."""
    from ..nets import MODEL_FILES

    paths = [os.path.join(model_dir, MODEL_FILES[k]) for k in sorted(MODEL_FILES)]
    key = tuple((p, os.path.getsize(p), os.path.getmtime(p)) for p in paths)
    if key not in _MODEL_HASHES:
        h = hashlib.sha256()
        for p in paths:
            with open(p, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
        _MODEL_HASHES[key] = h.hexdigest()
    return _MODEL_HASHES[key]


_CODE: dict = {}


def identity(model_dir) -> dict:
    """What a worker must share with the client: the project version, the code and the models."""
    if "code" not in _CODE:  # once per process: the code it imported
        _CODE.update(version=project_version(), code=code_hash())
    return {"version": _CODE["version"], "code": _CODE["code"], "models": models_hash(model_dir)}


def _short(h) -> str:
    return str(h)[:12]


def _worker_model_dir(expected: dict, client_dir: str):
    """The models folder on this worker whose bytes are the client's: the client's
    path, ``$DP_MODEL_DIR`` or the bundled ``models/``; ``(folder, None)`` or
    ``(None, why not)``."""
    from ..nets import MODEL_DIR, MODEL_ENV, resolve_model_dir

    seen = []
    for cand in (client_dir, os.environ.get(MODEL_ENV, ""), MODEL_DIR):
        if not cand:
            continue
        try:
            d = resolve_model_dir(cand)
            h = models_hash(d)
        except (UserError, OSError):
            continue
        if h == expected["models"]:
            return d, None
        seen.append(f"{d} (models {_short(h)})")
    return None, (f"has no models matching this client's (models {_short(expected['models'])} from "
                  f"{client_dir}; found {', '.join(seen) or 'none'}): put the client's models folder on the "
                  f"workers at the same path, in $DP_MODEL_DIR or as the bundled models/")


def check_worker(expected: dict, client_dir: str, needs_bpy: bool = False):
    """On a worker: ``(models folder, None)`` when it runs the client's version,
    code and models (and has ``bpy`` when ``needs_bpy``); else ``(None, why)``."""
    if "code" not in _CODE:
        _CODE.update(version=project_version(), code=code_hash())
    if (_CODE["version"], _CODE["code"]) != (expected["version"], expected["code"]):
        return None, (f"runs Dancing Points {_CODE['version']} (code {_short(_CODE['code'])}), this client "
                      f"{expected['version']} (code {_short(expected['code'])}): install the client's version "
                      f"on every worker and restart them")
    model_dir, why = _worker_model_dir(expected, client_dir)
    if model_dir is None:
        return None, why
    if needs_bpy:
        import importlib.util

        if importlib.util.find_spec("bpy") is None:
            return None, (f"has no bpy module (needed for blend, fbx and --render): pip install bpy in the "
                          f"workers' Python ({sys.executable}), or convert to npz or bvh on the cluster")
    return model_dir, None

