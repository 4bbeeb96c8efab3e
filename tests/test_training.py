"""Training side: a tiny configuration trains, exports ONNX, and onnxruntime agrees
with PyTorch; the training samples never reach a test frame."""
import json

import numpy as np
import onnx
from onnx import numpy_helper
import onnxruntime as ort
import pytest
import torch

from dancing_points_addon import features as F
from dancing_points_addon.partner_pose import HIP_BINS
from dancing_points_addon.skeleton import LOWER_BODY
from training.dataset import build_clips, split_range
from training import train as T
from training.data import (anchor_samples, contact_samples, default_pose, floor_levels_of, hip_heading_samples,
                           mapping_samples, time_reverse, tracking_samples)
from training.export import dequantize_int8, export, mapping_keep, tracker_keep
from training.model import ContactNet, HipHeadingNet, MappingNet, PoseAnchorNet, TrackingNet, VanillaTracker


@pytest.fixture(scope="module")
def clips(salsa_dir):
    return build_clips(salsa_dir, "train", mirror_aug=True)


@pytest.mark.parametrize("kind", ["mapping", "placement", "contacts", "anchor", "hip", "tracker", "vanilla"])
def test_tiny_train_export_onnx_matches_torch(clips, tmp_path, kind):
    torch.manual_seed(0)
    if kind == "mapping":
        x, y = mapping_samples(clips[:2])
        model, n_in, keep, name = MappingNet(F.MAP_IN, F.MAP_OUT, 32), F.MAP_IN, mapping_keep(), "mapping"
    elif kind == "contacts":
        x, y = contact_samples(clips[:2])
        assert y.shape[1] == 8 and set(np.unique(y)) <= {0.0, 1.0}
        model, n_in, keep, name = ContactNet(F.MAP_IN, 8, 32), F.MAP_IN, slice(None), "contacts"
    elif kind == "anchor":
        x, y = anchor_samples(clips[:2])
        assert y.shape[1] == 3 * len(LOWER_BODY) and np.abs(y[:, :3:2]).max() < 0.2  # hip joints beside the pelvis
        model, n_in, keep, name = PoseAnchorNet(F.MAP_IN, y.shape[1], 32), F.MAP_IN, slice(None), "pose_anchor"
    elif kind == "hip":
        x, y = hip_heading_samples(clips[:2])
        assert y.shape[1] == HIP_BINS and np.array_equal(y.sum(1), np.ones(len(y)))  # one bin per frame
        model, n_in, keep, name = HipHeadingNet(F.MAP_IN, HIP_BINS, 32), F.MAP_IN, slice(None), "hip_heading"
    elif kind == "placement":  # the mapping's network, also on the clips played backwards
        x, y = mapping_samples(clips[:2])
        xr, yr = mapping_samples(time_reverse(clips[:2]))
        w = np.ones((512, 2, len(MappingNet.GROUPS)), dtype=np.float32)
        w[256:] = T.REVERSE_WEIGHTS
        x, y = np.concatenate([x[:256], xr[:256]]), np.concatenate([y[:256], yr[:256]])
        model, n_in, keep, name = (MappingNet(F.MAP_IN, F.MAP_OUT, 32, loss="norm"), F.MAP_IN, mapping_keep(),
                                   "placement")
    else:
        x, y, _ = tracking_samples(clips[:2], "leader")
        cls = TrackingNet if kind == "tracker" else VanillaTracker
        model = cls(F.TRACK_IN, F.TRACK_OUT, 32, pose_dim=F.POSE_DIM)
        n_in, keep, name = F.TRACK_IN, tracker_keep(), "tracker_leader"
    if kind == "placement":
        info = T.train_model(model, x, y, epochs=2, batch=64, w=w)
    else:
        info = T.train_model(model, x[:512], y[:512], epochs=2, batch=64)
    assert np.isfinite(info["final"][{"contacts": "bce", "hip": "ce"}.get(kind, "rec")])
    path = str(tmp_path / f"{name}.onnx")
    extra = {"default_pose": default_pose(x)} if kind in ("tracker", "vanilla") else None
    if kind == "contacts":
        extra = {"floor_levels": {r: floor_levels_of(clips[:2], r) for r in ("leader", "follower")}}
    export(model, name, path, n_in, extra, weights="fp32")
    m = onnx.load(path)
    onnx.checker.check_model(m)
    assert m.opset_import[0].version >= 17
    meta = {p.key: p.value for p in m.metadata_props}
    assert json.loads(meta["layout"])["track_in"] == F.TRACK_IN
    assert "git_commit" in meta and "data_split" in meta and len(json.loads(meta["skeleton"])) == 31
    if kind in ("mapping", "placement"):  # the whole future second, as the runtime splices it
        assert meta["kind"] == kind and json.loads(meta["output_keys"]) == list(range(1, F.FUTURE + 1))
    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    xb = x[:16]
    got = sess.run(None, {"x": xb})[0]
    with torch.no_grad():
        want = model(torch.from_numpy(xb)).numpy()[:, keep]
    assert got.shape == want.shape
    err = np.abs(got - want).max()
    print(f"\n{kind}: onnxruntime vs torch max |diff| = {err:.2e}")
    assert err < 1e-4

    # the shipped form: int8 weight-only quantised, same metadata, close to float32
    qpath = str(tmp_path / f"{name}_int8.onnx")
    export(model, name, qpath, n_in, extra)
    qm = onnx.load(qpath)
    onnx.checker.check_model(qm)
    assert {n.op_type for n in qm.graph.node} & {"MatMulNBits"} and "Gemm" not in {n.op_type for n in qm.graph.node}
    qmeta = {p.key: p.value for p in qm.metadata_props}
    assert qmeta["weights"].startswith("int8") and qmeta["layout"] == meta["layout"]
    assert sum(t.raw_data.__len__() for t in qm.graph.initializer) < 0.4 * sum(
        t.raw_data.__len__() for t in m.graph.initializer)
    qgot = ort.InferenceSession(qpath, providers=["CPUExecutionProvider"]).run(None, {"x": xb})[0]
    rel = np.abs(qgot - want).max() / np.abs(want).max()
    print(f"{kind}: int8 vs torch max |diff| / max |y| = {rel:.2e}")
    assert rel < 0.01
    if kind == "mapping":
        _check_float_compute(tmp_path, qpath, xb, want, m)


