"""Device orientations as the body means them: a turn given for devices in
another convention is taken off, orientations that carry nothing are not
followed (one line says so), on real CMU takes and the shipped models."""
import numpy as np
import pytest

from dancing_points_addon.calibration import ORIENTATION_SPEED_LIMIT, calibrate, headset_take, read_poses
from dancing_points_addon.duet import save_npz
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.devices import DeviceOffsets, DeviceTurns, mirror_turn, parse_turn
from dancing_points_addon.inputs import HAND_BONES
from dancing_points_addon.formats.take import Take, write_take
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.rotations import matrix_to_quat, quat_to_matrix
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from support.helpers import run_cli
from test_runtime import test_take

SECONDS = 5.0


def turned(quats, turns):
    """``quats (T, 3, 4)`` reported by devices turned by ``turns`` (3 quaternions or None): ``q · turn``."""
    R = quat_to_matrix(quats)
    for d, t in enumerate(turns):
        if t is not None:
            R[:, d] = R[:, d] @ quat_to_matrix(np.asarray(t))
    return matrix_to_quat(R)


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def copy_take(take, quats=None, positions=None, **meta):
    return Take(take.time.copy(), take.positions.copy() if positions is None else positions,
                take.quats.copy() if quats is None else quats, {**take.meta, **meta}, take.source)


@pytest.fixture(scope="module")
def segment():
    """Take 08's first test seconds (joints) and the hand bones' rotations there."""
    from training.dataset import split_range

    take, lead30, _, lead, _ = test_take("08", SECONDS)
    a = 2 * split_range(lead.n_frames, "test")[0]
    return take, lead30, lead.rotations[a:a + take.n_frames][:, list(HAND_BONES)]


@pytest.fixture(scope="module")
def synth():
    return Synthesizer()


TURN = (0.85, 0.3, -0.35, 0.25)  # about 64 degrees


def test_parse_turn_and_mirror():
    q = parse_turn("2,0,0,0")
    assert q == (1.0, 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="quaternion"):
        parse_turn("1,0,0")
    with pytest.raises(InputError, match="not a rotation"):
        parse_turn("0.1,0,0,0")
    # the right hand's turn is the mirror image of the left's across the body's mid-plane
    M = np.diag([-1.0, 1.0, 1.0])
    R = quat_to_matrix(np.asarray(parse_turn(",".join(map(str, TURN)))))
    assert np.allclose(quat_to_matrix(np.asarray(mirror_turn(matrix_to_quat(R)))), M @ R @ M)


def test_a_given_turn_gives_the_untouched_duet(segment, synth):
    """Devices turned by constant rotations in their own axes, with those turns
    given (metadata, or the options), make exactly the duet of the untouched take."""
    take = segment[0]
    left = tuple(np.asarray(TURN) / np.linalg.norm(TURN))
    turns = ((0.97, 0.1, 0.2, -0.05), left, mirror_turn(left))
    turns = tuple(tuple(np.asarray(t) / np.linalg.norm(t)) for t in turns)
    reported = copy_take(take, quats=turned(take.quats, turns))
    want = synth.synthesize(take)
    meta = DeviceTurns(*turns).meta()
    by_meta = synth.synthesize(copy_take(reported, **meta))
    assert np.abs(by_meta.leader_positions - want.leader_positions).max() < 1e-4
    assert np.abs(by_meta.follower_positions - want.follower_positions).max() < 1e-4
    by_options = Synthesizer(SynthesisOptions(head_turn=turns[0], hand_turn=left)).synthesize(reported)
    assert np.abs(by_options.leader_positions - want.leader_positions).max() < 1e-4
    assert by_options.calibration.notice() is None
    # not given, the turned hands' orientation is followed as reported: the wrists turn away
    wrong = synth.synthesize(reported)
    assert np.abs(wrong.leader_rotations - want.leader_rotations).max() > 0.3


def test_random_orientations_are_not_followed(segment, synth, tmp_path):
    """Orientations drawn at random on every row carry nothing: the duet is the
    one made without following the devices, and one line says why."""
    take = segment[0]
    rng = np.random.default_rng(3)
    q = take.quats.copy()
    for d in range(3):
        q[:, d] = random_quats(rng, len(q))
    noisy = copy_take(take, quats=q)
    calib = calibrate(noisy)
    assert calib.followed == (False, False, False)
    assert min(calib.turn_speeds) > ORIENTATION_SPEED_LIMIT
    assert "not followed" in calib.notice() and "head, left hand, right hand" in calib.notice()
    assert max(calibrate(take).turn_speeds) < ORIENTATION_SPEED_LIMIT / 3  # a dancer's own: far below the limit
    duet = synth.synthesize(noisy)
    plain = Synthesizer(SynthesisOptions(follow_devices=False)).synthesize(noisy)
    assert np.array_equal(duet.leader_positions, plain.leader_positions)
    assert np.array_equal(duet.leader_rotations, plain.leader_rotations)
    out = tmp_path / "duet.npz"
    save_npz(duet, out)
    with np.load(out) as z:
        assert z["orientations_followed"].tolist() == [False, False, False]
        assert z["device_turns"].shape == (3, 4)
    # the hands alone: the head still followed
    q = take.quats.copy()
    q[:, 1:] = random_quats(rng, 2 * len(q)).reshape(len(q), 2, 4)
    assert calibrate(copy_take(take, quats=q)).followed == (True, False, False)


