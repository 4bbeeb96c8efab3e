"""The Blender add-on end to end, enabled in ``bpy`` as an extension (ext_util).

Import a real take (CMU salsa 60_10, the first 10 s) -> three keyframed empties;
synthesise and bake the duet with small models -> two armatures whose bones
follow the core's output to < 1 mm on every frame and whose skinned bodies
deform exactly like a numpy LBS; a headless Workbench render shows both bodies;
BVH and FBX files of the same motion (through Blender's importers) give the
same take as the CSV; bad input and failures leave the scene untouched.

Models: the shipped ``models/`` (``$DP_MODEL_DIR`` overrides).
"""
from __future__ import annotations

import os
import subprocess
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from support import blender_scene_util as bsu  # noqa: E402
from conftest import MODELS, SALSA  # noqa: E402
from support.ext_util import enable_extension, import_from_extension  # noqa: E402
from support.helpers import quat_angle_deg  # noqa: E402

from types import SimpleNamespace  # noqa: E402

from dancing_points_addon import blender_math as bm  # noqa: E402
from dancing_points_addon import skinning  # noqa: E402
from dancing_points_addon.formats.asf_amc import load_amc  # noqa: E402
from dancing_points_addon.resample import resample_take  # noqa: E402
from dancing_points_addon.skeleton import JOINT_NAMES, Motion  # noqa: E402
from dancing_points_addon.formats.take import take_from_motion, write_take  # noqa: E402
from dancing_points_addon.formats.take_read import read_take  # noqa: E402

SECONDS = 10.0
MM = 1e-3




def _cut(motion: Motion, seconds: float) -> Motion:
    n = int(round(seconds * motion.fps))
    return Motion(motion.positions[:n], motion.rotations[:n], motion.fps, motion.bone_vectors,
                  motion.source, dict(motion.meta))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The first 10 s of salsa take 60_10 as a take CSV and as a CMU-named BVH."""
    if not SALSA.exists():
        pytest.skip(f"shared data not found at {SALSA}")
    d = tmp_path_factory.mktemp("dp_addon")
    motion = _cut(load_amc(SALSA / "60_10.amc"), SECONDS)
    take = take_from_motion(motion)
    csv = d / "salsa60_10.csv"
    write_take(csv, take)
    from dancing_points_addon.formats.bvh import write_bvh
    bvh = d / "salsa60_10.bvh"
    write_bvh(bvh, motion)
    return {"dir": d, "csv": csv, "bvh": bvh, "motion": motion, "take": take}


def _import(path, **kw):
    before = {c.name for c in bpy.data.collections}
    assert bpy.ops.dancing_points.import_take(filepath=str(path), **kw) == {'FINISHED'}
    (name,) = [c.name for c in bpy.data.collections if c.name not in before]
    return bpy.data.collections[name]


# --------------------------------------------------------------------------- registration

def test_registered_entry_points():
    enable_extension()
    for op in ("import_take", "synthesize", "render_preview"):
        assert hasattr(bpy.ops.dancing_points, op)
    fh = bpy.types.FileHandler.bl_rna_get_subclass_py("DANCING_POINTS_FH_import_take")
    assert fh is not None
    assert set(fh.bl_file_extensions.split(";")) == {".csv", ".bvh", ".fbx", ".amc"}
    assert fh.bl_import_operator == "dancing_points.import_take"
    take_io = import_from_extension("operators.take_io")
    assert take_io.menu_func_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    syn = bpy.ops.dancing_points.synthesize.get_rna_type()
    assert syn.properties["foot_lock"].default is True
    assert syn.properties["model_dir"].is_hidden and syn.properties["model_dir"].is_skip_save
    for cls_name in ("DANCING_POINTS_OT_synthesize", "DANCING_POINTS_OT_import_take"):
        cls = bpy.types.Operator.bl_rna_get_subclass_py(cls_name)
        assert {'REGISTER', 'UNDO'} <= set(cls.bl_options)


def test_panels_draw():
    """The sidebar sub-panels draw without errors (a recording stand-in layout)."""
    bsu.fresh_scene()

    Rec = bsu.RecordingLayout

    for pid in ("VIEW3D_PT_dancing_points_take", "VIEW3D_PT_dancing_points_synthesis",
                "VIEW3D_PT_dancing_points_preview"):
        cls = bpy.types.Panel.bl_rna_get_subclass_py(pid)
        assert cls is not None and cls.bl_parent_id == "VIEW3D_PT_dancing_points"
        fake = type("Fake", (), {"layout": Rec()})
        cls.draw(fake, bpy.context)
        assert fake.layout.calls


# --------------------------------------------------------------------------- import

def test_import_csv_makes_keyed_empties(files):
    scene = bsu.fresh_scene()
    scene.render.fps = 24
    coll = _import(files["csv"], frame_start=5)
    take30 = resample_take(read_take(files["csv"]))
    T = take30.n_frames
    assert T == 300
    assert coll.name == "DP Take salsa60_10"
    s = coll.dancing_points
    assert (s.kind, s.n_frames, s.frame_start, s.fps, s.source_type) == ('TAKE', T, 5, 30.0, "csv")
    assert os.path.samefile(s.source, files["csv"])
    assert (scene.render.fps, scene.render.fps_base) == (30, 1.0)
    assert (scene.frame_start, scene.frame_end) == (5, 5 + T - 1)
    assert scene.dancing_points.take == coll
    keys = bsu.take_device_keys(coll)
    assert sorted(keys) == ["head", "lhand", "rhand"]
    names = {o["dp_device"]: o.name for o in coll.objects}
    assert names == {"head": "Head", "lhand": "LeftHand", "rhand": "RightHand"}
    for d, dev in enumerate(("head", "lhand", "rhand")):
        frames, loc, quat, tracked = keys[dev]
        np.testing.assert_array_equal(frames, 5 + np.arange(T))
        # SPEC §1: (x, y, z) -> (x, -z, y)
        p = take30.positions[:, d]
        np.testing.assert_allclose(loc, np.stack([p[:, 0], -p[:, 2], p[:, 1]], 1), atol=1e-5)
        q_b = bm.quat_to_blender(take30.quats[:, d])
        assert np.all(np.abs(np.sum(quat * q_b, -1)) > 1 - 1e-6)
        assert np.all(tracked == 1.0)
    # Read back for synthesis: the same take in motion space.
    take_collection = import_from_extension("operators.take_collection")
    back = take_collection.take_from_collection(bpy.context, coll)
    np.testing.assert_allclose(back.positions, take30.positions, atol=1e-5)
    np.testing.assert_allclose(back.time - back.time[0], take30.time - take30.time[0], atol=1e-9)
    dots = np.abs(np.sum(back.quats * take30.quats, -1))
    assert dots.min() > 1 - 1e-6


def test_import_lost_tracking_round_trip(files, tmp_path):
    """Lost rows (SPEC §3) come back as lost through the empties' dp_tracked flag."""
    bsu.fresh_scene()
    take = files["take"]
    pos, q = take.positions.copy(), take.quats.copy()
    pos[100:140, 1] = np.nan
    q[100:140, 1] = np.nan
    from dancing_points_addon.formats.take import Take
    path = tmp_path / "lost.csv"
    write_take(path, Take(take.time, pos, q, {"height_m": 1.62}, ""))
    coll = _import(path)
    assert abs(coll.dancing_points.height - 1.62) < 1e-6
    take_collection = import_from_extension("operators.take_collection")
    back = take_collection.take_from_collection(bpy.context, coll)
    ref = resample_take(read_take(path))
    np.testing.assert_array_equal(back.valid, ref.valid)
    assert not ref.valid[:, 1].all()
    assert back.height == pytest.approx(1.62)


