"""Two-bone IK, foot locking and end-effector IK (dancing_points_addon.ik) on real salsa data."""
import time

import numpy as np
import pytest

from training import metrics
from support.helpers import bone_twist_deg
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.foot_lock import FootLocker, FootLockOptions
from dancing_points_addon.ik import EndEffectorIK, rotation_between, two_bone_ik
from dancing_points_addon.scalar_kernels import two_bone_s
from dancing_points_addon.representation import contact_labels, floor_levels
from dancing_points_addon.skeleton import (FEET, JOINT_INDEX, JOINT_NAMES, PARENTS, TRACKED,
                                           bone_lengths_from_positions)

J = JOINT_INDEX
LEG_BONES = [J[s + n] for s in "lr" for n in ("femur", "tibia", "foot", "toes")]


@pytest.fixture(scope="module")
def take(salsa_dir):
    m = load_amc(salsa_dir / "60_01.amc").subsample(2)  # 30 Hz
    T = 600
    return m.positions[:T].copy(), m.rotations[:T].copy(), m.bone_vectors


def _smooth_drift(rng, T, amplitude=0.03, sigma=1.0):
    """Noisy, smooth horizontal drift (T, 3), |x|, |z| <= amplitude."""
    x = rng.normal(size=(T + 60, 2))
    k = np.exp(-0.5 * (np.arange(-30, 31) / sigma) ** 2)
    y = np.stack([np.convolve(x[:, i], k, "same") for i in range(2)], 1)[30:30 + T]
    y = y / np.abs(y).max() * amplitude
    return np.stack([y[:, 0], np.zeros(T), y[:, 1]], 1)


def _angle_between(a, b):
    c = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.arccos(np.clip(c, -1.0, 1.0))


# ---------------------------------------------------------------------------
# two-bone IK


def test_two_bone_ik_lengths_reach_plane_and_rotations():
    rng = np.random.default_rng(0)
    n = 2000
    hip = rng.normal(size=(n, 3))
    knee = hip + rng.normal(size=(n, 3))
    ankle = knee + rng.normal(size=(n, 3))
    target = hip + rng.normal(size=(n, 3)) * 1.5
    pole = hip + rng.normal(size=(n, 3))
    k2, a2, R1, R2 = two_bone_ik(hip, knee, ankle, target, pole)
    l1 = np.linalg.norm(knee - hip, axis=-1)
    l2 = np.linalg.norm(ankle - knee, axis=-1)
    assert np.abs(np.linalg.norm(k2 - hip, axis=-1) - l1).max() < 1e-9
    assert np.abs(np.linalg.norm(a2 - k2, axis=-1) - l2).max() < 1e-9
    d = np.linalg.norm(target - hip, axis=-1)
    reach = (d < l1 + l2) & (d > np.abs(l1 - l2))
    assert 0.3 < reach.mean() < 0.95
    assert np.linalg.norm(a2 - target, axis=-1)[reach].max() < 1e-9
    # out of reach: on the ray hip -> target, as far/near as the chain allows
    far = d >= l1 + l2
    u = (target - hip) / d[:, None]
    assert np.abs(np.linalg.norm(a2 - hip, axis=-1) - np.clip(d, np.abs(l1 - l2), l1 + l2)).max() < 1e-9
    assert np.linalg.norm(np.cross(a2 - hip, u), axis=-1)[far].max() < 1e-9
    # knee in the plane of (hip, target, pole)
    nrm = np.cross(target - hip, pole - hip)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    assert np.abs(np.sum(nrm * (k2 - hip), -1)).max() < 1e-9
    # ... on the pole's side
    def perp(v):
        return v - np.sum(v * u, -1, keepdims=True) * u
    side = np.sum(perp(k2 - hip) * perp(pole - hip), -1)
    assert np.all(side[reach] > -1e-12)
    # rotations: proper, and they take old directions to new ones
    for R in (R1, R2):
        assert np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max() < 1e-9
        assert np.abs(np.linalg.det(R) - 1).max() < 1e-9
    assert np.abs(np.einsum("nij,nj->ni", R1, knee - hip) - (k2 - hip)).max() < 1e-9
    assert np.abs(np.einsum("nij,nj->ni", R2, ankle - knee) - (a2 - k2)).max() < 1e-9
    # the scalar kernel used by the streaming solvers agrees
    for i in range(50):
        ks, as_, R1s, R2s = two_bone_s(hip[i], knee[i], ankle[i], target[i], pole[i])
        assert np.allclose(ks, k2[i], atol=1e-12) and np.allclose(as_, a2[i], atol=1e-12)
        assert np.allclose(np.reshape(R1s, (3, 3)), R1[i], atol=1e-9)
        assert np.allclose(np.reshape(R2s, (3, 3)), R2[i], atol=1e-9)


def test_two_bone_ik_keeps_a_solved_chain_and_handles_degenerate_poles():
    hip = np.zeros(3)
    knee = np.array([0.0, -0.4, 0.05])
    ankle = np.array([0.0, -0.8, 0.0])
    k2, a2, R1, R2 = two_bone_ik(hip, knee, ankle, ankle)  # target = current ankle
    assert np.allclose(k2, knee) and np.allclose(a2, ankle)
    assert np.allclose(R1, np.eye(3)) and np.allclose(R2, np.eye(3))
    # pole on the hip-target line: falls back to the old knee's side
    k2, a2, _, _ = two_bone_ik(hip, knee, ankle, [0, -0.7, 0], pole=[0, -0.35, 0])
    assert k2[2] > 0.05 and np.isclose(np.linalg.norm(a2 - [0, -0.7, 0]), 0)
    # opposite directions: a half turn, still a rotation
    R = rotation_between([1.0, 0, 0], [-1.0, 0, 0])
    assert np.allclose(R @ [1.0, 0, 0], [-1, 0, 0]) and np.isclose(np.linalg.det(R), 1)


