"""Export trained networks to ONNX with their feature layout as metadata.

The contact network (``contacts.onnx``) is exported whole, its probabilities
(sigmoid) in the graph; so are the pose anchor (``pose_anchor.onnx``) and the
hip-heading network (``hip_heading.onnx``, its bins' probabilities: softmax).

The exported tracker is the inference path only (estimator -> decoder) and
computes only the outputs the runtime reads: the first future key (the next
frame); its last layer is the trained one with the other keys' rows dropped,
so ONNX and PyTorch agree on every kept output. The mapping network keeps its
whole future second; so does the placement network (``placement.onnx``, the
mapping's shape, of which the runtime reads the follower's roots).

Re-export from the training checkpoints (no retraining):

    python -m training.export --checkpoints cache/checkpoints --out models

Weights are int8 (symmetric, blocks of 32 input weights), run by
onnxruntime's ``MatMulNBits``, which also quantises each layer's input; the
runtime multiplies the same weight values in float32 instead
(``dancing_points_addon.onnx_float``, of which :func:`dequantize_int8` is the
reference, written with the ``onnx`` package).
"""
from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import onnx
import torch
from torch import nn

from dancing_points_addon import features as F
from dancing_points_addon.skeleton import JOINT_NAMES

OPSET = 17
WEIGHTS = ("int8", "fp32")
INT8_BLOCK = 32
INT8_WEIGHTS = f"int8, symmetric, blocks of {INT8_BLOCK} (MatMulNBits, accuracy level 4: int8 compute)"


def tracker_keep() -> np.ndarray:
    return np.arange(F.KEY_OUT)  # key 1 = TRACK_KEYS[0]


WHOLE_FUTURE = ("mapping", "placement")  # the kinds exported with all their future frames (mapping_keep)


def mapping_keep() -> np.ndarray:
    return np.arange(F.MAP_OUT)  # all 30 future frames: the runtime picks its keys


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=os.path.dirname(os.path.abspath(__file__)), check=True).stdout.strip()
    except Exception:
        return "unknown"


def _rewrite(m: onnx.ModelProto, op_type: str, rewrite) -> onnx.ModelProto:
    """Replace every ``op_type`` node of ``m`` by the nodes ``rewrite(node,
    attributes, initializers)`` returns (it may add initializers); drop the
    initializers no node reads any more."""
    from onnx import helper

    inits = {i.name: i for i in m.graph.initializer}
    nodes = []
    for n in m.graph.node:
        if n.op_type != op_type:
            nodes.append(n)
            continue
        nodes.extend(rewrite(n, {x.name: helper.get_attribute_value(x) for x in n.attribute}, inits))
    del m.graph.node[:]
    m.graph.node.extend(nodes)
    used = {i for n in m.graph.node for i in n.input}
    keep = [i for i in m.graph.initializer if i.name in used]
    del m.graph.initializer[:]
    m.graph.initializer.extend(keep)
    return m


def gemm_to_matmul(m: onnx.ModelProto) -> onnx.ModelProto:
    """Rewrite every ``Gemm`` (alpha = beta = 1, transA = 0) as ``MatMul`` + ``Add``
    with the weight stored input-major: the form the MatMulNBits quantiser reads."""
    from onnx import helper, numpy_helper

    def rewrite(n, a, inits):
        if a.get("alpha", 1.0) != 1.0 or a.get("beta", 1.0) != 1.0 or a.get("transA", 0):
            raise ValueError(f"unsupported Gemm {n.name}")
        w = numpy_helper.to_array(inits[n.input[1]])
        w = w.T if a.get("transB", 0) else w
        m.graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(w), n.input[1] + "_in_out"))
        mid = n.output[0] + "_mm"
        return [helper.make_node("MatMul", [n.input[0], n.input[1] + "_in_out"], [mid], name=n.name + "_mm"),
                helper.make_node("Add", [mid, n.input[2]], [n.output[0]], name=n.name + "_bias")]

    return _rewrite(m, "Gemm", rewrite)


