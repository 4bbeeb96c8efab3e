"""The shipped networks: where they are, and one loader with one cache.

Every caller (the command line, the batch workers, the Blender operators, the
benchmark, training's evaluation) gets its networks from :func:`load_nets`; a
process loads a folder of models once per thread count.
"""
from __future__ import annotations

import json
import os
import threading

import numpy as np

from .errors import InputError, UserError
from .skeleton import LOWER_BODY

MODEL_ENV = "DP_MODEL_DIR"  # environment variable naming a folder of models
MODEL_DIR = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "models"))
# For a follower's take (role reversal: her three points in, his motion out) the networks on
# the mapping's input are those of this sub-folder of a models folder (same file names, trained
# with the roles exchanged); the trackers are each dancer's own and serve both roles: the
# tracked slot ("leader") takes her tracker, the partner slot ("follower") his.
ROLE_DIRS = {"leader": "", "follower": "follower"}
TRACKERS = ("leader", "follower")
# How the int8 networks multiply: "float", their 8-bit weights dequantized and multiplied in float32
# (``onnx_float``: the output a smooth function of the input, so 2 µm on a tracked point moves no
# joint by more than a fraction of a millimetre), or "int8", as the files say (ONNX Runtime
# quantises each layer's input to int8: about half the networks' time, but 2 µm of input can
# change a frame's output by a millimetre and the rest of the take by centimetres)
COMPUTE_MODES = ("float", "int8")
DEFAULT_COMPUTE = "float"
MODEL_FILES = {"mapping": "mapping.onnx", "placement": "placement.onnx", "contacts": "contacts.onnx",
               "anchor": "pose_anchor.onnx", "hip": "hip_heading.onnx", "leader": "tracker_leader.onnx",
               "follower": "tracker_follower.onnx"}


def meta_json(net, key):
    """A network's JSON metadata entry ``key`` (None when missing or malformed)."""
    v = (getattr(net, "meta", {}) or {}).get(key)
    if v is None:
        return None
    try:
        return json.loads(v)
    except (TypeError, ValueError):
        return None


def default_pose(net) -> np.ndarray:
    """A tracker's start-up pose, a pose feature vector (its ``default_pose`` metadata)."""
    meta = getattr(net, "meta", {}) or {}
    if "default_pose" not in meta:
        raise ValueError(f"model {getattr(net, 'path', net)} has no default_pose metadata")
    return np.asarray(json.loads(meta["default_pose"]), dtype=np.float64)


def contact_floor_levels(meta: dict):
    """The contact network's floor levels from its metadata, ``{"leader": [4 floats],
    "follower": [4 floats]}`` (metres, training scale), or None when they are
    missing or malformed."""
    import json

    try:
        levels = json.loads(meta["floor_levels"])
        out = {r: [float(v) for v in levels[r]] for r in ("leader", "follower")}
    except (ValueError, TypeError, KeyError):
        return None
    return out if all(len(v) == 4 for v in out.values()) else None


class ModelError(UserError):
    """The networks cannot be loaded (one user-facing line)."""


