"""Retargeting the synthesised duet onto other characters (``dancing_points.retarget``).

Two parts:

- bpy-free: bone-name conventions, presets, the glTF meshopt decoder, and the
  alignment of a rig in another rest pose (numpy only);
- in Blender (the extension enabled as in ``test_blender_addon``): a
  synthesised duet (5 s of CMU salsa 60_10) retargeted onto the two avatars of
  ``../shared/assets`` (imported with Blender's glTF importer, after decoding
  their meshopt compression) and onto two rigs this test builds (Unreal names,
  A-pose, other bone rolls and Euler rotation modes, the objects turned and
  moved). Every frame is evaluated by Blender and checked: the landmarks (hips,
  wrists, ankles, skull base) follow the source's after normalising by height
  (mean < 3 cm), the foot points planted on the source do not slide (< 1 cm),
  no bone turns more than 90 degrees between frames, the meshes deform, the
  rest pose and the rig's own action are untouched, held hands stay together.

  Normalising by height: positions horizontally about the duet's centre and
  vertically above the floor, divided by each character's height (its skull
  base, SPEC §2's head point, standing); errors are given at the source's size.
  The hips' and ankles' heights are counted from their standing heights (which
  differ between rigs by where they put these joints and by the leg-to-height
  proportion: the pelvis height follows the leg length, by design); the raw
  figures are printed as well, and the horizontal part of the plain
  height-normalised error, where no standing height enters, is asserted
  under 3 cm too.

Models: the shipped ``models/`` (``$DP_MODEL_DIR`` overrides).
"""
from __future__ import annotations

import contextlib
import json
import time

import numpy as np
import pytest

from conftest import ASSETS, MODELS, SALSA
from support.helpers import CM, SRC_POINTS, apose_rig, target_rig_from_bones
from dancing_points_addon.formats import gltf_meshopt
from dancing_points_addon import retarget as rt
from dancing_points_addon.retarget.solver import interp_poly

AVATARS = {"leader": "White_M_1_Casual.glb", "follower": "White_F_1_Casual.glb"}


# --------------------------------------------------------------------------- bpy-free