def quantize_int8(m: onnx.ModelProto) -> onnx.ModelProto:
    """int8 quantisation of every Linear layer's weights: symmetric, one scale
    per block of ``INT8_BLOCK`` input weights (onnxruntime's ``MatMulNBits``;
    accuracy level 4 also quantises the layer input per block at run time and
    multiplies in int8). At batch 1 the networks are memory-bound: a quarter of
    the weight bytes nearly halves their run time in the frame loop, and the
    closed-loop figures stay within noise of float32 (models/README.md)."""
    import logging

    from onnxruntime.quantization import matmul_nbits_quantizer as mq

    logging.getLogger(mq.__name__).setLevel(logging.WARNING)  # one INFO line per node otherwise
    cfg = mq.DefaultWeightOnlyQuantConfig(block_size=INT8_BLOCK, is_symmetric=True, accuracy_level=4, bits=8)
    q = mq.MatMulNBitsQuantizer(gemm_to_matmul(m), algo_config=cfg)
    q.process()
    return q.model.model


def dequantize_int8(m: onnx.ModelProto) -> onnx.ModelProto:
    """Every 8-bit ``MatMulNBits`` as a float32 ``MatMul`` of its dequantized
    weights: the same weight values, but the layer input is no longer
    quantised at run time (onnxruntime 1.22 has no float-compute path for 8-bit
    blocks). Symmetric blocks only (no zero-point input: 128 is the zero)."""
    from onnx import helper, numpy_helper

    def rewrite(n, a, inits):
        if a["bits"] != 8 or (len(n.input) > 3 and n.input[3]):
            raise ValueError(f"{n.name}: only symmetric 8-bit blocks are dequantized")
        k, cols = a["K"], a["N"]
        q = numpy_helper.to_array(inits[n.input[1]]).astype(np.float32)  # (N, blocks, block bytes)
        scale = numpy_helper.to_array(inits[n.input[2]]).astype(np.float32).reshape(cols, -1)
        w = ((q - 128.0) * scale[:, :, None]).reshape(cols, -1)[:, :k].T  # (K, N), input-major
        name = n.input[1] + "_float"
        m.graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(w), name))
        if len(n.input) > 5 and n.input[5]:  # a bias input
            mid = n.output[0] + "_mm"
            return [helper.make_node("MatMul", [n.input[0], name], [mid], name=n.name + "_float"),
                    helper.make_node("Add", [mid, n.input[5]], [n.output[0]], name=n.name + "_bias")]
        return [helper.make_node("MatMul", [n.input[0], name], [n.output[0]], name=n.name + "_float")]

    return _rewrite(m, "MatMulNBits", rewrite)


def export(model: nn.Module, kind: str, path: str, n_in: int, extra: dict | None = None,
           weights: str = "int8"):
    """Write ``model`` (eval mode, CPU) as ONNX at ``path`` atomically; ``weights``:
    "int8" (quantised weights, int8 compute: what ships) or "fp32" (the exact graph)."""
    if weights not in WEIGHTS:
        raise ValueError(f"weights must be one of {WEIGHTS}")
    keep = tracker_keep() if kind.startswith("tracker") else mapping_keep() if kind in WHOLE_FUTURE else None
    wrapped = model.cpu().eval().truncated(keep)
    dummy = torch.zeros(1, n_in)
    tmp = path + ".tmp"
    torch.onnx.export(wrapped, (dummy,), tmp, input_names=["x"], output_names=["y"],
                      dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}}, opset_version=OPSET,
                      dynamo=False)
    m = onnx.load(tmp)
    if weights == "int8":
        m = quantize_int8(m)
    meta = {
        "kind": kind,
        "layout": json.dumps(F.layout()),
        "fps": str(F.FPS),
        "past_frames": str(F.PAST),
        "future_frames": str(F.FUTURE),
        "output_keys": json.dumps([1] if kind.startswith("tracker") else list(range(1, F.FUTURE + 1))
                                  if kind in WHOLE_FUTURE else [0]),
        "skeleton": json.dumps(list(JOINT_NAMES)),
        "data_split": "CMU salsa takes 01-13 at 30 Hz, frames [0, floor(0.8*n30)) of each take (SPEC §5); "
                      "mirror augmented",
        "git_commit": git_commit(),
        "weights": "float32" if weights == "fp32" else INT8_WEIGHTS,
    }
    meta.update({k: (v if isinstance(v, str) else json.dumps(v)) for k, v in (extra or {}).items()})
    del m.metadata_props[:]
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(m, tmp)
    os.replace(tmp, path)
    return path


