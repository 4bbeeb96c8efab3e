"""A headset's own recording (SPEC §3 ``devices=openxr``), calibration to the
wearer (height, floor) and the accidents of real VR (tracking that comes
back, a take that starts lost, feet under the floor), on real CMU takes and
the shipped models."""
import numpy as np
import pytest

from conftest import SALSA
from dancing_points_addon import features as F
from dancing_points_addon.calibration import (TRAIN_HEIGHT, apply_calibration, calibrate, headset_take,
                                              height_from_head)
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.devices import DeviceOffsets, openxr_to_points
from dancing_points_addon.inputs import HAND_BONES, load_input
from dancing_points_addon.formats.take import Take
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.representation import DEVICE_FROM_HEAD
from dancing_points_addon.resample import resample_take
from dancing_points_addon.rotations import quat_to_matrix
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import FEET, JOINT_INDEX, TRACKED
from support.helpers import run_cli
from test_runtime import test_take

ARMS = [JOINT_INDEX[s + n] for s in "lr" for n in ("humerus", "radius", "hand", "fingers", "thumb")]
BODY = [j for j in range(31) if j not in ARMS]


@pytest.fixture(scope="module")
def synth():
    return Synthesizer()


@pytest.fixture(scope="module")
def take08():
    return test_take("08")


@pytest.fixture(scope="module")
def headset08(take08):
    """Take 08's test frames as a headset records them (view and grip poses)."""
    from training.dataset import split_range

    take, _, _, lead, _ = take08
    a = 2 * split_range(lead.n_frames, "test")[0]  # the 60 Hz test frames' start
    hands = lead.rotations[a:a + take.n_frames][:, list(HAND_BONES)]
    return headset_take(take, hands)


def angle_deg(A, B):
    tr = np.trace(np.swapaxes(A, -1, -2) @ B, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1)))


def test_headset_take_reads_back_as_the_joints(take08, headset08):
    """The reader turns view and grip poses back into exactly the §2 points, at
    the height it estimates itself (the writer wrote none)."""
    take = take08[0]
    assert headset08.meta["devices"] == "openxr" and "height_m" not in headset08.meta
    # the devices are not the joints: the eyes ~11 cm from the base of the skull, the fists ~7 cm past the wrists
    d = np.linalg.norm(headset08.positions - take.positions, axis=-1).mean(0)
    assert 0.09 < d[0] < 0.13 and (0.06 < d[1:]).all() and (d[1:] < 0.09).all(), d
    joints, xr = calibrate(take), calibrate(headset08)
    assert xr.devices == "openxr" and xr.height_source == "estimated"
    assert abs(xr.height - joints.height) < 1e-6
    back = apply_calibration(headset08, xr)
    assert np.abs(back.positions - take.positions).max() < 1e-6
    # the head device is the skull's either way; the grips carry the hand bones
    assert np.abs(np.abs((back.quats[:, 0] * take.quats[:, 0]).sum(-1)) - 1).max() < 1e-9


def test_headset_take_gives_the_joint_takes_duet(synth, take08, headset08):
    """Synthesised from the headset's poses, the duet is the joint take's: her
    and his body identical, his arms but the wrists within centimetres (the
    joints' hand orientation is the forearm's end, which places his elbows;
    a grip's is the hand's, which turns his hands)."""
    a = synth.synthesize(take08[0])
    b = synth.synthesize(headset08)
    assert b.calibration.devices == "openxr"
    # identical up to rounding: the points come back through the device offsets to ~1e-13 m,
    # which the closed loop carries on to at most hundredths of a millimetre
    assert np.abs(a.follower_positions - b.follower_positions).max() < 1e-4
    assert np.abs(a.leader_positions[:, BODY] - b.leader_positions[:, BODY]).max() < 1e-4
    d = np.linalg.norm(a.leader_positions - b.leader_positions, axis=-1)[:, ARMS]
    print(f"\nhis arms, joints against headset take: {d.mean() * 100:.2f} cm mean, {d.max() * 100:.1f} cm max")
    assert d.mean() < 0.05