def test_tracker_losses_route_gradients_as_documented(clips):
    """The tracker's losses: L_matching (squared distance of the latents) trains
    the encoder and the estimator, not the decoder; L_rec is the squared error
    of the decoded latent. Checked on real leader samples."""
    x, y, _ = tracking_samples(clips[:2], "leader")
    xb, yb = torch.from_numpy(x[:64]), torch.from_numpy(y[:64])

    torch.manual_seed(0)
    m = TrackingNet(F.TRACK_IN, F.TRACK_OUT, 32, pose_dim=F.POSE_DIM)
    m.fit_normalizers(xb, yb)
    m.eval()  # no dropout or noise: the same forward pass for every term
    m.zero_grad()
    xn, yn = m.nx.norm(xb), m.ny.norm(yb - m._base(xb))
    m._loss(xn, yn)["match"].backward()
    g = {k: float(sum(p.grad.abs().sum() for p in getattr(m, k).parameters() if p.grad is not None))
         for k in ("encoder", "estimator", "decoder")}
    assert g["encoder"] > 0 and g["estimator"] > 0 and g["decoder"] == 0
    with torch.no_grad():
        z_e = m._latent(m.encoder(torch.cat([xn, yn], dim=-1)))
        z_s = m._latent(m.estimator(xn))
        d = m._decode(z_e, xn) - yn
        losses = m._loss(xn, yn)
    torch.testing.assert_close(losses["rec"], (d ** 2).mean())
    torch.testing.assert_close(losses["match"], ((z_e - z_s) ** 2).sum(-1).mean())