def test_conventions_detected_and_mapped():
    mixamo = ["mixamorig:" + n for n in ("Hips", "Spine", "Spine1", "Spine2", "Neck", "Head", "LeftShoulder",
                                           "LeftArm", "LeftForeArm", "LeftHand", "RightShoulder", "RightArm",
                                           "RightForeArm", "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot",
                                           "LeftToeBase", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase")]
    m, conv = rt.auto_mapping(mixamo)
    assert conv == "mixamo"
    assert m["mixamorig:Hips"] == "root" and m["mixamorig:LeftForeArm"] == "lradius+lwrist"
    assert m["mixamorig:Neck"] == "lowerneck+upperneck"
    # Without the prefix: the same mapping.
    m2, conv2 = rt.auto_mapping([n.split(":")[1] for n in mixamo])
    assert conv2 == "mixamo" and len(m2) == len(m)
    # CMU BVH shares names with Mixamo but means other bones.
    cmu = ["Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "RHipJoint", "RightUpLeg",
           "RightLeg", "RightFoot", "RightToeBase", "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head",
           "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "RightShoulder", "RightArm", "RightForeArm",
           "RightHand"]
    m, conv = rt.auto_mapping(cmu)
    assert conv == "cmu_bvh" and m["Spine"] == "upperback" and m["LeftHand"] == "lwrist"
    rigify = ["DEF-spine", "DEF-spine.001", "DEF-spine.002", "DEF-spine.003", "DEF-spine.004", "DEF-spine.005",
              "DEF-spine.006", "DEF-thigh.L", "DEF-thigh.L.001", "DEF-shin.L", "DEF-shin.L.001", "DEF-foot.L",
              "DEF-thigh.R", "DEF-thigh.R.001", "DEF-shin.R", "DEF-shin.R.001", "DEF-foot.R", "DEF-upper_arm.L"]
    m, conv = rt.auto_mapping(rigify)
    assert conv == "rigify" and m["DEF-thigh.L.001"] == "lfemur" and m["DEF-spine.006"] == "head"
    # A 5-bone UE5 spine is mapped as one chain on the 3-bone source spine.
    ue5 = ["root", "pelvis", "spine_01", "spine_02", "spine_03", "spine_04", "spine_05", "neck_01", "neck_02",
           "head", "thigh_l", "calf_l", "foot_l", "ball_l", "thigh_r", "calf_r", "foot_r", "ball_r"]
    m, conv = rt.auto_mapping(ue5)
    assert conv == "unreal" and "root" not in m and m["pelvis"] == "root"
    assert {m["spine_0%d" % i] for i in range(1, 6)} == {"lowerback+upperback+thorax"}
    assert m["neck_01"] == "lowerneck" and m["neck_02"] == "upperneck"


def test_axis_angle_channels_round_trip_on_salsa_rotations():
    """The conversions the retarget uses for AXIS_ANGLE bones (writing keys and
    reading them back) round-trip to the same rotation: every joint of 300
    frames of CMU 60_10, the identity and a tiny rotation included. (The rigs of
    the Blender tests have no AXIS_ANGLE bones.)"""
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.rotations import (axis_angle_to_quat, matrix_to_quat, quat_to_axis_angle,
                                                quat_to_matrix, rotation_angle)

    R = load_amc(SALSA / "60_10.amc").rotations[:300]
    q = matrix_to_quat(R)
    q[0, 0] = (1.0, 0.0, 0.0, 0.0)
    q[0, 1] = (np.cos(5e-8), np.sin(5e-8), 0.0, 0.0)  # 1e-7 rad about +X
    aa = quat_to_axis_angle(-q)  # the sign of a quaternion does not matter
    np.testing.assert_allclose(aa[0, 1], (1e-7, 1.0, 0.0, 0.0), rtol=1e-9, atol=1e-15)
    assert (aa[..., 0] >= 0).all() and (aa[..., 0] <= np.pi + 1e-12).all()
    np.testing.assert_allclose(np.linalg.norm(aa[..., 1:], axis=-1), 1.0, atol=1e-9)
    np.testing.assert_allclose(aa[0, 0], (0.0, 0.0, 1.0, 0.0), atol=1e-12)  # identity: zero angle about +Y
    back = quat_to_matrix(axis_angle_to_quat(aa * np.array([1.0, 2.0, 2.0, 2.0])))  # any axis length
    err = rotation_angle(np.swapaxes(back, -1, -2) @ quat_to_matrix(q))
    assert err.max() < 1e-6, err.max()


def test_preset_round_trip_and_errors(tmp_path):
    presets = rt.builtin_conventions()
    assert {"mixamo", "rigify", "unreal", "cmu_bvh", "cmu_asf"} <= set(presets)
    path = tmp_path / "map.json"
    mapping = {"pelvis": "root", "thigh_l": "lfemur", "lowerarm_l": "lradius+lwrist"}
    rt.save_preset(path, mapping, name="mine")
    back = rt.load_preset(path)
    assert back["bones"] == mapping and back["name"] == "mine"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"bones": {"x": "lfemur+lhumerus"}}))
    with pytest.raises(rt.RetargetError, match="not the child"):
        rt.load_preset(bad)
    bad.write_text(json.dumps({"bones": {"x": "knee"}}))
    with pytest.raises(rt.RetargetError, match="unknown source bone"):
        rt.load_preset(bad)
    with pytest.raises(rt.RetargetError, match="exactly one bone mapped to 'root'"):
        rt.validate_mapping({"thigh_l": "lfemur"}, ["thigh_l"])
    # not text at all (an .npz picked by mistake), or JSON nested past Python's limit: one line naming the file
    binary = tmp_path / "take.npz"
    np.savez(binary, x=np.arange(3.0))
    with pytest.raises(rt.RetargetError, match=r"take\.npz: not a bone map \(not UTF-8 text\)$"):
        rt.load_preset(binary)
    bad.write_text("[" * 100000)
    with pytest.raises(rt.RetargetError, match=r"bad\.json: not a bone map \(JSON nested too deeply\)$"):
        rt.load_preset(bad)


def _fake_meshopt_stream():
    """A small attribute stream encoded by hand after the extension's spec
    (Appendix A): 16 elements of 4 bytes, one group per byte lane in 2-bit
    sentinel encoding (large deltas stored as extra bytes)."""
    rng = np.random.default_rng(0)
    elems = np.cumsum(rng.integers(-3, 4, size=(16, 4)), axis=0) % 256
    deltas = np.diff(np.vstack([np.zeros((1, 4), dtype=np.int64), elems]), axis=0)  # from the zero baseline
    out = bytearray([0xA0])
    for k in range(4):
        signed = [(int(v) + 128) % 256 - 128 for v in deltas[:, k]]  # 8-bit wrap-around delta
        zz = [2 * v if v >= 0 else -2 * v - 1 for v in signed]  # zigzag
        out.append(1)  # group header: bits 1 (2-bit sentinel encoding)
        packed, extra = [], []
        for i in range(0, 16, 4):
            byte = 0
            for v in zz[i:i + 4]:
                byte = (byte << 2) | min(v, 3)
                if v >= 3:
                    extra.append(v)
            packed.append(byte)
        out += bytes(packed) + bytes(extra)
    out += bytes(32)  # tail: the (zero) baseline element, padded to 32 bytes
    return bytes(out), elems.astype(np.uint8)


def test_meshopt_attribute_decoder_on_a_hand_encoded_stream():
    data, want = _fake_meshopt_stream()
    got = gltf_meshopt.decode_attributes(data, 16, 4)
    np.testing.assert_array_equal(got, want)