def test_wrong_body_offsets_move_his_points_by_the_error(synth, headset08, take08):
    """Offsets 2 cm wrong along one axis put his head and wrists about 2 cm
    from the truth: his wrists go where the points are, his head, which the
    rigid spine does not always reach on this take, about as far beyond."""
    true = take08[1]
    h = calibrate(headset08).height
    score = np.arange(len(true)) >= F.FPS
    for axis in range(3):
        err = np.zeros(3)
        err[axis] = 0.02
        wrong = DeviceOffsets(*(tuple(v) for v in DeviceOffsets().at(h) + err))
        duet = Synthesizer(SynthesisOptions(offsets=wrong)).synthesize(headset08)
        n = min(len(true), duet.n_frames)
        track = np.linalg.norm(duet.leader_positions[:n, TRACKED] - true[:n, TRACKED], axis=-1).mean(-1)[score[:n]]
        print(f"\noffsets 2 cm off along {'xyz'[axis]}: his head and wrists {track.mean() * 100:.2f} cm off")
        assert track.mean() < 0.03


def test_take_metadata_offsets_and_devices(tmp_path, headset08):
    """A take's own body offsets replace the defaults (used as given, not
    scaled); bad ones and unknown devices are refused with the file's name."""
    take = Take(headset08.time, headset08.positions, headset08.quats,
                dict(headset08.meta, head_offset_m="0,-0.05,0.1"), "x.csv")
    c = calibrate(take)
    assert c.offsets.head == (0.0, -0.05, 0.1) and c.offsets.lhand is None
    assert np.allclose(c.offsets.at(1.5)[0], (0.0, -0.05, 0.1))
    assert not np.allclose(c.offsets.at(1.5)[1], DeviceOffsets().at(1.7)[1])  # the defaults scale
    for meta, what in (({"head_offset_m": "0,0"}, "three numbers"), ({"lhand_offset_m": "0,0,2"}, "0.5 m"),
                       ({"devices": "vive"}, "unknown devices")):
        with pytest.raises(InputError, match=what) as e:
            calibrate(Take(take.time, take.positions, take.quats, dict(take.meta, **meta), "x.csv"))
        assert "x.csv" in str(e.value)


def test_height_is_estimated_and_the_follower_is_shorter(take08):
    """Without a height, the training leader's takes come out near his 1.70 m
    and the follower's (a shorter dancer) about 6 % shorter."""
    lead = calibrate(take08[0])
    assert lead.height_source == "estimated" and abs(lead.height - TRAIN_HEIGHT) < 0.04
    her = calibrate(load_input(str(SALSA / "61_08.amc")))
    assert 0.90 < her.height / lead.height < 0.97, her.height


def test_floor_off_by_centimetres_is_found_when_the_height_is_known(synth, take08):
    """A floor 10 cm up or down: with the height given, the floor is
    estimated and the duet is the unshifted one, moved with the floor."""
    take = take08[0]
    base = Synthesizer(SynthesisOptions(height=1.70)).synthesize(take)
    for shift in (0.1, -0.1):
        moved = Take(take.time, take.positions + (0.0, shift, 0.0), take.quats, dict(take.meta))
        out = Synthesizer(SynthesisOptions(height=1.70)).synthesize(moved)
        assert out.calibration.floor_source == "estimated"
        assert abs(out.calibration.floor_y - base.calibration.floor_y - shift) < 1e-9
        for role in ("leader", "follower"):
            d = getattr(out, role + "_positions") - (0.0, shift, 0.0) - getattr(base, role + "_positions")
            assert np.abs(d).max() < 1e-6, role
    # a floor given in the take is used as it is
    given = Take(take.time, take.positions, take.quats, {"floor_y": "0.03"})
    assert calibrate(given).floor_source == "given" and calibrate(given).floor_y == 0.03