class OnnxNet:
    """One ONNX network on onnxruntime's CPU provider, batch 1; ``compute``: see
    :data:`COMPUTE_MODES` (a network without 8-bit weights runs as it is)."""

    def __init__(self, path: str, threads: int = 1, compute: str = DEFAULT_COMPUTE):
        import onnxruntime as ort  # imported lazily: the core stays importable without it

        if compute not in COMPUTE_MODES:
            raise ValueError(f"compute must be one of {COMPUTE_MODES}, not {compute!r}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.path = path
        self.compute = compute
        model = path
        if compute == "float":
            from .onnx_float import float_compute

            with open(path, "rb") as f:
                model = float_compute(f.read())
        self.session = ort.InferenceSession(model, sess_options=opts, providers=["CPUExecutionProvider"])
        self.meta = dict(self.session.get_modelmeta().custom_metadata_map)
        self.input = self.session.get_inputs()[0].name
        self.output = self.session.get_outputs()[0].name
        # batch 1 (the frame loop): preallocated, bound input and output buffers
        # (io binding skips the per-call feed/fetch conversions, ~10 µs a run)
        n_in, n_out = self.session.get_inputs()[0].shape[1], self.session.get_outputs()[0].shape[1]
        self._one = None
        if isinstance(n_in, int) and isinstance(n_out, int):
            self._x1 = np.zeros((1, n_in), dtype=np.float32)
            self._y1 = np.zeros((1, n_out), dtype=np.float32)
            self._one = self.session.io_binding()
            self._one.bind_ortvalue_input(self.input, ort.OrtValue.ortvalue_from_numpy(self._x1))
            self._one.bind_ortvalue_output(self.output, ort.OrtValue.ortvalue_from_numpy(self._y1))
            self._run_options = ort.RunOptions()
            self._lock = threading.Lock()

    def __call__(self, x: np.ndarray) -> np.ndarray:
        # the bound buffers serve one caller at a time (the add-on may run two
        # syntheses on threads with the same nets): the other takes session.run
        if self._one is not None and x.shape == self._x1.shape and self._lock.acquire(blocking=False):
            try:
                self._x1[...] = x
                self.session.run_with_iobinding(self._one, self._run_options)
                return self._y1.copy()
            finally:
                self._lock.release()
        return self.session.run([self.output], {self.input: np.ascontiguousarray(x, dtype=np.float32)})[0]


def resolve_model_dir(explicit=None, role: str = "leader") -> str:
    """The models folder: ``explicit`` > ``$DP_MODEL_DIR`` > the bundled ``models/``;
    an :class:`InputError` naming it when a network file is missing (for a
    follower's take, also in its sub-folder :data:`ROLE_DIRS`)."""
    d = explicit or os.environ.get(MODEL_ENV, "") or MODEL_DIR
    d = os.path.abspath(os.path.expanduser(d))
    paths = model_paths(d, role)
    missing = [os.path.relpath(p, d) for p in paths.values() if not os.path.isfile(p)]
    if missing:
        what = "synthesis models" if role == "leader" else f"models for a {role}'s take"
        raise InputError(d, f"no {what} here (missing {', '.join(missing)})")
    return d


def model_paths(d: str, role: str = "leader") -> dict:
    """``{kind: path}`` of the networks of a models folder ``d`` for takes of ``role``."""
    if role == "leader":
        return {k: os.path.join(d, f) for k, f in MODEL_FILES.items()}
    paths = {k: os.path.join(d, ROLE_DIRS[role], f) for k, f in MODEL_FILES.items() if k not in TRACKERS}
    paths.update(leader=os.path.join(d, MODEL_FILES["follower"]), follower=os.path.join(d, MODEL_FILES["leader"]))
    return paths


def _load_one(path: str, threads: int, compute: str) -> OnnxNet:
    try:
        return OnnxNet(path, threads, compute)
    except ImportError:
        raise ModelError("onnxruntime is not installed in this Python") from None
    except Exception:  # noqa: BLE001 - a damaged or foreign file: one line naming it
        size = os.path.getsize(path)
        what = "an empty file" if size == 0 else "damaged or not an ONNX model"
        raise ModelError(f"{path}: ONNX Runtime cannot load this network ({what})") from None


_CACHE: dict = {}
_CACHE_LOCK = threading.Lock()


def load_nets(model_dir=None, threads: int = 1, role: str = "leader", compute: str | None = None) -> dict:
    """``{kind: OnnxNet}`` for every kind of :data:`MODEL_FILES` of a models folder (see
    :func:`resolve_model_dir`; ``role``: whose three points the takes hold),
    loaded once per process, role, thread count and ``compute``
    (:data:`COMPUTE_MODES`; None: :data:`DEFAULT_COMPUTE`), and again when a
    file changes. :class:`ModelError` when they cannot be loaded."""
    d = resolve_model_dir(model_dir, role)
    compute = DEFAULT_COMPUTE if compute is None else compute
    if compute not in COMPUTE_MODES:
        raise ValueError(f"compute must be one of {COMPUTE_MODES}, not {compute!r}")
    paths = model_paths(d, role)
    key = (d, role, max(1, int(threads)), compute, tuple(os.path.getmtime(p) for p in paths.values()))
    with _CACHE_LOCK:
        nets = _CACHE.get(key)
        if nets is None:
            nets = {k: _load_one(p, key[2], compute) for k, p in paths.items()}
            while len(_CACHE) >= len(ROLE_DIRS):  # a folder's two roles at a time
                _CACHE.pop(next(iter(_CACHE)))
            _CACHE[key] = nets
        return nets


def check_models(model_dir=None, threads: int = 1, role: str = "leader") -> str:
    """Check a models folder once, before any work (the command line and the batch
    call it at start-up): the seven files exist, load in ONNX Runtime, take and
    give the sizes of this version's feature layout (``features.layout``) and
    carry the metadata the runtime needs. Returns the folder; a
    :class:`UserError` (one line, naming the folder or file) otherwise."""
    import json

    from . import features as F

    nets = load_nets(model_dir, threads, role)
    d = resolve_model_dir(model_dir, role)
    paths = model_paths(d, role)
    want = F.layout()
    ins = {"leader": "track_in", "follower": "track_in"}
    sizes = {k: (want[ins.get(k, "map_in")], None) for k in MODEL_FILES}
    for kind, net in nets.items():
        path = paths[kind]
        try:
            layout = json.loads(net.meta.get("layout", "null"))
        except ValueError:
            layout = None
        if not isinstance(layout, dict):
            raise ModelError(f"{path}: not a Dancing Points model (no feature layout in its metadata)")
        for key in ("fps", "past", "future", "track_keys", "map_in", "map_out", "track_in", "key_out", "pose_dim"):
            if layout.get(key) != want[key]:
                raise ModelError(f"{path}: made for another feature layout ({key} {layout.get(key)!r}, "
                                 f"this version needs {want[key]!r})")
        n_in = net.session.get_inputs()[0].shape[-1]
        if isinstance(n_in, int) and n_in != sizes[kind][0]:
            raise ModelError(f"{path}: takes {n_in} inputs, the {kind} network needs {sizes[kind][0]}")
        if kind in ("leader", "follower") and "default_pose" not in net.meta:
            raise ModelError(f"{path}: no default_pose in its metadata")
        if kind == "contacts":
            n_out = net.session.get_outputs()[0].shape[-1]
            if isinstance(n_out, int) and n_out != 8:
                raise ModelError(f"{path}: gives {n_out} outputs, the contact network needs 8")
            if contact_floor_levels(net.meta) is None:
                raise ModelError(f"{path}: no floor_levels (four numbers per dancer) in its metadata")
        if kind in ("mapping", "placement"):
            n_out = net.session.get_outputs()[0].shape[-1]
            if isinstance(n_out, int) and n_out != want["map_out"]:
                raise ModelError(f"{path}: gives {n_out} outputs, the {kind} network needs {want['map_out']}")
        if kind == "anchor":
            n_out = net.session.get_outputs()[0].shape[-1]
            if isinstance(n_out, int) and n_out != 3 * len(LOWER_BODY):
                raise ModelError(f"{path}: gives {n_out} outputs, the pose anchor needs {3 * len(LOWER_BODY)}")
        if kind == "hip":
            from .partner_pose import HIP_BINS

            n_out = net.session.get_outputs()[0].shape[-1]
            if isinstance(n_out, int) and n_out != HIP_BINS:
                raise ModelError(f"{path}: gives {n_out} outputs, the hip-heading network needs {HIP_BINS}")
    return d
