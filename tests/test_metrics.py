"""SPEC §6 metrics that the runtime tests do not exercise: the pose with
placement factored out, on real frames of the CMU salsa data."""
import numpy as np
import pytest

from training import metrics as M
from training.dataset import FOLLOWER, LEADER
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.skeleton import JOINT_INDEX


@pytest.fixture(scope="module")
def duet(salsa_dir):
    lead = load_amc(f"{salsa_dir}/{LEADER}_01.amc").positions[:600:2]
    fol = load_amc(f"{salsa_dir}/{FOLLOWER}_01.amc").positions[:600:2]
    return lead, fol


def _turned_and_moved(pos, seed=0):
    """Each frame turned about the vertical by its own angle and moved on the floor."""
    rng = np.random.default_rng(seed)
    th = rng.uniform(-np.pi, np.pi, len(pos))
    c, s = np.cos(th), np.sin(th)
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    out = np.stack([c[:, None] * x + s[:, None] * z, y, -s[:, None] * x + c[:, None] * z], axis=-1)
    return out + np.array([1.5, 0.0, -2.0]) + rng.normal(0, 0.5, (len(pos), 1, 3)) * np.array([1, 0, 1])


def test_placed_pose_error_ignores_placement_and_sees_the_pose(duet):
    lead, fol = duet
    m = np.ones(len(fol), bool)
    moved = _turned_and_moved(fol)
    assert M.aggregate([M.fullbody_error(moved, fol, m)]) > 0.5  # metres: placement counts there
    assert M.aggregate([M.placed_pose_error(moved, fol, m)]) < 1e-9  # and not here
    # a pose difference is all that is left: the left wrist 10 cm higher on every frame
    bent = moved.copy()
    bent[:, JOINT_INDEX["lwrist"], 1] += 0.1
    assert M.aggregate([M.placed_pose_error(bent, fol, m)]) == pytest.approx(0.1 / 31, rel=1e-6)
    # the other dancer's body, placed: a real pose difference, neither zero nor a placement
    other = M.aggregate([M.placed_pose_error(lead, fol, m)])
    assert 0.03 < other < M.aggregate([M.fullbody_error(lead, fol, m)])
