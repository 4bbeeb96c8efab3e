"""The paper's representation on the real salsa takes: exact root-frame transforms,
plausible contact labels, AMC parsing speed, the SPEC §5 split and mirroring."""
import time

import numpy as np
import pytest

from dancing_points_addon import features as F
from dancing_points_addon.formats.asf_amc import load_amc, parse_asf
from training.dataset import (SALSA_TAKES, build_clips, mirror, n_train_frames, split_range)
from dancing_points_addon.representation import (contact_labels, floor_levels, hip_frame, pose_to_local,
                                                 root_compose, root_from_motion, root_relative, rot_to_local,
                                                 rot_to_world, to_local, to_world)
from dancing_points_addon.skeleton import FEET, FOOT_NAMES, JOINT_NAMES, bone_lengths_from_positions


@pytest.fixture(scope="module")
def salsa(salsa_dir):
    t = time.perf_counter()
    motions = {f"{s}_{k}": load_amc(salsa_dir / f"{s}_{k}.amc") for s in ("60", "61") for k in SALSA_TAKES}
    elapsed = time.perf_counter() - t
    print(f"\nparsed 26 salsa AMC files in {elapsed:.2f} s")
    return motions, elapsed


def test_parse_all_salsa_under_10s(salsa):
    motions, elapsed = salsa
    assert len(motions) == 26
    counts = {k: m.n_frames for k, m in motions.items()}
    assert counts["60_08"] == counts["61_08"] == 3421
    assert counts["60_10"] == 1197
    assert elapsed < 10.0


def test_skeleton_convention(salsa_dir):
    """Motion space: Y up, the rest character faces +Z with its left at +X; metres."""
    skel = parse_asf(salsa_dir / "60.asf")
    vec = dict(zip(skel.names, skel.bone_vectors))
    assert vec["lhipjoint"][0] > 0 > vec["rhipjoint"][0]
    assert vec["lfoot"][2] > 0  # toes point forward (+Z)
    assert vec["upperneck"][1] > 0
    m = load_amc(salsa_dir / "60_01.amc")
    # head-to-ankle height of the leader is about 1.54 m (data README)
    rest_height = np.linalg.norm(skel.bone_vectors, axis=1)
    assert 0.4 < rest_height[skel.index("lfemur")] < 0.45
    assert 1.3 < np.median(m.positions[:, JOINT_NAMES.index("upperneck"), 1]) < 1.6
    # FK keeps every bone's length on every frame
    bl = bone_lengths_from_positions(m.positions)
    assert np.abs(bl - m.bone_lengths()).max() < 1e-9


def test_root_frame_round_trip_every_salsa_frame(salsa):
    motions, _ = salsa
    worst_p = worst_r = worst_root = 0.0
    for m in motions.values():
        root = root_from_motion(m.positions, m.rotations)
        assert np.allclose(np.hypot(root[:, 2], root[:, 3]), 1.0)
        back = to_world(to_local(m.positions, root), root)
        worst_p = max(worst_p, np.abs(back - m.positions).max())
        rb = rot_to_world(rot_to_local(m.rotations, root), root)
        worst_r = max(worst_r, np.abs(rb - m.rotations).max())
        rel = root_relative(root[:1], root)
        worst_root = max(worst_root, np.abs(root_compose(root[:1], rel) - root).max())
    print(f"\nround trip world->root->world: positions {worst_p:.2e} m, rotations {worst_r:.2e}, "
          f"roots {worst_root:.2e}")
    assert worst_p < 1e-6 and worst_r < 1e-9 and worst_root < 1e-9


def test_root_is_under_the_head_and_faces_forward(salsa):
    motions, _ = salsa
    m = motions["60_01"]
    root = root_from_motion(m.positions, m.rotations)
    head = m.positions[:, JOINT_NAMES.index("upperneck")]
    assert np.allclose(root[:, 0], head[:, 0]) and np.allclose(root[:, 1], head[:, 2])
    # the toes are in front of the ankles in the root frame most of the time
    loc = to_local(m.positions, root)
    toes_ahead = loc[:, JOINT_NAMES.index("lfoot"), 2] > loc[:, JOINT_NAMES.index("ltibia"), 2]
    assert toes_ahead.mean() > 0.8


def test_contact_labels_leader(salsa):
    motions, _ = salsa
    shares = []
    for k in SALSA_TAKES:
        m = motions[f"60_{k}"].subsample(2)
        c = contact_labels(m.positions, m.fps)
        feet = m.positions[:, FEET]
        floor = floor_levels(feet[..., 1])
        height = feet[..., 1] - floor
        assert not np.any(c & (height > 0.10)), "contact while > 10 cm above the floor"
        shares.append(c.mean(0))
    share = np.mean(shares, axis=0)
    print("\nleader contact shares: " + ", ".join(f"{n} {s:.0%}" for n, s in zip(FOOT_NAMES, share)))
    assert np.all((share > 0.25) & (share < 0.85)), share


