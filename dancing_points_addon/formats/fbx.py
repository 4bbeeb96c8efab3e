"""FBX input for the bpy-free core: through Blender's own FBX importer.

An FBX file is a binary scene graph that only Blender's importer reads here;
the core never imports ``bpy``. :func:`load_fbx` runs the Blender side's
standalone reader (:data:`FBX_READER`, ``operators/fbx_take.py``) in a
``python`` process with the ``bpy`` module: it enables this checkout as the
extension, imports the file as *Import Dancing Points take* does (the head
and wrists read off the rig, the same code) and writes the take at the file's
own rate to a temporary ``.npz`` that is read back here. A file with several
armatures (a Dancing Points duet FBX: ``DP Leader`` and ``DP Follower``) gives
the one whose dance is ``role`` (default: the leader's), else one line naming
them; the take's ``source_armature`` says which was read. Without the ``bpy``
module the answer is one line saying how to get it.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

from ..errors import InputError
from .take import Take

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the checkout / extension
FBX_READER = os.path.join(ROOT, "operators", "fbx_take.py")
NO_BPY = ("reading an FBX file needs Blender's FBX importer: install the bpy module in this Python "
          "(pip install bpy), or import the file in Blender (File > Import > Dancing Points take) or convert it "
          "with blender --background --command dancing_points convert")


def bpy_available() -> bool:
    """Whether this Python has the ``bpy`` module (only looks; never imports it)."""
    return importlib.util.find_spec("bpy") is not None


def take_arrays(take: Take) -> dict:
    """A take as the arrays :func:`take_from_arrays` reads back (the reader's output)."""
    return {"time": np.asarray(take.time, dtype=np.float64), "positions": np.asarray(take.positions, np.float64),
            "quats": np.asarray(take.quats, dtype=np.float64),
            "meta": np.array(json.dumps({k: v for k, v in take.meta.items()}, default=str))}


def take_from_arrays(arrays, source: str) -> Take:
    meta = json.loads(str(arrays["meta"]))
    return Take(np.asarray(arrays["time"], dtype=np.float64), np.asarray(arrays["positions"], dtype=np.float64),
                np.asarray(arrays["quats"], dtype=np.float64), meta, source)


def load_fbx(path, input_fps=None, role=None) -> Take:
    """The three points of an FBX file's rig as a :class:`Take` at the file's
    rate (``input_fps`` overrides it), read by Blender's importer in a ``bpy``
    process; of several armatures, the one of ``role`` (``leader`` or
    ``follower``; None: the take's, else the leader's) as in Blender's
    *Import Dancing Points take*. :class:`InputError` (one line, naming the
    file) when it cannot be read, or when this Python has no ``bpy`` module."""
    path = os.fspath(path)
    if not bpy_available():
        raise InputError(path, NO_BPY)
    with tempfile.TemporaryDirectory(prefix="dp-fbx-") as tmp:
        out = os.path.join(tmp, "take.npz")
        cmd = [sys.executable, FBX_READER, os.path.abspath(path), out]
        if input_fps:
            cmd += ["--input-fps", repr(float(input_fps))]
        if role:
            cmd += ["--role", str(role)]
        env = dict(os.environ, PYTHONNOUSERSITE="1")
        res = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             env=env, text=True, errors="replace")
        if res.returncode != 0 or not os.path.isfile(out):
            lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error: ")]
            if lines:
                msg = lines[-1][len("error: "):]
                prefix = path + ": "
                raise InputError(path, msg[len(prefix):] if msg.startswith(prefix) else msg)
            tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
            raise InputError(path, f"Blender's FBX importer failed (exit status {res.returncode}: {tail})")
        with np.load(out, allow_pickle=False) as z:
            return take_from_arrays(z, path)
