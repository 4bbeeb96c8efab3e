"""The default bodies (smooth mannequins), rigid bone transforms and linear blend
skinning, on the real CMU skeleton and on the sample take's synthesised duet."""
import pathlib
import time

import numpy as np
import pytest

from dancing_points_addon import skinning
from dancing_points_addon.blender_math import consistent_pose
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.take_read import read_take
from dancing_points_addon.ik import bone_transforms, transforms_to_matrices
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.skeleton import rest_starts
from dancing_points_addon.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS
from dancing_points_addon.skinning import BodyError, lbs, lbs_frame, make_body

J = JOINT_INDEX
SAMPLE = pathlib.Path(__file__).resolve().parents[1] / "dancing_points_addon" / "samples" / "sample_take.csv"


@pytest.fixture(scope="module")
def motion(salsa_dir):
    return load_amc(salsa_dir / "60_01.amc").subsample(2)


@pytest.fixture(scope="module")
def body(motion):
    return make_body(motion.bone_vectors)


@pytest.fixture(scope="module")
def duet_poses():
    """The sample take's synthesised duet: per dancer ``(bone_vectors, positions, rotations)``,
    made rigid as the bake does (``blender_math.consistent_pose``)."""
    duet = Synthesizer().synthesize(read_take(SAMPLE))
    return {role: consistent_pose(getattr(duet, role + "_positions"), getattr(duet, role + "_rotations"))
            for role in ("leader", "follower")}


def _edges(F):
    return np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])


def _components(n, F):
    """Number of connected components of the mesh (union-find on its edges)."""
    parent = np.arange(n)
    e = _edges(F)
    while True:  # pointer jumping: each pass hooks every edge's larger root onto the smaller
        ra, rb = parent[e[:, 0]], parent[e[:, 1]]
        lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
        np.minimum.at(parent, hi, lo)
        parent = parent[parent]
        if np.all(parent[e[:, 0]] == parent[e[:, 1]]):
            break
    while not np.all(parent[parent] == parent):
        parent = parent[parent]
    return len(np.unique(parent))


def test_body_is_a_closed_outward_manifold(body):
    V, F = body.vertices, body.faces
    print(f"\nbody: {len(V)} vertices, {len(F)} triangles")
    assert 6000 <= len(V) <= 15000
    assert F.dtype.kind == "i" and F.shape[1] == 3
    assert F.min() == 0 and F.max() == len(V) - 1
    assert np.all(np.isfinite(V))
    # no degenerate faces, no repeated corners
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    assert area.min() > 1e-7
    assert np.all((F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2]))
    # closed 2-manifold, consistently oriented: every directed edge once, and its reverse once
    e = _edges(F).astype(np.int64)
    key = e[:, 0] * len(V) + e[:, 1]
    rev = e[:, 1] * len(V) + e[:, 0]
    assert len(np.unique(key)) == len(key)
    assert np.array_equal(np.sort(key), np.sort(rev))
    # one piece of genus 0 (V - E + F = 2), every vertex used; with closed manifold
    # edges this also rules out pinched (non-manifold) vertices
    n_edges = len(key) // 2
    assert len(V) - n_edges + len(F) == 2
    assert _components(len(V), F) == 1
    assert len(np.unique(F)) == len(V)
    # outward: positive signed volume (a slim person: 40-80 litres)
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6
    print(f"volume {vol * 1000:.1f} l")
    assert 0.035 < vol < 0.08


