"""Full-body files of other rigs give SPEC §3 ``joints`` orientations.

The hand orientation is the forearm's end (the hand bone's parent), never the
hand bone; rotations are relative to the SPEC rest pose whatever the file's
rest pose (T- or A-pose, any facing) and bone rolls; a rig whose rest pose
cannot be related to the SPEC's gives its points and ``orientations=none``
with one warning line. The rigs are built in Blender from a held-out salsa
segment (``tests/support/rig_builder.py``) and written with Blender's own BVH
and FBX exporters; the CSV is what ``extract`` writes of the same segment.
The full table (every naming, T and A, BVH and FBX, command line, batch and
Blender import): ``benchmarks/eval_rig_orientations.py``.
"""
from __future__ import annotations

import numpy as np
import pytest

from conftest import MODELS, SALSA
from support.helpers import cut, quat_angle_deg, run_cli
from support.rig_builder import NAMINGS, READ_BONES, rig_bones, spec_rest, _points

from dancing_points_addon.formats.rig_rest import rest_corrections, tracked_rig
from dancing_points_addon.formats.take import take_orientations_usable
from dancing_points_addon.rotations import axis_rotation
from dancing_points_addon.skeleton import JOINT_INDEX

MM = 1e-3


def _rest_rig(naming, pose="T", turn=np.eye(3), bone_vectors=None):
    """Names, parents and rest heads (motion space) of a test rig."""
    if bone_vectors is None:
        bone_vectors = _asf_vectors()
    bones = rig_bones(naming)
    J0, A = spec_rest(bone_vectors, pose)
    names = [b[0] for b in bones]
    parents = [names.index(b[1]) if b[1] is not None else -1 for b in bones]
    heads = np.stack([_points(J0, b[2]) for b in bones]) @ turn.T
    return names, parents, heads, A


_VEC = []


def _asf_vectors():
    if not _VEC:
        from dancing_points_addon.formats.asf_amc import load_amc
        if not SALSA.exists():
            pytest.skip("shared data not found")
        _VEC.append(load_amc(SALSA / "60_08.amc").bone_vectors)
    return _VEC[0]


@pytest.mark.parametrize("naming", sorted(NAMINGS))
@pytest.mark.parametrize("pose", ["T", "A"])
def test_which_bones_and_rest_corrections(naming, pose):
    names, parents, heads, A = _rest_rig(naming, pose)
    rig = tracked_rig(names, parents)
    assert rig.naming == naming
    assert tuple(names[i] for i in rig.rotations) == READ_BONES[naming]  # the forearm's end, not the hand
    Q, problem = rest_corrections(heads, parents, rig)
    assert problem == ""
    # the skull: the body faces +Z; each forearm: the rest pose's turn of the arm (A-pose: 45° down)
    assert np.abs(Q[0] - np.eye(3)).max() < 1e-12
    assert np.abs(Q[1] - A[JOINT_INDEX["lwrist"]]).max() < 1e-9
    assert np.abs(Q[2] - A[JOINT_INDEX["rwrist"]]).max() < 1e-9
    if pose == "A":
        assert np.abs(Q[1] - axis_rotation("Z", -np.pi / 4)).max() < 1e-9


@pytest.mark.parametrize("yaw_deg", [90.0, 180.0, 33.0])
def test_a_rig_facing_elsewhere(yaw_deg):
    turn = axis_rotation("Y", np.deg2rad(yaw_deg))
    names, parents, heads, A = _rest_rig("unreal", "A", turn)
    Q, problem = rest_corrections(heads, parents, tracked_rig(names, parents))
    assert problem == ""
    assert np.abs(Q[0] - turn).max() < 1e-6  # the skull's rest frame is the body's
    assert np.abs(Q[1] - turn @ A[JOINT_INDEX["lwrist"]]).max() < 1e-6