# ---------------------------------------------------------------------------
# foot locking


def _run_locker(locker, P, R, C):
    outP, outR = np.empty_like(P), np.empty_like(R)
    locks = []
    for t in range(len(P)):
        outP[t], outR[t] = locker.step(P[t], R[t], C[t])
        locks.append(locker.locks)
    return outP, outR, locks


def test_foot_locker_on_a_salsa_take(take):
    gt, rot, bv = take
    T = len(gt)
    floor = floor_levels(gt[:, FEET, 1])
    contacts = contact_labels(gt, 30.0, floor).astype(np.float64)
    rng = np.random.default_rng(0)
    pert = gt.copy()
    for s in "lr":  # noisy horizontal sliding of each leg below the hip (±3 cm)
        d = _smooth_drift(rng, T)
        for n in ("femur", "tibia", "foot", "toes"):
            pert[:, J[s + n]] += d
    mask = np.ones(T, bool)
    def skate(p):
        s, c = metrics.foot_skating(p, mask, floor)
        return s / c

    out, outR, locks = _run_locker(FootLocker(), pert, rot, contacts)

    sk_gt, sk_in, sk_out = skate(gt), skate(pert), skate(out)
    # skating restricted to pairs where the ground truth says "contact"
    def feet_v(p):
        return np.linalg.norm(np.diff(p[:, FEET][..., [0, 2]], axis=0), axis=-1) * 3000.0
    cpair = (contacts[1:] > 0.5) & (contacts[:-1] > 0.5)
    c_in, c_out = feet_v(pert)[cpair].mean(), feet_v(out)[cpair].mean()
    print(f"\nfoot skating (cm/s, SPEC metric): ground truth {sk_gt:.2f}, perturbed input {sk_in:.2f}, "
          f"foot-locked {sk_out:.2f} (ratio {sk_out / sk_in:.3f}); on ground-truth contact pairs: "
          f"input {c_in:.2f}, locked {c_out:.2f}")
    # the SPEC metric also counts fast, low foot motion that is no contact (the
    # ground truth itself skates ~20 cm/s on this take): the locker must remove
    # at least half of what the perturbation added, and nearly all sliding on contacts
    assert sk_out - sk_gt <= 0.5 * (sk_in - sk_gt)
    assert sk_out <= sk_gt
    assert c_out <= 0.1 * c_in

    # bone lengths of the input positions are kept (legs included)
    Lin, Lout = bone_lengths_from_positions(pert), bone_lengths_from_positions(out)
    assert np.abs(Lout - Lin).max() < 1e-3
    assert np.abs(Lout - Lin)[:, LEG_BONES].max() < 1e-9

    # no pops: nothing moves much farther per frame than in the input
    jin = np.linalg.norm(np.diff(pert, axis=0), axis=-1)
    jout = np.linalg.norm(np.diff(out, axis=0), axis=-1)
    dcorr = np.linalg.norm(np.diff(out - pert, axis=0), axis=-1)
    print(f"max per-frame jump: input {jin.max() * 100:.1f} cm, output {jout.max() * 100:.1f} cm; "
          f"max extra jump {(jout - jin).max() * 100:.1f} cm; max per-frame change of the correction "
          f"{dcorr.max() * 100:.1f} cm")
    assert jout.max() <= jin.max() + 1e-9
    assert (jout - jin).max() < 0.08
    assert dcorr.max() < 0.10

    # ankles sit on their lock points while locked (when the leg can reach them)
    errs, reachable = [], []
    for t in range(T):
        for side, (la, _) in enumerate(locks[t]):
            if la is None:
                continue
            hip, knee, ankle = (pert[t, J[("l", "r")[side] + n]] for n in ("hipjoint", "femur", "tibia"))
            reach = np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee)
            errs.append(np.linalg.norm(out[t, FEET[2 * side]] - la))
            reachable.append(np.linalg.norm(np.asarray(la) - hip) < reach - 1e-6)
    errs, reachable = np.array(errs), np.array(reachable)
    print(f"ankle-locked frames {len(errs)}: within 1 mm {np.mean(errs < 1e-3):.1%}, reachable "
          f"{reachable.mean():.1%}, max error when reachable {errs[reachable].max():.2e} m, "
          f"overall max {errs.max() * 100:.2f} cm")
    assert len(errs) > 200
    assert errs[reachable].max() < 1e-6
    assert np.mean(errs < 1e-3) > 0.9

    # rotations stay rotations and agree with the positions as well as the input's did
    assert np.abs(outR @ np.swapaxes(outR, -1, -2) - np.eye(3)).max() < 1e-9
    def starts(p):
        return p[:, np.maximum(PARENTS, 0)]
    for b in LEG_BONES:
        a_in = _angle_between(pert[:, b] - starts(pert)[:, b], rot[:, b] @ bv[b])
        a_out = _angle_between(out[:, b] - starts(out)[:, b], outR[:, b] @ bv[b])
        assert np.abs(a_out - a_in).max() < 1e-6, JOINT_NAMES[b]
    untouched = [i for i in range(31) if i not in LEG_BONES]
    assert np.array_equal(out[:, untouched], pert[:, untouched])
    assert np.array_equal(outR[:, untouched], rot[:, untouched])