def test_orientations_none_in_the_metadata(segment, synth):
    take = segment[0]
    calib = calibrate(copy_take(take, orientations="none"))
    assert calib.followed == (False, False, False) and "orientations=none" in calib.notice()
    assert calib.meta()["orientations"] == "none"


def test_headset_grips_without_orientation_keep_the_wrists_near(segment):
    """A headset take whose grips' orientations carry nothing: each wrist is put
    its body offset from the fist towards the shoulder, nearer the true wrist
    than the fist itself, and the duet stays on the points."""
    take, lead30, hands = segment
    xr = headset_take(take, hands)
    rng = np.random.default_rng(5)
    q = xr.quats.copy()
    q[:, 1:] = random_quats(rng, 2 * len(q)).reshape(len(q), 2, 4)
    noisy = copy_take(xr, quats=q)
    calib = calibrate(noisy)
    assert calib.followed == (True, False, False)
    points, _ = calib.read(noisy.positions, noisy.quats)
    off = np.linalg.norm(points[:, 1:] - take.positions[:, 1:], axis=-1).mean()
    fist = np.linalg.norm(xr.positions[:, 1:] - take.positions[:, 1:], axis=-1).mean()
    assert off < 0.06 and off < 0.8 * fist, (off, fist)
    # the head, followed, is read exactly as before
    assert np.allclose(points[:, 0], take.positions[:, 0], atol=1e-6)
    assert read_poses(xr.positions, xr.quats, "openxr", DeviceOffsets().at(calib.height))[0].shape == points.shape


def test_turn_options_and_metadata_on_the_command_line(segment, tmp_path):
    take = segment[0]
    src = tmp_path / "take.csv"
    write_take(src, copy_take(take, lhand_turn="1,0,0"))
    out = tmp_path / "duet.npz"
    res = run_cli("synthesize", str(src), "-o", str(out))
    assert res.returncode == 2 and not out.exists()
    assert "lhand_turn" in res.stderr and "take.csv:1:" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    write_take(src, take)
    res = run_cli("synthesize", str(src), "-o", str(out), "--hand-turn", "1,0,0")
    assert res.returncode == 2 and "--hand-turn" in res.stderr and not out.exists()
    rng = np.random.default_rng(11)
    q = take.quats.copy()
    q[:, 1:] = random_quats(rng, 2 * len(q)).reshape(len(q), 2, 4)
    write_take(src, copy_take(take, quats=q))
    res = run_cli("synthesize", str(src), "-o", str(out), "--head-turn", "1,0,0,0")
    assert res.returncode == 0, res.stderr
    warn = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "left hand, right hand orientations are not followed" in warn[0]
    assert read_take(src).meta.get("lhand_turn") is None


def test_blender_take_carries_turns_and_says_what_is_not_followed(segment, tmp_path, dp_extension):
    """In Blender: a take's device turns travel onto the take (Device Turns),
    back into the take it synthesises, and a take whose hand orientations
    carry nothing is baked with the Take panel saying so."""
    import bpy
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension

    take_collection = import_from_extension("operators.take_collection")
    take = segment[0]
    left = tuple(np.asarray(TURN) / np.linalg.norm(TURN))
    reported = copy_take(take, quats=turned(take.quats, (None, left, mirror_turn(left))),
                         **DeviceTurns(None, left, mirror_turn(left)).meta())
    path = tmp_path / "turned.csv"
    write_take(path, reported)
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(path)) == {'FINISHED'}
    coll = next(c for c in bpy.data.collections if c.dancing_points.kind == 'TAKE')
    assert np.allclose(tuple(coll.dancing_points.lhand_turn), left, atol=1e-6)
    assert tuple(coll.dancing_points.head_turn) == (1.0, 0.0, 0.0, 0.0)
    back = take_collection.take_from_collection(bpy.context, coll)
    calib = calibrate(back)
    assert np.allclose(calib.turns.lhand, left, atol=1e-6) and np.allclose(calib.turns.rhand, mirror_turn(left),
                                                                           atol=1e-6)
    assert calib.turns.head is None
    # random hand orientations: baked, and the panel says which are not followed
    rng = np.random.default_rng(2)
    q = take.quats.copy()
    q[:, 1:] = random_quats(rng, 2 * len(q)).reshape(len(q), 2, 4)
    path = tmp_path / "noisy.csv"
    write_take(path, copy_take(take, quats=q))
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(path)) == {'FINISHED'}
    coll = next(c for c in bpy.data.collections if c.dancing_points.kind == 'TAKE')
    bpy.context.scene.dancing_points.take = coll
    assert bpy.ops.dancing_points.synthesize() == {'FINISHED'}
    assert "left hand, right hand orientations are not followed" in coll.dancing_points.orientations_used
