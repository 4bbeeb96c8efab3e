"""Full-body rigs of other namings, animated with a SPEC §2 motion (needs ``bpy``).

:func:`build_rig` makes an armature whose bones are named as a Mixamo, Unreal
(UE5 mannequin), Rigify (``DEF-`` bones), VRoid or ASF rig, standing in a
T-pose (the SPEC's rest pose) or an A-pose (arms 45° down), with optional
random bone rolls, and keys it so that its bones follow the motion exactly;
:func:`export_rig` writes it with Blender's own BVH or FBX exporter (default
settings; an FBX gets a small skinned mesh so that it carries the rest pose).
:func:`rig_bones` and :func:`spec_rest` need no ``bpy``.

Where the naming has no forearm's-end bone (every one but ASF), the forearm
runs from the elbow to the wrist and turns with SPEC bone ``lwrist`` (the
forearm with its twist: ASF ``lwrist`` only twists about the forearm, so the
wrist lands where the motion has it); Rigify's forearm is split in two
(``DEF-forearm.L``, ``DEF-forearm.L.001``), both turning so. The hand bone
starts at the wrist and bends with SPEC ``lhand``.
"""
from __future__ import annotations

import numpy as np

from dancing_points_addon.rotations import axis_rotation, matrix_to_quat
from dancing_points_addon.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS, rest_joints

# Motion space (Y up) -> Blender (Z up).
C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

def _sided(fmt: dict, side_names: dict):
    out = {}
    for s, side in (("l", "L"), ("r", "R")):
        for k, v in fmt.items():
            out[s + k] = v.format(**side_names[side])
    return out


_MIX_SIDE = {"L": {"S": "Left"}, "R": {"S": "Right"}}
_UE_SIDE = {"L": {"s": "l"}, "R": {"s": "r"}}
_RIG_SIDE = {"L": {"S": "L"}, "R": {"S": "R"}}
_VRM_SIDE = {"L": {"S": "L"}, "R": {"S": "R"}}

NAMINGS = {
    "mixamo": {"root": "mixamorig:Hips", "lowerback": "mixamorig:Spine", "upperback": "mixamorig:Spine1",
               "thorax": "mixamorig:Spine2", "lowerneck": "mixamorig:Neck", "upperneck": "mixamorig:Neck1",
               "head": "mixamorig:Head",
               **_sided({"hipjoint": "mixamorig:{S}HipJoint", "femur": "mixamorig:{S}UpLeg",
                         "tibia": "mixamorig:{S}Leg", "foot": "mixamorig:{S}Foot", "toes": "mixamorig:{S}ToeBase",
                         "clavicle": "mixamorig:{S}Shoulder", "humerus": "mixamorig:{S}Arm",
                         "radius": "mixamorig:{S}ForeArm", "hand": "mixamorig:{S}Hand",
                         "fingers": "mixamorig:{S}HandIndex1", "thumb": "mixamorig:{S}HandThumb1"}, _MIX_SIDE)},
    "unreal": {"root": "pelvis", "lowerback": "spine_01", "upperback": "spine_02", "thorax": "spine_03",
               "lowerneck": "neck_01", "upperneck": "neck_02", "head": "head",
               **_sided({"hipjoint": "hipjoint_{s}", "femur": "thigh_{s}", "tibia": "calf_{s}", "foot": "foot_{s}",
                         "toes": "ball_{s}", "clavicle": "clavicle_{s}", "humerus": "upperarm_{s}",
                         "radius": "lowerarm_{s}", "hand": "hand_{s}", "fingers": "index_01_{s}",
                         "thumb": "thumb_01_{s}"}, _UE_SIDE)},
    "rigify": {"root": "DEF-spine", "lowerback": "DEF-spine.001", "upperback": "DEF-spine.002",
               "thorax": "DEF-spine.003", "lowerneck": "DEF-spine.004", "upperneck": "DEF-spine.005",
               "head": "DEF-spine.006",
               **_sided({"hipjoint": "DEF-pelvis.{S}", "femur": "DEF-thigh.{S}", "tibia": "DEF-shin.{S}",
                         "foot": "DEF-foot.{S}", "toes": "DEF-toe.{S}", "clavicle": "DEF-shoulder.{S}",
                         "humerus": "DEF-upper_arm.{S}", "radius": "DEF-forearm.{S}", "hand": "DEF-hand.{S}",
                         "fingers": "DEF-f_index.01.{S}", "thumb": "DEF-thumb.01.{S}"}, _RIG_SIDE)},
    "vrm": {"root": "J_Bip_C_Hips", "lowerback": "J_Bip_C_Spine", "upperback": "J_Bip_C_Chest",
            "thorax": "J_Bip_C_UpperChest", "lowerneck": "J_Bip_C_Neck", "upperneck": "J_Adj_C_Neck2",
            "head": "J_Bip_C_Head",
            **_sided({"hipjoint": "J_Adj_{S}_Hip", "femur": "J_Bip_{S}_UpperLeg", "tibia": "J_Bip_{S}_LowerLeg",
                      "foot": "J_Bip_{S}_Foot", "toes": "J_Bip_{S}_ToeBase", "clavicle": "J_Bip_{S}_Shoulder",
                      "humerus": "J_Bip_{S}_UpperArm", "radius": "J_Bip_{S}_LowerArm", "hand": "J_Bip_{S}_Hand",
                      "fingers": "J_Bip_{S}_Index1", "thumb": "J_Bip_{S}_Thumb1"}, _VRM_SIDE)},
    "asf": {n: n for n in JOINT_NAMES},
}
# The bone whose orientation a reader should give per device (head, lhand, rhand).
READ_BONES = {"mixamo": ("mixamorig:Head", "mixamorig:LeftForeArm", "mixamorig:RightForeArm"),
              "unreal": ("head", "lowerarm_l", "lowerarm_r"),
              "rigify": ("DEF-spine.006", "DEF-forearm.L.001", "DEF-forearm.R.001"),
              "vrm": ("J_Bip_C_Head", "J_Bip_L_LowerArm", "J_Bip_R_LowerArm"),
              "asf": ("head", "lwrist", "rwrist")}