def test_import_amc_matches_core(files):
    bsu.fresh_scene()
    coll = _import(SALSA / "60_10.amc")
    ref = resample_take(take_from_motion(load_amc(SALSA / "60_10.amc")))
    take_collection = import_from_extension("operators.take_collection")
    back = take_collection.take_from_collection(bpy.context, coll)
    assert back.n_frames == ref.n_frames
    np.testing.assert_allclose(back.positions, ref.positions, atol=1e-5)


def _export_fbx(files, path, rest_frame):
    """BVH -> Blender -> FBX. ``rest_frame``: export while the rig stands in its
    rest pose (a key at frame 0), so the FBX's rest pose is the BVH's; else the
    exporter's rest pose is the pose at frame 100 of the dance."""
    bsu.fresh_scene()
    bpy.ops.import_anim.bvh(filepath=str(files["bvh"]), update_scene_fps=True, update_scene_duration=True)
    scene = bpy.context.scene
    assert scene.render.fps == 60
    arm = next(o for o in scene.objects if o.type == 'ARMATURE')
    f0, f1 = (int(round(x)) for x in arm.animation_data.action.frame_range)
    assert f1 - f0 + 1 == len(files["motion"].positions)
    if rest_frame:
        for fc in bsu.all_fcurves(arm):
            rest_value = 1.0 if fc.data_path.endswith("rotation_quaternion") and fc.array_index == 0 else 0.0
            fc.keyframe_points.insert(f0 - 1, rest_value)
        scene.frame_set(f0 - 1)
    else:
        scene.frame_set(f0 + 99)
    # Export exactly the BVH's frames (the BVH importer's range ends one frame later).
    scene.frame_start, scene.frame_end = f0, f1
    bpy.ops.export_scene.fbx(filepath=str(path), object_types={'ARMATURE'}, bake_anim=True,
                             bake_anim_use_all_actions=False, bake_anim_use_nla_strips=False,
                             bake_anim_simplify_factor=0.0, add_leaf_bones=False)
    assert path.exists()


def _compare_takes(ref, keys, label):
    errs = {}
    for dev in ("head", "lhand", "rhand"):
        f, loc, quat, tr = keys[dev]
        rf, rloc, rquat, _ = ref[dev]
        assert len(f) == len(rf), (label, dev)
        err = np.linalg.norm(loc - rloc, axis=-1).max()
        ang = quat_angle_deg(quat, rquat)
        print(f"\n{label} {dev}: max position error {err / MM:.4f} mm, rotation error "
              f"max {ang.max():.4f} deg, median {np.median(ang):.4f} deg")
        errs[dev] = (err, ang)
    return errs


def test_bvh_and_fbx_give_the_csv_take(files):
    """A BVH of the motion and an FBX exported by Blender from it, both imported
    through Blender's importers, give the CSV's take (< 1 mm, < 0.05°)."""
    fbx = files["dir"] / "salsa60_10.fbx"
    _export_fbx(files, fbx, rest_frame=True)
    bsu.fresh_scene()
    ref_coll = _import(files["csv"])
    ref = bsu.take_device_keys(ref_coll)
    before = bsu.id_snapshot()
    results = {}
    for ext in ("bvh", "fbx"):
        coll = _import(files[ext] if ext == "bvh" else fbx)
        assert coll.dancing_points.source_type == ext
        assert abs(coll.dancing_points.source_fps - 60.0) < 1e-3
        results[ext] = bsu.take_device_keys(coll)
    after = bsu.id_snapshot()
    # The importers' rigs and actions are gone again: only the two take collections,
    # their 6 empties and 6 actions were added.
    assert len(after["objects"]) - len(before["objects"]) == 6
    assert len(after["armatures"]) == len(before["armatures"]) == 0
    assert len(after["actions"]) - len(before["actions"]) == 6
    for ext, keys in results.items():
        for dev, (err, ang) in _compare_takes(ref, keys, ext).items():
            assert err < 1 * MM, (ext, dev, err)
            assert ang.max() < 0.05, (ext, dev, ang.max())


