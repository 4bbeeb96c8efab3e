"""Retargeting onto the rigs Blender users have.

- bpy-free: the new conventions are detected (Rigify meta-rig, VRM as exported
  by VRoid, VRM 1.0 humanoid names), a rig of made-up names is mapped by its
  structure (pelvis, legs, spine, arms, sides).
- in Blender: the 5 s salsa duet of ``test_retarget`` retargeted onto a Rigify
  human meta-rig, the rig Rigify generates from it (the bundled ``rigify``
  add-on enabled), a VRoid-named rig and a rig of made-up names. Every frame is
  evaluated by Blender and checked as in ``test_retarget._check_rig``: wrists,
  ankles and skull base of the deform bones follow the source's after
  normalising by height (mean < 3 cm), planted feet do not slide (< 1 cm), and
  the rig really moves (deform bones > 20 cm over the take). On the generated
  Rigify rig the keys are on its controls, the limbs in FK, and switching back
  to IK keeps the pose. A rig whose constraints override the mapped bones gets a
  clear error and keeps its action and pose.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import MODELS, SALSA
from support.helpers import SRC_POINTS, TGT_POINTS, apose_rig, target_rig_from_bones
from dancing_points_addon import retarget as rt
from dancing_points_addon.retarget import rigify as rgf
from dancing_points_addon.retarget.structure import structural_mapping


CM = 1e-2


# --------------------------------------------------------------------------- bpy-free

def _vrm_bones(names=None):
    """A VRoid-like rig (T-pose, facing -Y: the left side at +X): ``(name, parent,
    head, tail, roll)``; ``names`` renames the VRoid bone names."""
    bones = [("Root", None, (0, 0, 0), (0, 0, 0.1), 0.0),
             ("J_Bip_C_Hips", "Root", (0, 0, 0.95), (0, 0, 1.02), 0.0),
             ("J_Bip_C_Spine", "J_Bip_C_Hips", (0, 0, 1.02), (0, 0, 1.12), 0.0),
             ("J_Bip_C_Chest", "J_Bip_C_Spine", (0, 0, 1.12), (0, 0, 1.24), 0.0),
             ("J_Bip_C_UpperChest", "J_Bip_C_Chest", (0, 0, 1.24), (0, 0, 1.38), 0.0),
             ("J_Bip_C_Neck", "J_Bip_C_UpperChest", (0, 0, 1.38), (0, 0, 1.48), 0.0),
             ("J_Bip_C_Head", "J_Bip_C_Neck", (0, 0, 1.48), (0, 0, 1.66), 0.0)]
    for x, s in ((1, "L"), (-1, "R")):
        p = "J_Bip_{:s}_".format(s)
        bones += [(p + "Shoulder", "J_Bip_C_UpperChest", (0.02 * x, 0, 1.36), (0.16 * x, 0, 1.36), 0.0),
                  (p + "UpperArm", p + "Shoulder", (0.16 * x, 0, 1.36), (0.44 * x, 0, 1.36), 0.0),
                  (p + "LowerArm", p + "UpperArm", (0.44 * x, 0, 1.36), (0.70 * x, 0, 1.36), 0.0),
                  (p + "Hand", p + "LowerArm", (0.70 * x, 0, 1.36), (0.79 * x, 0, 1.36), 0.0),
                  (p + "UpperLeg", "J_Bip_C_Hips", (0.09 * x, 0, 0.93), (0.09 * x, 0, 0.50), 0.0),
                  (p + "LowerLeg", p + "UpperLeg", (0.09 * x, 0, 0.50), (0.09 * x, 0.01, 0.09), 0.0),
                  (p + "Foot", p + "LowerLeg", (0.09 * x, 0.01, 0.09), (0.09 * x, -0.12, 0.02), 0.0),
                  (p + "ToeBase", p + "Foot", (0.09 * x, -0.12, 0.02), (0.09 * x, -0.18, 0.02), 0.0)]
    if names:
        bones = [(names.get(n, n), names.get(p, p) if p else None, h, t, r) for n, p, h, t, r in bones]
    return bones


def _madeup_bones():
    """The Unreal-like A-pose rig of ``test_retarget`` (facing +Y, other rolls) with
    made-up names, hip bones between the pelvis and the thighs and a head end
    bone: nothing a preset knows."""
    bones = apose_rig()
    out = []
    for n, p, h, t, r in bones:
        if n.startswith("thigh_"):
            side = n[-1]
            out.append(("hip_" + side, "pelvis", (0, 0, 0.88), h, 0.0))
            p = "hip_" + side
        out.append((n, p, h, t, r))
    out.append(("head_end", "head", (0, 0.02, 1.64), (0, 0.02, 1.66), 0.0))
    rng = np.random.default_rng(16)
    words = ["Zork", "Blip", "Quux", "Fjord", "Mimsy", "Tove", "Wabe", "Borogove", "Rath", "Snark", "Jubjub",
             "Boojum", "Vorpal", "Tulgey", "Frabjous", "Callay", "Uffish", "Manxome", "Beamish", "Slithy"]
    rename = {}
    for i, (n, *_rest) in enumerate(out):
        rename[n] = "{:s}_{:02d}".format(words[int(rng.integers(len(words)))], i)
    return [(rename[n], rename[p] if p else None, h, t, r) for n, p, h, t, r in out], rename


VRM1 = {"J_Bip_C_Hips": "hips", "J_Bip_C_Spine": "spine", "J_Bip_C_Chest": "chest",
        "J_Bip_C_UpperChest": "upperChest", "J_Bip_C_Neck": "neck", "J_Bip_C_Head": "head"}
for _s, _side in (("L", "left"), ("R", "right")):
    for _a, _b in (("Shoulder", "Shoulder"), ("UpperArm", "UpperArm"), ("LowerArm", "LowerArm"), ("Hand", "Hand"),
                   ("UpperLeg", "UpperLeg"), ("LowerLeg", "LowerLeg"), ("Foot", "Foot"), ("ToeBase", "Toes")):
        VRM1["J_Bip_{:s}_{:s}".format(_s, _a)] = _side + _b
METARIG = {"J_Bip_C_Hips": "spine", "J_Bip_C_Spine": "spine.001", "J_Bip_C_Chest": "spine.002",
           "J_Bip_C_UpperChest": "spine.003", "J_Bip_C_Neck": "spine.004", "J_Bip_C_Head": "spine.006"}
for _s in "LR":
    for _a, _b in (("Shoulder", "shoulder"), ("UpperArm", "upper_arm"), ("LowerArm", "forearm"), ("Hand", "hand"),
                   ("UpperLeg", "thigh"), ("LowerLeg", "shin"), ("Foot", "foot"), ("ToeBase", "toe")):
        METARIG["J_Bip_{:s}_{:s}".format(_s, _a)] = "{:s}.{:s}".format(_b, _s)


def test_new_conventions_detected_and_mapped():
    presets = rt.builtin_conventions()
    assert {"rigify_metarig", "vrm0", "vrm1"} <= set(presets)
    expect = {"J_Bip_C_Hips": "root", "J_Bip_L_UpperLeg": "lfemur", "J_Bip_R_LowerLeg": "rtibia",
              "J_Bip_L_LowerArm": "lradius+lwrist", "J_Bip_R_Hand": "rhand", "J_Bip_C_Head": "head",
              "J_Bip_C_UpperChest": "thorax", "J_Bip_L_ToeBase": "ltoes", "J_Bip_R_Shoulder": "rclavicle"}
    for conv, rename in (("vrm0", {}), ("vrm1", VRM1), ("rigify_metarig", METARIG)):
        names = [b[0] for b in _vrm_bones(rename)]
        m, got = rt.auto_mapping(names)
        assert got == conv, (conv, got)
        for k, v in expect.items():
            assert m[rename.get(k, k)] == v, (conv, k, m.get(rename.get(k, k)))
        rt.validate_mapping(m, names)
    # A meta-rig's 3-bone neck chain (spine.004-.006) and a generated Rigify rig.
    names = [b[0] for b in _vrm_bones(METARIG)] + ["spine.005"]
    m, _ = rt.auto_mapping(names)
    assert m["spine.004"] == "lowerneck" and m["spine.005"] == "upperneck" and m["spine.006"] == "head"
    generated = [c for c, _ in rgf.CONTROLS + rgf.IK_CONTROLS] + sorted({d for _, d in rgf.CONTROLS}) + [
        "thigh_parent.L", "thigh_parent.R", "upper_arm_parent.L", "upper_arm_parent.R", "ORG-thigh.L"]
    assert rgf.is_generated_rigify(generated) and not rgf.is_generated_rigify(names)
    assert rt.auto_mapping(generated)[1] == "rigify"


def test_made_up_names_mapped_by_structure():
    """Pelvis, legs, spine, neck, head, arms and the sides found from the hierarchy
    and the rest pose, whatever the names: the same mapping as the Unreal preset
    gives the rig with its real names (a turned A-pose rig, hip bones, end bone)."""
    bones, rename = _madeup_bones()
    world = np.eye(4)
    world[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    rig = target_rig_from_bones(bones, world)
    assert rt.auto_mapping(rig.names)[0] == {}
    mapping, roles = structural_mapping(rig)
    want, _ = rt.auto_mapping(list(rename))
    want = {rename[k]: v for k, v in want.items()}
    assert mapping == want, {k: (mapping.get(k), want.get(k)) for k in set(mapping) | set(want)
                             if mapping.get(k) != want.get(k)}
    assert roles["lthigh"] == rename["thigh_l"] and roles["rhand"] == rename["hand_r"]
    # VRM geometry facing -Y (left at +X), names stripped: sides right as well.
    vb = _vrm_bones({n: "b{:02d}".format(i) for i, (n, *_r) in enumerate(_vrm_bones())})
    m, roles = structural_mapping(target_rig_from_bones(vb))
    ref = {b[0]: b for b in vb}
    assert ref[roles["lhand"]][2][0] > 0 and ref[roles["rthigh"]][2][0] < 0
    assert m[roles["spine3"]] == "thorax" and m[roles["neck1"]] == "lowerneck+upperneck"
    with pytest.raises(rt.RetargetError, match="no pelvis found"):
        structural_mapping(target_rig_from_bones(vb[:7]))


# --------------------------------------------------------------------------- in Blender

try:
    import bpy
except ImportError:
    bpy = None

if bpy is not None:
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension
    from support.retarget_util import baked_salsa_duet, check_rig, evaluate, points, reference

METARIG_POINTS = {"lhip": "thigh.L", "rhip": "thigh.R", "head": "spine.006", "lwrist": "hand.L", "rwrist": "hand.R",
                  "lankle": "foot.L", "rankle": "foot.R", "lball": "toe.L", "rball": "toe.R"}
TGT_POINTS.setdefault("rigify_metarig", METARIG_POINTS)
TGT_POINTS.setdefault("rigify_def", {k: "DEF-" + v for k, v in METARIG_POINTS.items()})
TGT_POINTS.setdefault("vrm0", {"lhip": "J_Bip_L_UpperLeg", "rhip": "J_Bip_R_UpperLeg", "head": "J_Bip_C_Head",
                                  "lwrist": "J_Bip_L_Hand", "rwrist": "J_Bip_R_Hand", "lankle": "J_Bip_L_Foot",
                                  "rankle": "J_Bip_R_Foot", "lball": "J_Bip_L_ToeBase", "rball": "J_Bip_R_ToeBase"})


ROLES = {"metarig": "leader", "rigify": "leader", "vrm": "leader", "odd": "follower", "metarig_follower": "follower",
         "rigify_follower": "follower", "vrm_follower": "follower"}


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    if bpy is None:
        pytest.skip("bpy not installed")
    if not SALSA.exists():
        pytest.skip("shared data not found")
    d = tmp_path_factory.mktemp("dp_retarget_rigs")
    duet, dp = baked_salsa_duet(d, MODELS)
    out = {"duet": duet, "dp": dp, "dir": d, "rigs": {}, "refs": {}, "times": {}}
    # Rigify: the human meta-rig, and the rig generated from (a copy of) it.
    if bsu.enable_rigify() is not None:
        bpy.ops.object.armature_human_metarig_add()
        meta = bpy.context.active_object
        meta.name = "Human Metarig"
        meta.location = (-1.0, 0.5, 0.0)
        meta.rotation_euler = (0.0, 0.0, 0.4)
        bpy.context.view_layer.update()
        t0 = time.perf_counter()
        bpy.ops.pose.rigify_generate()
        rig = bpy.context.active_object
        out["times"]["rigify_generate"] = time.perf_counter() - t0
        assert rig is not meta and rig.type == 'ARMATURE' and "DEF-spine" in rig.data.bones
        rig.name = "Rigify Rig"
        rig.location = (1.0, -0.5, 0.0)
        bpy.context.view_layer.update()
        out["rigs"]["metarig"], out["rigs"]["rigify"] = meta, rig
        # The follower onto a second meta-rig (long legs for her size), scaled to her
        # 1.66 m like the made-up rig below, so that held hands meet.
        bpy.ops.object.armature_human_metarig_add()
        meta_f = bpy.context.active_object
        meta_f.name = "Human Metarig Follower"
        meta_f.location = (0.5, 1.5, 0.0)
        meta_f.scale = (1.66 / 1.78,) * 3
        bpy.context.view_layer.update()
        bpy.ops.pose.rigify_generate()
        rig_f = bpy.context.active_object
        assert rig_f is not meta_f and "DEF-spine" in rig_f.data.bones
        rig_f.name = "Rigify Rig Follower"
        rig_f.location = (2.0, 1.5, 0.0)
        rig_f.scale = (1.66 / 1.78,) * 3  # generated at the meta-rig's own size: scaled to hers
        bpy.context.view_layer.update()
        out["rigs"]["metarig_follower"], out["rigs"]["rigify_follower"] = meta_f, rig_f
    else:
        out["rigify_missing"] = "the bundled 'rigify' add-on is not available in this bpy build"
    # Sizes: the leader's rigs 1.78 m to the skull base (the meta-rig's), the
    # follower's 1.66 m: the source dancers' ratio (1.07), so that held hands meet
    # where they should on both.
    vrm = bsu.build_armature("VRoid Dancer", [(n, p, tuple(1.2 * np.array(h)), tuple(1.2 * np.array(t)), r)
                                              for n, p, h, t, r in _vrm_bones()], ('QUATERNION', 'XYZ'),
                             (0.8, 1.2, 0.0), 0.3)
    madeup, _ = _madeup_bones()
    odd = bsu.build_armature("Odd Dancer", [(n, p, tuple(1.13 * np.array(h)), tuple(1.13 * np.array(t)), r)
                                            for n, p, h, t, r in madeup], ('ZXY', 'QUATERNION'),
                             (-1.5, -0.5, 0.0), -np.pi / 2)
    vrm_f = bsu.build_armature("VRoid Follower", [(n, p, tuple(1.12 * np.array(h)), tuple(1.12 * np.array(t)), r)
                                                  for n, p, h, t, r in _vrm_bones()], ('QUATERNION', 'XYZ'),
                               (-0.8, 2.2, 0.0), -0.5)
    out["rigs"]["vrm"], out["rigs"]["odd"], out["rigs"]["vrm_follower"] = vrm, odd, vrm_f
    out["refs"] = {k: reference(o) for k, o in out["rigs"].items()}
    # The duet onto the generated Rigify rig (leader) and the made-up rig (follower);
    # then the leader alone onto the meta-rig and the VRM rig (their hands close onto
    # the follower's rig), and the follower alone onto her meta-rig, the rig
    # generated from it and her VRM rig: both dancers on every kind of rig.
    t0 = time.perf_counter()
    lead = out["rigs"].get("rigify")
    assert bpy.ops.dancing_points.retarget_duet(duet=duet.name, leader_target=lead.name if lead else "",
                                                follower_target=odd.name) == {'FINISHED'}
    out["times"]["duet rigify+odd" if lead else "odd"] = time.perf_counter() - t0
    for kind in ("metarig", "vrm", "metarig_follower", "rigify_follower", "vrm_follower"):
        if kind in out["rigs"]:
            t0 = time.perf_counter()
            assert bpy.ops.dancing_points.retarget(source=dp[ROLES[kind]].name,
                                                   target=out["rigs"][kind].name) == {'FINISHED'}
            out["times"][kind] = time.perf_counter() - t0
    print("\ntimes (s): " + ", ".join("{:s} {:.2f}".format(k, v) for k, v in out["times"].items()))
    frames = bsu.fcurve_keys(dp["leader"], 'pose.bones["root"].location', 0)[0].astype(int)
    W = evaluate([dp["leader"], dp["follower"]], frames)
    out["centre"] = np.mean([points(W[a.name], [pb.name for pb in a.pose.bones], SRC_POINTS, tails=True,
                                        lengths={b.name: b.length for b in a.data.bones})["hips"][:, :2].mean(0)
                             for a in dp.values()], axis=0)
    out["frames"] = frames
    return out




def _deform_displacement(obj, frames):
    """Largest displacement (m) over the take of the deform bones' heads (median over the bones)."""
    names = [b.name for b in obj.data.bones if b.use_deform]
    W = evaluate([obj], frames)[obj.name]
    idx = [i for i, pb in enumerate(obj.pose.bones) if pb.name in set(names)]
    heads = W[:, idx, :3, 3]
    return float(np.median(np.linalg.norm(heads - heads[:1], axis=-1).max(0)))