def test_rest_poses_that_cannot_be_related_give_no_orientations():
    names, parents, heads, _ = _rest_rig("mixamo", "T")
    rig = tracked_rig(names, parents)
    i = names.index
    # lying on its back
    lying = heads @ axis_rotation("X", np.pi / 2).T
    assert "not upright" in rest_corrections(lying, parents, rig)[1]
    # left elbow bent 90° forward in the rest pose
    bent = heads.copy()
    elbow = bent[i("mixamorig:LeftForeArm")]
    for n in ("mixamorig:LeftHand", "mixamorig:LeftHandIndex1", "mixamorig:LeftHandThumb1"):
        v = bent[i(n)] - elbow
        bent[i(n)] = elbow + np.array([0.0, v[1], np.linalg.norm(v[[0, 2]])])
    Q, problem = rest_corrections(bent, parents, rig)
    assert Q is None and "left forearm does not point sideways" in problem
    # a hand bone without a parent
    orphan = list(parents)
    orphan[i("mixamorig:RightHand")] = -1
    Q, problem = rest_corrections(heads, orphan, tracked_rig(names, orphan))
    assert Q is None and "right hand bone has no parent" in problem


def test_orientations_metadata():
    assert take_orientations_usable({}) and take_orientations_usable({"orientations": ""})
    assert not take_orientations_usable({"orientations": "none"})
    assert not take_orientations_usable({"orientations": " None "})


# --------------------------------------------------------------------------- rigs built in Blender


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    pytest.importorskip("bpy")
    if not SALSA.exists():
        pytest.skip("shared data not found")
    from support import blender_scene_util as bsu
    from support.rig_builder import build_rig, export_rig
    from dancing_points_addon.formats.take import take_from_motion, write_take
    from training.evaluate import test_segments

    d = tmp_path_factory.mktemp("rigs")
    motion = cut(next(test_segments(str(SALSA), ("08",)))["lead60"], 0, 120)  # 2 s
    write_take(d / "take.csv", take_from_motion(motion))
    files = {}
    for naming, pose, seed in (("unreal", "A", 3), ("rigify", "T", 4)):
        for ext in ("bvh", "fbx"):
            bsu.fresh_scene()
            arm = build_rig(motion, naming, pose, roll_seed=seed)
            files[naming, ext] = export_rig(arm, d / f"{naming}_{pose}.{ext}")
    bsu.fresh_scene()
    arm = build_rig(motion, "mixamo", "T", roll_seed=5)
    bpy = pytest.importorskip("bpy")
    bpy.context.scene.frame_set(30)  # the dance's pose on the export frame stands in for the rest pose
    files["unskinned"] = export_rig(arm, d / "unskinned.fbx", skinned=False)
    return {"dir": d, "motion": motion, "files": files}


def _compare(take, ref):
    n = min(take.n_frames, ref.n_frames)
    pos = np.linalg.norm(take.positions[:n] - ref.positions[:n], axis=-1).mean(0)
    ang = quat_angle_deg(take.quats[:n], ref.quats[:n]).mean(0)
    return pos, ang


@pytest.mark.parametrize("naming", ["unreal", "rigify"])
def test_core_and_blender_readers_give_the_csv_orientations(rigs, naming):
    import bpy
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension
    from dancing_points_addon.inputs import load_input
    from dancing_points_addon.formats.take_read import read_take

    take_rig = import_from_extension("operators.take_rig")
    ref = read_take(rigs["dir"] / "take.csv")
    bvh, fbx = rigs["files"][naming, "bvh"], rigs["files"][naming, "fbx"]
    core = load_input(bvh)  # Blender's BVH export: Z up, the rest pose's rolls and A-pose in its OFFSETs
    pos, ang = _compare(core, ref)
    assert pos.max() < 0.01 * MM and ang.max() < 0.01, (pos, ang)
    assert take_orientations_usable(core.meta)
    bsu.fresh_scene()
    read = take_rig.read_rig_take(bpy.context, bvh, ".bvh", axis_up='Z', axis_forward='Y')
    pos, ang = _compare(read, ref)
    assert pos.max() < 0.01 * MM and ang.max() < 0.01, (pos, ang)
    bsu.fresh_scene()
    read = take_rig.read_rig_take(bpy.context, fbx, ".fbx")  # keys simplified by the exporter
    pos, ang = _compare(read, ref)
    assert pos.max() < 3 * MM and ang.max() < 1.0, (pos, ang)
    assert read.meta["source_naming"] == naming
    # the hand bone, which bends at the wrist, is far from the device's orientation
    from dancing_points_addon.rotations import matrix_to_quat
    R = rigs["motion"].rotations[:, JOINT_INDEX["lhand"]]
    assert quat_angle_deg(matrix_to_quat(R), ref.quats[:, 1]).mean() > 10.0