def test_fbx_with_a_posed_rest_pose(files):
    """An FBX whose rest pose is a frame of the dance: positions stay exact; the
    device rotations cannot be related to the SPEC rest pose and are not
    guessed: the take says ``orientations=none`` (the device follow is off)."""
    fbx = files["dir"] / "salsa60_10_posed_rest.fbx"
    _export_fbx(files, fbx, rest_frame=False)
    bsu.fresh_scene()
    ref = bsu.take_device_keys(_import(files["csv"]))
    coll = _import(fbx)
    keys = bsu.take_device_keys(coll)
    for dev, (f, loc, quat, tr) in keys.items():
        assert np.linalg.norm(loc - ref[dev][1], axis=-1).max() < 1 * MM, dev
    assert coll.dancing_points.orientations == "none"
    take = import_from_extension("operators.take_collection").take_from_collection(bpy.context, coll)
    assert take.meta.get("orientations") == "none"


# --------------------------------------------------------------------------- errors

def _assert_unchanged(state):
    assert bsu.scene_state() == state


@pytest.mark.parametrize("content, match", [
    ("time,head_px\n0,1\n", "missing header column"),
    ("", "no header"),
    ("not a take at all", "unknown header column"),
])
def test_bad_take_reports_and_creates_nothing(tmp_path, content, match):
    bsu.fresh_scene()
    path = tmp_path / "bad.csv"
    path.write_text(content)
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match=match):
        bpy.ops.dancing_points.import_take(filepath=str(path))
    _assert_unchanged(state)


@pytest.mark.parametrize("name, content, match", [
    ("missing.csv", None, "no such file"),
    ("motion.txt", "x", "unsupported file type"),
    ("broken.bvh", "HIERARCHY\nROOT Hips\n{\n", "bvh"),
    ("ascii.fbx", "; FBX 7.4.0 project file\n", "not a binary FBX"),
])
def test_bad_files_report_one_line(tmp_path, name, content, match):
    bsu.fresh_scene()
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match=match) as info:
        bpy.ops.dancing_points.import_take(filepath=str(path))
    assert "Traceback" not in str(info.value)
    _assert_unchanged(state)


def test_synthesize_without_take_or_models_creates_nothing(files, tmp_path):
    bsu.fresh_scene()
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match="no active take"):
        bpy.ops.dancing_points.synthesize()
    _assert_unchanged(state)
    _import(files["csv"])
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match="no synthesis models"):
        bpy.ops.dancing_points.synthesize(model_dir=str(tmp_path))
    _assert_unchanged(state)


def test_failures_and_cancel_leave_scene_unchanged(files, monkeypatch):
    bsu.fresh_scene()
    coll = _import(files["csv"])
    state = bsu.scene_state()
    bake = import_from_extension("operators.bake")
    runtime = import_from_extension("dancing_points_addon.runtime")

    def boom(*a, **k):
        raise RuntimeError("simulated bake failure")

    monkeypatch.setattr(bake, "key_armature", boom)
    with pytest.raises(RuntimeError, match="simulated bake failure"):
        bpy.ops.dancing_points.synthesize(model_dir=MODELS)
    _assert_unchanged(state)
    monkeypatch.undo()

    def cancelled(self, take, progress=None):
        progress(1, 10)
        raise KeyboardInterrupt("cancelled")

    monkeypatch.setattr(runtime.Synthesizer, "synthesize", cancelled)
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS) == {'CANCELLED'}
    _assert_unchanged(state)
    monkeypatch.undo()

    # A take whose Head empty was deleted: one line, nothing made.
    bpy.data.objects.remove(bpy.data.objects["Head"])
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match="has no Head empty"):
        bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=coll.name)
    _assert_unchanged(state)


# --------------------------------------------------------------------------- synthesis and bake

@pytest.fixture(scope="module")
def baked(files):
    """Import the CSV take, synthesise with the operator (defaults: foot locking on)."""
    scene = bsu.fresh_scene()
    coll = _import(files["csv"])
    take_collection = import_from_extension("operators.take_collection")
    take = take_collection.take_from_collection(bpy.context, coll)
    t0 = time.perf_counter()
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS) == {'FINISHED'}
    t_op = time.perf_counter() - t0
    duets = [c for c in bpy.data.collections if c.dancing_points.kind == 'DUET']
    assert len(duets) == 1
    # The core on the same take (as the operator read it back from the empties).
    runtime = import_from_extension("dancing_points_addon.runtime")
    synth = runtime.Synthesizer(runtime.SynthesisOptions(models=MODELS, foot_lock=True))
    t0 = time.perf_counter()
    duet = synth.synthesize(take)
    t_core = time.perf_counter() - t0
    print(f"\nsynthesize operator {t_op:.2f} s (core loop alone {t_core:.2f} s) for {duet.n_frames} frames")
    return {"scene": scene, "take": coll, "duet_coll": duets[0], "duet": duet, "frame_start": 1}


def _rig(duet_coll, role):
    arms = [o for o in duet_coll.objects if o.type == 'ARMATURE' and o.get("dp_role") == role]
    bodies = [o for o in duet_coll.objects if o.type == 'MESH' and o.get("dp_role") == role]
    assert len(arms) == 1 and len(bodies) == 1
    return arms[0], bodies[0]