def test_body_proportions_and_weights(body, motion):
    V = body.vertices
    W = body.dense_weights()
    # a plausible human: ~1.6-1.7 m tall in rest pose (head top to sole), arm span
    # about the height, wider at the shoulders than at the hips, not a stick
    h = np.ptp(V[:, 1])
    print(f"\nrest height {h:.3f} m, span {np.ptp(V[:, 0]):.3f} m, depth {np.ptp(V[:, 2]):.3f} m")
    assert 1.5 < h < 2.0 and 0.9 < np.ptp(V[:, 0]) / h < 1.2 and 0.15 < np.ptp(V[:, 2]) < 0.4
    sole = V[:, 1].min()
    ends = rest_starts(motion.bone_vectors) + motion.bone_vectors
    assert abs(sole - min(ends[J["ltoes"], 1], ends[J["rtoes"], 1])) < 0.05  # feet on the floor
    assert V[:, 1].max() > ends[J["head"], 1]  # the skull covers the head bone
    # weights
    assert body.indices.shape == body.weights.shape and body.indices.shape == (len(V), 4)
    assert body.indices.min() >= 0 and body.indices.max() < 31
    assert np.all(np.isfinite(body.weights)) and body.weights.min() >= 0
    assert np.abs(body.weights.sum(1) - 1).max() < 1e-12
    assert np.abs(W.sum(1) - 1).max() < 1e-12
    # weights are multiples of 1/1024 (few distinct values: fast vertex groups in Blender)
    assert np.abs(body.weights * 1024 - np.round(body.weights * 1024)).max() < 1e-9
    assert body.part_names == tuple(JOINT_NAMES) and np.array_equal(body.part, body.indices[:, 0])
    assert np.all(np.take_along_axis(body.weights, np.argsort(-body.weights, 1), 1) == body.weights)
    # the skull is nearly rigid on the head bone; the hip joint bones carry nothing
    head = body.part == J["head"]
    assert head.sum() > 300 and W[head][:, J["head"]].mean() > 0.85
    assert W[:, J["lhipjoint"]].max() == 0 and W[:, J["rhipjoint"]].max() == 0
    # joints blend smoothly: every vertex within 7 cm of the knee is moved by both leg bones
    knee = body.rest_start[J["ltibia"]]
    near_knee = np.linalg.norm(V - knee, axis=1) < 0.07
    assert near_knee.sum() > 100
    assert np.all(W[near_knee][:, J["lfemur"]] > 0.2) and np.all(W[near_knee][:, J["ltibia"]] > 0.2)
    elbow = body.rest_start[J["rradius"]]
    near_elbow = np.linalg.norm(V - elbow, axis=1) < 0.04
    assert near_elbow.sum() > 30
    assert np.all(W[near_elbow][:, J["rhumerus"]] > 0.2) and np.all(W[near_elbow][:, J["rradius"]] > 0.2)
    # left and right alike (the skeleton is not quite symmetric: within 20 %)
    counts = np.bincount(body.part, minlength=31)
    for a, b in (("lfemur", "rfemur"), ("lhumerus", "rhumerus"), ("lwrist", "rwrist")):
        assert abs(counts[J[a]] - counts[J[b]]) < 0.2 * counts[J[a]]


def test_every_vertex_within_its_bones_envelope(body, motion):
    """The envelope rule: each vertex lies within ``r_max(b) + 3.5 cm`` of the axis
    of the weight capsule of its highest-weight bone ``b`` (``r_max``: the capsule's
    larger radius), and within 16 cm of it in any case; ``Body.envelope`` (the
    distance to the bone's own segment) is at most 26 cm (the pelvis around the
    root joint) and 16 cm for every other bone."""
    V = body.vertices
    bones, a, b, r1, r2 = skinning.weight_capsules(motion.bone_vectors)
    slot = np.full(31, -1)
    slot[bones] = np.arange(len(bones))
    top = slot[body.indices[:, 0]]
    assert top.min() >= 0
    dist = np.empty(len(V))
    for k in range(len(bones)):
        m = top == k
        if m.any():
            dist[m] = skinning.bone_segment_distances(V[m], a[k:k + 1], b[k:k + 1])[:, 0]
    excess = dist - np.maximum(r1, r2)[top]
    print(f"\nvertex distance to its capsule axis: max {dist.max() * 100:.1f} cm; "
          f"beyond the capsule radius: max {excess.max() * 100:.1f} cm; "
          f"envelope per bone (cm): " + ", ".join(f"{JOINT_NAMES[i]} {body.envelope[i] * 100:.0f}"
                                                   for i in np.nonzero(body.envelope)[0]))
    assert excess.max() < 0.035 and dist.max() < 0.16
    starts = rest_starts(motion.bone_vectors)
    seg = skinning.bone_segment_distances(V, starts, starts + motion.bone_vectors)[np.arange(len(V)), body.part]
    env = np.zeros(31)
    np.maximum.at(env, body.part, seg)
    np.testing.assert_allclose(body.envelope, env, atol=1e-12)
    assert body.envelope[J["root"]] < 0.26 and np.delete(body.envelope, J["root"]).max() < 0.16