def test_mapping_norm_loss_measures_each_point_per_frame():
    """The mapping's norm loss (the shipped recipe) takes the Euclidean length
    of each frame's root position, heading and three tracked points per
    dancer, unsquared, and averages them: an error of (3, 4) normalised units
    in one root position, or of (0, 3, 4) in one tracked point, counts 5 over
    the 60 × 5 groups; spread over two groups it counts each part's own
    length."""
    m = MappingNet(F.MAP_IN, F.MAP_OUT, 8, loss="norm")
    groups = 2 * F.FUTURE * 5
    yn = torch.zeros(1, F.MAP_OUT)
    for where in ([0, 1], [F.ROOT_DIM + 3 + 1, F.ROOT_DIM + 3 + 2]):  # a root position, the second point
        d = torch.zeros(1, F.MAP_OUT)
        d[0, [F.FRAME_DIM * 7 + w for w in where]] = torch.tensor([3.0, 4.0])
        assert m.map_loss(d, yn).item() == pytest.approx(5.0 / groups, abs=1e-5)
    d = torch.zeros(1, F.MAP_OUT)
    d[0, [F.FRAME_DIM * 7 + 1, F.FRAME_DIM * 7 + 2]] = torch.tensor([3.0, 4.0])  # root z and heading cos
    assert m.map_loss(d, yn).item() == pytest.approx(7.0 / groups, abs=1e-5)
    # the squared error (the pose anchor's): (9 + 16) / outputs
    assert MappingNet(F.MAP_IN, F.MAP_OUT, 8, loss="mse").map_loss(d, yn).item() == pytest.approx(25.0 / F.MAP_OUT)
    with pytest.raises(ValueError):
        MappingNet(F.MAP_IN, 30, 8, loss="norm")


def test_mapping_loss_weighs_dancers_and_groups():
    """Per-sample weights of the mapping's norm loss (the placement network's
    recipe: on the clips played backwards only her outputs count): per dancer
    ``(B, 2)`` or per dancer and group ``(B, 2, 5)``; a weight of 0 leaves that
    part out, and the mean is over what counts. All ones is the unweighted
    loss; the squared error takes no weights."""
    torch.manual_seed(0)
    m = MappingNet(F.MAP_IN, F.MAP_OUT, 8, loss="norm")
    pred, yn = torch.randn(4, F.MAP_OUT), torch.randn(4, F.MAP_OUT)
    assert m.map_loss(pred, yn, torch.ones(4, 2)).item() == pytest.approx(m.map_loss(pred, yn).item(), rel=1e-6)
    d = torch.zeros(1, F.MAP_OUT)
    d[0, [F.FRAME_DIM * 7 + 0, F.FRAME_DIM * 7 + 1]] = torch.tensor([3.0, 4.0])  # her root position, frame 4
    zero = torch.zeros(1, F.MAP_OUT)
    w = torch.tensor([[1.0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0]])[None]  # root positions only
    d[0, F.FRAME_DIM * 6] = 12.0  # his root x, frame 4: counts
    assert m.map_loss(d, zero, w).item() == pytest.approx((5.0 + 12.0) / (2 * F.FUTURE), abs=1e-5)
    d[0, F.FRAME_DIM * 6 + 5] = 10.0  # his first point, frame 4: left out
    d[0, F.FRAME_DIM * 7 + 2] = 10.0  # her heading: left out
    assert m.map_loss(d, zero, w).item() == pytest.approx((5.0 + 12.0) / (2 * F.FUTURE), abs=1e-5)
    assert m.map_loss(d, zero, torch.tensor([[0.0, 1.0]])).item() == pytest.approx(
        (5.0 + 10.0) / (F.FUTURE * 5), abs=1e-5)  # all her groups: her position (5) and heading (10) count
    w = torch.tensor(T.REVERSE_WEIGHTS, dtype=torch.float32)[None]  # the placement network's: all hers
    assert m.map_loss(d, zero, w).item() == pytest.approx((5.0 + 10.0) / (F.FUTURE * 5), abs=1e-5)
    assert m.map_loss(pred, yn, torch.ones(4, 2, 5)).item() == pytest.approx(m.map_loss(pred, yn).item(), rel=1e-6)
    with pytest.raises(ValueError, match="norm loss"):
        MappingNet(F.MAP_IN, F.MAP_OUT, 8, loss="mse").map_loss(pred, yn, torch.ones(4, 2))


def test_training_samples_stay_inside_train_frames(salsa_dir, clips):
    """Every sample's future window ends inside its clip, and each clip holds exactly
    the train frames of its take, so no test frame reaches training or normalisation."""
    for c in clips:
        n = c.n_frames
        take = c.name[:2]
        n60 = {"01": 2242, "02": 2101, "03": 1830, "04": 1871, "05": 1678, "06": 1772, "07": 2071,
               "08": 3421, "09": 2575, "10": 1197, "11": 2108, "12": 1690, "13": 2271}[take]
        assert n == split_range(n60, "train")[1]
    x, y = mapping_samples(clips)
    assert len(x) == sum(c.n_frames - F.FUTURE for c in clips)
    xt, yt, _ = tracking_samples(clips, "follower")
    assert len(xt) == len(x) and xt.shape[1] == F.TRACK_IN and yt.shape[1] == F.TRACK_OUT


