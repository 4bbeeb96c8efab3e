"""Role reversal (SPEC §3 ``role=follower``): the follower wears the headset,
she is tracked and the leader is synthesised, by the networks trained with the
roles exchanged (``models/follower/``); the outputs keep their dance roles."""
import numpy as np
import pytest

from conftest import SALSA
from dancing_points_addon import features as F
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.take import Take, take_from_motion, write_take
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.nets import MODEL_DIR, ROLE_DIRS, check_models
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import PARENTS, TRACKED, Motion
from support.helpers import run_cli
from training.dataset import split_range


def follower_take(take_no="10"):
    """The follower's test frames of a salsa take as a ``role=follower`` take,
    and both dancers' 30 Hz ground truth (her, him)."""
    her = load_amc(SALSA / f"61_{take_no}.amc")
    him = load_amc(SALSA / f"60_{take_no}.amc")
    a, _ = split_range(her.n_frames, "test")
    m = Motion(her.positions[2 * a:], her.rotations[2 * a:], her.fps, her.bone_vectors)
    take = take_from_motion(m)
    take.time = take.time - take.time[0]
    take.meta["role"] = "follower"
    n = (take.n_frames + 1) // 2
    return take, her.positions[::2][a:a + n], him.positions[::2][a:a + n]


follower_take.__test__ = False


@pytest.fixture(scope="module")
def reversed10():
    take, her, him = follower_take("10")
    return take, her, him, Synthesizer().synthesize(take)


def test_the_follower_is_tracked_and_the_leader_synthesised(reversed10):
    take, her, him, duet = reversed10
    assert duet.tracked_role == "follower" and duet.calibration.role == "follower"
    n = min(len(her), duet.n_frames)
    score = np.arange(n) >= F.FPS
    track = np.linalg.norm(duet.follower_positions[:n, TRACKED] - her[:n, TRACKED], axis=-1).mean(-1)[score]
    body = np.linalg.norm(duet.follower_positions[:n] - her[:n], axis=-1).mean(-1)[score]
    his = np.linalg.norm(duet.leader_positions[:n] - him[:n], axis=-1).mean(-1)[score]
    print(f"\nreversed take 10: her tracking {track.mean() * 100:.2f} cm, her body {body.mean() * 100:.2f} cm, "
          f"his body {his.mean() * 100:.1f} cm")
    assert track.mean() < 0.015 and body.mean() < 0.14
    assert np.isfinite(duet.leader_positions).all() and his.mean() < 0.8
    # each dancer on their own skeleton: her bones hers (shorter), his his
    lengths = {r: np.linalg.norm(duet.bone_vectors[r], axis=-1).sum() for r in ("leader", "follower")}
    assert lengths["follower"] < lengths["leader"]
    # the same take read as the leader's gives her points a leader's body and a synthesised follower
    fwd = Synthesizer().synthesize(Take(take.time, take.positions, take.quats, {}))
    assert fwd.tracked_role == "leader"
    assert np.linalg.norm(fwd.leader_positions[:n, TRACKED] - her[:n, TRACKED], axis=-1).mean() < 0.03


def test_role_option_overrides_the_take(reversed10):
    take, *_ = reversed10
    plain = Take(take.time, take.positions, take.quats, {})
    duet = Synthesizer(SynthesisOptions(role="follower")).synthesize(plain)
    assert duet.tracked_role == "follower"
    assert np.array_equal(duet.follower_positions, reversed10[3].follower_positions)
    # one synthesizer serves both roles, take after take
    s = Synthesizer()
    assert s.synthesize(plain).tracked_role == "leader" and s.synthesize(take).tracked_role == "follower"


def test_unknown_role_is_refused_with_file_and_line(tmp_path):
    take, *_ = follower_take("10")
    path = tmp_path / "t.csv"
    write_take(path, take)
    text = path.read_text().replace("# role=follower", "# role=partner")
    path.write_text(text)
    with pytest.raises(InputError, match=r"t\.csv:\d+: unknown role 'partner'"):
        read_take(path)


def test_synthesize_cli_names_files_by_dance_role(tmp_path):
    take, *_ = follower_take("10")
    path = tmp_path / "hers.csv"
    write_take(path, Take(take.time, take.positions, take.quats, {}))
    res = run_cli("synthesize", str(path), "-o", str(tmp_path / "d.npz"), "--role", "follower")
    assert res.returncode == 0, res.stderr
    assert "follower tracked" in res.stdout
    z = np.load(tmp_path / "d.npz")
    assert str(z["tracked_role"]) == "follower"
    res = run_cli("synthesize", str(path), "-o", str(tmp_path / "d.bvh"), "--role", "follower")
    assert res.returncode == 0, res.stderr
    # her BVH is the tracked dancer's: its head joint on her points
    from dancing_points_addon.formats.bvh import load_bvh
    her = load_bvh(tmp_path / "d_follower.bvh")
    assert np.abs(her.positions[:, TRACKED[0]] - z["follower_positions"][:, TRACKED[0]]).max() < 1e-3


def test_the_follower_models_are_shipped_and_checked():
    """The networks on the mapping's input for her takes are models/follower/'s
    (trained with the roles exchanged); the trackers are each dancer's own."""
    import os

    from dancing_points_addon.nets import load_nets

    assert check_models(role="follower") == MODEL_DIR
    nets = load_nets(role="follower")
    assert os.path.dirname(nets["mapping"].path) == os.path.join(MODEL_DIR, ROLE_DIRS["follower"])
    assert nets["leader"].path == os.path.join(MODEL_DIR, "tracker_follower.onnx")  # hers, in the tracked slot
    assert nets["follower"].path == os.path.join(MODEL_DIR, "tracker_leader.onnx")
    assert '"tracked_role": "follower"' in nets["mapping"].meta.get("train", "") or \
        nets["mapping"].meta.get("tracked_role") == "follower"


