"""The contact network (``models/contacts.onnx``): both dancers' foot
contacts at the current frame from the leader's past 0.5 s of three points (the
mapping network's input). It times the follower's steps (her foot lock plants
and lifts her feet as it says). Beside it the pose anchor (``models/pose_anchor.onnx``),
on the same input: her lower body, which her closed-loop legs are pulled towards."""
import json

import numpy as np
import pytest

from dancing_points_addon.nets import load_nets


@pytest.fixture(scope="module")
def test_clips(salsa_dir):
    """The 13 takes' test frames (ground truth, not mirrored)."""
    from training.dataset import build_clips

    return build_clips(salsa_dir, "test", mirror_aug=False)


@pytest.fixture(scope="module")
def test_frames(test_clips):
    """The mapping input and both dancers' SPEC §6 contacts at every frame of the
    test clips."""
    from training.data import contact_samples

    return contact_samples(test_clips)


def test_contact_network_knows_when_the_feet_are_down(test_frames):
    """On the test frames, where the network says contact (p > 0.5) the foot is
    down more often than it is at all: at least 8 points of precision over the
    true contact rate, for each dancer (a network that only learnt how often a
    foot is down scores the rate itself), and it finds most of the contacts."""
    x, y = test_frames
    p = load_nets()["contacts"](x)
    assert p.shape == y.shape == (len(x), 8) and np.all((p >= 0) & (p <= 1))
    for who, cols in (("leader", slice(0, 4)), ("follower", slice(4, 8))):
        pc, tc = p[:, cols] > 0.5, y[:, cols] > 0.5
        precision = (pc & tc).sum() / pc.sum()
        recall = (pc & tc).sum() / tc.sum()
        print(f"\n{who}: precision {precision:.3f} (true contact rate {tc.mean():.3f}), recall {recall:.3f}")
        assert precision >= tc.mean() + 0.08
        assert recall >= 0.6


def test_contact_network_carries_each_dancers_floor(test_clips):
    """Its metadata holds each dancer's floor level per foot point (the median of
    the train takes' 5th-percentile heights): the follower's locks go there.
    Within 2 cm of the test frames' own floor levels, ankles above balls."""
    from dancing_points_addon.representation import floor_levels
    from dancing_points_addon.skeleton import FEET

    meta = json.loads(load_nets()["contacts"].meta["floor_levels"])
    clips = test_clips
    for role in ("leader", "follower"):
        shipped = np.array(meta[role])
        true = np.median([floor_levels(getattr(c, role).positions[:, FEET, 1]) for c in clips], axis=0)
        print(f"\n{role} floor levels (cm): shipped {np.round(shipped * 100, 1)}, "
              f"test frames {np.round(true * 100, 1)}")
        assert np.abs(shipped - true).max() < 0.02
        assert shipped[0] > shipped[1] and shipped[2] > shipped[3]


def test_pose_anchor_knows_her_legs(test_clips):
    """The pose anchor (``models/pose_anchor.onnx``): her lower body in her own
    hip frame from the leader's past 0.5 s. On the test frames it is closer to
    her true legs than the networks' prior (her tracker's default pose, the
    train pose nearest the mean): 11.2 against 12.2 cm per joint."""
    from dancing_points_addon import features as F
    from dancing_points_addon.representation import hip_frame, to_local
    from dancing_points_addon.runtime import Synthesizer
    from dancing_points_addon.skeleton import LOWER_BODY
    from training.data import anchor_samples

    x, y = anchor_samples(test_clips)
    p = load_nets()["anchor"](x)
    prior = F.pose_positions(Synthesizer().default_pose["partner"])[None]
    prior = to_local(prior, hip_frame(prior))[:, LOWER_BODY].reshape(1, -1)
    err = {k: 100 * np.linalg.norm((v - y).reshape(len(y), -1, 3), axis=-1).mean()
           for k, v in (("anchor", p), ("prior", prior))}
    print(f"\nher lower body (cm per joint): anchor {err['anchor']:.2f}, prior {err['prior']:.2f}")
    assert p.shape == y.shape and err["anchor"] <= err["prior"] - 0.5



def test_hip_heading_network_knows_where_her_hips_face(test_clips, salsa_dir):
    """The hip-heading network (``models/hip_heading.onnx``): her hip heading
    relative to his root from his past 0.5 s, over 36 bins. On the test frames the
    bins' circular mean is closer to her true hip heading than the mapping's
    prediction of her heading (her head's, the next frame's: what her hips were
    turned towards before) and than the train frames' own distribution of that
    turn (what a network that learnt only the prior would say)."""
    from dancing_points_addon import features as F
    from dancing_points_addon.partner_pose import HIP_BINS, hip_heading_from_probs
    from dancing_points_addon.representation import hip_heading
    from training.data import hip_heading_samples, mapping_inputs
    from training.dataset import build_clips

    nets = load_nets()
    prior = hip_heading_samples(build_clips(salsa_dir, "train", mirror_aug=True))[1].mean(0)
    errs = {"network": [], "mapping": [], "prior": []}
    for c in test_clips:
        x = mapping_inputs(c)
        p = nets["hip"](x)
        assert p.shape == (len(x), HIP_BINS) and np.allclose(p.sum(1), 1.0, atol=1e-4)
        true = hip_heading(c.follower.positions)
        roots = c.leader.roots
        (_, _), (f_roots, _) = F.decode_mapping(nets["mapping"](x), roots)
        guesses = {"network": np.array([hip_heading_from_probs(q, r) for q, r in zip(p, roots)]),
                   "mapping": np.arctan2(f_roots[:, 0, 3], f_roots[:, 0, 2]),
                   "prior": np.array([hip_heading_from_probs(prior, r) for r in roots])}
        for k, g in guesses.items():
            errs[k].append(np.degrees(np.abs(np.angle(np.exp(1j * (g - true))))))
    err = {k: float(np.concatenate(v).mean()) for k, v in errs.items()}
    print(f"\nher hip heading, test frames (deg): network {err['network']:.2f}, mapping {err['mapping']:.2f}, "
          f"train prior {err['prior']:.2f}")
    assert err["network"] <= err["mapping"] - 1.0
    assert err["network"] <= err["prior"] - 10.0
