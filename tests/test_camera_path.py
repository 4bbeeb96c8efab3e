"""The follow camera's maths (``dancing_points_addon.camera_path``, no bpy):
on the sample take's duet, and on the same duet made hard to frame (a jump
across the floor, the follower stepping far out), every frame keeps both
dancers whole in the frame, at least 55 % of its height, centred in the
middle fifth, with a bounded acceleration."""
import numpy as np
import pytest

from conftest import MODELS, ROOT
from dancing_points_addon import blender_math as bm
from dancing_points_addon import camera_path as cp
from dancing_points_addon.inputs import load_input
from dancing_points_addon.resample import resample_take
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import JOINT_NAMES

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
FOV = 2 * np.arctan(18.0 / 35.0)  # a 35 mm lens on the 36 mm sensor (the DP Camera)
ASPECT = 16 / 9
FOOT = [JOINT_NAMES.index(n) for n in ("lfoot", "ltoes", "rfoot", "rtoes")]


@pytest.fixture(scope="module")
def duet():
    take = resample_take(load_input(str(SAMPLE)), 30.0)
    return Synthesizer(SynthesisOptions(models=MODELS, foot_lock=True)).synthesize(take)


def _points(lead, foll):
    return bm.to_blender(np.concatenate([lead, foll], axis=1))


def _view(lead):
    v = bm.to_blender(bm.hip_forward(lead[0]))
    c, s = np.cos(np.deg2rad(60.0)), np.sin(np.deg2rad(60.0))
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], 0.0])


def _check(points, path, fps=30.0):
    """The acceptance constraints on every frame, with the core's projection
    (independent of what follow_camera reports about itself)."""
    ndc, depth = cp.project(points, path.locations, path.rotations, FOV, ASPECT)
    assert (depth > 0.5).all()
    x, y = ndc[..., 0], ndc[..., 1]
    assert np.abs(ndc).max() <= 1.0, "a joint outside the frame"
    fill = (y.max(1) - y.min(1)) / 2
    centre = (x.max(1) + x.min(1)) / 2
    assert fill.min() >= 0.55, fill.min()
    assert np.abs(centre).max() <= 0.2, np.abs(centre).max()  # the middle fifth: |x| <= 1/5 of the half width
    acc = np.diff(path.locations, 2, axis=0) * fps ** 2
    return fill, centre, float(np.linalg.norm(acc, axis=1).max())


def test_follow_camera_on_the_sample_duet(duet):
    pts = _points(duet.leader_positions, duet.follower_positions)
    path = cp.follow_camera(pts, FOV, ASPECT, _view(duet.leader_positions), 30.0)
    fill, centre, acc = _check(pts, path)
    print(f"\nsample duet: fill {fill.min():.3f}..{fill.max():.3f}, |centre| <= {np.abs(centre).max():.3f}, "
          f"max accel {acc:.2f} m/s², max speed {path.max_speed:.2f} m/s, {path.iterations} pass(es)")
    assert acc == pytest.approx(path.max_accel)
    assert acc < 1.0  # m/s²: a smooth dolly, no jerks
    assert path.sigma == pytest.approx(30.0)  # the full smoothing (1 s) held
    # the rotation is fixed (a dolly, no pan), orthonormal, the camera above the couple looking down a little
    R = path.rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert R[2, 2] > 0 and R[2, 2] < 0.3  # camera z (back) points slightly up: it looks slightly down


def hidden_share(lead, foll, path):
    """The share of frames in which less than half of the farther dancer's
    projected box (the bounding box of his or her bones in the image, through
    the path's perspective camera) is uncovered by the nearer dancer's box."""
    boxes, depth = [], []
    for pts in (lead, foll):
        ndc, d = cp.project(pts, path.locations, path.rotations, FOV, ASPECT)
        boxes.append(np.concatenate([ndc.min(1), ndc.max(1)], axis=1))  # x0, y0, x1, y1
        depth.append(d.mean(1))
    far_is_f = depth[1] > depth[0]
    near = np.where(far_is_f[:, None], boxes[0], boxes[1])
    far = np.where(far_is_f[:, None], boxes[1], boxes[0])
    ox = np.clip(np.minimum(near[:, 2], far[:, 2]) - np.maximum(near[:, 0], far[:, 0]), 0, None)
    oy = np.clip(np.minimum(near[:, 3], far[:, 3]) - np.maximum(near[:, 1], far[:, 1]), 0, None)
    uncovered = 1.0 - ox * oy / ((far[:, 2] - far[:, 0]) * (far[:, 3] - far[:, 1]))
    return float(np.mean(uncovered < 0.5))