def test_bake_structure_and_keys(baked):
    duet = baked["duet"]
    T = duet.n_frames
    coll = baked["duet_coll"]
    assert coll.name == "DP Duet salsa60_10"
    frames = baked["frame_start"] + np.arange(T)
    for role, label in (("leader", "Leader"), ("follower", "Follower")):
        arm, body = _rig(coll, role)
        assert label in arm.name
        assert [b.name for b in arm.data.bones] == list(JOINT_NAMES)
        action = arm.animation_data.action
        assert action.name == f"DP {label} salsa60_10 v1"
        fcs = bsu.all_fcurves(arm)
        paths = {(fc.data_path, fc.array_index) for fc in fcs}
        assert len(fcs) == 31 * 4 + 3
        for n in JOINT_NAMES:
            for i in range(4):
                assert (f'pose.bones["{n}"].rotation_quaternion', i) in paths
        assert ('pose.bones["root"].location', 0) in paths
        for fc in fcs:  # a keyframe on every frame
            f, _, _ = bsu.compat().read_keys(fc)
            np.testing.assert_array_equal(f, frames)
        # Skinned body: one vertex group per bone, an Armature modifier on the rig.
        assert body.parent == arm
        assert {g.name for g in body.vertex_groups} == set(JOINT_NAMES)
        mods = [m for m in body.modifiers if m.type == 'ARMATURE']
        assert len(mods) == 1 and mods[0].object == arm
        assert body.data.materials[0] is not None
    lead_col = np.array(_rig(coll, "leader")[1].data.materials[0].diffuse_color[:3])
    foll_col = np.array(_rig(coll, "follower")[1].data.materials[0].diffuse_color[:3])
    assert lead_col[2] > lead_col[0] and foll_col[0] > foll_col[2]
    scene = baked["scene"]
    assert scene.camera is not None
    assert any(o.type == 'LIGHT' for o in scene.objects)


def test_bone_tails_match_core_output(baked):
    """Every bone's evaluated head and tail = the core's joint positions (Z up), all frames."""
    duet = baked["duet"]
    frames = baked["frame_start"] + np.arange(duet.n_frames)
    for role in ("leader", "follower"):
        arm, _ = _rig(baked["duet_coll"], role)
        pos, rot = getattr(duet, role + "_positions"), getattr(duet, role + "_rotations")
        bv, cpos, crot = bm.consistent_pose(pos, rot)
        heads, tails = bsu.posed_heads_tails(arm, frames, JOINT_NAMES)
        want = bm.to_blender(cpos)
        err_tail = np.linalg.norm(tails[:, 1:] - want[:, 1:], axis=-1)
        err_root = np.linalg.norm(heads[:, 0] - want[:, 0], axis=-1)
        raw = np.linalg.norm(tails[:, 1:] - bm.to_blender(pos)[:, 1:], axis=-1)
        print(f"\n{role}: bone tail error max {err_tail.max() / MM:.4f} mm, mean {err_tail.mean() / MM:.4f} mm; "
              f"root {err_root.max() / MM:.4f} mm; vs the raw (not yet rigid) network output: "
              f"max {raw.max() / MM:.2f} mm, mean {raw.mean() / MM:.2f} mm")
        assert err_tail.max() < 1 * MM
        assert err_root.max() < 1 * MM


def test_skinned_bodies_match_numpy_lbs(baked):
    duet = baked["duet"]
    T = duet.n_frames
    for role in ("leader", "follower"):
        arm, body = _rig(baked["duet_coll"], role)
        rest, w = bsu.mesh_rest_and_weights(body, list(JOINT_NAMES))
        assert np.all(np.abs(w.sum(1) - 1.0) < 1e-5)
        bv, cpos, crot = bm.consistent_pose(getattr(duet, role + "_positions"), getattr(duet, role + "_rotations"))
        idx = np.broadcast_to(np.arange(31), w.shape)
        worst = 0.0
        for k in (0, T // 3, T // 2, T - 1):
            got = bsu.evaluated_vertices(body, baked["frame_start"] + k)
            M = bm.skin_transforms(cpos[k:k + 1], crot[k:k + 1], bv)[0]
            want = skinning.lbs_frame(SimpleNamespace(vertices=rest, indices=idx, weights=w), M)
            worst = max(worst, float(np.linalg.norm(got - want, axis=-1).max()))
        print(f"\n{role}: deformed mesh vs numpy LBS: max {worst / MM:.4f} mm over 4 frames, {len(rest)} vertices")
        assert worst < 1 * MM


def test_render_preview_shows_both_bodies(baked, tmp_path):
    scene = baked["scene"]
    engine = scene.render.engine
    mid = baked["frame_start"] + baked["duet"].n_frames // 2
    out = tmp_path / "prev_"
    t0 = time.perf_counter()
    assert bpy.ops.dancing_points.render_preview(filepath=str(out), file_format='PNG', frame_start=mid,
                                                 frame_end=mid, resolution_percentage=25) == {'FINISHED'}
    t_render = time.perf_counter() - t0
    assert scene.render.engine == engine  # settings restored
    png = tmp_path / f"prev_{mid:04d}.png"
    assert png.exists()
    px = bsu.load_png(png)
    rgb, alpha = px[..., :3], px[..., 3]
    fg = alpha > 0.5
    blue = fg & (rgb[..., 2] > rgb[..., 0] + 0.1)
    red = fg & (rgb[..., 0] > rgb[..., 2] + 0.1)
    print(f"\nrender {px.shape[1]}x{px.shape[0]} in {t_render:.2f} s: {fg.sum()} body pixels, "
          f"{blue.sum()} leader-blue, {red.sum()} follower-red")
    assert blue.sum() > 50 and red.sum() > 50


def _small_disk(path):
    """A 64 KiB tmpfs at ``path`` (a full disk for a render), or None where mounting
    is not allowed."""
    path.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(path)], capture_output=True)
    return path if res.returncode == 0 else None


