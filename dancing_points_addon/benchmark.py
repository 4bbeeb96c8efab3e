"""Latency of the frame-by-frame loop, per character-frame, against a compute floor.

    python -m dancing_points_addon benchmark [--frames 2000] [--threads 1]

Runs the product loop (:class:`~.runtime.Synthesizer`, batch 1) over the
embedded sample take, repeated to the frame count, timing every frame and
splitting it into the networks (every ONNX run), pose recovery (rigid
pose, foot locking, optional IK) and features (everything else: input
cleaning, feature building, decoding). A duet frame holds two characters, so
per character-frame = frame time / 2.

The compute floor is the bare matrix–vector products of the same weights in
numpy on the same machine (one float32 ``W @ x`` per Linear layer of the seven
networks, no activations; int8 layers dequantised): what the networks'
arithmetic costs at the least in plain float32. It is timed in blocks between
the loop's blocks, so both see the same machine (a shared machine's speed
drifts by 2× within minutes). The command runs numpy's BLAS on one thread
(``OPENBLAS_NUM_THREADS=1`` … unless set), like onnxruntime.
"""
from __future__ import annotations

import os
import time

import numpy as np

from .nets import MODEL_FILES, load_nets, resolve_model_dir
from .runtime import Synthesizer
from .synthesis_options import SynthesisOptions

SAMPLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "samples", "sample_take.csv")


class _Timed:
    """Wraps a network and adds its run time to a shared clock."""

    def __init__(self, net, clock):
        self.net, self.clock = net, clock
        self.meta = getattr(net, "meta", {})
        self.path = getattr(net, "path", "")

    def __call__(self, x):
        t = time.perf_counter()
        y = self.net(x)
        self.clock[0] += time.perf_counter() - t
        return y


class _TimedSynth(Synthesizer):
    def __init__(self, *a, clocks=None, **k):
        self._clocks = clocks
        super().__init__(*a, **k)

    def _recover(self, stage, pos, rot, contacts, targets):
        t = time.perf_counter()
        out = super()._recover(stage, pos, rot, contacts, targets)
        self._clocks["recovery"][0] += time.perf_counter() - t
        return out


def onnx_weights(path):
    """The Linear layers' weights of an ONNX file as float32 ``(out, in)`` matrices,
    in graph order (needs ``onnx``): float initializers as they are, int8
    ``MatMulNBits`` layers dequantised (blockwise ``(q - zero) · scale``)."""
    import onnx
    from onnx import helper, numpy_helper

    m = onnx.load(path)
    inits = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    mats = []
    for n in m.graph.node:
        if n.op_type == "MatMulNBits":
            a = {x.name: helper.get_attribute_value(x) for x in n.attribute}
            if a.get("bits", 4) != 8 or (len(n.input) > 3 and n.input[3]):
                raise ValueError(f"{path}: {n.name}: only symmetric 8-bit MatMulNBits layers are read")
            N, K, bs = a["N"], a["K"], a["block_size"]
            q = inits[n.input[1]].reshape(N, -1, bs).astype(np.float32)
            scale = inits[n.input[2]].reshape(N, -1, 1).astype(np.float32)
            zero = 2.0 ** (a["bits"] - 1)  # symmetric: zero point in the middle of the range
            mats.append(((q - zero) * scale).reshape(N, -1)[:, :K])
        elif n.op_type in ("Gemm", "MatMul"):
            w = inits.get(n.input[1])
            if w is not None and w.ndim == 2 and min(w.shape) > 1:
                transposed = n.op_type == "MatMul" or not any(
                    x.name == "transB" and helper.get_attribute_value(x) for x in n.attribute)
                mats.append((w.T if transposed else w).astype(np.float32))
    return mats


