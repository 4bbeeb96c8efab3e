"""Cross-checks of our kinematics against Blender's own evaluation (bpy module).

a. AMC forward kinematics (asf_amc.load_amc) vs an armature built in Blender
   from the ASF and posed from the raw AMC values (rotations composed with
   mathutils, the hierarchy evaluated by Blender), every frame of a whole take.
b. BVH: our writer -> Blender's BVH importer (compared with the Motion), then
   Blender's BVH exporter -> our parser (compared with Blender's evaluated
   bones, and back to the Motion), every frame.
"""
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from support.blender_util import (asf_axes, asf_local_matrix, build_asf_armature,  # noqa: E402
                                  empty_scene, pose_points)
from mathutils import Vector  # noqa: E402

from dancing_points_addon.formats.asf_amc import load_amc, parse_amc, parse_asf  # noqa: E402
from dancing_points_addon.formats.bvh import bvh_to_motion, fk, parse_bvh, write_bvh  # noqa: E402
from dancing_points_addon.skeleton import CMU_BVH_NAMES, JOINT_NAMES, PARENTS  # noqa: E402

TOL_M = 0.5e-3


@pytest.mark.parametrize("take", ["60_10", "61_10"])
def test_amc_fk_matches_blender_armature(salsa_dir, take):
    t0 = time.perf_counter()
    subject = take.split("_")[0]
    asf, amc = salsa_dir / f"{subject}.asf", salsa_dir / f"{take}.amc"
    motion = load_amc(amc)
    skel = parse_asf(asf)
    values, n = parse_amc(amc, skel)
    axes = asf_axes(asf)

    empty_scene()
    obj = build_asf_armature(skel, roll=0.7)
    names = skel.names
    rest = {nm: obj.data.bones[nm].matrix_local.to_3x3() for nm in names}
    pbs = [obj.pose.bones[nm] for nm in names]
    for pb in pbs:
        pb.rotation_mode = "QUATERNION"
    view_layer = bpy.context.view_layer

    heads = np.zeros((n, len(names), 3))
    tails = np.zeros((n, len(names), 3))
    for f in range(n):
        for j, bone in enumerate(skel.bones):
            v = values.get(bone.name)
            if v is None:
                continue
            b = rest[bone.name]
            # Pose basis in bone space: B^T · L · B, L the motion-space local rotation.
            local = asf_local_matrix(axes[bone.name], bone.dofs, v[f])
            pbs[j].rotation_quaternion = (b.transposed() @ local @ b).to_quaternion()
            if j == 0:
                t = Vector([v[f][k] * skel.scale for k, d in enumerate(bone.dofs) if d[0] == "t"])
                pbs[0].location = b.transposed() @ t
        view_layer.update()
        heads[f], tails[f] = pose_points(obj, names)

    spec = [names.index(nm) for nm in JOINT_NAMES]
    blender = tails[:, spec].copy()
    blender[:, 0] = heads[:, spec[0]]  # SPEC root joint = root translation (bone start)
    err = np.linalg.norm(blender - motion.positions, axis=-1)
    took = time.perf_counter() - t0
    print(f"\n{take}: AMC FK vs Blender armature, {n} frames x 31 joints: "
          f"max {err.max() * 1e3:.6f} mm, mean {err.mean() * 1e3:.6f} mm ({took:.1f} s)")
    assert n == motion.n_frames
    assert err.max() < TOL_M


def _spec_points_from_bvh_bones(names, heads, tails):
    """SPEC joint positions from Blender bones named in the CMU BVH naming."""
    idx = {nm: i for i, nm in enumerate(names)}
    out = np.zeros((heads.shape[0], len(JOINT_NAMES), 3))
    for k, jn in enumerate(JOINT_NAMES):
        kids = np.nonzero(PARENTS == k)[0]
        if k == 0:
            out[:, 0] = heads[:, idx[CMU_BVH_NAMES[jn]]]
        elif len(kids):
            out[:, k] = heads[:, idx[CMU_BVH_NAMES[JOINT_NAMES[kids[0]]]]]
        else:
            out[:, k] = tails[:, idx[CMU_BVH_NAMES[jn]]]
    return out


def test_bvh_blender_export_matches_parser(salsa_dir, tmp_path):
    t0 = time.perf_counter()
    motion = load_amc(salsa_dir / "60_10.amc")
    n = motion.n_frames
    ours = write_bvh(tmp_path / "ours.bvh", motion)

    empty_scene()
    # Y-up file -> Blender Z-up: (x, y, z) -> (x, -z, y), the SPEC's boundary map.
    res = bpy.ops.import_anim.bvh(filepath=str(ours), target="ARMATURE", global_scale=1.0,
                                  frame_start=1, use_fps_scale=False, update_scene_fps=True,
                                  rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
    assert res == {"FINISHED"}
    obj = bpy.context.object
    assert obj.type == "ARMATURE"
    assert np.allclose(np.array(obj.matrix_world), np.eye(4))  # armature space = world
    names = [b.name for b in obj.data.bones]
    scene = bpy.context.scene
    heads = np.zeros((n, len(names), 3))
    tails = np.zeros((n, len(names), 3))
    for f in range(n):
        scene.frame_set(1 + f)
        heads[f], tails[f] = pose_points(obj, names)

    # 1. Our writer, read by Blender's importer, gives back the Motion.
    spec = _spec_points_from_bvh_bones(names, heads, tails)
    spec_motion = np.stack([spec[..., 0], spec[..., 2], -spec[..., 1]], axis=-1)  # Z up -> Y up
    err_import = np.linalg.norm(spec_motion - motion.positions, axis=-1)

    # 2. Blender's exporter (armature space: no axis options exist; scale 1,
    #    an explicit rotation order unlike ours), read by our parser.
    out = tmp_path / "blender.bvh"
    res = bpy.ops.export_anim.bvh(filepath=str(out), global_scale=1.0, frame_start=1, frame_end=n,
                                  rotate_mode="XZY", root_transform_only=False)
    assert res == {"FINISHED"}
    data = parse_bvh(out)
    assert data.n_frames == n and data.fps == 60.0
    assert any(len(c) == 6 for c in data.channels[1:]), "exporter writes positions on loose child bones"
    pose = fk(data, scale=1.0)
    order = [names.index(nm) for nm in data.names]
    err_joints = np.linalg.norm(pose.positions - heads[:, order], axis=-1)
    ends = [names.index(data.names[j]) for j in data.end_parents]
    err_ends = np.linalg.norm(pose.end_positions - tails[:, ends], axis=-1)
    err_export = max(err_joints.max(), err_ends.max())

    # 3. And that file (Z up) back to the SPEC motion.
    back = bvh_to_motion(data)
    assert back.meta["bvh_up"] == "Z" and back.meta["bvh_scale"] == 1.0
    err_back = np.linalg.norm(back.positions - motion.positions, axis=-1)
    rot_back = np.abs(back.rotations - motion.rotations).max()

    took = time.perf_counter() - t0
    print(f"\nour BVH -> Blender import vs Motion: max {err_import.max() * 1e3:.6f} mm"
          f"\nBlender export -> parse_bvh vs Blender bones ({len(order)} joints, {len(ends)} end sites,"
          f" {n} frames): max {err_export * 1e3:.6f} mm"
          f"\nBlender export -> bvh_to_motion vs Motion: max {err_back.max() * 1e3:.6f} mm,"
          f" rotation entries {rot_back:.2e} ({took:.1f} s)")
    assert err_import.max() < TOL_M
    assert err_export < TOL_M
    assert err_back.max() < TOL_M
    assert rot_back < 1e-3