def test_head_and_hands_follow_the_devices(synth, take08):
    """His skull turns as the head device does and each forearm's end as its
    hand device (``joints``: the wrist bones'): the head within a degree, the
    forearms within a few degrees (his arm is solved to point the forearm's end
    along the device; where the arm cannot reach, its elbow only swings);
    turned off, they are the network's, tens of degrees off."""
    from dancing_points_addon.resample import resample_take

    take = take08[0]
    tk = resample_take(take, F.FPS)
    dev = quat_to_matrix(tk.quats)
    score = slice(int(F.FPS), None)
    on = synth.synthesize(take)
    off = Synthesizer(SynthesisOptions(follow_devices=False)).synthesize(take)
    figures = []
    for duet in (on, off):
        R = duet.leader_rotations
        head = angle_deg(R[:, JOINT_INDEX["head"]], dev[:, 0] @ DEVICE_FROM_HEAD)[score].mean()
        wrists = np.mean([angle_deg(R[:, JOINT_INDEX[b]], dev[:, i])[score].mean()
                          for i, b in ((1, "lwrist"), (2, "rwrist"))])
        figures.append((head, wrists))
    print(f"\nhead / wrists off the devices: following {figures[0][0]:.1f} / {figures[0][1]:.1f} deg, "
          f"not following {figures[1][0]:.1f} / {figures[1][1]:.1f} deg")
    assert figures[0][0] < 1.0 and figures[0][1] < 5.0
    assert figures[1][0] > 10.0 and figures[1][1] > 20.0
    # only rotations of the head and hands change: the wrists stay on the tracked points
    assert np.abs(on.leader_positions[:, TRACKED] - off.leader_positions[:, TRACKED]).max() < 1e-9


def test_forearm_follow_keeps_the_wrist_point_in_and_out_of_reach(synth, take08):
    """One frame of his pose, the left wrist device turned: within reach, the
    wrist bone ends up along the device's axis; a device axis that would need
    a longer arm leaves the arm to its elbow swing. Either way the wrist point
    stays where it was, and every bone keeps its length."""
    from dancing_points_addon.device_follow import DeviceFollow
    from dancing_points_addon.ik import rotation_between
    from dancing_points_addon.skeleton import bone_lengths_from_positions

    duet = synth.synthesize(take08[0])
    P0, R0 = duet.leader_positions[60].copy(), duet.leader_rotations[60].copy()
    follow = DeviceFollow(synth.bone_vectors["tracked"])
    J = JOINT_INDEX
    e = synth.bone_vectors["tracked"][J["lwrist"]]
    e = e / np.linalg.norm(e)
    sh, el, re, wr = (P0[J[b]] for b in ("lclavicle", "lhumerus", "lradius", "lwrist"))
    out = (wr - sh) / np.linalg.norm(wr - sh)
    side = np.cross(out, (0.0, 1.0, 0.0))
    bent = out + 1.5 * side / np.linalg.norm(side)
    bent /= np.linalg.norm(bent)
    # along ``-out`` the radius would have to end past the wrist, farther than the arm reaches
    reach = np.linalg.norm(el - sh) + np.linalg.norm(re - el)
    assert np.linalg.norm(wr - sh) + np.linalg.norm(wr - re) > reach
    for axis, reachable in ((bent, True), (-out, False)):
        P, R = follow.step(P0.copy(), R0.copy(), None, (rotation_between(e, axis), None))
        assert np.abs(P[J["lwrist"]] - wr).max() < 1e-9
        lengths = bone_lengths_from_positions(np.stack([P, P0]))
        assert np.abs(lengths[0] - lengths[1]).max() < 1e-9
        angle = np.degrees(np.arccos(np.clip(R[J["lwrist"]] @ e @ axis, -1.0, 1.0)))
        if reachable:
            assert angle < 1e-4
        else:
            assert angle > 10.0  # the elbow swung, the wrist point kept