@pytest.mark.skipif(not (ASSETS / AVATARS["leader"]).exists(), reason="avatars not found")
def test_meshopt_glb_decodes_to_valid_geometry(tmp_path):
    """The avatars' meshopt streams decode to in-range indices and unit normals."""
    doc, binary = gltf_meshopt.read_glb(ASSETS / AVATARS["follower"])
    assert "EXT_meshopt_compression" in doc["extensionsRequired"]
    out = gltf_meshopt.decompress_glb(ASSETS / AVATARS["follower"], tmp_path / "f.glb")
    doc2, bin2 = gltf_meshopt.read_glb(out)
    assert "EXT_meshopt_compression" not in doc2.get("extensionsUsed", [])
    prim = doc2["meshes"][0]["primitives"][0]
    acc = doc2["accessors"]
    pos = acc[prim["attributes"]["POSITION"]]
    idx = acc[prim["indices"]]
    bv = doc2["bufferViews"][idx["bufferView"]]
    dt = {5123: np.uint16, 5125: np.uint32}[idx["componentType"]]
    ind = np.frombuffer(bin2, dtype=dt, count=idx["count"], offset=bv["byteOffset"] + idx.get("byteOffset", 0))
    assert ind.max() < pos["count"] and len(np.unique(ind)) > 0.9 * pos["count"]
    nrm = acc[prim["attributes"]["NORMAL"]]
    bvn = doc2["bufferViews"][nrm["bufferView"]]
    raw = np.frombuffer(bin2, dtype=np.int8, count=nrm["count"] * 4,
                        offset=bvn["byteOffset"] + nrm.get("byteOffset", 0)).reshape(-1, 4)[:, :3] / 127.0
    assert np.abs(np.linalg.norm(raw, axis=1) - 1).max() < 0.03