def test_render_preview_reports_a_full_disk(baked, tmp_path):
    """A render that cannot write its frames (a full disk; where mounting is not
    allowed, frame paths that are folders) fails with one line and leaves no
    zero-byte images; a blank render is not a success either."""
    scene = baked["scene"]
    mid = baked["frame_start"] + baked["duet"].n_frames // 2
    disk = _small_disk(tmp_path / "disk")
    try:
        if disk is None:  # no tmpfs here: make the frames unwritable instead
            disk = tmp_path / "disk"
            for f in range(mid, mid + 3):
                (disk / f"prev_{f:04d}.png").mkdir()
        with pytest.raises(RuntimeError, match="not written"):
            bpy.ops.dancing_points.render_preview(filepath=str(disk / "prev_"), file_format='PNG', frame_start=mid,
                                                  frame_end=mid + 2, resolution_percentage=100)
        assert not [f for f in disk.iterdir() if f.is_file() and f.stat().st_size == 0]
    finally:
        subprocess.run(["umount", str(tmp_path / "disk")], capture_output=True)
    # nothing in front of the camera: a blank frame is reported, not written off as done
    cam = scene.camera
    saved = cam.location.copy()
    cam.location = (1e4, 1e4, 1e4)
    try:
        with pytest.raises(RuntimeError, match="blank"):
            bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / "blank_"), file_format='PNG',
                                                  frame_start=mid, frame_end=mid, resolution_percentage=10)
    finally:
        cam.location = saved


def test_rebake_makes_a_new_version(baked):
    coll1 = baked["duet_coll"]
    lead1, _ = _rig(coll1, "leader")
    act1 = lead1.animation_data.action
    q1 = bsu.fcurve_keys(lead1, 'pose.bones["lfemur"].rotation_quaternion', 0)[1].copy()
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=baked["take"].name) == {'FINISHED'}
    duets = sorted((c for c in bpy.data.collections if c.dancing_points.kind == 'DUET'),
                   key=lambda c: c.dancing_points.version)
    assert [c.dancing_points.version for c in duets] == [1, 2]
    lead2, _ = _rig(duets[1], "leader")
    assert lead2 != lead1
    assert lead2.animation_data.action.name.endswith("v2")
    assert lead1.animation_data.action == act1  # untouched
    np.testing.assert_array_equal(bsu.fcurve_keys(lead1, 'pose.bones["lfemur"].rotation_quaternion', 0)[1], q1)
    assert duets[0].hide_render and not duets[1].hide_render
    # the stage refitted, not doubled: one floor mesh, one camera follow action
    assert [m.get("dp_stage") for m in bpy.data.meshes].count("floor") == 1
    assert [a.get("dp_stage") for a in bpy.data.actions].count("action") == 1


def test_a_failed_rebake_leaves_the_scene_as_it_was(baked, monkeypatch):
    """A bake that fails late (in the stage's refit) takes back everything:
    the earlier duets shown as they were, the floor's mesh and the camera's
    follow action kept, the frame range, camera and rig unchanged, no new
    data-block left."""
    scene = baked["scene"]
    stage = import_from_extension("operators.stage")
    bake = import_from_extension("operators.bake")
    kinds = ("collections", "objects", "meshes", "actions", "armatures", "materials", "cameras")
    before = {k: sorted(getattr(bpy.data, k).keys()) for k in kinds}
    shown = {c.name: (c.hide_viewport, c.hide_render) for c in bpy.data.collections
             if c.dancing_points.kind == 'DUET'}
    assert any(not v[0] for v in shown.values())
    floor = stage.stage_object(stage.find_stage(scene), "floor")
    rig = stage.stage_object(stage.find_stage(scene), "camera_rig")
    mesh, follow, action = floor.data, rig[stage.FOLLOW_PROP], rig.animation_data.action
    view = (scene.frame_start, scene.frame_end, scene.camera, tuple(rig.location), tuple(rig[stage.WIDE_PROP]))

    def fail(*args, **kwargs):
        raise RuntimeError("injected failure")

    monkeypatch.setattr(stage, "find_obstacles", fail)
    short = runtime_duet_slice(baked["duet"], 60)
    with pytest.raises(RuntimeError, match="injected failure"):
        bake.bake_duet(bpy.context, short, baked["take"].name, 1)
    assert {k: sorted(getattr(bpy.data, k).keys()) for k in kinds} == before
    assert {c.name: (c.hide_viewport, c.hide_render) for c in bpy.data.collections
            if c.dancing_points.kind == 'DUET'} == shown
    assert floor.data == mesh and rig[stage.FOLLOW_PROP] == follow and rig.animation_data.action == action
    assert (scene.frame_start, scene.frame_end, scene.camera, tuple(rig.location),
            tuple(rig[stage.WIDE_PROP])) == view


def test_synthesis_keeps_the_users_edit_mode(baked):
    """Synthesising while the user edits a mesh leaves that mesh in edit mode
    (the bake itself needs object mode)."""
    mesh = bpy.data.meshes.new("User Mesh")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    obj = bpy.data.objects.new("User Mesh", mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = (40.0, 40.0, 0.0)  # out of the dancers' way
    view_layer = bpy.context.view_layer
    prev = view_layer.objects.active
    view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode='EDIT')
    try:
        versions = [c.dancing_points.version for c in bpy.data.collections if c.dancing_points.kind == 'DUET']
        assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=baked["take"].name) == {'FINISHED'}
        assert len([c for c in bpy.data.collections if c.dancing_points.kind == 'DUET']) == len(versions) + 1
        assert view_layer.objects.active == obj and obj.mode == 'EDIT'
    finally:
        if obj.mode != 'OBJECT':
            bpy.ops.object.mode_set(mode='OBJECT')
        view_layer.objects.active = prev
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(mesh)