def test_foot_locker_is_causal_and_resets(take):
    gt, rot, _ = take
    C = contact_labels(gt[:200], 30.0).astype(float)
    locker = FootLocker()
    a, ar, _ = _run_locker(locker, gt[:200], rot[:200], C)
    locker.reset()
    b, br, _ = _run_locker(locker, gt[:120], rot[:120], C[:120])  # a prefix gives the same frames
    assert np.array_equal(a[:120], b) and np.array_equal(ar[:120], br)
    # no contact: the prediction passes through untouched
    c, cr, _ = _run_locker(FootLocker(), gt[:50], rot[:50], np.zeros((50, 4)))
    assert np.array_equal(c, gt[:50]) and np.array_equal(cr, rot[:50])


def test_foot_locker_floor_snap(take):
    gt, rot, _ = take
    P, R = gt[:300], rot[:300]
    floor = floor_levels(gt[:, FEET, 1])
    C = contact_labels(gt, 30.0, floor)[:300].astype(float)
    out, _, locks = _run_locker(FootLocker(floor=floor), P, R, C)
    seen = 0
    for t in range(1, len(P)):
        for side in (0, 1):
            for k, lock in enumerate(locks[t][side]):
                if lock is not None and locks[t - 1][side][k] is not lock:  # engaged at t
                    # snapped down to the floor level, never raised above the point's current
                    # output height (the output blends from there onto the lock)
                    assert lock[1] <= floor[2 * side + k] + 1e-12
                    assert lock[1] <= out[t, FEET[2 * side + k], 1] + 1e-3
                    seen += 1
    assert seen > 10
    dcorr = np.linalg.norm(np.diff(out - P, axis=0), axis=-1)
    assert dcorr.max() < 0.10


def test_foot_locker_release_blends_back_to_the_prediction(take):
    gt, rot, _ = take
    T, N = 40, 6
    P = gt[:T].copy()
    P[:, [J["ltibia"], J["lfoot"], J["ltoes"]]] += np.linspace(0, 0.08, T)[:, None, None] * [1.0, 0, 0]
    C = np.zeros((T, 4))
    C[:20, 0] = 0.9  # left ankle in contact for 20 frames, then released
    C[20:, 0] = 0.5  # between the thresholds: hysteresis keeps the lock
    C[25:, 0] = 0.1
    out, _, locks = _run_locker(FootLocker(FootLockOptions(blend_frames=N)), P, rot[:T], C)
    ankle = J["ltibia"]
    assert all(locks[t][0][0] is not None for t in range(25))
    assert np.allclose(out[:25, ankle], out[0, ankle], atol=1e-6)  # locked
    assert locks[25][0][0] is None
    assert np.linalg.norm(out[25 + N - 1, ankle] - P[25 + N - 1, ankle]) > 1e-4  # still blending
    assert np.array_equal(out[25 + N:], P[25 + N:])  # then back on the prediction
    step = np.linalg.norm(np.diff(out[:, ankle], axis=0), axis=-1)
    assert step.max() < 0.04  # a 7 cm offset released over 6 frames, no pop


def test_foot_locker_step_time(take):
    gt, rot, _ = take
    locker = FootLocker()
    c1 = np.ones(4)
    for t in range(5):
        locker.step(gt[100 + t], rot[100 + t], c1)
    n = 1000
    t0 = time.perf_counter()
    for _ in range(n):
        locker.step(gt[105], rot[105], c1)
    us = (time.perf_counter() - t0) / n * 1e6
    free = FootLocker()
    t0 = time.perf_counter()
    for _ in range(n):
        free.step(gt[105], rot[105], np.zeros(4))
    us_free = (time.perf_counter() - t0) / n * 1e6
    print(f"\nFootLocker.step: {us:.1f} µs with both feet locked, {us_free:.1f} µs free")
    assert us < 1000  # generous: a shared CI machine; the target is < 40 µs


# ---------------------------------------------------------------------------
# end-effector IK


def _subtree(root):
    out = [root]
    for c in range(31):
        if PARENTS[c] in out and c not in out:
            out.append(c)
    return out


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _perturb_upper_body(rng, P, R):
    """Turn the upper arms, forearms and neck of a real pose by up to ~20°."""
    P, R = P.copy(), R.copy()
    for bone, amp in [(s + b, a) for s in "lr" for b, a in (("humerus", 0.35), ("radius", 0.4))] + [("lowerneck", 0.3)]:
        D = _rot(rng.normal(size=3), rng.uniform(-amp, amp))
        sub = _subtree(J[bone])
        piv = P[PARENTS[J[bone]]]
        P[sub] = (P[sub] - piv) @ D.T + piv
        R[sub] = D @ R[sub]
    return P, R


