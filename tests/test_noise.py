"""Micrometres of tracker noise change the duet by micrometres.

The shipped networks hold 8-bit weights; ONNX Runtime's ``MatMulNBits`` would
also quantise every layer's input to int8, which makes each network a step
function of its input: 2 µm on the tracked points turned into millimetres on
the first frame and, through the trackers' feedback, the foot lock's steps and
her holds, into centimetres (up to 20 cm of a leg). The runtime multiplies the
same weights in float32 (``nets.DEFAULT_COMPUTE``, ``onnx_float``), rewritten
in memory from the files.

* ``onnx_float.float_compute`` is exactly ``training.export.dequantize_int8``
  (the ``onnx`` package's rewrite) on every shipped network;
* 2 µm of Gaussian noise on every tracked position of each SPEC §6 test take
  (the leader's test frames of all 13 salsa takes as a take): every joint of
  both dancers stays within 1 cm of the clean run (float compute), where the
  int8 compute moves one by centimetres.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from conftest import MODELS

from dancing_points_addon.nets import MODEL_FILES, OnnxNet, load_nets
from dancing_points_addon.onnx_float import OnnxRewriteError, float_compute
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions

SIGMA = 2e-6  # m


def test_float_compute_is_the_onnx_packages_rewrite():
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from training.export import dequantize_int8

    rng = np.random.default_rng(0)
    for kind, name in MODEL_FILES.items():
        path = os.path.join(MODELS, name)
        with open(path, "rb") as f:
            data = f.read()
        ours = float_compute(data)
        m = onnx.load_from_string(ours)
        ops = {n.op_type for n in m.graph.node}
        assert "MatMulNBits" not in ops and "MatMul" in ops, (kind, ops)
        assert {p.key: p.value for p in m.metadata_props} == {
            p.key: p.value for p in onnx.load(path).metadata_props}  # the metadata kept
        ref = dequantize_int8(onnx.load(path)).SerializeToString()
        a = ort.InferenceSession(ours, providers=["CPUExecutionProvider"])
        b = ort.InferenceSession(ref, providers=["CPUExecutionProvider"])
        q = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
        x = rng.normal(size=(3, a.get_inputs()[0].shape[1])).astype(np.float32)
        feed = {a.get_inputs()[0].name: x}
        ya, yb, yq = (s.run(None, feed)[0] for s in (a, b, q))
        np.testing.assert_array_equal(ya, yb)
        assert np.abs(ya - yq).max() < 0.1 * (np.abs(yq).max() + 1e-3)  # the same network, int8 compute aside
        # rewritten once: nothing left to rewrite
        assert float_compute(ours) == ours
    with pytest.raises(OnnxRewriteError):
        float_compute(b"\x3a\xff\xff")  # a graph field longer than the file


def test_the_runtime_multiplies_in_float():
    nets = load_nets(MODELS)
    assert {n.compute for n in nets.values()} == {"float"}
    # a tiny change of the input is a tiny change of the output (no quantisation step)
    rng = np.random.default_rng(1)
    for kind in ("mapping", "contacts", "leader"):
        net = nets[kind]
        n_in = net.session.get_inputs()[0].shape[1]
        x = rng.normal(size=(1, n_in)).astype(np.float32)
        int8 = OnnxNet(net.path, compute="int8")
        steps_f, steps_q = [], []
        for _ in range(10):
            x2 = x + rng.normal(scale=1e-5, size=x.shape).astype(np.float32)
            steps_f.append(np.abs(net(x2) - net(x)).max())
            steps_q.append(np.abs(int8(x2) - int8(x)).max())
        print(f"\n{kind}: 1e-5 on the input moves the output by {max(steps_f):.2e} (float), "
              f"{max(steps_q):.2e} (int8 compute)")
        assert max(steps_f) < 2e-4


def _noise_runs(salsa_dir, tmp_path, compute, takes=None, draws=1):
    from training.dataset import SALSA_TAKES
    from training.evaluate import segment_take, test_segments

    nets = load_nets(MODELS, compute=compute)
    rng = np.random.default_rng(38)
    worst = {}
    for seg in test_segments(str(salsa_dir), takes or SALSA_TAKES):
        take = segment_take(seg, str(tmp_path))
        clean = Synthesizer(SynthesisOptions(models=MODELS), nets=nets).synthesize(take)
        for _ in range(draws):
            noisy = type(take)(take.time, take.positions + rng.normal(0.0, SIGMA, take.positions.shape),
                               take.quats, take.meta, take.source)
            out = Synthesizer(SynthesisOptions(models=MODELS), nets=nets).synthesize(noisy)
            for role in ("leader", "follower"):
                d = np.linalg.norm(getattr(clean, f"{role}_positions") - getattr(out, f"{role}_positions"),
                                   axis=-1)
                worst[(seg["take"], role)] = max(worst.get((seg["take"], role), 0.0), float(d.max()))
    return worst


def test_two_micrometres_of_noise_move_no_joint_a_centimetre(salsa_dir, tmp_path):
    worst = _noise_runs(salsa_dir, tmp_path, "float", draws=2)
    for role in ("leader", "follower"):
        w = {t: d for (t, r), d in worst.items() if r == role}
        t = max(w, key=w.get)
        print(f"\n2 µm noise, 13 test takes × 2 draws, {role}: largest joint change {100 * w[t]:.3f} cm (take {t})")
    assert max(worst.values()) < 0.01


@pytest.mark.eval
def test_the_int8_compute_is_what_flipped(salsa_dir, tmp_path):
    # the same noise through the int8 compute: millimetres on every take, centimetres on some
    worst = _noise_runs(salsa_dir, tmp_path, "int8", takes=("02", "06", "07"))
    print("\nint8 compute, 2 µm noise: "
          + ", ".join(f"{t} {r} {100 * d:.2f} cm" for (t, r), d in sorted(worst.items())))
    assert max(worst.values()) > 0.02