def runtime_duet_slice(duet, n):
    """The first ``n`` frames of ``duet`` (another extent: the stage would be refitted)."""
    runtime = import_from_extension("dancing_points_addon.runtime")
    keys = ("leader_positions", "leader_rotations", "leader_contacts",
            "follower_positions", "follower_rotations", "follower_contacts")
    return runtime.Duet(duet.time[:n], **{k: getattr(duet, k)[:n] for k in keys})


def test_bake_time_60s(baked):
    """Bake time of a 60 s duet (both armatures, bodies, 1800 keys per channel),
    beyond synthesis. Target < 2 s."""
    duet = baked["duet"]
    runtime = import_from_extension("dancing_points_addon.runtime")
    bake = import_from_extension("operators.bake")
    reps = int(np.ceil(60 * 30 / duet.n_frames))
    tile = {k: np.concatenate([getattr(duet, k)] * reps)[:1800] for k in
            ("leader_positions", "leader_rotations", "leader_contacts",
             "follower_positions", "follower_rotations", "follower_contacts")}
    long = runtime.Duet(np.arange(1800) / 30.0, **tile)
    t0 = time.perf_counter()
    coll, rigs = bake.bake_duet(bpy.context, long, baked["take"].name, 1)
    dt = time.perf_counter() - t0
    print(f"\nbake of a 60 s duet (1800 frames, 2 armatures + bodies): {dt:.2f} s")
    arm, _ = rigs["leader"]
    f, _ = bsu.fcurve_keys(arm, 'pose.bones["root"].location', 0)
    assert len(f) == 1800
    assert dt < 10.0


def test_render_preview_video(baked, tmp_path):
    mid = baked["frame_start"] + baked["duet"].n_frames // 2
    out = tmp_path / "video_"
    assert bpy.ops.dancing_points.render_preview(filepath=str(out), file_format='FFMPEG', frame_start=mid,
                                                 frame_end=mid + 2, resolution_percentage=10) == {'FINISHED'}
    (video,) = tmp_path.glob("video_*.mp4")
    assert video.stat().st_size > 1000
    assert bpy.context.scene.render.image_settings.file_format != 'FFMPEG'  # restored


# --------------------------------------------------------------------------- the modal (UI) path

class _FakeWindowManager:
    def __init__(self, wm):
        self._wm = wm
        self.timers = []
        self.handlers = []
        self.progress = []

    def event_timer_add(self, step, window=None):
        self.timers.append(step)
        return object()

    def event_timer_remove(self, timer):
        self.timers.pop()

    def modal_handler_add(self, op):
        self.handlers.append(op)

    def progress_begin(self, a, b):
        self.progress.append(("begin", a, b))

    def progress_update(self, v):
        self.progress.append(("update", v))

    def progress_end(self):
        self.progress.append(("end",))


class _UIContext:
    """``bpy.context`` as seen by an operator run from the UI: a window, a window
    manager that records timers, progress and modal handlers, a workspace."""

    def __init__(self):
        self.window = object()
        self.window_manager = _FakeWindowManager(bpy.context.window_manager)
        self.status = []
        ctx = self

        class Workspace:
            def status_text_set(self, text):
                ctx.status.append(text)

        self.workspace = Workspace()

    def __getattr__(self, name):
        return getattr(bpy.context, name)


def _ui_operator():
    """An instance-like stand-in carrying the synthesise operator's methods (the
    real operator cannot be invoked with a window in background mode)."""
    cls = bpy.types.Operator.bl_rna_get_subclass_py("DANCING_POINTS_OT_synthesize")

    class Op:
        take = ""
        foot_lock = True
        hand_ik = False
        follow_devices = True
        model_dir = MODELS

        def __init__(self):
            self.reports = []

        def report(self, kind, msg):
            self.reports.append((set(kind), msg))

    for name, fn in cls.__dict__.items():
        if callable(fn) and not name.startswith("__") and name not in ("bl_rna", "poll"):
            setattr(Op, name, fn)
    return Op()


class _Event:
    def __init__(self, type, value='NOTHING'):
        self.type, self.value = type, value


def test_modal_synthesis_progress_and_finish(files):
    bsu.fresh_scene()
    _import(files["csv"])
    ctx, op = _UIContext(), _ui_operator()
    assert op.invoke(ctx, _Event('LEFTMOUSE', 'PRESS')) == {'RUNNING_MODAL'}
    assert ctx.window_manager.handlers == [op] and ctx.window_manager.timers
    assert op.modal(ctx, _Event('MOUSEMOVE')) == {'PASS_THROUGH'}
    deadline = time.time() + 120
    while True:
        res = op.modal(ctx, _Event('TIMER'))
        if res != {'RUNNING_MODAL'}:
            break
        assert time.time() < deadline
        time.sleep(0.05)
    assert res == {'FINISHED'}, op.reports
    assert not ctx.window_manager.timers  # timer removed
    assert ctx.window_manager.progress[-1] == ("end",)
    assert any(s and "Esc to cancel" in s for s in ctx.status) and ctx.status[-1] is None
    assert len([c for c in bpy.data.collections if c.dancing_points.kind == 'DUET']) == 1