def test_grip_turns_the_forearm_by_the_dancers_hand_bend(synth, take08):
    """For a headset's grip (the hand bone's orientation, the bend at the
    wrist unknown), the forearm's end turns towards the grip bent back by
    ``hand_flex``: all the way with ``forearm_share=1`` (the forearm of the
    pose the grip came from, when that pose's bend is given), a share of the
    way by default; the wrist point and every bone length kept; without a bend
    nothing but the hand turns."""
    from dancing_points_addon.device_follow import DeviceFollow, DeviceFollowOptions, hand_flex

    shipped = DeviceFollowOptions().forearm_share
    from dancing_points_addon.ik import rotation_between
    from dancing_points_addon.skeleton import bone_lengths_from_positions

    duet = synth.synthesize(take08[0])
    P0, R0 = duet.leader_positions[60].copy(), duet.leader_rotations[60].copy()
    J = JOINT_INDEX
    bv = synth.bone_vectors["tracked"]
    e = bv[J["lwrist"]] / np.linalg.norm(bv[J["lwrist"]])
    # the grip of the same arm with its forearm end turned 25 degrees about the elbow-to-wrist normal
    fore = R0[J["lwrist"]] @ e
    turn = rotation_between(fore, fore + 0.47 * np.cross(fore, (0.0, 1.0, 0.0)))
    flex = hand_flex(R0)
    grip = turn @ R0[J["lwrist"]] @ flex[0]
    want = turn @ fore
    wr = P0[J["lwrist"]].copy()

    def angle(R, axis):
        return np.degrees(np.arccos(np.clip(R[J["lwrist"]] @ e @ axis, -1.0, 1.0)))

    start = angle(R0, want)
    assert start > 20.0
    got = {}
    for share in (1.0, shipped):
        follow = DeviceFollow(bv, "hand", DeviceFollowOptions(forearm_share=share), hand_flex=flex)
        P, R = follow.step(P0.copy(), R0.copy(), None, (grip, None))
        assert np.abs(P[J["lwrist"]] - wr).max() < 1e-9
        lengths = bone_lengths_from_positions(np.stack([P, P0]))
        assert np.abs(lengths[0] - lengths[1]).max() < 1e-9
        got[share] = angle(R, want)
    print(f"\nforearm off the grip's estimate: {start:.1f} deg before, {got[shipped]:.1f} at the default "
          f"share, {got[1.0]:.4f} all the way")
    assert got[1.0] < 1e-4 and 0.1 * start < got[shipped] < 0.5 * start
    P, R = DeviceFollow(bv, "hand").step(P0.copy(), R0.copy(), None, (grip, None))
    assert abs(angle(R, want) - start) < 1e-6 and np.abs(P[J["lradius"]] - P0[J["lradius"]]).max() < 1e-12


def test_hands_back_after_a_loss_blend_in(synth, take08):
    """Hands lost for 0.4 s: when tracking returns, his wrists come back over a
    few frames, never faster than 0.15 m a frame."""
    take = take08[0]
    lost = (take.time >= 2.0) & (take.time < 2.4)
    gap = Take(take.time, take.positions.copy(), take.quats.copy(), dict(take.meta))
    gap.positions[lost, 1:] = np.nan
    gap.quats[lost, 1:] = np.nan
    w = [JOINT_INDEX["lwrist"], JOINT_INDEX["rwrist"]]
    steps = np.linalg.norm(np.diff(synth.synthesize(gap).leader_positions[:, w], axis=0), axis=-1).max()
    clean = np.linalg.norm(np.diff(synth.synthesize(take).leader_positions[:, w], axis=0), axis=-1).max()
    print(f"\nlargest wrist step: {steps:.3f} m a frame after the loss, {clean:.3f} without it")
    assert steps <= 0.15