@pytest.mark.parametrize("lean", [0.0, 0.5])
def test_end_effector_ik_hits_the_tracked_points(take, lean):
    gt, rot, bv = take
    rng = np.random.default_rng(1)
    ee = EndEffectorIK(lean=lean)
    spine = [J["lowerback"], J["upperback"], J["thorax"]]
    before, after = [], []
    for f in range(0, 600, 12):
        P, R = _perturb_upper_body(rng, gt[f], rot[f])
        target = gt[f, TRACKED] + rng.normal(size=(3, 3)) * 0.01  # the tracked points, ±1 cm
        out, outR = ee.step(P, R, target)
        before.append(np.linalg.norm(P[TRACKED] - target, axis=-1))
        after.append(np.linalg.norm(out[TRACKED] - target, axis=-1))
        L0 = bone_lengths_from_positions(P[None])[0]
        L1 = bone_lengths_from_positions(out[None])[0]
        dl = np.abs(L1 - L0)
        assert dl[spine].max() <= ee.max_stretch / 3 + 1e-9
        dl[spine] = 0
        assert dl.max() < 1e-9
        # rotations stay consistent with the positions as far as they were
        st_in, st_out = P[np.maximum(PARENTS, 0)], out[np.maximum(PARENTS, 0)]
        a_in = _angle_between(P[1:] - st_in[1:], np.einsum("nab,nb->na", R[1:], bv[1:]))
        a_out = _angle_between(out[1:] - st_out[1:], np.einsum("nab,nb->na", outR[1:], bv[1:]))
        assert np.abs(a_out - a_in).max() < 1e-6
        assert np.allclose(outR[J["head"]], R[J["head"]])  # the head keeps its measured orientation
        assert np.array_equal(out[:11], P[:11])  # root and legs untouched
    before, after = np.array(before), np.array(after)
    print(f"\nEndEffectorIK(lean={lean}): tracked-point error {before.mean() * 100:.2f} cm before, "
          f"{after.mean() * 100:.2e} cm after (max {after.max() * 1000:.2e} mm)")
    assert before.mean() > 0.03
    assert after.max() < 1e-6


def test_end_effector_ik_reach_and_lost_tracking(take):
    gt, rot, _ = take
    P, R = gt[300], rot[300]
    ee = EndEffectorIK()
    # a wrist target 8 cm beyond the straight arm: the clavicle helps
    sh, wr = P[J["lclavicle"]], P[J["lwrist"]]
    arm = (np.linalg.norm(P[J["lhumerus"]] - sh) + np.linalg.norm(wr - P[J["lhumerus"]]))
    far = sh + (wr - sh) / np.linalg.norm(wr - sh) * (arm + 0.08)
    target = np.stack([P[TRACKED[0]], far, P[TRACKED[2]]])
    out, _ = ee.step(P, R, target)
    assert np.linalg.norm(out[J["lwrist"]] - far) < 1e-6
    L0 = bone_lengths_from_positions(P[None])[0]
    assert np.abs(bone_lengths_from_positions(out[None])[0] - L0).max() < 1e-9
    # far out of reach: as close as possible, lengths kept, nothing explodes
    target[1] = sh + np.array([3.0, 0, 0])
    out, outR = ee.step(P, R, target)
    assert np.all(np.isfinite(out)) and np.abs(bone_lengths_from_positions(out[None])[0] - L0).max() < 1e-9
    # lost tracking (NaN): that chain is left alone
    target = P[TRACKED] + 0.05
    target[2] = np.nan
    out, outR = ee.step(P, R, target)
    rarm = _subtree(J["rhumerus"])
    assert np.allclose(out[rarm] - out[J["rclavicle"]], P[rarm] - P[J["rclavicle"]])
    assert np.linalg.norm(out[J["lwrist"]] - target[1]) < 1e-6


def test_end_effector_ik_step_time(take):
    gt, rot, _ = take
    ee = EndEffectorIK()
    P, R = gt[100], rot[100]
    target = P[TRACKED] + 0.02
    n = 1000
    t0 = time.perf_counter()
    for _ in range(n):
        ee.step(P, R, target)
    us = (time.perf_counter() - t0) / n * 1e6
    print(f"\nEndEffectorIK.step: {us:.1f} µs")
    assert us < 2000


def test_foot_locker_drift_release_is_a_step_not_a_slide(take):
    """A planted foot whose prediction slides away (contact stays on) is released
    when it drifts past ``max_drift`` and catches up by stepping: every blend
    frame between release and landing is above the SPEC skating height, so the
    foot never moves horizontally while low."""
    P, R, C = _drifting_lock(take)  # slides 60 cm over 2 s, contact all along
    T = len(P)
    locker = FootLocker()
    out, _, locks = _run_locker(locker, P, R, C)
    ankle, ball = J["ltibia"], J["lfoot"]
    released = [t for t in range(1, T) if locks[t - 1][0][0] is not None and locks[t][0][0] is None]
    assert released, "the drifting lock must be released"
    plant = out[released[0] - 1, ankle, 1]
    for t in released:
        mid = out[t + 1:t + locker.blend_frames - 2]
        assert (mid[:, ankle, 1] > plant + 0.025).all() and (mid[:, ball, 1] > P[t, ball, 1] + 0.02).all()
    low = (out[:, [ankle, ball], 1] - out[:, [ankle, ball], 1].min(0)) < 0.025
    speed = np.linalg.norm(np.diff(out[:, [ankle, ball]][..., [0, 2]], axis=0), axis=-1) * 30.0
    pairs = low[1:] & low[:-1]
    print(f"\ndrifting foot: {len(released)} release(s); horizontal speed on low frame pairs "
          f"{speed[pairs].mean() * 100:.2f} cm/s (prediction: 30 cm/s)")
    assert speed[pairs].mean() < 0.25 * 0.30  # the slide itself is 30 cm/s