@pytest.mark.parametrize("kind", ["metarig", "rigify", "vrm", "odd", "metarig_follower", "rigify_follower",
                                  "vrm_follower"])
def test_rig_follows_the_duet(rigs, kind):
    if kind not in rigs["rigs"]:
        pytest.skip(rigs.get("rigify_missing", "rig not built"))
    obj = rigs["rigs"][kind]
    ref = rigs["refs"][kind]
    conv = {"metarig": "rigify_metarig", "metarig_follower": "rigify_metarig", "rigify": "rigify_def",
            "rigify_follower": "rigify_def", "vrm": "vrm0", "vrm_follower": "vrm0"}.get(kind)
    if kind == "odd":  # its landmark bones, found by the structural mapping
        m = {i.target: i.source for i in obj.dp_retarget_map if i.source}
        inv = {}
        for bone, chain in m.items():
            inv.setdefault(chain, bone)
        conv = "odd"
        TGT_POINTS[conv] = {"lhip": inv["lfemur"], "rhip": inv["rfemur"], "head": inv["head"],
                               "lwrist": inv["lhand"], "rwrist": inv["rhand"], "lankle": inv["lfoot"],
                               "rankle": inv["rfoot"], "lball": inv["ltoes"], "rball": inv["rtoes"]}
        assert obj.get("dp_retarget_convention") == "structure"
    means, slide, step = check_rig(rigs, ROLES[kind], obj, ref, conv, "{:s} rig, {:s}".format(kind, ROLES[kind]))
    moved = _deform_displacement(obj, rigs["frames"])
    print(f"  deform bones move {moved / CM:.1f} cm over the take (median over the bones of the largest)")
    assert max(means[k] for k in ("hands", "feet", "head")) < 3 * CM, means
    assert slide < 1 * CM
    assert moved > 20 * CM
    action = obj.animation_data.action
    assert action.name.startswith("DP ") and action.get("dp_retarget_source") == rigs["dp"][ROLES[kind]].name