def _apose_target():
    """:func:`apose_rig` as a :class:`TargetRig` (rest matrices with the given
    rolls; the object turned 90 degrees about Z and moved)."""
    world = np.eye(4)
    world[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # turned 90 degrees
    world[:3, 3] = (1.5, -0.5, 0.0)
    return target_rig_from_bones(apose_rig(), world)


def _rest_source():
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.skeleton import rest_joints

    bv = load_amc(SALSA / "60_10.amc").bone_vectors
    ends = rest_joints(bv)
    return bv, ends - [0, ends[:, 1].min() - 0.02, 0]  # toes 2 cm above the floor


def test_alignment_of_an_apose_rig_numpy():
    """Source in its rest pose -> every mapped target segment points exactly like
    its source segment (T-pose arms on an A-pose rig, any roll)."""
    if not SALSA.exists():
        pytest.skip("shared data not found")
    rig = _apose_target()
    names = rig.names
    mapping, conv = rt.auto_mapping(names)
    assert conv == "unreal"
    bv, ends = _rest_source()
    ret = rt.Retargeter(bv, rig, mapping, foot_lock=False, match_hands=False, match_head=False, match_feet=False)
    pos = ends[None]
    rot = np.broadcast_to(np.eye(3), (1, 31, 3, 3)).copy()
    pose = ret.solve(pos, rot)
    heads = pose.W[0, :, :3, 3]
    pts, _ = rt.source_world(pos, rot)
    worst = 0.0
    for name, chain in ret.mapping.items():
        b = rig.index[name]
        if chain == "root":
            continue
        sg = ret.seg[b]
        dt = ret._end_world(pose.W, b)[0] - heads[b]
        ds = interp_poly(pts[:, sg["chain"]], sg["s"], sg["f1"])[0] - interp_poly(
            pts[:, sg["chain"]], sg["s"], sg["f0"])[0]
        ang = np.degrees(np.arccos(np.clip(dt @ ds / np.linalg.norm(dt) / np.linalg.norm(ds), -1, 1)))
        worst = max(worst, ang)
    print(f"\nA-pose rig vs source rest pose: worst segment direction error {worst:.2e} deg")
    assert worst < 1e-3
    # The turned rig faces the source's way (-Y) after alignment: its left hip is at +X.
    lm = ret.landmarks(pose.W)
    hips_l = pose.W[0, rig.index["thigh_l"], :3, 3]
    hips_r = pose.W[0, rig.index["thigh_r"], :3, 3]
    assert hips_l[0] > hips_r[0]
    assert lm["head"][0, 2] > lm["hips"][0, 2] > lm["lankle"][0, 2]



def test_planted_source_feet_stay_planted_on_the_target_numpy():
    """A source whose pelvis bobs and sways while both feet stay planted (leg IK
    on the source): on a rig of other proportions the feet slide without foot
    locking and stay put with it."""
    from dancing_points_addon.ik import two_bone_ik
    from dancing_points_addon.skeleton import JOINT_INDEX as J

    if not SALSA.exists():
        pytest.skip("shared data not found")
    bv, ends = _rest_source()
    T = 60
    t = np.arange(T) / 30.0
    off = np.stack([0.05 * np.sin(2 * np.pi * t), -0.06 - 0.04 * np.sin(4 * np.pi * t),
                    0.03 * np.cos(2 * np.pi * t)], 1)
    pos = np.repeat(ends[None], T, 0)
    rot = np.repeat(np.eye(3)[None, None], T, 0).repeat(31, 1)
    legs = {s: [J[s + n] for n in ("hipjoint", "femur", "tibia", "foot", "toes")] for s in "lr"}
    pos += off[:, None]
    for s, (hj, fe, ti, fo, to) in legs.items():
        knee, ankle, R1, R2 = two_bone_ik(pos[:, hj], pos[:, fe], pos[:, ti], ends[ti][None].repeat(T, 0))
        pos[:, fe], pos[:, ti] = knee, ankle
        pos[:, fo], pos[:, to] = ends[fo], ends[to]
        rot[:, fe], rot[:, ti] = R1, R2
    assert np.abs(pos[:, J["ltibia"]] - ends[J["ltibia"]]).max() < 1e-6  # the source is planted
    rig = _apose_target()
    mapping, _ = rt.auto_mapping(rig.names)
    slides = {}
    for lock in (False, True):
        ret = rt.Retargeter(bv, rig, mapping, foot_lock=lock)
        pose = ret.solve(pos, rot)
        lm = ret.landmarks(pose.W)
        slides[lock] = max(np.linalg.norm(lm[k] - lm[k][0], axis=-1).max() for k in rt.FOOT_POINTS)
    print(f"\nplanted source feet: target foot points move up to {slides[False] / CM:.2f} cm without foot "
          f"locking, {slides[True] / CM:.4f} cm with it")
    assert slides[True] < 1e-3 < slides[False]


# --------------------------------------------------------------------------- in Blender

try:
    import bpy
except ImportError:  # the bpy-free tests above still run
    bpy = None

if bpy is not None:
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension
    from support.retarget_util import baked_salsa_duet, check_rig, evaluate, points, reference


def _build_apose_rig(name="UE Dancer", size=1.0, modes=('QUATERNION', 'XYZ', 'ZXY')):
    """The :func:`apose_rig` (scaled by ``size``) as a Blender armature with a
    skinned box body, bones in the rotation ``modes`` in turn (twist bones not
    connected, no box on the root)."""
    bones = [(n, p, tuple(size * np.array(h)), tuple(size * np.array(t)), r) for n, p, h, t, r in apose_rig()]
    return bsu.build_armature(name, bones, modes, (1.5, -0.5, 0.0), np.pi / 2,
                              connect=lambda bone: "twist" not in bone, box=0.04, no_box=("root",))


def _import_avatar(path, tmpdir):
    plain = gltf_meshopt.decompress_glb(path, tmpdir / path.name)
    before = set(bpy.data.objects)
    assert bpy.ops.import_scene.gltf(filepath=str(plain)) == {'FINISHED'}
    new = [o for o in bpy.data.objects if o not in before]
    arm = next(o for o in new if o.type == 'ARMATURE')
    meshes = [o for o in new if o.type == 'MESH' and any(m.type == 'ARMATURE' and m.object == arm
                                                         for m in o.modifiers)]
    return arm, max(meshes, key=lambda o: len(o.data.vertices))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    if bpy is None:
        pytest.skip("bpy not installed")
    if not SALSA.exists() or not (ASSETS / AVATARS["leader"]).exists():
        pytest.skip("shared data or avatars not found")
    d = tmp_path_factory.mktemp("dp_retarget")
    duet, dp = baked_salsa_duet(d, MODELS)
    avatars = {role: _import_avatar(ASSETS / f, d) for role, f in AVATARS.items()}
    refs = {role: reference(a) for role, (a, _) in avatars.items()}
    lead = avatars["leader"][0]
    t0 = time.perf_counter()
    assert bpy.ops.dancing_points.retarget_duet(duet=duet.name, leader_target=lead.name,
                                                follower_target=avatars["follower"][0].name) == {'FINISHED'}
    t_avatars = time.perf_counter() - t0
    ue = {"leader": _build_apose_rig("UE Leader", 1.04), "follower": _build_apose_rig("UE Follower", 0.95,
                                                                                   ('ZXY', 'QUATERNION', 'YZX'))}
    ue["follower"].location = (-1.0, 2.0, 0.0)
    ue_ref = {r: reference(o) for r, o in ue.items()}
    # The built follower already has an action of its own: it must survive untouched.
    compat = bsu.compat()
    old, slot = compat.new_action_for(ue["follower"], "Users Own Action")
    compat.write_keys(compat.ensure_fcurves(old, slot, 'pose.bones["pelvis"].location', 0, "pelvis"),
                      [1, 2], [0.0, 0.0])
    t0 = time.perf_counter()
    assert bpy.ops.dancing_points.retarget_duet(duet=duet.name, leader_target=ue["leader"].name,
                                                follower_target=ue["follower"].name) == {'FINISHED'}
    t_ue = time.perf_counter() - t0
    print(f"\nmodels {MODELS}: retarget of both avatars {t_avatars:.2f} s, of both built rigs {t_ue:.2f} s")
    frames = bsu.fcurve_keys(dp["leader"], 'pose.bones["root"].location', 0)[0].astype(int)
    # The duet's centre (hip joints' midpoint, both source dancers, all frames): the
    # point about which positions are normalised by height.
    W = evaluate([dp["leader"], dp["follower"]], frames)
    centre = np.mean([points(W[a.name], [pb.name for pb in a.pose.bones], SRC_POINTS, tails=True,
                              lengths={b.name: b.length for b in a.data.bones})["hips"][:, :2].mean(0)
                      for a in dp.values()], axis=0)
    return {"duet": duet, "dp": dp, "avatars": avatars, "refs": refs, "ue": ue, "ue_ref": ue_ref, "frames": frames,
            "dir": d, "centre": centre}


@pytest.mark.parametrize("role", ["leader", "follower"])
def test_avatars_follow_the_duet(scene, role):
    arm, body = scene["avatars"][role]
    means, slide, step = check_rig(scene, role, arm, scene["refs"][role], "mixamo", f"avatar {role}")
    assert max(means.values()) < 3 * CM, means
    assert slide < 1 * CM
    assert step < 90.0
    # The avatar's own mesh deforms (Blender's Armature modifier), its mesh data is untouched.
    f = scene["frames"]
    a = bsu.evaluated_vertices(body, f[len(f) // 4])
    b = bsu.evaluated_vertices(body, f[3 * len(f) // 4])
    moved = np.linalg.norm(a - b, axis=-1)
    print(f"  mesh '{body.name}': {len(a)} vertices, moved up to {moved.max() / CM:.1f} cm between two frames")
    assert moved.max() > 5 * CM


def test_new_actions_and_the_rigs_own_action_kept(scene):
    lead, _ = scene["avatars"]["leader"]
    action = lead.animation_data.action
    assert action.name.startswith("DP ") and action.get("dp_retarget_source") == scene["dp"]["leader"].name
    ue = scene["ue"]["follower"]
    assert ue.animation_data.action.name.startswith("DP ")
    old = bpy.data.actions["Users Own Action"]
    assert old.use_fake_user  # kept although the rig now plays the new action
    compat = bsu.compat()
    fc = list(compat.fcurves_of(old, old.slots[0] if compat.SLOTTED else None))
    assert len(fc) == 1 and list(compat.read_keys(fc[0])[0]) == [1.0, 2.0]
    # One key per frame on every bone.
    frames = scene["frames"]
    f, _ = bsu.fcurve_keys(lead, 'pose.bones["LeftUpLeg"].rotation_quaternion', 0)
    np.testing.assert_array_equal(f, frames)
    # The mapping is stored on the rig, editable and exportable.
    m = {i.target: i.source for i in lead.dp_retarget_map if i.source}
    assert m["LeftForeArm"] == "lradius+lwrist" and len(lead.dp_retarget_map) == len(lead.data.bones)
    path = scene["dir"] / "avatar_map.json"
    assert bpy.ops.dancing_points.retarget_map_save(target=lead.name, filepath=str(path)) == {'FINISHED'}
    assert rt.load_preset(path)["bones"] == m
    # A missing file is said to be missing (not taken for a convention's name) and changes nothing;
    # a '//' path of an unsaved .blend is refused, not written to the folder Blender started in.
    with pytest.raises(RuntimeError, match="bone map file not found"):
        bpy.ops.dancing_points.retarget_map_load(target=lead.name, filepath=str(scene["dir"] / "nope.json"))
    assert {i.target: i.source for i in lead.dp_retarget_map if i.source} == m
    assert not bpy.data.filepath
    for op in (bpy.ops.dancing_points.retarget_map_save, bpy.ops.dancing_points.retarget_map_load):
        with pytest.raises(RuntimeError, match="not saved yet"):
            op(target=lead.name, filepath="//bone_map.json")


def _wrist_gaps(W, sources, targets, target_hands):
    """Per frame, the distances ``(T, 4)`` of every leader-wrist/follower-wrist pair:
    of the Dancing Points armatures ``sources`` (bone tails of lwrist, rwrist) and of
    the rigs ``targets`` (heads of ``target_hands``), from evaluated matrices ``W``."""
    def points(obj, names, tails):
        idx = [b.name for b in obj.pose.bones]
        m = [W[obj.name][:, idx.index(n)] for n in names]
        if tails:
            return np.stack([np.einsum("tij,j->ti", x, [0, obj.data.bones[n].length, 0, 1])[:, :3]
                             for x, n in zip(m, names)], 1)
        return np.stack([x[:, :3, 3] for x in m], 1)

    def gaps(a, b):
        return np.linalg.norm(a[:, :, None] - b[:, None], axis=-1).reshape(len(a), 4)

    sl, sf = (points(o, ["lwrist", "rwrist"], True) for o in sources)
    tl, tf = (points(o, list(target_hands), False) for o in targets)
    return gaps(sl, sf), gaps(tl, tf)


def _assert_held_hands_meet(W, sources, targets, target_hands, what):
    """Where the source dancers' wrists are < 15 cm apart, the targets' wrists are
    at the source's gap (median error < 3 cm)."""
    ds, dt = _wrist_gaps(W, sources, targets, target_hands)
    held = ds < 0.15
    assert held.any(), "the clip must hold hands somewhere for this test to mean anything"
    gap = np.abs(dt[held] - ds[held])
    print(f"\n{what}: {held.sum()} held pair-frames; |target gap - source gap| mean {gap.mean() / CM:.2f} cm, "
          f"median {np.median(gap) / CM:.2f} cm, max {gap.max() / CM:.2f} cm")
    assert np.median(gap) < 3 * CM


def test_hands_that_hold_stay_together(scene):
    """Where the source dancers' wrists are < 15 cm apart, the avatars' are too
    (at the source's gap, up to arm reach)."""
    frames = scene["frames"]
    dp = scene["dp"]
    (la, _), (fa, _) = scene["avatars"]["leader"], scene["avatars"]["follower"]
    W = evaluate([dp["leader"], dp["follower"], la, fa], frames)

    _assert_held_hands_meet(W, (dp["leader"], dp["follower"]), (la, fa), ("LeftHand", "RightHand"), "hand holds")


@pytest.mark.parametrize("role", ["leader", "follower"])
def test_apose_rigs_of_another_convention(scene, role):
    ue = scene["ue"][role]
    means, slide, step = check_rig(scene, role, ue, scene["ue_ref"][role], "unreal",
                                    f"built Unreal A-pose rig, {role}")
    assert max(means.values()) < 3 * CM, means
    assert slide < 1 * CM
    assert step < 90.0
    body = next(o for o in bpy.data.objects if o.parent == ue and o.type == 'MESH')
    f = scene["frames"]
    moved = np.linalg.norm(bsu.evaluated_vertices(body, f[10]) - bsu.evaluated_vertices(body, f[-10]), axis=-1)
    assert moved.max() > 5 * CM
    # Euler bones were keyed in their own rotation mode.
    pb = next(p for p in ue.pose.bones if p.rotation_mode not in ('QUATERNION', 'AXIS_ANGLE'))
    assert bsu.fcurve_keys(ue, 'pose.bones["{:s}"].rotation_euler'.format(pb.name), 0)[0].size == len(f)


def test_single_dancer_closes_hands_on_the_partners_rig(scene):
    """``retarget(source, target)`` for one dancer: where the dancers hold hands,
    its wrists meet those of the rig the partner was retargeted onto (fixed)."""
    dp, ue = scene["dp"], scene["ue"]
    assert bpy.ops.dancing_points.retarget(source=dp["follower"].name, target=ue["follower"].name) == {'FINISHED'}
    frames = scene["frames"]
    W = evaluate([dp["leader"], dp["follower"], ue["leader"], ue["follower"]], frames)

    _assert_held_hands_meet(W, (dp["leader"], dp["follower"]), (ue["leader"], ue["follower"]), ("hand_l", "hand_r"),
                            "single-dancer retarget")


def test_an_avatar_with_an_action_of_its_own_keeps_its_size(scene):
    """The glTF avatars carry their node's transform (a scale of 0.01) on the
    Hips pose bone. A copy that already has an action of its own (one key on
    its hips) is retargeted as the fixture's avatar was, at its own size: it
    was 100 times too big (its rest pose taken as the reference)."""
    d = scene["dir"] / "own_action"
    d.mkdir()
    arm, body = _import_avatar(ASSETS / AVATARS["leader"], d)
    try:
        arm.pose.bones["Hips"].keyframe_insert("location", frame=1)
        assert arm.animation_data.action is not None
        assert bpy.ops.dancing_points.retarget(source=scene["dp"]["leader"].name, target=arm.name) == {'FINISHED'}
        frames = scene["frames"][::10]
        ref = scene["avatars"]["leader"][0]
        W = evaluate([arm, ref], frames)
        head = [pb.name for pb in arm.pose.bones].index("Head")
        mine, theirs = W[arm.name][:, head, :3, 3], W[ref.name][:, head, :3, 3]
        assert np.abs(mine[:, 2] - theirs[:, 2]).max() < 2 * CM, (mine[:, 2].max(), theirs[:, 2].max())
    finally:
        for o in (body, arm):
            bpy.data.objects.remove(o)


def _rig_state(obj):
    """What a retarget may change on a rig, as plain values: its custom properties
    (reference pose, source, mapping convention), bone map, action, visibility."""
    compat = bsu.compat()
    action, _ = compat.assigned_action(obj)
    return {"custom": {k: compat.plain_value(v) for k, v in obj.items()},
            "map": [(i.target, i.source) for i in obj.dp_retarget_map] if obj.is_property_set("dp_retarget_map")
            else None,
            "action": (action.name, action.use_fake_user) if action is not None else None,
            "animation_data": obj.animation_data is not None,
            "hidden": (obj.hide_get(), obj.hide_viewport, obj.hide_render),
            "actions": sorted(bpy.data.actions.keys())}


@contextlib.contextmanager
def _avatar_copy(scene, folder):
    """A fresh copy of the leader's avatar for one test, retargeted from the
    fixture's leader: ``(source, rig, others)``; the rig, its body and the
    objects the test puts in ``others`` are removed after it, and the source's
    link to the fixture's rig is put back."""
    src = scene["dp"]["leader"]
    linked = src.get("dp_retarget_target")
    d = scene["dir"] / folder
    d.mkdir()
    arm, body = _import_avatar(ASSETS / AVATARS["leader"], d)
    others = []
    try:
        yield src, arm, others
    finally:
        for o in (body, arm, *others):
            bpy.data.objects.remove(o)
        if linked is not None:
            src["dp_retarget_target"] = linked


def test_a_failed_retarget_leaves_the_rig_as_it_was(scene):
    """A retarget that fails (a constraint overrides a mapped bone, a preset that
    does not fit, the other rig of a duet run not mappable) leaves the rig exactly
    as it was: no bone map, reference pose or other property of the run stays on
    it, a bone map the user edited is not overwritten, its action and pose are its own."""
    with _avatar_copy(scene, "failed") as (src, arm, others):
        tiny = bsu.build_armature("Two Bones", [("Zork", None, (0, 0, 0), (0, 0, 0.5), 0.0),
                                                ("Blip", "Zork", (0, 0, 0.5), (0, 0, 1.0), 0.0)], body=False)
        empty = bpy.data.objects.new("Thigh Holder", None)
        bpy.context.scene.collection.objects.link(empty)
        others += [tiny, empty]
        con = arm.pose.bones["LeftUpLeg"].constraints.new('COPY_ROTATION')
        con.target = empty
        arm.pose.bones["Head"].rotation_quaternion = (0.9, 0.1, 0.0, 0.0)
        failures = (
            (lambda: bpy.ops.dancing_points.retarget(source=src.name, target=arm.name), "constraints override"),
            (lambda: bpy.ops.dancing_points.retarget(source=src.name, target=arm.name, preset="unreal"),
             "exactly one bone mapped to 'root'"),
            (lambda: bpy.ops.dancing_points.retarget_duet(duet=scene["duet"].name, leader_target=arm.name,
                                                          follower_target=tiny.name), "Two Bones"))

        def fail_all(what):
            for run, why in failures:
                before, pose = _rig_state(arm), bsu.pose_channels(arm)
                with pytest.raises(RuntimeError, match=why):
                    run()
                assert _rig_state(arm) == before, (what, why)
                np.testing.assert_allclose(bsu.pose_channels(arm), pose, atol=1e-7)

        fail_all("a rig never retargeted")
        assert "dp_reference_basis" not in arm and not arm.is_property_set("dp_retarget_map")
        # Retargeted once (the constraint off), its bone map edited by the user, then failing again.
        con.enabled = False
        assert bpy.ops.dancing_points.retarget(source=src.name, target=arm.name) == {'FINISHED'}
        con.enabled = True
        next(i for i in arm.dp_retarget_map if i.target == "Neck").source = "lowerneck"
        fail_all("a retargeted rig with an edited bone map")
        assert next(i.source for i in arm.dp_retarget_map if i.target == "Neck") == "lowerneck"


def test_retargeting_again_replaces_the_previous_output_action(scene):
    """Retargeting a rig again replaces the retarget's previous action on it (it
    was kept with a fake user: ten runs left ten 84-bone actions): removed when
    nothing else uses it, kept when the user assigned it elsewhere or renamed it.
    The rig's own action is kept (fake user) as before."""
    with _avatar_copy(scene, "again") as (src, arm, others):
        keeper = bpy.data.objects.new("Keeper", None)
        bpy.context.scene.collection.objects.link(keeper)
        others += [keeper]
        compat = bsu.compat()
        own, slot = compat.new_action_for(arm, "Avatar Own Action")
        compat.write_keys(compat.ensure_fcurves(own, slot, 'pose.bones["Hips"].location', 0, "Hips"), [1, 2],
                          [0.0, 0.0])

        def retarget():
            assert bpy.ops.dancing_points.retarget(source=src.name, target=arm.name) == {'FINISHED'}
            return arm.animation_data.action

        first = retarget()
        assert own.name in bpy.data.actions and own.use_fake_user and own.users == 1
        count = len(bpy.data.actions)
        outputs = [first.session_uid]  # (a removed action's name is free for the next one)
        for _ in range(3):
            outputs.append(retarget().session_uid)
        left = {a.session_uid for a in bpy.data.actions} & set(outputs[:-1])
        print(f"\n4 retargets onto '{arm.name}': {count} actions after the first, {len(bpy.data.actions)} after "
              f"the last; {len(left)} of the 3 replaced outputs left")
        assert len(bpy.data.actions) == count and not left
        assert arm.animation_data.action.name == f"DP {arm.name} {src.name}"  # its name, not "… .001"
        assert own.name in bpy.data.actions and own.use_fake_user
        # The user's own use of an output: assigned to another object, or renamed: kept.
        used = arm.animation_data.action
        keeper.animation_data_create().action = used
        renamed = retarget()
        assert keeper.animation_data.action == used and used.name in bpy.data.actions
        renamed.name = "My Favourite Take"
        retarget()
        assert renamed.name in bpy.data.actions and renamed.use_fake_user
        assert len(bpy.data.actions) == count + 2


def test_bad_input_reports_one_line(scene):
    dp = scene["dp"]
    with pytest.raises(RuntimeError, match="no object named"):
        bpy.ops.dancing_points.retarget(source=dp["leader"].name, target="nope")
    cam = bpy.context.scene.camera
    with pytest.raises(RuntimeError, match="must be an armature"):
        bpy.ops.dancing_points.retarget(source=dp["leader"].name, target=cam.name)
    ue = scene["ue"]["leader"]
    with pytest.raises(RuntimeError, match="not a Dancing Points armature"):
        bpy.ops.dancing_points.retarget(source=ue.name, target=scene["avatars"]["leader"][0].name)
    # a duet's own dancer is no target (its baked dance would be replaced); one rig, one part;
    # a rig name that does not exist is an error, not a dancer silently left out
    acts = {o.name: o.animation_data.action for o in (dp["follower"], ue)}
    with pytest.raises(RuntimeError, match="is a Dancing Points armature"):
        bpy.ops.dancing_points.retarget(source=dp["leader"].name, target=dp["follower"].name)
    duet = scene["duet"].name
    with pytest.raises(RuntimeError, match="picked for both dancers"):
        bpy.ops.dancing_points.retarget_duet(duet=duet, leader_target=ue.name, follower_target=ue.name)
    with pytest.raises(RuntimeError, match="no object named 'Her Rig'"):
        bpy.ops.dancing_points.retarget_duet(duet=duet, leader_target=ue.name, follower_target="Her Rig")
    assert {o.name: o.animation_data.action for o in (dp["follower"], ue)} == acts


def test_loading_a_file_that_is_no_bone_map_reports_one_line(tmp_path):
    if bpy is None:
        pytest.skip("no bpy module")
    rig = bpy.data.objects.new("My Rig", bpy.data.armatures.new("My Rig"))  # (the module's scene stays)
    bpy.context.scene.collection.objects.link(rig)
    try:
        binary = tmp_path / "take.npz"
        np.savez(binary, x=np.arange(3.0))
        with pytest.raises(RuntimeError, match=r"take\.npz: not a bone map \(not UTF-8 text\)") as exc:
            bpy.ops.dancing_points.retarget_map_load(target=rig.name, filepath=str(binary))
        assert str(binary) in str(exc.value) and "UnicodeDecodeError" not in str(exc.value)
        assert len(rig.dp_retarget_map) == 0
    finally:
        data = rig.data
        bpy.data.objects.remove(rig)
        bpy.data.armatures.remove(data)


def test_panel_draws_and_rig_files_load(scene, tmp_path):
    """The Retarget sub-panel draws (a recording stand-in layout); a rig saved in a
    .blend and a meshopt .glb load through ``load_rig_file`` (the batch command's way in)."""

    Rec = bsu.RecordingLayout

    cls = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_retarget")
    assert cls is not None and cls.bl_parent_id == "VIEW3D_PT_dancing_points"
    bpy.context.view_layer.objects.active = scene["ue"]["leader"]
    fake = type("Fake", (), {"layout": Rec()})
    cls.draw(fake, bpy.context)
    assert any(c[0] == "template_list" for c in fake.layout.calls)
    rmod = import_from_extension("operators.retarget")
    path = tmp_path / "rig.blend"
    bpy.data.libraries.write(str(path), {scene["ue"]["leader"]})
    arm = rmod.load_rig_file(str(path))
    assert arm.type == 'ARMATURE' and len(arm.data.bones) == len(scene["ue"]["leader"].data.bones)
    arm = rmod.load_rig_file(str(ASSETS / AVATARS["follower"]))
    assert len(arm.data.bones) == 84
    with pytest.raises(import_from_extension("dancing_points_addon.retarget").RetargetError,
                       match="unsupported rig file type"):
        rmod.load_rig_file(str(ASSETS / "VALID_AVATARS_LICENSE.txt"))
    # A file that fails leaves nothing of itself in the scene, and its line names it:
    # a .glb cut short, a .glb and a .blend without an armature.
    err = import_from_extension("dancing_points_addon.retarget").RetargetError
    cut = tmp_path / "cut.glb"
    data = (ASSETS / AVATARS["leader"]).read_bytes()
    cut.write_bytes(data[:len(data) // 3])
    mesh = bpy.data.meshes.new("Plain Cube")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    cube = bpy.data.objects.new("Plain Cube", mesh)
    bpy.context.scene.collection.objects.link(cube)
    bpy.data.libraries.write(str(tmp_path / "cube.blend"), {cube})
    for o in bpy.context.scene.objects:
        o.select_set(o == cube)
    assert bpy.ops.export_scene.gltf(filepath=str(tmp_path / "cube.glb"), use_selection=True) == {'FINISHED'}
    bpy.data.objects.remove(cube)
    bpy.data.meshes.remove(mesh)
    kinds = ("objects", "collections", "meshes", "armatures", "materials", "images", "actions")
    for path, why in ((cut, "is the file complete"), (tmp_path / "cube.glb", "has no armature"),
                      (tmp_path / "cube.blend", "has no armature")):
        before = {k: sorted(getattr(bpy.data, k).keys()) for k in kinds}
        with pytest.raises(err, match=why) as info:
            rmod.load_rig_file(str(path))
        assert str(path) in str(info.value)
        assert {k: sorted(getattr(bpy.data, k).keys()) for k in kinds} == before