def test_foot_locker_relock_during_a_step_lands_smoothly(take):
    """A contact that comes on in the middle of a catch-up step waits for the
    landing: the step completes (no drop from the lifted height, never below
    where the foot was planted), then the point locks where the foot landed."""
    P, R, C = _drifting_lock(take)
    T = len(P)
    C[:, 1] = 0.0  # the ankle's contact only
    first = _run_locker(FootLocker(), P, R, C)[2]
    rel = next(t for t in range(1, T) if first[t - 1][0][0] is not None and first[t][0][0] is None)
    C[rel + 3:, 1] = 0.9  # the ball contact comes on three frames into the step
    out, _, locks = _run_locker(FootLocker(), P, R, C)
    ankle = J["ltibia"]
    plant = out[rel - 1, ankle, 1]
    y = out[rel - 1:rel + 12, ankle, 1] - plant
    print("\nankle height over the step and re-lock (cm): " + " ".join(f"{v * 100:.1f}" for v in y))
    N = FootLocker().blend_frames
    ball_locked = [t for t in range(rel, T) if locks[t][0][1] is not None]
    assert ball_locked and ball_locked[0] == rel + N  # not in the air: on landing
    assert y.min() > -1e-3 and np.abs(np.diff(y)).max() < 0.03
    assert abs(out[rel + N + 2, ankle, 1] - P[rel + N + 2, ankle, 1]) < 1e-3  # landed on the prediction


def _drifting_lock(take, T=60):
    """A standing frame whose left foot (prediction) slides 60 cm forward over
    2 s with its ankle and ball contact on all along: the lock drifts and is
    released into catch-up steps."""
    gt, rot, _ = take
    P = np.repeat(gt[100:101], T, axis=0)
    R = np.repeat(rot[100:101], T, axis=0)
    P[:, [J["ltibia"], J["lfoot"], J["ltoes"]]] += np.linspace(0, 0.6, T)[:, None, None] * [1.0, 0, 0]
    C = np.zeros((T, 4))
    C[:, 0] = C[:, 1] = 0.9
    return P, R, C


def test_foot_locker_step_frames_sets_the_catch_up_steps_length(take):
    """``step_frames`` is the catch-up step's length apart from the lock's blend:
    after a drift release the foot is in the air for that many frames, then the
    point locks again on landing (with the default, ``blend_frames``, it is in
    the air for ``blend_frames``)."""
    P, R, C = _drifting_lock(take)
    for kw, n in (({}, 10), ({"step_frames": 5}, 5), ({"step_frames": 14}, 14)):
        locks = _run_locker(FootLocker(FootLockOptions(blend_frames=10, max_drift=0.1, **kw)), P, R, C)[2]
        released = [t for t in range(1, len(P)) if locks[t - 1][0][0] is not None and locks[t][0][0] is None]
        relocked = [next(u for u in range(t, len(P)) if locks[u][0][0] is not None) for t in released[:-1]]
        assert released and relocked
        assert all(u - t == n for t, u in zip(released, relocked)), (kw, released, relocked)


def test_foot_locker_heel_released_alone_relocks_after_the_locks_blend(take):
    """The heel slides 20 cm while the ball stays (ball prediction still): the
    ankle lock drifts off and the side stays planted on its ball. The ankle may
    lock again once the lock's blend is over, whatever the catch-up step's
    length (a whole-side release waits for the step; this is not one)."""
    gt, rot, _ = take
    T = 60
    P = np.repeat(gt[100:101], T, axis=0)
    R = np.repeat(rot[100:101], T, axis=0)
    P[:, J["ltibia"]] += np.linspace(0, 0.2, T)[:, None] * [1.0, 0, 0]
    C = np.zeros((T, 4))
    C[:, 0] = C[:, 1] = 0.9
    for step_frames in (5, 10, 14):
        options = FootLockOptions(blend_frames=10, max_drift=0.05, step_frames=step_frames)
        locks = _run_locker(FootLocker(options), P, R, C)[2]
        assert all(lk[0][1] is not None for lk in locks)  # the ball holds throughout
        off = next(t for t in range(1, T) if locks[t - 1][0][0] is not None and locks[t][0][0] is None)
        back = next((t for t in range(off, T) if locks[t][0][0] is not None), None)
        assert back == off + 10, (step_frames, off, back)


def test_foot_locker_step_and_swing_hand_off_without_a_pop(take):
    """A foot swept forward at 0.9 m/s whose contact comes and goes (15 frames
    off, 15 on): it swings (lifted by the clearance), plants, steps when the lock
    drifts or lets go, and swings again. The step lifts from where the foot was
    planted (its ball too) and the swing after a plant rises from the floor
    again (its clearance does not carry over from before the plant), so the
    foot never moves up or down more than 3 cm a frame: the step's own first
    rise is 6 · sin(π / 7) = 2.6 cm. (Before, the carried-over clearance made it
    jump 4.9 cm.)"""
    P, R = _swinging_foot(take, T=60, speed=0.9)
    ankle, ball = J["ltibia"], J["lfoot"]
    floor = [P[0, ankle, 1], P[0, ball, 1], P[0, J["rtibia"], 1], P[0, J["rfoot"], 1]]
    C = np.zeros((60, 4))
    C[15:30, :2] = C[45:, :2] = 0.9
    locker = FootLocker(FootLockOptions(blend_frames=10, step_frames=7, step_height=0.04, step_max=0.06, max_drift=0.3,
                                        clearance=0.05, clear_rate=0.125, lift_ball=True, land_still=True),
                        floor=floor)
    out, _, locks = _run_locker(locker, P, R, C)
    assert any(lk[0] == (None, None) for lk in locks[15:30]) or any(lk[0][0] is not None for lk in locks[15:30])
    jump = np.abs(np.diff(out[:, [ankle, ball], 1], axis=0)).max()
    print(f"\nlargest vertical move of the ankle or ball in a frame: {jump * 100:.2f} cm")
    assert jump < 0.03


