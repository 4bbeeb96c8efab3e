"""Procedural body, rigid bone transforms and linear blend skinning on the real CMU skeleton."""
import numpy as np
import pytest

from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.ik import bone_transforms, transforms_to_matrices
from dancing_points_addon.skeleton import rest_starts
from dancing_points_addon.skeleton import JOINT_INDEX, PARENTS
from dancing_points_addon.skinning import lbs, lbs_frame, make_body

J = JOINT_INDEX


@pytest.fixture(scope="module")
def motion(salsa_dir):
    return load_amc(salsa_dir / "60_01.amc").subsample(2)


@pytest.fixture(scope="module")
def body(motion):
    return make_body(motion.bone_vectors)


def test_body_mesh_and_weights(body):
    V, F = body.vertices, body.faces
    print(f"\nbody: {len(V)} vertices, {len(F)} triangles, parts {body.part_names}")
    assert 3000 <= len(V) <= 6500
    assert F.dtype.kind == "i" and F.shape[1] == 3
    assert F.min() == 0 and F.max() == len(V) - 1
    assert np.all(np.isfinite(V))
    # no degenerate faces, no repeated corners
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    assert area.min() > 1e-7
    assert np.all((F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2]))
    # closed parts face outwards (positive signed volume)
    for p, name in enumerate(body.part_names):
        f = F[body.part[F[:, 0]] == p]
        vol = np.einsum("ij,ij->i", V[f[:, 0]], np.cross(V[f[:, 1]], V[f[:, 2]])).sum() / 6
        assert vol > 0, name
    # weights
    assert body.indices.shape == body.weights.shape and body.indices.shape[0] == len(V)
    assert body.indices.min() >= 0 and body.indices.max() < 31
    assert np.all(np.isfinite(body.weights)) and body.weights.min() >= 0
    assert np.abs(body.weights.sum(1) - 1).max() < 1e-12
    W = body.dense_weights()
    assert np.abs(W.sum(1) - 1).max() < 1e-12
    # each part is driven by its own bones; joints blend smoothly (several influences)
    head = body.part == body.part_names.index("head")
    assert W[head][:, J["head"]].mean() > 0.8
    lleg = body.part == body.part_names.index("lleg")
    assert set(np.unique(body.indices[lleg][body.weights[lleg] > 0])) <= {J["lhipjoint"], J["lfemur"], J["ltibia"]}
    knee = body.rest_start[J["ltibia"]]
    near_knee = lleg & (np.linalg.norm(body.vertices - knee, axis=1) < 0.07)
    assert near_knee.sum() > 10
    assert np.all(W[near_knee][:, J["lfemur"]] > 0.2) and np.all(W[near_knee][:, J["ltibia"]] > 0.2)
    # a plausible human: ~1.7 m tall in rest pose (head top to sole), wider at the shoulders than the hips
    assert 1.5 < np.ptp(V[:, 1]) < 2.0


def test_rest_pose_and_identity_reproduce_the_mesh(body, motion):
    V = body.vertices
    eye = np.broadcast_to(np.eye(3), (31, 3, 3))
    assert np.abs(lbs_frame(body, (eye, np.zeros((31, 3)))) - V).max() < 1e-9
    # the rest pose through bone_transforms: positions = rest ends, rotations = identity
    ends = rest_starts(motion.bone_vectors) + motion.bone_vectors
    R, t = bone_transforms(ends[None].repeat(3, 0), eye[None].repeat(3, 0), body.rest_start)
    assert np.abs(t).max() < 1e-12
    X = lbs(body, (R, t))
    assert X.shape == (3, len(V), 3) and np.abs(X - V).max() < 1e-9
    assert np.abs(lbs(body, transforms_to_matrices(R, t)) - V).max() < 1e-9


def test_bone_transforms_map_rest_bones_to_posed_bones(motion, body):
    P, R = motion.positions[::100], motion.rotations[::100]  # FK motion: positions agree with rotations
    Rb, t = bone_transforms(P, R, body.rest_start)
    rs = rest_starts(motion.bone_vectors)
    re = rs + motion.bone_vectors
    start = P[:, np.maximum(PARENTS, 0)]
    start[:, 0] = P[:, 0]
    assert np.abs(np.einsum("tjab,jb->tja", Rb, rs) + t - start).max() < 1e-6
    assert np.abs(np.einsum("tjab,jb->tja", Rb, re) + t - P).max() < 1e-6
    # child start = parent end in rest pose
    for j in range(1, 31):
        assert np.allclose(rs[j], re[PARENTS[j]])


def test_skinned_body_follows_the_skeleton(motion, body):
    frames = np.arange(0, 900, 30)
    P, R = motion.positions[frames], motion.rotations[frames]
    X = lbs(body, bone_transforms(P, R, body.rest_start), chunk=7)  # chunks not dividing T
    assert X.shape == (len(frames), body.n_vertices, 3) and np.all(np.isfinite(X))
    one = lbs_frame(body, bone_transforms(P[5], R[5], body.rest_start))
    assert np.abs(one - X[5]).max() < 1e-9
    # every vertex near its skeleton
    d = np.linalg.norm(X[:, :, None] - P[:, None], axis=-1).min(-1)
    print(f"\nmax vertex-to-nearest-joint distance: {d.max() * 100:.1f} cm")
    assert d.max() < 0.25
    # each part stays near its own bone (e.g. the head around the head bone)
    head = body.part == body.part_names.index("head")
    hc = X[:, head].mean(1)
    assert np.linalg.norm(hc - 0.5 * (P[:, J["upperneck"]] + P[:, J["head"]]), axis=-1).max() < 0.06
    lfoot = body.part == body.part_names.index("lfoot")
    assert np.linalg.norm(X[:, lfoot].mean(1) - P[:, J["lfoot"]], axis=-1).max() < 0.08
    # rigidly weighted vertices keep their distances (head is nearly rigid)
    rigid = head & (body.dense_weights()[:, J["head"]] > 1 - 1e-9)
    a, b = np.nonzero(rigid)[0][:2]
    assert np.allclose(np.linalg.norm(X[:, a] - X[:, b], axis=-1),
                       np.linalg.norm(body.vertices[a] - body.vertices[b]), atol=1e-9)
    # the mesh moves between frames; a global translation moves it rigidly
    assert np.linalg.norm(X[1] - X[0], axis=-1).mean() > 0.05
    shift = np.array([0.3, 0.0, -1.2])
    Xs = lbs(body, bone_transforms(P[:2] + shift, R[:2], body.rest_start))
    assert np.abs(Xs - X[:2] - shift).max() < 1e-9