def test_body_scales_with_the_skeleton_and_is_deterministic(motion):
    bv = motion.bone_vectors
    a = make_body(bv)
    skinning.mannequin._cached.cache_clear()
    t0 = time.perf_counter()
    b = make_body(bv)
    dt = time.perf_counter() - t0
    print(f"\nmake_body (not cached): {dt:.2f} s")
    assert dt < 3.0
    for x, y in ((a.vertices, b.vertices), (a.faces, b.faces), (a.indices, b.indices), (a.weights, b.weights)):
        assert np.array_equal(x, y)
    assert b.vertices is not a.vertices  # fresh arrays from the cache
    b.vertices[0] += 1.0
    assert np.array_equal(make_body(bv).vertices, a.vertices)
    # a skeleton 0.85 times the size: the same mannequin, 0.85 times the size
    small = make_body(0.85 * bv)
    assert np.array_equal(small.faces, a.faces)
    assert np.abs(small.vertices - 0.85 * a.vertices).max() < 1e-9
    # the same weights (up to a rounding tie: one 1/1024 step on a few vertices)
    dw = np.abs(small.dense_weights() - a.dense_weights()).max(1)
    assert dw.max() <= 1 / 1024 + 1e-12 and (dw > 0).mean() < 0.01


@pytest.mark.parametrize("bad, match", [
    (np.zeros((30, 3)), r"shape \(31, 3\)"),
    (np.full((31, 3), np.nan), "not all finite"),
    ("not numbers", "not numbers"),
])
def test_bad_bone_vectors_are_refused(bad, match):
    with pytest.raises(BodyError, match=match):
        make_body(bad)


def test_zero_length_limb_is_refused(motion):
    bv = motion.bone_vectors.copy()
    bv[J["ltibia"]] = 0.0
    with pytest.raises(BodyError, match="ltibia"):
        make_body(bv)
    with pytest.raises(BodyError, match="upright T-pose"):
        make_body(motion.bone_vectors * np.array([1.0, -1.0, 1.0]))


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
    # the skull stays around the head bone, the foot around its bone
    head = body.part == J["head"]
    hc = X[:, head].mean(1)
    assert np.linalg.norm(hc - 0.5 * (P[:, J["upperneck"]] + P[:, J["head"]]), axis=-1).max() < 0.06
    lfoot = body.part == J["lfoot"]
    mid_foot = 0.5 * (P[:, J["ltibia"]] + P[:, J["lfoot"]])  # ankle and ball of the foot
    assert np.linalg.norm(X[:, lfoot].mean(1) - mid_foot, axis=-1).max() < 0.06
    # rigidly weighted vertices keep their distances
    rigid = head & (body.dense_weights()[:, J["head"]] == 1.0)
    a, b = np.nonzero(rigid)[0][[0, -1]]
    assert np.allclose(np.linalg.norm(X[:, a] - X[:, b], axis=-1),
                       np.linalg.norm(body.vertices[a] - body.vertices[b]), atol=1e-9)
    # the mesh moves between frames; a global translation moves it rigidly
    assert np.linalg.norm(X[1] - X[0], axis=-1).mean() > 0.05
    shift = np.array([0.3, 0.0, -1.2])
    Xs = lbs(body, bone_transforms(P[:2] + shift, R[:2], body.rest_start))
    assert np.abs(Xs - X[:2] - shift).max() < 1e-9