A_POSE_DEG = 45.0


def _subtree(n):
    out = [n]
    for c in range(len(JOINT_NAMES)):
        if PARENTS[c] >= 0 and PARENTS[c] in out and c not in out:
            out.append(c)
    return out


def rig_bones(naming):
    """``[(name, parent name | None, head, tail, rotation bone)]``: points as
    ``(a, b, w)`` = ``(1 - w)·J[a] + w·J[b]`` of SPEC joint positions ``J``
    (``b = -1``: the root's tail, 10 cm above ``a``); rotation bone: the SPEC
    bone whose global rotation the bone turns with."""
    names = NAMINGS[naming]
    ji = JOINT_INDEX
    out = []
    rig_of = {}
    for n, spec in enumerate(JOINT_NAMES):
        if spec == "root":
            out.append((names[spec], None, (0, 0, 0.0), (0, -1, 1.0), 0))
            rig_of[n] = names[spec]
            continue
        par = int(PARENTS[n])
        if naming != "asf" and spec[1:] == "wrist":
            rig_of[n] = rig_of[par]  # merged into the forearm
            continue
        if naming != "asf" and spec[1:] == "radius":
            wrist = ji[spec[0] + "wrist"]
            if naming == "rigify":
                out.append((names[spec], rig_of[par], (par, par, 0.0), (par, wrist, 0.5), wrist))
                second = names[spec] + ".001"
                out.append((second, names[spec], (par, wrist, 0.5), (wrist, wrist, 0.0), wrist))
                rig_of[n] = second
            else:
                out.append((names[spec], rig_of[par], (par, par, 0.0), (wrist, wrist, 0.0), wrist))
                rig_of[n] = names[spec]
            continue
        out.append((names[spec], rig_of[par], (par, par, 0.0), (n, n, 0.0), n))
        rig_of[n] = names[spec]
    return out


def _points(J, pt):
    a, b, w = pt
    if b < 0:
        return J[..., a, :] + np.array([0.0, 0.1, 0.0])
    return (1.0 - w) * J[..., a, :] + w * J[..., b, :]


def spec_rest(bone_vectors, pose="T"):
    """SPEC rest joint positions ``(31, 3)`` (motion space), the arms turned 45°
    down about the forward axis for ``pose='A'``, and each bone's turn ``(31, 3, 3)``."""
    J = rest_joints(np.asarray(bone_vectors, dtype=np.float64)).copy()
    A = np.broadcast_to(np.eye(3), (len(JOINT_NAMES), 3, 3)).copy()
    if pose == "A":
        for side, sign in (("l", -1.0), ("r", 1.0)):
            turn = axis_rotation("Z", sign * np.deg2rad(A_POSE_DEG))
            pivot = J[JOINT_INDEX[side + "clavicle"]].copy()
            for n in _subtree(JOINT_INDEX[side + "humerus"]):
                J[n] = pivot + turn @ (J[n] - pivot)
                A[n] = turn
    return J, A