def test_foot_locker_lift_ball_lifts_the_whole_foot(take):
    """A catch-up step whose predicted foot turns toes-down as it leaves (the ball
    4 cm lower than where it was planted): the ankle is lifted either way, but
    only with ``lift_ball`` does the ball leave the floor too (at least
    ``step_height · sin(π k / N)`` over where it was planted, k frames into the
    step, within 5 mm); without it the ball drags along under its planted height
    (SPEC §6 counts that as skating)."""
    P, R, C = _drifting_lock(take)
    ankle, ball = J["ltibia"], J["lfoot"]
    N, h = 7, 0.04
    worst = {}
    for lift_ball in (True, False):
        locker = FootLocker(FootLockOptions(blend_frames=10, step_frames=N, step_height=h, step_max=h, max_drift=0.1,
                                            lift_ball=lift_ball))
        locks = _run_locker(locker, P, R, C)[2]
        t = next(t for t in range(1, len(P)) if locks[t - 1][0] != (None, None) and locks[t][0] == (None, None))
        Q = P.copy()
        Q[t:, [ball, J["ltoes"]], 1] -= 0.04  # toes down from the release on
        locker = FootLocker(FootLockOptions(blend_frames=10, step_frames=N, step_height=h, step_max=h, max_drift=0.1,
                                            lift_ball=lift_ball))
        out, _, locks = _run_locker(locker, Q, R, C)
        assert locks[t - 1][0] != (None, None) and locks[t][0] == (None, None)
        a0, b0 = out[t - 1, ankle, 1], out[t - 1, ball, 1]  # planted heights
        gaps = []
        for k in range(1, N):  # frame t + k - 1 is k frames into the step
            lift = h * np.sin(np.pi * k / N)
            assert out[t + k - 1, ankle, 1] >= a0 + lift - 1e-6
            gaps.append(out[t + k - 1, ball, 1] - (b0 + lift))
        worst[lift_ball] = min(gaps)
    print(f"\nball over its planted height + the step's lift, worst frame (cm): with lift_ball "
          f"{worst[True] * 100:.2f}, without {worst[False] * 100:.2f}")
    # (the step lifts from the ball's height on the release frame, which the predicted foot's
    # new length moves by a few millimetres from the last planted frame's)
    assert worst[True] >= -0.005
    assert worst[False] < -0.02


def _swinging_foot(take, T=40, speed=0.9):
    """The left foot of a standing frame swept forward along the floor at
    ``speed`` m/s (prediction), everything else still."""
    gt, rot, _ = take
    P = np.repeat(gt[100:101], T, axis=0)
    R = np.repeat(rot[100:101], T, axis=0)
    leg = [J["ltibia"], J["lfoot"], J["ltoes"]]
    P[:, leg] += (np.arange(T) * speed / 30.0)[:, None, None] * [1.0, 0, 0]
    return P, R


def test_foot_locker_clearance_lifts_a_fast_free_foot(take):
    """A free foot sweeping along the floor at 0.9 m/s is lifted by the swing
    clearance (full above 0.6 m/s, reached at most a quarter a frame): both its
    points ``clearance`` over their floors once up to speed; a foot slower than
    0.3 m/s and the other, still foot pass through untouched."""
    P, R = _swinging_foot(take)
    ankle, ball, rankle = J["ltibia"], J["lfoot"], J["rtibia"]
    floor = [P[0, ankle, 1], P[0, ball, 1], P[0, rankle, 1], P[0, J["rfoot"], 1]]
    out, _, locks = _run_locker(FootLocker(FootLockOptions(clearance=0.05), floor=floor), P, R, np.zeros((len(P), 4)))
    assert all(lk == [(None, None), (None, None)] for lk in locks)
    lift = np.minimum(out[:, ankle, 1] - floor[0], out[:, ball, 1] - floor[1])
    print("\nswing clearance over the first frames (cm): " + " ".join(f"{v * 100:.1f}" for v in lift[:8]))
    assert np.all(lift[6:] > 0.05 - 1e-6) and np.abs(np.diff(lift)).max() <= 0.0125 + 1e-6
    assert np.allclose(out[:, rankle], P[:, rankle])
    slow, _ = _swinging_foot(take, speed=0.25)
    out2, _, _ = _run_locker(FootLocker(FootLockOptions(clearance=0.05), floor=floor), slow, R, np.zeros((len(P), 4)))
    assert np.allclose(out2, slow)


def test_foot_locker_clear_rate_sets_how_fast_the_clearance_rises(take):
    """``clear_rate``: the swing clearance's lift changes by at most that share of
    ``clearance`` a frame (a sixteenth: 3 mm a frame for 5 cm), and still gets
    there."""
    P, R = _swinging_foot(take, T=40)
    ankle, ball = J["ltibia"], J["lfoot"]
    floor = [P[0, ankle, 1], P[0, ball, 1], P[0, J["rtibia"], 1], P[0, J["rfoot"], 1]]
    locker = FootLocker(FootLockOptions(clearance=0.05, clear_rate=1 / 16), floor=floor)
    out, _, _ = _run_locker(locker, P, R, np.zeros((40, 4)))
    lift = np.minimum(out[:, ankle, 1] - floor[0], out[:, ball, 1] - floor[1])
    assert np.abs(np.diff(lift)).max() <= 0.05 / 16 + 1e-6
    assert np.all(lift[20:] > 0.05 - 1e-6)