@pytest.mark.parametrize("role", ["leader", "follower"])
def test_duet_bodies_deform_without_tears_or_collapse(duet_poses, role):
    """Every frame of the sample take's synthesised duet, both dancers, posed by
    LBS. Rules: no triangle edge stretches beyond 3 times its rest length, and
    99.9 % of (edge, frame) pairs stay within 1.9 times (her poses, by the
    training run of her tracker, reach 1.80-1.85 on this take); triangles collapse
    (posed area < 5 % of rest) or fold over (normal against the rest normal
    turned with the triangle's main bone) in at most 0.05 % and 0.15 % of
    (triangle, frame) pairs, and only where bones blend (triangles on one
    bone move rigidly)."""
    bv, pos, rot = duet_poses[role]
    body = make_body(bv)
    V, F = body.vertices, body.faces
    R, t = bone_transforms(pos, rot, body.rest_start)
    T = len(pos)
    assert T > 300

    def edges(X):
        return np.stack([np.linalg.norm(X[..., F[:, k], :] - X[..., F[:, (k + 1) % 3], :], axis=-1)
                         for k in range(3)], -1)

    def cross(X):
        return np.cross(X[..., F[:, 1], :] - X[..., F[:, 0], :], X[..., F[:, 2], :] - X[..., F[:, 0], :])

    E0, C0 = edges(V), cross(V)
    A0 = np.linalg.norm(C0, axis=-1)
    N0 = C0 / A0[:, None]
    main = body.indices[F[:, 0], 0]
    one_bone = np.all((body.weights[F, 0] == 1.0) & (body.indices[F, 0] == main[:, None]), axis=1)
    hist = np.zeros(200, dtype=np.int64)  # edge ratio histogram, bins of 0.05 up to 10
    ratio_max, ratio_min, collapsed, flipped, worst_flip_frame = 0.0, np.inf, 0, 0, 0.0
    for a in range(0, T, 64):
        b = min(a + 64, T)
        X = lbs(body, (R[a:b], t[a:b]))
        if a == 0:  # the dense and the sparse evaluation agree
            assert np.abs(lbs_frame(body, (R[0], t[0])) - X[0]).max() < 1e-9
        ER = edges(X) / E0
        C = cross(X)
        AR = np.linalg.norm(C, axis=-1) / A0
        cos = np.einsum("tfi,tfi->tf", C, np.einsum("tfij,fj->tfi", R[a:b, main], N0))
        ratio_max, ratio_min = max(ratio_max, ER.max()), min(ratio_min, ER.min())
        hist += np.bincount(np.minimum((ER / 0.05).astype(int), 199).ravel(), minlength=200)
        collapsed += int((AR < 0.05).sum())
        flipped += int((cos < 0).sum())
        worst_flip_frame = max(worst_flip_frame, float((cos < 0).mean(1).max()))
        # triangles on one bone move rigidly
        assert np.abs(ER[:, one_bone] - 1.0).max() < 1e-9
        assert not np.any((AR < 0.05)[:, one_bone]) and not np.any((cos < 0)[:, one_bone])
    n = T * len(F)
    q999 = 0.05 * (np.searchsorted(np.cumsum(hist), 0.999 * hist.sum()) + 1)
    print(f"\n{role}: {T} frames, {len(F)} triangles: edge ratio posed/rest {ratio_min:.3f}..{ratio_max:.2f} "
          f"(99.9 % <= {q999:.2f}); collapsed (area < 5 %) {collapsed / n:.1e}, folded {flipped / n:.1e} "
          f"of (triangle, frame) pairs, worst frame {worst_flip_frame:.1e}")
    assert ratio_max < 3.0 and q999 <= 1.9
    assert collapsed / n < 5e-4 and flipped / n < 1.5e-3 and worst_flip_frame < 1e-2