class _Floor:
    """The bare mat-vec products of all seven networks' weights (the mapping, the
    placement network, the contact network, the pose anchor and the hip-heading network once, each
    tracker once), timed one duet
    frame at a time."""

    def __init__(self, model_dir):
        self.chain = [np.ascontiguousarray(w) for f in MODEL_FILES.values()
                      for w in onnx_weights(os.path.join(model_dir, f))]
        rng = np.random.default_rng(0)
        self.xs = [rng.standard_normal(w.shape[1], dtype=np.float32) for w in self.chain]
        self.macs = sum(w.size for w in self.chain)
        self.time(10)  # warm up

    def time(self, repeats):
        times = np.empty(repeats)
        for r in range(repeats):
            t = time.perf_counter()
            for w, x in zip(self.chain, self.xs):
                w @ x
            times[r] = time.perf_counter() - t
        return times


def run(frames=2000, threads=1, model_dir=None, take_path=SAMPLE, foot_lock=True, hand_ik=True, blocks=10,
        compute=None):
    """Time ``frames`` duet frames of the loop and as many passes of the compute
    floor, interleaved in ``blocks`` (a shared machine's speed drifts: the ratio
    compares the two under the same conditions)."""
    from .resample import resample_take
    from .formats.take_read import read_take

    model_dir = resolve_model_dir(model_dir)
    clocks = {"networks": [0.0], "recovery": [0.0]}
    nets = {k: _Timed(net, clocks["networks"]) for k, net in load_nets(model_dir, threads, compute=compute).items()}
    synth = _TimedSynth(SynthesisOptions(foot_lock=foot_lock, hand_ik=hand_ik), nets=nets, clocks=clocks)
    take = resample_take(read_take(take_path))
    valid = take.valid
    floor = _Floor(model_dir)
    total, net_t, rec_t = (np.empty(frames) for _ in range(3))
    floor_t = []
    warm = 60
    k = -1
    per_block = -(-frames // max(1, int(blocks)))
    i = -warm
    while i < frames:
        end = min(i + per_block, frames) if i >= 0 else 0
        while i < end:
            k = (k + 1) % take.n_frames
            if k == 0:
                synth.reset()
            clocks["networks"][0] = clocks["recovery"][0] = 0.0
            t = time.perf_counter()
            synth.step(take.positions[k], take.quats[k], valid[k])
            dt = time.perf_counter() - t
            if i >= 0:
                total[i], net_t[i], rec_t[i] = dt, clocks["networks"][0], clocks["recovery"][0]
            i += 1
        if i > 0:
            floor_t.append(floor.time(per_block))
    floor_s = float(np.median(np.concatenate(floor_t)))
    per = {name: arr / 2.0 * 1000.0 for name, arr in
           (("total", total), ("networks", net_t), ("recovery", rec_t), ("features", total - net_t - rec_t))}
    return {"frames": frames, "threads": threads, "compute": next(iter(nets.values())).net.compute,
            "median_ms": {k: float(np.median(v)) for k, v in per.items()},
            "p99_ms": {k: float(np.percentile(v, 99)) for k, v in per.items()},
            "floor_ms": floor_s / 2.0 * 1000.0, "macs_per_frame": floor.macs,
            "ratio_to_floor": float(np.median(per["total"]) / (floor_s / 2.0 * 1000.0))}


def report(res) -> str:
    lines = [f"latency per character-frame over {res['frames']} duet frames, batch 1, "
             f"{res['threads']} onnxruntime thread(s), networks multiplied in {res['compute']}:",
             f"  {'':12s} {'median':>9s} {'p99':>9s}"]
    for k in ("total", "features", "networks", "recovery"):
        lines.append(f"  {k:12s} {res['median_ms'][k]:8.3f}ms {res['p99_ms'][k]:8.3f}ms")
    lines.append(f"  compute floor (bare numpy float32 mat-vec of the same weights, one thread, "
                 f"{res['macs_per_frame'] / 1e6:.2f} M MACs per duet frame, timed between the loop's blocks): "
                 f"{res['floor_ms']:.3f} ms per character-frame")
    lines.append(f"  ratio total / floor: {res['ratio_to_floor']:.1f}x")
    return "\n".join(lines)