def test_foot_locker_land_still_plants_where_the_foot_was(take):
    """A free foot moving at 0.9 m/s whose contact comes on as it stops: with
    ``land_still`` it plants where it was on the frame before (no horizontal
    motion into the lock, so no skating on the landing), without it the landing
    frame still carries the foot's 3 cm of motion; then it stays put."""
    P, R = _swinging_foot(take)
    P[21:] = P[20]  # the prediction stops where the contact comes on
    ankle = J["ltibia"]
    C = np.zeros((len(P), 4))
    C[20:, 0] = C[20:, 1] = 0.9
    for still in (True, False):
        out, _, locks = _run_locker(FootLocker(FootLockOptions(land_still=still)), P, R, C)
        assert locks[19][0] == (None, None) and locks[20][0][0] is not None
        step = np.linalg.norm((out[20, ankle] - out[19, ankle])[[0, 2]])
        after = np.linalg.norm(np.diff(out[20:, ankle][:, [0, 2]], axis=0), axis=-1).max()
        print(f"\nland_still={still}: ankle moves {step * 100:.2f} cm into the lock, "
              f"then at most {after * 100:.2f} cm a frame")
        assert after < 1e-9
        assert (step < 1e-9) if still else (step > 0.02)


def test_swing_arm_ik_reaches_keeps_lengths_and_bends_as_a_hinge(take):
    """``EndEffectorIK(arm="swing")`` on perturbed real poses: the wrists land on
    their targets, every bone keeps its length, the rotations stay consistent
    with the positions, and the elbow stays a hinge: the forearm's turn
    relative to the upper arm is about the bend plane's normal (the angle
    between the upper arm's and the forearm's roll changes by no more than
    the elbow's own flexion), so the forearm does not spin about itself. (The
    pole method's minimal rotations fail this: 32° beyond the flexion.)"""
    gt, rot, bv = take
    rng = np.random.default_rng(3)
    ee = EndEffectorIK(arm="swing")
    worst_roll = 0.0
    for f in range(0, 600, 12):
        P, R = _perturb_upper_body(rng, gt[f], rot[f])
        target = gt[f, TRACKED] + rng.normal(size=(3, 3)) * 0.02  # the tracked points, ±2 cm
        target[0] = np.nan  # the arms only
        out, outR = ee.step(P, R, target)
        assert np.linalg.norm(out[TRACKED[1:]] - target[1:], axis=-1).max() < 1e-6
        L0 = bone_lengths_from_positions(P[None])[0]
        assert np.abs(bone_lengths_from_positions(out[None])[0] - L0).max() < 1e-9
        st_in, st_out = P[np.maximum(PARENTS, 0)], out[np.maximum(PARENTS, 0)]
        a_in = _angle_between(P[1:] - st_in[1:], np.einsum("nab,nb->na", R[1:], bv[1:]))
        a_out = _angle_between(out[1:] - st_out[1:], np.einsum("nab,nb->na", outR[1:], bv[1:]))
        assert np.abs(a_out - a_in).max() < 1e-6
        for s in "lr":
            # the forearm's rotation relative to the upper arm, before and after:
            # a hinge changes it only by a turn about the elbow's axis (the bend
            # plane's normal), i.e. its angle changes by the flexion change
            h, r = J[s + "humerus"], J[s + "radius"]
            rel0, rel1 = R[h].T @ R[r], outR[h].T @ outR[r]
            d = rel1 @ rel0.T
            turn = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
            sh, el, wr = J[s + "clavicle"], J[s + "humerus"], J[s + "wrist"]
            flex = [_angle_between(p[el] - p[sh], p[wr] - p[el]) for p in (P, out)]
            worst_roll = max(worst_roll, turn - abs(np.degrees(flex[1] - flex[0])))
    print(f"\nswing arm IK: largest forearm turn beyond the elbow's flexion {worst_roll:.2e} deg")
    assert worst_roll < 1e-4


def test_end_effector_ik_rejects_an_unknown_arm_method():
    with pytest.raises(ValueError, match="arm must be"):
        EndEffectorIK(arm="ccd")


# ---------------------------------------------------------------------------
# arm speed limit and leg joints


def _rel_turns(R, bones, ref=J["thorax"]):
    """Per frame and bone, the turn (degrees) of each bone relative to ``ref`` since the last frame."""
    rel = np.einsum("tji,tbjk->tbik", R[:, ref], R[:, bones])
    step = np.einsum("tbji,tbjk->tbik", rel[:-1], rel[1:])
    return np.degrees(np.arccos(np.clip((np.trace(step, axis1=2, axis2=3) - 1) / 2, -1, 1)))