def test_split_boundaries_never_touch_test_frames(salsa_dir):
    for n60 in (2242, 1197, 3421, 2101):
        n30 = (n60 + 1) // 2
        a, b = split_range(n60, "train")
        c, d = split_range(n60, "test")
        assert (a, b, c, d) == (0, int(np.floor(0.8 * n30)), int(np.floor(0.8 * n30)), n30)
    clips = build_clips(salsa_dir, "train", mirror_aug=True)
    by_name = {c.name: c for c in clips}
    for k in SALSA_TAKES:
        full = load_amc(salsa_dir / f"60_{k}.amc").subsample(2)
        n_train = n_train_frames(full.n_frames)
        clip = by_name[k]
        assert clip.n_frames == n_train
        assert np.array_equal(clip.leader.positions, full.positions[:n_train])
        assert by_name[k + "m"].n_frames == n_train
    # training samples need a full future second inside the clip: none reaches frame n_train
    from training.data import sample_times
    assert sample_times(100).max() + F.FUTURE == 99


def test_mirror_is_a_valid_motion(salsa_dir):
    m = load_amc(salsa_dir / "60_02.amc").subsample(2)
    p, r = mirror(m.positions, m.rotations)
    # lengths: the mirrored body has the other side's bones
    bl = bone_lengths_from_positions(p)
    assert np.abs(bl[:, JOINT_NAMES.index("lfemur")] - m.bone_lengths()[JOINT_NAMES.index("rfemur")]).max() < 1e-9
    assert np.allclose(np.linalg.det(r), 1.0)
    pp, rr = mirror(p, r)
    assert np.allclose(pp, m.positions) and np.allclose(rr, m.rotations)
    # mirrored rotations still map rest bones to posed bones of the mirrored skeleton
    vec = m.bone_vectors[list(__import__("dancing_points_addon.skeleton", fromlist=["MIRROR"]).MIRROR)]
    vec = vec * np.array([-1.0, 1.0, 1.0])
    from dancing_points_addon.skeleton import PARENTS
    posed = p[:, 1:] - p[:, np.maximum(PARENTS, 0)][:, 1:]
    assert np.abs(np.einsum("tnab,nb->tna", r[:, 1:], vec[1:]) - posed).max() < 1e-9


def test_one_pose_frames_are_the_batch_forms_bit_for_bit():
    """The frame loop's one-pose paths (a hip frame, a pose into its root) give the batch forms' bits."""
    rng = np.random.default_rng(3)
    pos, rot = rng.normal(size=(300, 31, 3)), rng.normal(size=(300, 31, 3, 3))
    assert np.array_equal(np.array([hip_frame(p) for p in pos]), hip_frame(pos))
    roots = hip_frame(pos)
    for p, r, root in zip(pos[:20, None], rot[:20, None], roots[:20, None]):
        lp, lr = pose_to_local(p, r, root)
        assert np.array_equal(lp, to_local(p, root)) and np.array_equal(lr, rot_to_local(r, root))


def test_mapping_inputs_of_a_block_are_each_windows_bit_for_bit():
    """The read-ahead block's mapping inputs (one call, windows slid on) are each window's own."""
    rng = np.random.default_rng(4)
    roots, tracked = rng.normal(size=(F.PAST + 40, 4)), rng.normal(size=(F.PAST + 40, 3, 3))
    roots[:, 2:] /= np.linalg.norm(roots[:, 2:], axis=1, keepdims=True)
    for n in (1, 2, 5, 41):
        block = F.mapping_inputs(roots[:F.PAST], tracked[:F.PAST], roots[F.PAST:F.PAST + n - 1],
                                 tracked[F.PAST:F.PAST + n - 1])
        one = [F.mapping_input(roots[None, k:k + F.PAST], tracked[None, k:k + F.PAST]) for k in range(n)]
        assert np.array_equal(block, np.concatenate(one))


def test_joint_blocks_are_slices_or_refused():
    """An arm's or a leg's joints read as one block of rows; joints that are not
    consecutive are refused by name, not read as a wrong block."""
    from dancing_points_addon.skeleton import JOINT_INDEX, joint_block, joint_rows

    arm = [JOINT_INDEX["l" + n] for n in ("clavicle", "humerus", "radius", "wrist", "hand", "fingers", "thumb")]
    assert joint_block(arm) == slice(arm[0], arm[0] + 7)
    with pytest.raises(ValueError, match="lhumerus, lclavicle"):
        joint_block(arm[1::-1])
    spread = (JOINT_INDEX["root"], JOINT_INDEX["lowerneck"])
    assert np.array_equal(np.arange(31)[joint_rows(spread)], spread)
    assert joint_rows(spread[::-1]) == list(spread[::-1])