def test_each_dancers_skeleton_whoever_is_tracked():
    """A dancer's skeleton by dance role is the same whichever dancer the take
    tracks (Blender's *Live* builds its two rigs from it before the first
    frame): the synthesizer's own slots are the tracked dancer and the partner."""
    lead, fol = Synthesizer(), Synthesizer(SynthesisOptions(role="follower"))
    a, b = lead.role_bone_vectors(), fol.role_bone_vectors()
    assert set(a) == set(b) == {"leader", "follower"}
    for role in a:
        np.testing.assert_array_equal(a[role], b[role])
    assert not np.allclose(a["leader"], a["follower"])  # two different bodies
    np.testing.assert_array_equal(fol.bone_vectors["tracked"], a["follower"])


def test_five_minute_follower_take_stays_together():
    """A 5-minute continuous take of the follower (salsa take 61_01 played forth
    and back at 60 Hz, role=follower): the synthesised leader within 3 m of her
    (pelvis, horizontally) in every frame, her pelvis within 0.5 m of her head,
    every value finite (what the leader's takes must meet too)."""
    take = take_from_motion(load_amc(SALSA / "61_01.amc"))
    n = take.n_frames
    idx = np.concatenate([np.arange(n), np.arange(n - 2, 0, -1)])
    idx = np.tile(idx, 5 * 60 * 60 // len(idx) + 1)[:5 * 60 * 60]
    long = Take(np.arange(len(idx)) / 60.0, take.positions[idx], take.quats[idx], {"role": "follower"})
    duet = Synthesizer().synthesize(long)
    lp, fp = duet.leader_positions, duet.follower_positions
    assert duet.tracked_role == "follower" and np.isfinite(lp).all() and np.isfinite(fp).all()
    apart = np.linalg.norm((fp[:, 0] - lp[:, 0])[:, [0, 2]], axis=-1)
    head = long.positions[::2][:len(fp), 0]
    off = np.linalg.norm((fp[:, 0] - head)[:, [0, 2]], axis=-1)
    print(f"\nleader-follower max {apart.max():.2f} m (last minute {apart[-1800:].max():.2f}); "
          f"her pelvis-head max {off.max():.2f} m")
    assert apart.max() < 3.0 and off.max() < 0.5


def test_his_output_is_low_passed_his_state_not(reversed10):
    """A follower's take: the synthesised leader's output keeps a share of the
    last frame (``PoseOptions.out_smooth``, by his dance role), on his own
    skeleton, without moving his tracker's state or her; her partner in a
    leader's take is not smoothed."""
    from dancing_points_addon.follower import OUT_SMOOTH, FollowerOptions, PoseOptions

    take, her, him, duet = reversed10
    assert OUT_SMOOTH["leader"] > 0.0 and OUT_SMOOTH["follower"] == 0.0
    raw = Synthesizer(follower=FollowerOptions(pose=PoseOptions(out_smooth=0.0))).synthesize(take)
    np.testing.assert_array_equal(raw.follower_positions, duet.follower_positions)  # her, tracked: untouched

    def jerk(p):
        return np.linalg.norm(np.diff(p, n=3, axis=0), axis=-1).mean() * F.FPS ** 3

    smooth, plain, truth = jerk(duet.leader_positions), jerk(raw.leader_positions), jerk(him)
    lag = np.linalg.norm(duet.leader_positions - raw.leader_positions, axis=-1).mean()
    print(f"\nhis jitter {plain:.0f} -> {smooth:.0f} m/s³ (truth {truth:.0f}); "
          f"the smoothing moved him {lag * 100:.2f} cm")
    assert smooth < 0.85 * plain and lag < 0.03
    bones = np.linalg.norm(duet.bone_vectors["leader"], axis=-1)[1:]
    pos = duet.leader_positions
    got = np.linalg.norm(pos[:, 1:] - pos[:, PARENTS[1:]], axis=-1)
    assert np.abs(got - bones).max() < 1e-6  # still his skeleton
    r = duet.leader_rotations
    assert np.abs(r @ np.swapaxes(r, -1, -2) - np.eye(3)).max() < 1e-9  # still rotations


def test_output_smoothing_keeps_a_still_pose_and_follows_a_moved_one(reversed10):
    from dancing_points_addon.pose import OutputSmoothing, bone_vectors_from_pose

    duet = reversed10[3]
    pos, rot = duet.leader_positions[40], duet.leader_rotations[40]
    vec = bone_vectors_from_pose(pos, rot)
    s = OutputSmoothing(0.3, vec)
    for _ in range(3):  # a pose that stays, stays exactly (a planted foot does not slide)
        p2, r2 = s(pos.copy(), rot.copy())
        np.testing.assert_allclose(p2, pos, atol=1e-9)
        np.testing.assert_allclose(r2, rot, atol=1e-9)
    moved = pos + np.array([0.1, 0.0, 0.0])
    steps = [float(s(moved.copy(), rot.copy())[0][0, 0] - pos[0, 0]) for _ in range(12)]
    assert 0.065 < steps[0] < 0.075 and steps[-1] > 0.0999 and all(np.diff(steps) >= 0)  # 70 % at once, then there
    assert OutputSmoothing(0.0, vec)(pos, rot)[0] is pos
    with pytest.raises(ValueError, match="within 0..1"):
        OutputSmoothing(1.0, vec)