def _turn_rate(path, fps=30.0):
    """The camera's largest angular speed (deg/s), from its rotations (the angle between frames)."""
    R = path.rotations
    rel = np.einsum("tji,tjk->tik", R[:-1], R[1:])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.rad2deg(np.arccos(cos)).max() * fps)


@pytest.fixture(scope="module")
def test_take_duet(salsa_dir, tmp_path_factory):
    """The duet of salsa take 03's test frames (SPEC §6, as a take)."""
    from training.evaluate import segment_take, test_segments

    seg = next(test_segments(str(salsa_dir), ("03",)))
    take = segment_take(seg, str(tmp_path_factory.mktemp("take03")))
    return Synthesizer(SynthesisOptions(models=MODELS, foot_lock=True)).synthesize(take)


@pytest.mark.parametrize("which", ["sample", "take 03"])
def test_the_camera_turns_so_neither_dancer_hides_the_other(duet, test_take_duet, which):
    """The view direction turns slowly (at most 60°/s, bounded angular
    acceleration) so that the farther dancer is mostly in sight: in at most 40 %
    of the frames is less than half of the farther dancer's box uncovered (a
    view fixed at the leader's first facing + 60°: 83 % on the sample, 60 % on
    take 03). The framing holds on every frame as with a fixed view."""
    d = duet if which == "sample" else test_take_duet
    lead, foll = bm.to_blender(d.leader_positions), bm.to_blender(d.follower_positions)
    pts = np.concatenate([lead, foll], axis=1)
    fixed = cp.follow_camera(pts, FOV, ASPECT, _view(d.leader_positions), 30.0)
    sides = cp.visible_directions(lead, foll, _view(d.leader_positions), 30.0)
    path = cp.follow_camera(pts, FOV, ASPECT, sides, 30.0)
    fill, centre, acc = _check(pts, path)
    before, after = hidden_share(lead, foll, fixed), hidden_share(lead, foll, path)
    rate = _turn_rate(path)
    print(f"\n{which}: the farther dancer mostly hidden in {100 * after:.1f} % of the frames ({100 * before:.1f} % "
          f"with the fixed view); turns at most {rate:.1f}°/s (reported {path.max_turn_rate:.1f}, angular "
          f"acceleration {path.max_turn_accel:.1f}°/s²); fill {fill.min():.3f}..{fill.max():.3f}, |centre| <= "
          f"{np.abs(centre).max():.3f}, max accel {acc:.2f} m/s²")
    assert after <= 0.40 and after < before - 0.2
    assert rate <= 60.0 and path.max_turn_rate == pytest.approx(rate, rel=0.02, abs=0.2)
    assert path.max_turn_accel <= 60.0
    assert acc < 1.0  # m/s²: the camera still glides
    R = path.rotations
    np.testing.assert_allclose(np.einsum("tji,tjk->tik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert (R[:, 2, 2] > 0).all() and (R[:, 2, 2] < 0.3).all()  # always looking slightly down, never rolled
    np.testing.assert_allclose(R[:, 2, 0], 0.0, atol=1e-12)  # the image's x axis stays horizontal


def test_visible_directions_keep_the_view_when_nothing_hides():
    """Two dancers far apart side by side (never in each other's way): the
    camera keeps the view it was given and does not turn."""
    T = 90
    lead = np.zeros((T, 4, 3))  # a box 0.5 m wide (x and y), 1.7 m tall
    lead[:, :, :2] = [[-0.25, -0.25], [0.25, 0.25], [-0.25, 0.25], [0.25, -0.25]]
    lead[:, 1::2, 2] = 1.7
    foll = lead.copy()
    foll[:, :, 0] += 2.0
    sides = cp.visible_directions(lead, foll, (0.0, -1.0, 0.0), 30.0)
    np.testing.assert_allclose(sides, np.broadcast_to([0.0, -1.0, 0.0], sides.shape), atol=1e-9)
    # given a view along their line (one behind the other), it takes the nearest side from
    # which the farther one is in sight (60 % of the box uncovered), and stays there
    sides = cp.visible_directions(lead, foll, (1.0, 0.0, 0.0), 30.0)
    h = np.arctan2(sides[:, 1], sides[:, 0])
    assert 5.0 < np.rad2deg(abs(h[0])) < 30.0 and np.ptp(h) < 1e-9
    assert (cp.uncovered_shares(lead, foll, h[:1]) >= 0.6 - 1e-9).all()
    assert (cp.uncovered_shares(lead, foll, [0.0]) < 0.01).all()  # straight along the line: hidden


def test_follow_camera_corrects_hard_frames(duet):
    """The couple travelling 3 m in a second and the follower stepping 2.5 m out
    (in a second, back in the next): the smoothed wish breaks the constraints
    there, the correction passes restore them on every frame (smoothing over
    half a second at least), and the acceleration stays bounded."""
    lead = duet.leader_positions.copy()
    foll = duet.follower_positions.copy()
    T = len(lead)
    k = np.arange(T)
    travel = np.clip((k - T // 2) / 30.0, 0.0, 1.0) * 3.0
    out = np.clip(np.minimum(k - T // 4, T // 4 + 60 - k) / 30.0, 0.0, 1.0) * 2.5
    lead[:, :, 0] += travel[:, None]
    foll[:, :, 0] += (travel - out)[:, None]
    pts = _points(lead, foll)
    path = cp.follow_camera(pts, FOV, ASPECT, _view(lead), 30.0)
    assert path.iterations > 1 and path.sigma >= 15.0  # corrected, still smoothed over >= 0.5 s
    fill, centre, acc = _check(pts, path)
    print(f"\nhard duet: {path.iterations} passes, fill >= {fill.min():.3f}, |centre| <= "
          f"{np.abs(centre).max():.3f}, max accel {acc:.2f} m/s²")
    assert acc < 15.0


def test_follow_camera_keeps_the_frame_through_a_jump(duet):
    """A jump of 3 m in one frame (a tracking glitch) no smooth path can follow:
    the frame is kept anyway (the smoothing is reduced), and says so."""
    lead = duet.leader_positions.copy()
    foll = duet.follower_positions.copy()
    T = len(lead)
    lead[T // 2:, :, 0] += 3.0
    foll[T // 2:, :, 0] += 3.0
    pts = _points(lead, foll)
    path = cp.follow_camera(pts, FOV, ASPECT, _view(lead), 30.0)
    assert path.sigma < 15.0
    _check(pts, path)
    assert path.max_accel > 50.0  # reported: a cut, in effect


def test_follow_camera_handles_lost_frames_and_rejects_nothing(duet):
    pts = _points(duet.leader_positions, duet.follower_positions)
    pts[10:20] = np.nan  # frames with nothing known hold the last known ones
    path = cp.follow_camera(pts, FOV, ASPECT, _view(duet.leader_positions), 30.0)
    assert np.isfinite(path.locations).all()
    with pytest.raises(ValueError):
        cp.follow_camera(np.full((5, 4, 3), np.nan), FOV, ASPECT, (0, -1, 0))
    with pytest.raises(ValueError):
        cp.follow_camera(np.zeros((0, 4, 3)), FOV, ASPECT, (0, -1, 0))


def test_smooth_is_zero_phase_and_keeps_ends():
    x = np.zeros(200)
    x[100] = 1.0
    y = cp.smooth(x, 5.0)
    assert int(np.argmax(y)) == 100 and y.sum() == pytest.approx(1.0)  # no lag, nothing lost
    ramp = np.linspace(0.0, 1.0, 50)
    np.testing.assert_allclose(cp.smooth(ramp, 3.0)[20:30], ramp[20:30], atol=1e-12)  # a line stays a line


def test_interpolate_frames_and_floor(duet):
    vals = np.arange(5, dtype=float)[:, None] * np.array([1.0, 2.0])
    got = cp.interpolate_frames(vals, 1 + 0.8 * np.arange(5), np.array([1.0, 1.4, 4.2, 9.0]))
    np.testing.assert_allclose(got[:, 0], [0.0, 0.5, 4.0, 4.0])
    # the floor under the duet's feet: between the feet's lowest joints and a sole's thickness below them
    for pos in (duet.leader_positions, duet.follower_positions):
        low = pos[:, FOOT, 1].min(1)
        z = cp.floor_level(pos[:, FOOT, 1])
        assert np.percentile(low, 5) - 0.04 < z < np.median(low)
    verts, quads, parity = cp.checker_floor((-2.3, -1.0), (1.2, 0.5), 0.25)
    assert (verts[:, 2] == 0.25).all()
    assert verts[:, 0].min() == -3.0 and verts[:, 0].max() == 2.0 and verts[:, 1].max() == 1.0
    assert len(quads) == 5 * 2 and set(parity.tolist()) == {0, 1}
    centres = verts[quads].mean(1)
    # neighbouring squares differ
    for a in range(len(quads)):
        for b in range(len(quads)):
            if np.isclose(np.abs(centres[a, :2] - centres[b, :2]).sum(), 1.0):
                assert parity[a] != parity[b]