def build_rig(motion, naming, pose="T", roll_seed=None, name="Rig", frame_start=1):
    """An armature named ``name`` with ``naming``'s bones, resting in ``pose``
    (``'T'`` or ``'A'``), bone rolls random when ``roll_seed`` is given, keyed
    on frames ``frame_start ...`` with ``motion`` (a SPEC §2 :class:`Motion`);
    the scene's frame rate and range are set to the motion's."""
    import bpy

    from . import blender_scene_util as bsu

    bones = rig_bones(naming)
    J0, A = spec_rest(motion.bone_vectors, pose)
    rng = np.random.default_rng(roll_seed) if roll_seed is not None else None
    rolls = [float(rng.uniform(-np.pi, np.pi)) if rng is not None else 0.0 for _ in bones]
    obj = bsu.build_armature(name, [(bname, parent, C @ _points(J0, head), C @ _points(J0, tail), roll)
                                    for (bname, parent, head, tail, _rot), roll in zip(bones, rolls)],
                             body=False, connect=lambda bone: False)
    arm_data = obj.data
    # Posed armature-space matrices of every bone, then their pose channels.
    T = motion.n_frames
    Jt = np.asarray(motion.positions, dtype=np.float64)
    R = np.asarray(motion.rotations, dtype=np.float64)
    rest = {b[0]: np.array(arm_data.bones[b[0]].matrix_local) for b in bones}
    posed = {}
    for bname, _parent, head, _tail, rot in bones:
        P = np.zeros((T, 4, 4))
        # posed bone vector = R_spec · spec rest vector = R_spec · Aᵀ · rig rest vector
        P[:, :3, :3] = C @ (R[:, rot] @ A[rot].T) @ C.T @ rest[bname][:3, :3]
        P[:, :3, 3] = _points(Jt, head) @ C.T
        P[:, 3, 3] = 1.0
        posed[bname] = P
    compat = bsu.compat()
    action, slot = compat.new_action_for(obj, name + "Action")
    frames = frame_start + np.arange(T)
    for bname, parent, _head, _tail, _rot in bones:
        if parent is None:
            basis = np.linalg.inv(rest[bname])[None] @ posed[bname]
        else:
            basis = (np.linalg.inv(rest[bname]) @ rest[parent])[None] @ np.linalg.inv(posed[parent]) @ posed[bname]
        pb = obj.pose.bones[bname]
        pb.rotation_mode = 'QUATERNION'
        q = matrix_to_quat(basis[:, :3, :3])
        dots = np.sum(q[1:] * q[:-1], axis=-1)
        q[1:] *= np.where(np.cumsum(dots < 0) % 2 == 1, -1.0, 1.0)[:, None]
        path = f'pose.bones["{bname}"]'
        for i in range(3):
            compat.write_keys(compat.ensure_fcurves(action, slot, path + ".location", i, bname), frames,
                              basis[:, i, 3])
        for i in range(4):
            compat.write_keys(compat.ensure_fcurves(action, slot, path + ".rotation_quaternion", i, bname),
                              frames, q[:, i])
    scene = bpy.context.scene
    scene.render.fps = int(round(motion.fps))
    scene.render.fps_base = 1.0
    scene.frame_start, scene.frame_end = frame_start, frame_start + T - 1
    scene.frame_set(frame_start)
    return obj


def export_rig(obj, path, skinned=True):
    """Write the rig with Blender's own exporter (by the extension of ``path``),
    default settings; an FBX gets a small mesh deformed by the root bone so
    that the file carries the rest pose (``skinned=False``: none, and Blender
    writes the pose of the current frame as the rest pose)."""
    import bpy

    path = str(path)
    scene = bpy.context.scene
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    if path.endswith(".bvh"):
        res = bpy.ops.export_anim.bvh(filepath=path, frame_start=scene.frame_start, frame_end=scene.frame_end)
    else:
        if skinned and not any(c.type == 'MESH' for c in obj.children):
            mesh = bpy.data.meshes.new(obj.name + "Body")
            mesh.from_pydata([(0.05, 0, 1.0), (-0.05, 0, 1.0), (0, 0.05, 1.0), (0, 0, 1.05)], [],
                             [(0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 2, 3)])
            body = bpy.data.objects.new(obj.name + "Body", mesh)
            scene.collection.objects.link(body)
            body.vertex_groups.new(name=obj.data.bones[0].name).add([0, 1, 2, 3], 1.0, 'REPLACE')
            body.modifiers.new("Armature", 'ARMATURE').object = obj
            body.parent = obj
        res = bpy.ops.export_scene.fbx(filepath=path)
    assert res == {'FINISHED'}, res
    return path