def test_arm_turn_limit_passes_real_arms_and_slows_a_flip(take):
    """``ArmTurnLimit(30)``: a real dancer's arms (take 60_01, 20 s) pass bit for
    bit; a forearm flipped by 130 degrees in one frame (what a stateless arm IK
    does when a hold's target passes the shoulder) turns 30 degrees a frame
    towards its new pose instead, reaches it in five frames and then follows
    it exactly; bone lengths and the rigid hand stay."""
    from dancing_points_addon.ik import ArmTurnLimit

    P, R, _ = take
    arms = [J[s + n] for s in "lr" for n in ("humerus", "radius")]
    assert _rel_turns(R, arms).max() < 30.0  # (the real arms stay under the limit)
    lim = ArmTurnLimit(30.0)
    for t in range(len(P)):
        p, r = lim.step(P[t].copy(), R[t].copy())
        assert np.array_equal(p, P[t]) and np.array_equal(r, R[t])
    assert lim.engaged == 0

    # a flip: from frame 100 on, the left forearm group turned by 130 degrees about the upper arm's axis
    el, group = J["lhumerus"], [J["l" + n] for n in ("radius", "wrist", "hand", "fingers", "thumb")]
    Pf, Rf = P[:160].copy(), R[:160].copy()
    for t in range(100, 160):
        axis = Pf[t, el] - Pf[t, J["lclavicle"]]
        Q = rotation_about(axis / np.linalg.norm(axis), np.radians(130.0))
        Pf[t, group] = (Pf[t, group] - Pf[t, el]) @ Q.T + Pf[t, el]
        Rf[t, group] = Q @ Rf[t, group]
    lim.reset()
    out = [lim.step(Pf[t].copy(), Rf[t].copy()) for t in range(160)]
    Po, Ro = np.array([o[0] for o in out]), np.array([o[1] for o in out])
    turns = _rel_turns(Ro, arms)
    print(f"\nflip: largest forearm turn {_rel_turns(Rf, arms).max():.1f} deg a frame, limited "
          f"{turns.max():.1f}; engaged on {lim.engaged} frames")
    assert _rel_turns(Rf, arms)[99].max() > 120.0 and turns.max() <= 30.0 + 1e-6
    assert 4 <= lim.engaged <= 5
    np.testing.assert_allclose(Po[105:], Pf[105:], atol=1e-9)
    np.testing.assert_allclose(Ro[105:], Rf[105:], atol=1e-9)
    chain = np.linalg.norm(Po[:, 1:] - Po[:, PARENTS[1:]], axis=-1)
    np.testing.assert_allclose(chain, np.linalg.norm(Pf[:, 1:] - Pf[:, PARENTS[1:]], axis=-1), atol=1e-9)
    g = Po[:, group] - Po[:, [J["lradius"]]]
    gf = Pf[:, group] - Pf[:, [J["lradius"]]]
    np.testing.assert_allclose(np.einsum("tgi,tgi->tg", g, g), np.einsum("tgi,tgi->tg", gf, gf), atol=1e-9)


def rotation_about(axis, angle):
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_leg_joints_put_hips_on_the_pelvis_and_limit_twist(salsa_dir):
    """``pose.LegJoints`` on the follower's real legs (take 61_01, 20 s): her
    hip joints already turn with her pelvis and her leg twists are within the
    limits, so nothing moves (to rounding). Her hip joint bones swung 25
    degrees off the pelvis and her thighs twisted 80 degrees: the hip joints go
    back on the pelvis (the legs move with them, keeping their shape) and the
    thighs' twist comes back to 45 degrees without moving a joint (the data are
    float32: equal within 1e-6)."""
    from dancing_points_addon.pose import LEG_CHAINS, LegJoints

    m = load_amc(salsa_dir / "61_01.amc").subsample(2)
    P, R = m.positions[:600], m.rotations[:600]
    legs = LegJoints(m.bone_vectors)
    for t in range(0, 600, 7):
        p, r = legs(P[t].copy(), R[t].copy())
        np.testing.assert_allclose(p, P[t], atol=1e-6)  # (the data are float32)
        np.testing.assert_allclose(r, R[t], atol=1e-6)

    Pb, Rb = P[::7].copy(), R[::7].copy()
    for chain in LEG_CHAINS:
        h, f = chain[0], chain[1]
        for t in range(len(Pb)):  # the hip joint bone swung about the pelvis
            Q = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(25.0))
            Pb[t, chain] = (Pb[t, chain] - Pb[t, 0]) @ Q.T + Pb[t, 0]
            Rb[t, chain] = Q @ Rb[t, chain]
            d = Pb[t, f] - Pb[t, h]  # the thigh twisted about itself
            Q = rotation_about(d / np.linalg.norm(d), np.radians(80.0))
            Rb[t, f] = Q @ Rb[t, f]
    assert np.abs(bone_twist_deg(Rb, Pb, LEG_CHAINS[0][1])).min() > 45.0
    out = [legs(Pb[t].copy(), Rb[t].copy()) for t in range(len(Pb))]
    Po, Ro = np.array([o[0] for o in out]), np.array([o[1] for o in out])
    for chain in LEG_CHAINS:
        np.testing.assert_allclose(Ro[:, chain[0]], Ro[:, 0], atol=1e-12)
        np.testing.assert_allclose(Po[:, chain[0]], P[::7, chain[0]], atol=1e-6)  # back where the pelvis has it
        shape = Po[:, chain[1:]] - Po[:, chain[:1]]
        np.testing.assert_allclose(shape, Pb[:, chain[1:]] - Pb[:, chain[:1]], atol=1e-9)  # the leg's shape kept
        tw = np.abs(bone_twist_deg(Ro, Po, chain[1]))
        print(f"\nthigh twist after: {tw.min():.2f}..{tw.max():.2f} deg")
        assert tw.max() <= 45.0 + 1e-6 and np.mean(np.abs(tw - 45.0) < 1e-6) > 0.9
        np.testing.assert_allclose(np.abs(bone_twist_deg(Ro, Po, chain[2])), 0.0, atol=1e-6)  # the shin: a hinge