def test_synthesize_of_an_a_pose_bvh_gives_the_csv_duet(rigs, tmp_path):
    from support.helpers import run_cli_long

    out = {}
    for name, src in (("csv", rigs["dir"] / "take.csv"), ("bvh", rigs["files"]["unreal", "bvh"])):
        res = run_cli_long("synthesize", src, "-o", tmp_path / f"{name}.npz", "--models", MODELS)
        assert res.returncode == 0, res.stderr
        out[name] = np.load(tmp_path / f"{name}.npz")
    for role in ("leader", "follower"):
        d = np.linalg.norm(out["bvh"][role + "_positions"] - out["csv"][role + "_positions"], axis=-1)
        assert d.mean() < 0.1 * MM, (role, d.mean())
    elbows = [JOINT_INDEX["lhumerus"], JOINT_INDEX["rhumerus"]]
    d = np.linalg.norm(out["bvh"]["leader_positions"][:, elbows] - out["csv"]["leader_positions"][:, elbows], axis=-1)
    assert d.mean() < 0.1 * MM


def test_a_rig_without_its_rest_pose_gives_points_without_orientations(rigs, tmp_path):
    """Blender's FBX export of an armature that deforms no mesh: the pose of the
    export frame stands in for the rest pose; the orientations are not guessed."""
    import bpy
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension
    from dancing_points_addon.formats.take_read import read_take

    path = rigs["files"]["unskinned"]
    res = run_cli("extract", path, "-o", tmp_path / "x.csv", timeout=300)
    assert res.returncode == 0, res.stderr
    warn = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    assert len(warn) == 1 and "orientations cannot be read" in warn[0] and "unskinned.fbx" in warn[0], res.stderr
    back, ref = read_take(tmp_path / "x.csv"), read_take(rigs["dir"] / "take.csv")
    assert not take_orientations_usable(back.meta)
    n = min(back.n_frames, ref.n_frames)
    assert np.linalg.norm(back.positions[:n] - ref.positions[:n], axis=-1).mean() < 3 * MM  # the points are read
    # the Blender import says so and its take carries it to the synthesis
    take_collection = import_from_extension("operators.take_collection")
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(path)) == {'FINISHED'}
    coll = next(c for c in bpy.data.collections if c.dancing_points.kind == 'TAKE')
    assert coll.dancing_points.orientations == "none"
    assert not take_orientations_usable(take_collection.take_from_collection(bpy.context, coll).meta)


def _with_extra_bones(naming, extra):
    """A test rig's names and parents plus ``extra`` bones ``(name, parent name)``."""
    bones = rig_bones(naming)
    names = [b[0] for b in bones]
    parents = [names.index(b[1]) if b[1] is not None else -1 for b in bones]
    for name, parent in extra:
        names.append(name)
        parents.append(names.index(parent))
    return names, parents