def test_a_take_that_starts_lost_starts_where_the_dancer_is_first_seen(synth):
    """Take 02 moved to (+3, 0, −2) with its first 1.5 s lost: both dancers
    start there, their pelvises never jump more than 0.3 m a frame."""
    take = test_take("02")[0]
    moved = Take(take.time, take.positions + (3.0, 0.0, -2.0), take.quats.copy(), {})
    lost = moved.time < 1.5
    moved.positions[lost] = np.nan
    moved.quats[lost] = np.nan
    duet = synth.synthesize(moved)
    for role in ("leader", "follower"):
        pelvis = getattr(duet, role + "_positions")[:, 0]
        step = np.linalg.norm(np.diff(pelvis, axis=0), axis=-1).max()
        start = np.linalg.norm(pelvis[0, [0, 2]] - (3.0 + take.positions[45, 0, 0], -2.0 + take.positions[45, 0, 2]))
        print(f"\n{role}: largest pelvis step {step:.3f} m, "
              f"first pelvis {start:.2f} m from where the head is first seen")
        assert step <= 0.3 and start < 1.5, role


def test_feet_never_go_through_the_floor(synth):
    """Take 11's test segment starts in a dip where his predicted body crouches
    below the input: his feet are lifted, never below -3 cm."""
    take = test_take("11")[0]
    duet = synth.synthesize(take)
    for role in ("leader", "follower"):
        low = getattr(duet, role + "_positions")[:, FEET, 1].min()
        print(f"\n{role}: lowest foot point {low * 100:.1f} cm")
        assert low > -0.03, role


def test_extract_devices_openxr_and_synthesize_devices_cli(tmp_path):
    """``extract --devices openxr`` writes a headset take; ``synthesize`` reads it
    (its metadata say openxr) and prints what it estimated; ``--devices``
    overrides the take's; a bad offset is one line."""
    out = tmp_path / "xr.csv"
    res = run_cli("extract", str(SALSA / "60_10.amc"), "-o", str(out), "--devices", "openxr")
    assert res.returncode == 0, res.stderr
    take = read_take(out)
    assert take.meta["devices"] == "openxr"
    joints = load_input(str(SALSA / "60_10.amc"))
    back = apply_calibration(take, calibrate(take))
    assert np.abs(back.positions - joints.positions).max() < 1e-5
    res = run_cli("synthesize", str(out), "-o", str(tmp_path / "d.npz"))
    assert res.returncode == 0, res.stderr
    assert "estimated" in res.stdout and "devices openxr" in res.stdout
    z = np.load(tmp_path / "d.npz")
    assert str(z["devices"]) == "openxr" and str(z["height_source"]) == "estimated"
    # estimated from the head at the networks' 30 Hz frames (as Blender's 30 fps keys of the take would)
    assert abs(float(z["height_m"]) - height_from_head(resample_take(joints, 30.0).positions[:, 0, 1])) < 1e-6
    res = run_cli("synthesize", str(out), "-o", str(tmp_path / "e.npz"), "--devices", "joints", "--height", "1.7",
                  "--floor-y", "0.02")
    assert res.returncode == 0, res.stderr
    z = np.load(tmp_path / "e.npz")
    assert str(z["devices"]) == "joints" and float(z["floor_y"]) == 0.02 and str(z["floor_source"]) == "given"
    res = run_cli("synthesize", str(out), "-o", str(tmp_path / "f.npz"), "--head-offset", "0,0")
    assert res.returncode == 2 and "three numbers" in res.stderr and not (tmp_path / "f.npz").exists()



def test_extract_turns_a_headset_take_back_into_joints_and_sets_the_role(tmp_path):
    """``extract`` of a headset take keeps it as it is, ``--devices joints`` turns
    it back into the §2 points (the mocap's, within the file's precision), and
    ``--role`` writes the role (SPEC §7: it overrides the take's). Negative
    offsets are accepted as written in the help (``--hand-offset -0.025,0.07,0``)."""
    xr = tmp_path / "xr.csv"
    assert run_cli("extract", str(SALSA / "60_10.amc"), "-o", str(xr), "--devices", "openxr").returncode == 0
    same = tmp_path / "same.csv"
    res = run_cli("extract", str(xr), "-o", str(same), "--role", "follower")
    assert res.returncode == 0, res.stderr
    t = read_take(same)
    assert t.meta["devices"] == "openxr" and t.meta["role"] == "follower"
    back = tmp_path / "back.csv"
    res = run_cli("extract", str(xr), "-o", str(back), "--devices", "joints", "--hand-offset", "-0.025,0.07,0")
    assert res.returncode == 0, res.stderr
    t = read_take(back)
    joints = load_input(str(SALSA / "60_10.amc"))
    assert t.meta["devices"] == "joints" and "role" not in t.meta
    assert np.abs(t.positions - joints.positions).max() < 1e-4