def test_fit_and_val_cut_the_train_frames_only():
    """The recipe-selection splits: "fit" then "val" tile exactly the train frames
    of every take, so choosing a recipe on "val" never touches a test frame."""
    for n60 in (2242, 2101, 1197, 3421, 1):
        a, b = split_range(n60, "train")
        fa, fb = split_range(n60, "fit")
        va, vb = split_range(n60, "val")
        assert (fa, fb, vb) == (a, va, b) and fa <= fb <= vb
        assert vb <= split_range(n60, "test")[0]


def _check_float_compute(tmp_path, qpath, xb, want, float_model):
    """The runtime's float compute (``onnx_float``, whose reference is
    ``export.dequantize_int8``): the same int8 weight values, multiplied in
    float32; its output as close to the float network's as the int8 compute's."""
    path = str(tmp_path / "float_compute.onnx")
    fm = dequantize_int8(onnx.load(qpath))
    onnx.checker.check_model(fm)
    onnx.save(fm, path)
    ops = {n.op_type for n in fm.graph.node}
    assert "MatMulNBits" not in ops and "MatMul" in ops
    # the same int8 weight values: in every block of 32 input weights, integer multiples
    # of the block's scale (its largest magnitude / 128); the float network's are not
    for W in [numpy_helper.to_array(t) for t in fm.graph.initializer if t.name.endswith("_float")]:
        blocks = W[:W.shape[0] // 32 * 32].reshape(-1, 32, W.shape[1])
        steps = blocks / np.maximum(np.abs(blocks).max(1, keepdims=True) / 128.0, 1e-30)
        assert np.abs(steps - np.round(steps)).max() < 1e-3
    fb = [numpy_helper.to_array(t) for t in float_model.graph.initializer if t.name.endswith("weight")][0][:, :32]
    fsteps = fb / (np.abs(fb).max(1, keepdims=True) / 128.0)
    assert np.abs(fsteps - np.round(fsteps)).max() > 0.1
    got = ort.InferenceSession(path, providers=["CPUExecutionProvider"]).run(None, {"x": xb})[0]
    rel = np.abs(got - want).max() / np.abs(want).max()
    print(f"mapping, int8 weights multiplied in float32 vs torch: {rel:.2e}")
    assert rel < 0.01


def test_train_command_trains_and_reexports_the_placement_network(salsa_dir, tmp_path):
    """``python -m training.train --only placement`` (tiny configuration, fit
    split; the shipped recipe, which ``models/placement.onnx`` is): only
    ``placement.onnx`` and the report are written, with its kind and the
    backwards recipe in its training figures and a note of what the runtime
    reads; its checkpoint re-exports through ``training.export`` to the same
    network and metadata."""
    import onnx as _onnx

    from training import export as X

    out, cache, again = tmp_path / "m", tmp_path / "cache", tmp_path / "again"
    assert T.main(["--data", str(salsa_dir), "--config", "tiny", "--only", "placement",
                   "--split", "fit", "--out", str(out), "--cache", str(cache)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["placement.onnx", "training_report.json"]
    report = json.loads((out / "training_report.json").read_text())
    assert set(report["models"]) == {"placement"} and report["overrides"] == {}
    assert report["models"]["placement"]["reverse"] == "follower" and report["models"]["placement"]["loss"] == "norm"
    meta = {p.key: p.value for p in _onnx.load(str(out / "placement.onnx")).metadata_props}
    assert meta["kind"] == "placement" and "follower's roots" in meta["outputs"]
    assert json.loads(meta["output_keys"]) == list(range(1, F.FUTURE + 1))
    assert X.main(["--checkpoints", str(cache / "checkpoints"), "--out", str(again), "--names", "placement"]) == 0
    meta2 = {p.key: p.value for p in _onnx.load(str(again / "placement.onnx")).metadata_props}
    assert meta2["kind"] == "placement" and meta2["outputs"] == meta["outputs"]
    x = np.random.default_rng(0).standard_normal((4, F.MAP_IN)).astype(np.float32)
    a, b = (ort.InferenceSession(str(d / "placement.onnx"), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
            for d in (out, again))
    assert a.shape == (4, F.MAP_OUT) and np.allclose(a, b, atol=1e-5)


def test_solo_clips_hold_the_trackers_takes_only():
    """SPEC §5: the trackers may learn from solo takes 05_01-05_10 and never from
    05_11-05_20. Each 120 Hz take gives its four 30 Hz phases; fit and val tile
    the take; no split reaches a held-out take."""
    from conftest import SOLO
    from training.dataset import SOLO_HELD_OUT, solo_clips

    fit, val = solo_clips(SOLO, "fit", mirror_aug=False), solo_clips(SOLO, "val", mirror_aug=False)
    train = solo_clips(SOLO, "train")
    takes = {c.name[:5] for c in train}
    assert takes == {f"05_{i:02d}" for i in range(1, 11)} and not takes & set(SOLO_HELD_OUT)
    assert len(train) == 2 * len(takes) * 4 and all(c.follower is None for c in train)
    checked = 0
    for take in takes:  # the four phases of fit hold the first 80 % of the 120 Hz frames, val the rest
        n120 = sum(c.n_frames for c in train if c.name.startswith(take) and not c.mirrored)
        n_fit = sum(c.n_frames for c in fit if c.name.startswith(take))
        assert n_fit == int(np.floor(0.8 * n120))
        assert all(c.n_frames > F.FUTURE for c in val)  # a phase too short for a sample is left out
        phases = [c for c in val if c.name.startswith(take)]
        if len(phases) == 4:  # all four kept: val holds the rest of the take
            assert sum(c.n_frames for c in phases) == n120 - n_fit
            checked += 1
    assert checked >= 5
    for split in ("test", "held-out"):
        with pytest.raises(ValueError, match="held out"):
            solo_clips(SOLO, split)


def test_body_clips_bring_every_body_to_the_training_head_and_reshape_within_the_spread(clips):
    """A tracker of several bodies learns each at the runtime's scale (its
    upright head at the training leader's) and from body-shape copies whose
    bones keep one length through the clip, within the spread of the source's."""
    from dancing_points_addon.skeleton import bone_lengths_from_positions
    from training.data import body_clips, head_height, reshape_body

    few = clips[:4]
    his = head_height(c.leader.positions for c in few)
    out, n_first = body_clips(few, None, ("follower", "leader"), his, np.random.default_rng(1), 0.08, 1)
    assert len(out) == 2 * 2 * len(few) and n_first == len(few)
    bodies = [out[:len(few)], out[len(few):2 * len(few)]]
    for body in bodies:
        assert abs(head_height(c.leader.positions for c in body) - his) < 1e-9
    src = few[0].follower
    assert np.allclose(reshape_body(src.positions, src.rotations, np.ones(31)), src.positions, atol=1e-9)
    copy, orig = out[2 * len(few)], out[0]
    lc, lo = bone_lengths_from_positions(copy.leader.positions), bone_lengths_from_positions(orig.leader.positions)
    assert np.ptp(lc[:, 1:], axis=0).max() < 1e-6  # rigid: one length per bone through the clip
    ratio = lc[0, 1:] / lo[0, 1:]
    ratio /= np.median(ratio)  # the copy is scaled back to the head height as a whole
    assert 1.01 < ratio.max() / ratio.min() < 1.08 / 0.92 + 1e-6  # each group within 1 ± 0.08, not all alike
    assert abs(head_height([copy.leader.positions]) - his) < 1e-9


def test_solo_segments_are_the_held_out_takes_at_their_own_rate(salsa_dir):
    """SPEC §6 "on unseen dancers": the held-out solo takes whole at 120 Hz,
    scored against every 4th frame; val is the end of the trackers' takes."""
    from conftest import SOLO
    from training.evaluate import solo_segments

    test = list(solo_segments(SOLO, "test", salsa_dir))
    assert [s["take"] for s in test] == [f"05_{i:02d}" for i in range(11, 21)]
    s = test[0]
    assert s["lead60"].fps == 120.0 and len(s["lead"][0]) == (s["lead60"].n_frames + 3) // 4
    assert np.array_equal(s["lead"][0][1], s["lead60"].positions[4])
    val = list(solo_segments(SOLO, "val", salsa_dir))
    assert [s["take"] for s in val] == [f"05_{i:02d}" for i in range(1, 11)]
    with pytest.raises(ValueError):
        list(solo_segments(SOLO, "train"))