def test_full_rigs_read_the_forearm_not_its_helpers():
    # UE5's mannequin: twist bones beside the hand (skinning helpers) are not read
    names, parents = _with_extra_bones("unreal", [("lowerarm_twist_01_l", "lowerarm_l"),
                                                  ("lowerarm_twist_02_l", "lowerarm_l"),
                                                  ("upperarm_twist_01_l", "upperarm_l"), ("ik_hand_root", "pelvis"),
                                                  ("ik_hand_l", "ik_hand_root")])
    rig = tracked_rig(names, parents)
    assert [names[i] for i in rig.rotations] == ["head", "lowerarm_l", "lowerarm_r"]
    assert [names[i] for i in rig.points] == ["head", "hand_l", "hand_r"]
    # a whole generated Rigify rig: controls, ORG- and MCH- bones beside the DEF- ones
    extra = [("root", "DEF-spine"), ("head", "DEF-spine.005"), ("hand_ik.L", "root"), ("ORG-forearm.L", "DEF-spine"),
             ("ORG-hand.L", "ORG-forearm.L"), ("MCH-forearm_tweak.L", "ORG-forearm.L")]
    names, parents = _with_extra_bones("rigify", extra)
    rig = tracked_rig(names, parents)
    assert rig.naming == "rigify"
    assert [names[i] for i in rig.rotations] == ["head", "DEF-forearm.L.001", "DEF-forearm.R.001"]
    # CMU-converted BVH names: the hand point is LeftFingerBase, its orientation LeftHand (ASF lwrist)
    from dancing_points_addon.skeleton import CMU_BVH_NAMES, JOINT_NAMES, PARENTS
    cmu = [CMU_BVH_NAMES[n] for n in JOINT_NAMES]
    rig = tracked_rig(cmu, PARENTS)
    assert rig.naming == "cmu"
    assert [cmu[i] for i in rig.points] == ["Head", "LeftFingerBase", "RightFingerBase"]
    assert [cmu[i] for i in rig.rotations] == ["Head", "LeftHand", "RightHand"]


def test_an_amc_of_an_a_pose_asf(tmp_path):
    """An ASF whose arms rest 45° down: the hand orientations still carry the
    SPEC rest pose's forearm direction (+X / −X) onto the posed forearm."""
    import re

    from support.helpers import trim_amc
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.inputs import load_input
    from dancing_points_addon.rotations import quat_to_matrix

    if not SALSA.exists():
        pytest.skip("shared data not found")
    text = (SALSA / "60.asf").read_text()
    arm = {"l": ("lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb")}
    arm["r"] = tuple("r" + n[1:] for n in arm["l"])
    for side, sign in (("l", -1.0), ("r", 1.0)):
        turn = axis_rotation("Z", sign * np.pi / 4)
        for bone in arm[side]:
            m = re.search(rf"name {bone}\s*\n\s*direction ([^\n]+)\n", text)
            d = turn @ np.array([float(x) for x in m.group(1).split()])
            text = text[:m.start(1)] + " ".join(f"{x:.9g}" for x in d) + text[m.end(1):]
    for name, asf in (("t", SALSA / "60.asf"), ("a", tmp_path / "a.asf")):
        if name == "a":
            asf.write_text(text)
        trim_amc(SALSA / "60_08.amc", tmp_path / f"{name}.amc", 40)
        take = load_input(tmp_path / f"{name}.amc", asf=asf)
        motion = load_amc(tmp_path / f"{name}.amc", asf)
        assert take_orientations_usable(take.meta)
        for dev, (a, b, x) in ((1, ("lradius", "lwrist", 1.0)), (2, ("rradius", "rwrist", -1.0))):
            fore = motion.positions[:, JOINT_INDEX[b]] - motion.positions[:, JOINT_INDEX[a]]
            fore /= np.linalg.norm(fore, axis=-1, keepdims=True)
            got = quat_to_matrix(take.quats[:, dev]) @ np.array([x, 0.0, 0.0])
            assert np.abs(got - fore).max() < 1e-6, (name, dev)
            # the ASF's own rotations (relative to its rest pose) would not: the A-pose's 45°
            own = motion.rotations[:, JOINT_INDEX[b]] @ np.array([x, 0.0, 0.0])
            off = np.degrees(np.arccos(np.clip(np.sum(own * fore, -1), -1.0, 1.0)))
            assert (off.min() > 40.0) if name == "a" else (off.max() < 1e-4), (name, dev, off.min())