def test_openxr_conversion_keeps_lost_devices_lost():
    pos = np.zeros((3, 3, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (3, 3, 1))
    pos[1, 2] = np.nan
    q[1, 2] = np.nan
    p, qq = openxr_to_points(pos, q, DeviceOffsets().at(1.7))
    assert np.isnan(p[1, 2]).all() and np.isnan(qq[1, 2]).all() and np.isfinite(p[[0, 2]]).all()


def test_moving_a_pose_keeps_its_ankles_and_bones(synth, take08):
    """``pose.move_keeping_feet``: everything above the legs moves by the shift,
    the ankles stay (the knees bend for it), the feet are carried only as far
    as the ankles move; every bone keeps its length."""
    from dancing_points_addon.pose import move_keeping_feet
    from dancing_points_addon.skeleton import bone_lengths_from_positions

    duet = synth.synthesize(take08[0])
    P0, R0 = duet.leader_positions[90].copy(), duet.leader_rotations[90].copy()
    shift = np.array([0.02, -0.03, 0.01])
    P, R = move_keeping_feet(P0, R0, shift)
    assert P is not P0 and np.array_equal(P0, duet.leader_positions[90])  # the input untouched
    legs = [JOINT_INDEX[s + n] for s in "lr" for n in ("femur", "tibia", "foot", "toes")]
    above = [j for j in range(31) if j not in legs]
    assert np.abs(P[above] - P0[above] - shift).max() < 1e-12
    ankles = [JOINT_INDEX["ltibia"], JOINT_INDEX["rtibia"]]
    assert np.abs(P[ankles] - P0[ankles]).max() < 1e-9
    lengths = bone_lengths_from_positions(np.stack([P, P0]))
    assert np.abs(lengths[0] - lengths[1]).max() < 1e-9
    # the rotations agree with the positions: each leg bone's rest direction, turned, is its posed direction
    from dancing_points_addon.skeleton import PARENTS

    bv = synth.bone_vectors["tracked"]
    rest_dir = bv / np.linalg.norm(bv, axis=-1, keepdims=True).clip(1e-12)
    for pose, rots in ((P0, R0), (P, R)):
        for j in legs:
            d = pose[j] - pose[PARENTS[j]]
            assert np.abs(rots[j] @ rest_dir[j] - d / np.linalg.norm(d)).max() < 1e-6


def test_the_tracked_head_point_reaches_its_device(take08):
    """The tracked dancer's head point reaches its device: his body moves most
    of the way there (``TrackedOptions.head_reach``), his legs keeping his
    ankles; the rigid spine alone (``head_reach=0``) left it more than twice
    as far."""
    from dancing_points_addon.tracked_pose import TrackedOptions

    take, shipped = take08[0], TrackedOptions().head_reach
    off = {}
    for reach in (shipped, 0.0):
        duet = Synthesizer(tracked=TrackedOptions(head_reach=reach)).synthesize(take)
        tk = resample_take(apply_calibration(take, duet.calibration), F.FPS)
        n = min(len(tk.positions), len(duet.leader_positions))
        off[reach] = np.linalg.norm(duet.leader_positions[30:n, TRACKED[0]] - tk.positions[30:n, 0], axis=-1).mean()
    print(f"\nhead point off its device: {100 * off[0.0]:.2f} cm with the spine alone, "
          f"{100 * off[shipped]:.2f} as shipped")
    assert shipped > 0.0 and off[shipped] < 0.012 and off[shipped] < 0.5 * off[0.0]