def main(argv=None):
    import argparse

    from .model import ContactNet, HipHeadingNet, MappingNet, PoseAnchorNet, TrackingNet, VanillaTracker

    ap = argparse.ArgumentParser(prog="python -m training.export", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", default="cache/checkpoints")
    ap.add_argument("--out", default="models")
    ap.add_argument("--names", default="mapping,placement,contacts,pose_anchor,hip_heading,tracker_leader,"
                                       "tracker_follower",
                    help="checkpoints to export (e.g. vanilla_leader,pastinput_follower for the ablations)")
    ap.add_argument("--weights", choices=WEIGHTS, default="int8",
                    help="int8: weights stored as 8-bit blocks (shipped; the runtime multiplies them in float32); "
                         "fp32: the exact float graph")
    ap.add_argument("--default-pose-from", default=None, metavar="DATA",
                    help="recompute the trackers' start-up pose from this data's unmirrored train split")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    report = {}
    rp = os.path.join(args.out, "training_report.json")
    if os.path.exists(rp):
        with open(rp) as f:
            report = json.load(f).get("models", {})
    clips = None
    for name in args.names.split(","):
        ck = torch.load(os.path.join(args.checkpoints, f"{name}.pt"), weights_only=False)
        meta = dict(ck["meta"])
        if name in WHOLE_FUTURE:
            m, n_in, kind = MappingNet(F.MAP_IN, F.MAP_OUT, meta["hidden"]), F.MAP_IN, name
        elif name == "contacts":
            m, n_in, kind = ContactNet(F.MAP_IN, hidden=meta["hidden"], layers=meta["layers"]), F.MAP_IN, "contacts"
        elif name == "pose_anchor":
            m, n_in, kind = PoseAnchorNet(F.MAP_IN, hidden=meta["hidden"], layers=meta["layers"]), F.MAP_IN, "anchor"
        elif name == "hip_heading":
            m, n_in, kind = HipHeadingNet(F.MAP_IN, hidden=meta["hidden"], layers=meta["layers"]), F.MAP_IN, \
                "hip_heading"
        else:
            role = meta.get("role") or name.rsplit("_", 1)[1]
            cls = VanillaTracker if meta.get("ablation") == "a" else TrackingNet
            m, n_in, kind = cls(F.TRACK_IN, F.TRACK_OUT, meta["hidden"], pose_dim=F.POSE_DIM), F.TRACK_IN, \
                f"tracker_{role}"
            meta["role"] = role
            if args.default_pose_from:
                from training.dataset import load_clips

                from .data import default_pose, tracking_samples

                clips = clips or load_clips(args.default_pose_from, "train", mirror_aug=True)
                x, _, where = tracking_samples(clips, role, past_input=meta.get("ablation") == "b")
                meta["default_pose"] = default_pose(x, where, clips)
                ck["meta"] = meta
                torch.save(ck, os.path.join(args.checkpoints, f"{name}.pt"))
        m.load_state_dict(ck["state_dict"])
        if name in report:
            meta["train"] = report[name]
        print("exported", export(m, kind, os.path.join(args.out, f"{name}.onnx"), n_in, meta, args.weights))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