def test_rigify_rig_keys_its_controls_in_fk(rigs):
    if "rigify" not in rigs["rigs"]:
        pytest.skip(rigs.get("rigify_missing", "rig not built"))
    rig = rigs["rigs"]["rigify"]
    paths = {fc.data_path for fc in bsu.all_fcurves(rig)}
    keyed = sorted({p.split('"')[1] for p in paths})
    print("\nkeyed on the generated Rigify rig: " + ", ".join(keyed))
    for c in ("torso", "hips", "chest", "neck", "head", "thigh_fk.L", "shin_fk.L", "foot_fk.L", "upper_arm_fk.R",
              "forearm_fk.R", "hand_fk.R", "hand_ik.L", "foot_ik.R"):
        assert c in keyed, c
    assert not any(k.startswith(("DEF-", "ORG-", "MCH-")) for k in keyed)
    frames = rigs["frames"]
    for b, p in rgf.IK_FK_PROPS:
        f, v = bsu.fcurve_keys(rig, 'pose.bones["{:s}"]["{:s}"]'.format(b, p), 0)
        assert len(f) == len(frames) and np.all(v == rgf.FK_VALUE)
    # Switching the limbs back to IK keeps the pose (the IK controls are keyed to it).
    compat = bsu.compat()
    action, slot = compat.assigned_action(rig)
    lm = TGT_POINTS["rigify_def"]
    names = [pb.name for pb in rig.pose.bones]
    check = [frames[0], frames[len(frames) // 2]]
    fk = evaluate([rig], check)[rig.name]
    fcs = [compat.find_fcurve(action, slot, 'pose.bones["{:s}"]["{:s}"]'.format(b, p), 0) for b, p in rgf.IK_FK_PROPS]
    try:
        for fc in fcs:
            fc.mute = True
        for b, p in rgf.IK_FK_PROPS:
            rig.pose.bones[b][p] = rgf.IK_VALUE
        ik = evaluate([rig], check)[rig.name]
    finally:
        for fc in fcs:
            fc.mute = False
        for b, p in rgf.IK_FK_PROPS:
            rig.pose.bones[b][p] = rgf.FK_VALUE
    errs = {k: np.linalg.norm(ik[:, names.index(bn), :3, 3] - fk[:, names.index(bn), :3, 3], axis=-1).max()
            for k, bn in lm.items()}
    print("  IK vs FK on frames {}: ".format(check) + ", ".join(f"{k} {v / CM:.2f} cm" for k, v in errs.items()))
    assert max(errs.values()) < 1 * CM, errs


def test_overriding_constraints_give_an_error_and_leave_the_rig(rigs):
    """A rig whose left thigh is held by a Copy Rotation constraint: the retarget
    reports why, and the rig keeps its own action and pose."""
    dp = rigs["dp"]
    obj = bsu.build_armature("Held Dancer", _vrm_bones(), location=(3.0, 0.0, 0.0), body=False)
    empty = bpy.data.objects.new("Holder", None)
    bpy.context.scene.collection.objects.link(empty)
    con = obj.pose.bones["J_Bip_L_UpperLeg"].constraints.new('COPY_ROTATION')
    con.target = empty
    compat = bsu.compat()
    own, slot = compat.new_action_for(obj, "Held Own Action")
    compat.write_keys(compat.ensure_fcurves(own, slot, 'pose.bones["J_Bip_C_Spine"].location', 0, "J_Bip_C_Spine"),
                      [1, 20], [0.0, 0.05])
    obj.pose.bones["J_Bip_C_Head"].rotation_quaternion = (0.9, 0.1, 0.0, 0.0)
    bpy.context.scene.frame_set(bpy.context.scene.frame_current)
    before = bsu.pose_channels(obj)
    actions = sorted(a.name for a in bpy.data.actions)
    with pytest.raises(RuntimeError, match="does not follow the retargeted motion.*constraints override"):
        bpy.ops.dancing_points.retarget(source=dp["leader"].name, target=obj.name)
    assert obj.animation_data.action == own
    assert sorted(a.name for a in bpy.data.actions) == actions
    assert not own.use_fake_user
    np.testing.assert_allclose(bsu.pose_channels(obj), before, atol=1e-7)
    assert "dp_retarget_source" not in obj


def test_metarig_auto_map_and_rig_file_for_the_batch(rigs, tmp_path):
    """The bone-map operator finds the meta-rig's convention; a generated Rigify rig
    saved in a .blend loads through ``load_rig_file`` and retargets through
    ``retarget_duet_onto`` (the batch command's ``--follower-rig`` path)."""
    if "rigify" not in rigs["rigs"]:
        pytest.skip(rigs.get("rigify_missing", "rig not built"))
    meta, rig = rigs["rigs"]["metarig"], rigs["rigs"]["rigify"]
    assert bpy.ops.dancing_points.retarget_map_auto(target=meta.name) == {'FINISHED'}
    assert meta.get("dp_retarget_convention") == "rigify_metarig"
    odd = rigs["rigs"]["odd"]
    stored = {i.target: i.source for i in odd.dp_retarget_map if i.source}
    assert bpy.ops.dancing_points.retarget_map_auto(target=odd.name, convention='STRUCTURE') == {'FINISHED'}
    assert {i.target: i.source for i in odd.dp_retarget_map if i.source} == stored
    # The bone-map box says how the rig was mapped and that a Rigify rig's controls are keyed.
    cls = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_retarget")
    for obj, text in ((rig, "Rigify rig"), (meta, "Convention: rigify_metarig"),
                      (rigs["rigs"]["odd"], "Mapped by structure")):
        bpy.context.view_layer.objects.active = obj
        fake = type("Fake", (), {"layout": bsu.RecordingLayout()})
        cls.draw(fake, bpy.context)
        labels = [k.get("text", "") for name, a, k in fake.layout.calls if name == "label"]
        assert any(t.startswith(text) for t in labels), (obj.name, labels)
    path = tmp_path / "rigify_rig.blend"
    bpy.data.libraries.write(str(path), {rig})
    rmod = import_from_extension("operators.retarget")
    loaded = rmod.load_rig_file(str(path))
    assert loaded != rig and len(loaded.data.bones) == len(rig.data.bones)
    loaded.animation_data_clear()
    for k in ("dp_reference_basis", "dp_retarget_source"):
        loaded.pop(k, None)
    loaded.dp_retarget_map.clear()
    out = rmod.retarget_duet_onto(None, loaded, rigs["duet"], hide_bodies=False)
    info = out["follower"]
    assert info["controls"] and info["verified_error"] < 2 * CM
    print(f"\nloaded Rigify rig: verified on {import_from_extension('operators.retarget.apply').CHECK_FRAMES} "
          f"frames, largest landmark error {info['verified_error'] / CM:.2f} cm")


def test_batch_takes_rigify_and_made_up_rigs(rigs, tmp_path):
    """``batch --leader-rig rigify.blend --follower-rig odd.blend`` (a fresh Blender
    process, the rigify add-on not enabled there): the generated Rigify rig's
    controls and the made-up rig are keyed on every frame; the Rigify widgets are
    not put in the scene."""
    if "rigify" not in rigs["rigs"]:
        pytest.skip(rigs.get("rigify_missing", "rig not built"))
    from support.helpers import read_report, run_batch, run_bpy_script

    files = {}
    for kind in ("rigify", "odd"):  # as they are: retargeted once already (stored mapping and reference pose)
        files[kind] = tmp_path / (kind + ".blend")
        bpy.data.libraries.write(str(files[kind]), {rigs["rigs"][kind]})
    csv = rigs["dir"] / "salsa_5s.csv"
    out = tmp_path / "out"
    t0 = time.perf_counter()
    res = run_batch(csv, out, "blend", "--leader-rig", files["rigify"], "--follower-rig", files["odd"], jobs=1)
    print(f"\nbatch with a Rigify and a made-up rig: {time.perf_counter() - t0:.1f} s")
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    frames = read_report(out)["files"][0]["frames"]
    got = run_bpy_script(f"""
        import json, bpy
        bpy.ops.wm.open_mainfile(filepath={str(out / "salsa_5s.blend")!r})
        arms = {{}}
        for o in bpy.context.scene.objects:
            if o.type != 'ARMATURE' or o.name.startswith("DP "):
                continue
            fcs = action_fcurves(o.animation_data.action if o.animation_data else None)
            keyed = sorted({{fc.data_path.split('"')[1] for fc in fcs}})
            n = max([len(fc.keyframe_points) for fc in fcs] or [0])
            arms[o.name] = [len(o.data.bones), keyed, n]
        widgets = sorted(o.name for o in bpy.context.scene.objects if o.name.startswith("WGT-"))
        print("RESULT " + json.dumps([arms, widgets]))
        """)
    arms, widgets = got
    print({k: (v[0], len(v[1]), v[2]) for k, v in arms.items()})
    assert len(arms) == 2 and not widgets, got
    rig = next(v for v in arms.values() if v[0] > 500)
    odd = next(v for v in arms.values() if v[0] < 500)
    assert {"torso", "thigh_fk.L", "hand_fk.R", "thigh_parent.L"} <= set(rig[1]) and rig[2] == frames, rig
    assert not any(k.startswith("DEF-") for k in rig[1])
    assert odd[2] == frames