def test_modal_synthesis_escape_leaves_scene_unchanged(files, monkeypatch):
    bsu.fresh_scene()
    _import(files["csv"])
    state = bsu.scene_state()
    runtime = import_from_extension("dancing_points_addon.runtime")
    real = runtime.Synthesizer.synthesize
    started = []

    def slow(self, take, progress=None):  # the real loop, slowed so Esc lands mid-way
        def prog(i, n):
            started.append(i)
            time.sleep(0.05)
            return progress(i, n)
        return real(self, take, progress=prog)

    monkeypatch.setattr(runtime.Synthesizer, "synthesize", slow)
    ctx, op = _UIContext(), _ui_operator()
    assert op.invoke(ctx, _Event('LEFTMOUSE', 'PRESS')) == {'RUNNING_MODAL'}
    while not started:
        time.sleep(0.01)
    assert op.modal(ctx, _Event('TIMER')) == {'RUNNING_MODAL'}
    assert op.modal(ctx, _Event('ESC', 'PRESS')) == {'CANCELLED'}
    assert not op._thread.is_alive()
    assert not ctx.window_manager.timers
    assert any("cancelled" in m for _, m in op.reports)
    _assert_unchanged(state)


def _fresh_bake(files):
    """A fresh scene with the CSV take imported and baked by the operator."""
    bsu.fresh_scene()
    coll = _import(files["csv"])
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS) == {'FINISHED'}
    (duet,) = [c for c in bpy.data.collections if c.dancing_points.kind == 'DUET']
    return coll, duet


def test_bake_matches_the_command_line_duet(files):
    """The Blender bake of an imported CSV take and the command line's duet of
    the same file (the core on the file's own samples) are the same duet:
    per joint, mean ≤ 1 mm and max ≤ 1 cm (the take went through float32
    keyframes on the way)."""
    _, duet_coll = _fresh_bake(files)
    runtime = import_from_extension("dancing_points_addon.runtime")
    cli = runtime.Synthesizer(runtime.SynthesisOptions(models=MODELS)).synthesize(read_take(files["csv"]))
    frames = 1 + np.arange(cli.n_frames)
    for role in ("leader", "follower"):
        arm, _ = _rig(duet_coll, role)
        _, tails = bsu.posed_heads_tails(arm, frames, JOINT_NAMES)
        _, cpos, _ = bm.consistent_pose(getattr(cli, role + "_positions"), getattr(cli, role + "_rotations"))
        err = np.linalg.norm(tails[:, 1:] - bm.to_blender(cpos)[:, 1:], axis=-1)
        print(f"\n{role}: bake vs command line, mean {err.mean() / MM:.4f} mm, max {err.max() / MM:.4f} mm")
        assert err.mean() <= 1 * MM
        assert err.max() <= 10 * MM


def test_edited_take_reads_its_keyframes(files):
    """The stored full-precision samples stand in for the keyframes only while the
    empties still show them: a moved device (an animator's edit) wins."""
    take_collection = import_from_extension("operators.take_collection")
    bsu.fresh_scene()
    coll = _import(files["csv"])
    take = take_collection.take_from_collection(bpy.context, coll)
    assert take_collection.stored_samples(coll, take.positions, take.quats) is not None
    moved = take.positions.copy()
    moved[5, 1] += 0.01  # the left hand 1 cm away on one frame
    assert take_collection.stored_samples(coll, moved, take.quats) is None


def test_a_take_longer_than_its_keys_is_refused(files):
    """A take's Frames setting past its keyframes (a script or the property
    UI set it) is refused in one line, not synthesised as held poses."""
    take_collection = import_from_extension("operators.take_collection")
    bsu.fresh_scene()
    coll = _import(files["csv"])
    T = coll.dancing_points.n_frames
    coll.dancing_points.n_frames = 100_000
    state = bsu.scene_state()
    with pytest.raises(RuntimeError, match=f"has 100000 frames .* set Frames to {T} or key the rest"):
        bpy.ops.dancing_points.synthesize(model_dir=MODELS)
    _assert_unchanged(state)
    coll.dancing_points.n_frames = T - 10  # fewer frames than keys: a shortened take, read as such
    assert take_collection.take_from_collection(bpy.context, coll).n_frames == T - 10
    # one hand's keys ending early: the take ends where every device is keyed
    coll.dancing_points.n_frames = T
    compat = import_from_extension("operators.compat")
    hand = import_from_extension("operators.props").device_objects(coll)["lhand"]
    action, slot = compat.assigned_action(hand)
    for path, n in (("location", 3), ("rotation_quaternion", 4)):
        for i in range(n):
            kp = compat.find_fcurve(action, slot, path, i).keyframe_points
            for _ in range(5):
                kp.remove(kp[len(kp) - 1])
    user_error = import_from_extension("dancing_points_addon.errors").UserError
    with pytest.raises(user_error, match=f"has {T} frames .* set Frames to {T - 5} or key the rest"):
        take_collection.take_from_collection(bpy.context, coll)


