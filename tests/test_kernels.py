"""One formula, two speeds: the frame loop's scalar kernels give what their
batch forms give (the rotation between two directions, a quaternion's
matrix), the same bits where the arithmetic is the same."""
from __future__ import annotations

import numpy as np

from dancing_points_addon.ik import rotation_between
from dancing_points_addon.representation import segments_gap
from dancing_points_addon.rotations import quat_to_matrix
from dancing_points_addon.scalar_kernels import I3, clip01, rot_between_s, segments_gap_s


def _pairs():
    rng = np.random.default_rng(7)
    u, v = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    u[:3] = [[1.0, 0, 0], [0, 1.0, 0], [0.3, -0.2, 0.9]]
    v[:3] = -u[:3]  # opposite directions: a half turn
    u[3], v[4] = 0.0, 0.0  # a zero vector: the identity
    v[5] = 2.5 * u[5]  # the same direction: the identity
    return u, v


def test_rotation_between_scalar_is_the_batch_form():
    u, v = _pairs()
    batch = rotation_between(u, v)
    scalar = np.array([rot_between_s(*a, *b) for a, b in zip(u.tolist(), v.tolist())]).reshape(-1, 3, 3)
    assert np.abs(batch - scalar).max() < 1e-12
    assert np.array_equal(scalar[3].ravel(), I3) and np.array_equal(scalar[4].ravel(), I3)
    np.testing.assert_allclose(scalar[5], np.eye(3), atol=1e-12)
    for a, b, R in zip(u[:3], v[:3], scalar[:3]):  # half turns take u to -u and stay rotations
        np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # every result takes u's direction to v's
    ok = np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1) > 0
    got = np.einsum("nij,nj->ni", scalar[ok], u[ok] / np.linalg.norm(u[ok], axis=1, keepdims=True))
    np.testing.assert_allclose(got, v[ok] / np.linalg.norm(v[ok], axis=1, keepdims=True), atol=1e-12)


def test_quat_to_matrix_one_and_many_agree_bit_for_bit():
    q = np.random.default_rng(3).normal(size=(100, 4)) * 1.7  # not unit: normalised on the way
    many = quat_to_matrix(q)
    one = np.array([quat_to_matrix(x) for x in q])
    assert np.array_equal(many, one)
    np.testing.assert_allclose(many @ np.swapaxes(many, -1, -2), np.broadcast_to(np.eye(3), many.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(many), 1.0, atol=1e-12)
    # a zero quaternion is no rotation: NaN, on both paths, without an exception
    assert np.isnan(quat_to_matrix(np.zeros(4))).all() and np.isnan(quat_to_matrix(np.zeros((2, 4)))).all()


def test_segments_gap_one_pair_is_the_batch_form_bit_for_bit():
    rng = np.random.default_rng(11)
    p0, p1, q0, q1 = rng.normal(size=(4, 500, 3))
    p1[:20] = p0[:20] + 0.7 * (q1[:20] - q0[:20])  # parallel segments
    p1[20:30] = p0[20:30]  # a collapsed segment
    q1[25:35] = q0[25:35]
    p0[40], p1[40] = q0[40], q1[40]  # the same segment twice
    batch = segments_gap(p0, p1, q0, q1)
    one = np.array([segments_gap_s(*x) for x in zip(p0.tolist(), p1.tolist(), q0.tolist(), q1.tolist())])
    assert np.array_equal(batch, one)
    for x in (-2.0, -0.0, 0.0, 1e-300, 0.5, 1.0, 3.0, np.inf, -np.inf):
        assert np.array_equal(np.float64(clip01(x)), np.clip(x, 0.0, 1.0))
        assert np.signbit(clip01(x)) == np.signbit(np.clip(x, 0.0, 1.0))
    assert np.isnan(clip01(np.nan))