def test_headset_take_import_calibration_on_the_take(files, tmp_path):
    """A headset's take (devices=openxr) imports as such; the Devices option
    overrides the file; synthesising stores the estimated height and the floor
    on the take; a floor given in the panel reaches the synthesis; the baked
    leader is the core's duet of the same take."""
    from dancing_points_addon.calibration import headset_take

    bsu.fresh_scene()
    xr = tmp_path / "headset.csv"
    write_take(xr, headset_take(files["take"]))
    coll = _import(xr)
    s = coll.dancing_points
    assert s.devices == 'openxr' and s.height == 0.0 and not s.use_floor_y and s.height_source == ""
    take_collection = import_from_extension("operators.take_collection")
    take = take_collection.take_from_collection(bpy.context, coll)
    assert take.meta["devices"] == "openxr"
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=coll.name) == {'FINISHED'}
    runtime = import_from_extension("dancing_points_addon.runtime")
    duet = runtime.Synthesizer(runtime.SynthesisOptions(models=MODELS)).synthesize(take)
    assert s.height_source == "estimated" and abs(s.height_used - duet.calibration.height) < 1e-5
    assert s.floor_source == "assumed" and s.floor_used == 0.0
    (duet_coll,) = [c for c in bpy.data.collections if c.dancing_points.kind == 'DUET'
                    and c.dancing_points.take_name == coll.name]
    arm, _ = _rig(duet_coll, "leader")
    scene = bpy.context.scene
    for k in (0, duet.n_frames // 2, duet.n_frames - 1):
        scene.frame_set(s.frame_start + k)
        head = arm.matrix_world @ arm.pose.bones["upperneck"].tail
        assert np.linalg.norm(bm.to_motion(np.array(head)) - duet.leader_positions[k, 15]) < 1e-3
    # the panel's floor and height reach the synthesis as given
    s.use_floor_y, s.floor_y, s.height = True, 0.02, 1.75
    take = take_collection.take_from_collection(bpy.context, coll)
    assert take.meta["floor_y"] == pytest.approx(0.02) and take.height == pytest.approx(1.75)
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=coll.name) == {'FINISHED'}
    assert s.height_source == "given" and s.floor_source == "given" and s.floor_used == pytest.approx(0.02)
    # the import option overrides the file's devices
    coll2 = _import(xr, devices='joints')
    assert coll2.dancing_points.devices == 'joints'


def test_take_height_and_floor_out_of_range_are_refused(files):
    """The take's Dancer Height and Floor Height have the command line's ranges
    (``--height``, ``--floor-y``): hard bounds on the properties, and a check
    when the take is read for synthesis, for values a script or an older file
    holds past the bounds (a floor of 1e6 m once reached the stage: a 47.8 GiB
    checker floor)."""
    from dancing_points_addon.formats.limits import FLOOR_RANGE_M
    from dancing_points_addon.formats.limits import HEIGHT_RANGE_M

    bsu.fresh_scene()
    coll = _import(files["csv"])
    s = coll.dancing_points
    props = s.bl_rna.properties
    assert props["height"].hard_min == 0.0 and props["height"].hard_max == HEIGHT_RANGE_M[1]
    assert (props["floor_y"].hard_min, props["floor_y"].hard_max) == (-FLOOR_RANGE_M, FLOOR_RANGE_M)
    s.use_floor_y, s.floor_y, s.height = True, 1e6, 50.0
    assert s.floor_y == FLOOR_RANGE_M and s.height == HEIGHT_RANGE_M[1]  # clamped
    s.floor_y, s.height = 0.0, 0.0
    name = coll.name
    for key, value, match in (
            ("floor_y", 1e6, f"take '{name}': Floor Height must be within ±1 m, got 1e\\+06"),
            ("floor_y", float("nan"), "Floor Height must be within ±1 m, got nan"),
            ("height", 5.0, f"take '{name}': Dancer Height must be between 0.5 and 3 m, got 5$"),
            ("height", 0.3, "Dancer Height must be between 0.5 and 3 m, got 0.3"),
            ("height", -1.0, "Dancer Height must be between 0.5 and 3 m, got -1")):
        s[key] = value  # as a script or an older file can: past the property's bounds
        state = bsu.scene_state()
        with pytest.raises(RuntimeError, match=match) as info:
            bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=name)
        assert "\n" not in str(info.value).strip()
        _assert_unchanged(state)
        s[key] = 0.0
    s.use_floor_y = False
    s["floor_y"] = 1e6  # not given: not used, not checked
    take_collection = import_from_extension("operators.take_collection")
    assert "floor_y" not in take_collection.take_from_collection(bpy.context, coll).meta


def test_import_start_frame_within_blenders_frames(files):
    """Start Frame is a scene frame (0 or later, as a scene's start) whose take
    ends by Blender's last frame (MAXFRAME): past it, one line naming the
    largest Start Frame that fits, and nothing made (a start of 1e8 once
    collapsed the keys to float32's steps and clamped the scene's range)."""
    bsu.fresh_scene()
    maxframe = bpy.types.Scene.bl_rna.properties["frame_end"].hard_max
    prop = bpy.ops.dancing_points.import_take.get_rna_type().properties["frame_start"]
    assert (prop.hard_min, prop.hard_max) == (0, maxframe)
    T = resample_take(files["take"], 30.0).n_frames
    state = bsu.scene_state()
    for start in (100_000_000, maxframe - T + 2):
        with pytest.raises(RuntimeError, match=f"would end on frame {min(start, maxframe) + T - 1}, past Blender's "
                                               f"last frame {maxframe}: set Start Frame to at most "
                                               f"{maxframe - T + 1}"):
            bpy.ops.dancing_points.import_take(filepath=str(files["csv"]), frame_start=start)
        _assert_unchanged(state)
    coll = _import(files["csv"], frame_start=maxframe - T + 1)  # the last start that fits: every key its frame
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (maxframe - T + 1, maxframe)
    compat = import_from_extension("operators.compat")
    take_collection = import_from_extension("operators.take_collection")
    for obj in take_collection.device_objects(coll).values():
        fc = compat.find_fcurve(*compat.assigned_action(obj), "location", 0)
        assert [k.co[0] for k in fc.keyframe_points] == list(range(maxframe - T + 1, maxframe + 1))
    bsu.fresh_scene()
    coll = _import(files["csv"], frame_start=-50)  # before a scene's first frame: from frame 0
    assert coll.dancing_points.frame_start == 0 and bpy.context.scene.frame_start == 0
