"""The preview: the stage, the follow camera, timing, burn-in.

The embedded sample take is imported and synthesised headless with the
shipped models; then, on every frame of the take, the bones of both armatures
(heads and tails, evaluated by Blender) are projected through the scene
camera with ``bpy_extras.object_utils.world_to_camera_view``: all inside the
frame, the couple at least 55 % of the frame height, its centre in the middle
fifth. A rendered frame shows the floor under the feet and the two dancers'
colours; the burn-in is stamped and the scene's settings come back. A 24 fps
and a 60 fps scene play the duet at the take's real speed. Re-running does not
duplicate the stage, and a user's own camera, world and light stay as they were.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from support import blender_scene_util as bsu  # noqa: E402
from conftest import MODELS, ROOT  # noqa: E402
from support.ext_util import import_from_extension  # noqa: E402

from dancing_points_addon import blender_math as bm  # noqa: E402
from dancing_points_addon.inputs import load_input  # noqa: E402
from dancing_points_addon.resample import resample_take  # noqa: E402
from dancing_points_addon.skeleton import JOINT_NAMES  # noqa: E402

SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
TAKE = "DP Take sample_take"


def _import_and_synthesize(**import_kw):
    assert bpy.ops.dancing_points.import_take(filepath=str(SAMPLE), **import_kw) == {'FINISHED'}
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=TAKE) == {'FINISHED'}


def _arms():
    duets = [c for c in bpy.data.collections if c.dancing_points.kind == 'DUET' and not c.hide_render]
    duet = max(duets, key=lambda c: c.dancing_points.version)
    return {o.get("dp_role"): o for o in duet.objects if o.type == 'ARMATURE'}


def _bone_points(arm, depsgraph):
    """Heads and tails ``(62, 3)`` (world) of the evaluated bones."""
    ev = arm.evaluated_get(depsgraph)
    mw = np.array(ev.matrix_world)
    pts = np.array([[*pb.head, 1.0] for pb in ev.pose.bones] + [[*pb.tail, 1.0] for pb in ev.pose.bones])
    return pts @ mw.T[:, :3]


def _farther_mostly_hidden(v_lead, v_foll):
    """Whether less than half of the farther dancer's box (the bounding box of
    the bones in the image, from ``world_to_camera_view`` points: x, y, depth)
    is uncovered by the nearer dancer's box."""
    near, far = (v_lead, v_foll) if v_lead[:, 2].mean() < v_foll[:, 2].mean() else (v_foll, v_lead)
    (n0, n1), (f0, f1) = (near[:, :2].min(0), near[:, :2].max(0)), (far[:, :2].min(0), far[:, :2].max(0))
    overlap = np.clip(np.minimum(n1, f1) - np.maximum(n0, f0), 0.0, None).prod()
    return 1.0 - overlap / np.prod(f1 - f0) < 0.5


def _max_turn_rate(rotations, fps):
    """The largest angle between consecutive camera rotations ``(T, 3, 3)``, in degrees a second."""
    rel = np.einsum("tji,tjk->tik", rotations[:-1], rotations[1:])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.rad2deg(np.arccos(cos)).max() * fps)


def _stage_ids(kind):
    return sorted(x.name for x in getattr(bpy.data, kind) if x.get("dp_stage"))


@pytest.fixture(scope="module")
def preview():
    scene = bsu.fresh_scene()
    t0 = time.perf_counter()
    _import_and_synthesize()
    print(f"\nimport + synthesise + bake + stage: {time.perf_counter() - t0:.1f} s")
    return scene


def test_follow_camera_frames_both_dancers_on_every_frame(preview, tmp_path):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    scene = preview
    stage = import_from_extension("operators.stage")
    cam = scene.camera
    assert cam is not None and cam.get("dp_stage") == "camera" and scene.dancing_points.camera_mode == 'FOLLOW'
    assert (scene.frame_start, scene.frame_end) == (1, 343)  # the timeline is the duet
    arms = _arms()
    frames = range(scene.frame_start, scene.frame_end + 1)
    # The whole preview rendered (small: 96 x 54): the dancers show in every frame, both
    # colours in nearly all (the camera turns slowly round the couple so that neither
    # hides the other; one dancer's arm round the other still covers a few frames).
    t0 = time.perf_counter()
    assert bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / "f_"), file_format='PNG',
                                                 resolution_percentage=5, burn_in=False) == {'FINISHED'}
    both = 0
    for f in frames:
        px = bsu.load_png(tmp_path / f"f_{f:04d}.png")[..., :3]
        blue = (px[..., 2] > px[..., 0] + 0.15).sum()
        red = (px[..., 0] > px[..., 2] + 0.15).sum()
        assert blue + red >= 40, (f, blue, red)
        both += blue >= 10 and red >= 10
    print(f"\n{len(frames)} frames rendered in {time.perf_counter() - t0:.1f} s; both dancers' colours "
          f"in {both} of them")
    assert both >= 0.88 * len(frames)
    fills, centres, lo, hi = [], [], [], []
    cam_loc, cam_rot, hidden = [], [], []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for f in frames:
        scene.frame_set(f)
        cam_loc.append(np.array(cam.matrix_world.translation))
        cam_rot.append(np.array(cam.matrix_world.to_3x3().normalized()))
        pts = np.concatenate([_bone_points(arms["leader"], depsgraph), _bone_points(arms["follower"], depsgraph)])
        v = np.array([world_to_camera_view(scene, cam, Vector(p)) for p in pts])
        hidden.append(_farther_mostly_hidden(v[:len(v) // 2], v[len(v) // 2:]))
        assert (v[:, 2] > 0).all()  # in front of the camera
        lo.append(v[:, :2].min(0))
        hi.append(v[:, :2].max(0))
        fills.append(v[:, 1].max() - v[:, 1].min())
        centres.append((v[:, 0].max() + v[:, 0].min()) / 2)
    lo, hi, fills, centres = map(np.array, (lo, hi, fills, centres))
    acc = np.linalg.norm(np.diff(np.array(cam_loc), 2, axis=0), axis=1).max() * (scene.render.fps ** 2)
    turn = _max_turn_rate(np.array(cam_rot), scene.render.fps)
    print(f"\nfollow camera over {len(fills)} frames: joints within x {lo[:, 0].min():.3f}..{hi[:, 0].max():.3f}, "
          f"y {lo[:, 1].min():.3f}..{hi[:, 1].max():.3f}; couple height {fills.min():.3f}..{fills.max():.3f} "
          f"of the frame; centre x {centres.min():.3f}..{centres.max():.3f}; camera max accel {acc:.2f} m/s², "
          f"turning at most {turn:.1f}°/s; the farther dancer mostly hidden in {100 * np.mean(hidden):.1f} % "
          f"of the frames")
    assert np.mean(hidden) <= 0.40
    assert turn <= 60.0
    assert lo.min() >= 0.0 and hi.max() <= 1.0  # every joint of both dancers inside the frame
    assert fills.min() >= 0.55
    assert np.abs(centres - 0.5).max() <= 0.1  # the middle fifth
    assert acc < 1.0
    assert stage.find_stage(scene)["dp_camera_max_accel"] == pytest.approx(acc, rel=0.05)
    # the wide shot is the other mode: a still camera; back to follow
    scene.dancing_points.camera_mode = 'WIDE'
    rig = cam.parent
    assert rig.animation_data.action is None
    scene.frame_set(1)
    m1 = np.array(cam.matrix_world)
    scene.frame_set(200)
    np.testing.assert_allclose(np.array(cam.matrix_world), m1)
    scene.dancing_points.camera_mode = 'FOLLOW'
    assert rig.animation_data.action is not None and rig.animation_data.action.name == rig["dp_follow_action"]


def test_render_shows_floor_dancers_and_burn_in(preview, tmp_path):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    scene = preview
    f = 172
    before = (scene.render.use_stamp, scene.render.stamp_note_text, scene.display.shading.show_shadows,
              scene.display.shading.color_type, scene.render.engine, scene.display.render_aa)
    t0 = time.perf_counter()
    for burn, name in ((True, "on_"), (False, "off_")):
        assert bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / name), file_format='PNG',
                                                     frame_start=f, frame_end=f, resolution_percentage=25,
                                                     burn_in=burn) == {'FINISHED'}
    print(f"\ntwo frames rendered in {time.perf_counter() - t0:.1f} s")
    assert (scene.render.use_stamp, scene.render.stamp_note_text, scene.display.shading.show_shadows,
            scene.display.shading.color_type, scene.render.engine, scene.display.render_aa) == before  # restored
    on = bsu.load_png(tmp_path / f"on_{f:04d}.png")[..., :3]  # bottom row first
    off = bsu.load_png(tmp_path / f"off_{f:04d}.png")[..., :3]
    H, W = off.shape[:2]
    # the two dancers in two clearly different colours
    blue = (off[..., 2] > off[..., 0] + 0.15).sum()
    red = (off[..., 0] > off[..., 2] + 0.15).sum()
    assert blue > 0.005 * H * W and red > 0.005 * H * W, (blue, red)
    # the floor: the pixels just below the lowest foot are not the background (the world's colour,
    # at the top of the frame)
    scene.frame_set(f)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    arms = _arms()
    pts = np.concatenate([_bone_points(arms[r], depsgraph) for r in ("leader", "follower")])
    v = np.array([world_to_camera_view(scene, scene.camera, Vector(p)) for p in pts])
    low = v[np.argmin(v[:, 1])]
    row = int(low[1] * H) - max(2, H // 25)
    col = int(low[0] * W)
    background = np.median(off[H - 3:H, W // 3:2 * W // 3].reshape(-1, 3), axis=0)
    below = off[row - 2:row + 1, max(col - 20, 0):col + 20].reshape(-1, 3)
    assert background.min() > 0.6  # a light background (the stage's world)
    floor_diff = np.abs(below - background).max(1)
    print(f"background {background.round(3)}, under the feet {below.mean(0).round(3)}")
    assert (floor_diff > 0.05).mean() > 0.9
    # the burn-in: only the stamp's strips differ between the two renders
    diff = np.abs(on - off).max(-1) > 0.1
    rows = np.flatnonzero(diff.any(1))
    assert len(rows) > 0
    assert rows.min() < H * 0.2 or rows.max() > H * 0.8
    assert not diff[int(H * 0.25):int(H * 0.75)].any()


def test_first_preview_in_blenders_startup_scene(tmp_path):
    """Blender's default scene (Cube, Camera, Light): import the sample take,
    synthesise, Render Preview. The preview renders through the DP Camera's
    follow shot (the startup Camera stays the scene camera and is not moved);
    the default cube, which stands where the couple dances, is named after the
    bake and, once hidden in previews, hides nothing; it is still there."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    bsu.fresh_scene()
    bpy.ops.wm.read_homefile()  # the startup file: Cube, Camera, Light
    stage = import_from_extension("operators.stage")
    scene = bpy.context.scene
    assert sorted(o.name for o in scene.objects) == ["Camera", "Cube", "Light"]
    camera, cube = scene.objects["Camera"], scene.objects["Cube"]
    bpy.ops.mesh.primitive_plane_add(size=30.0)  # a floor of the user's under their feet is not in the way
    bpy.context.active_object.name = "My Floor"
    before = np.array(camera.matrix_world), camera.data.lens
    assert bpy.ops.dancing_points.import_take(filepath=str(SAMPLE)) == {'FINISHED'}
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=TAKE) == {'FINISHED'}
    assert [o.name for o in stage.obstacles(scene)] == ["Cube"]  # said after the bake, in one line
    assert scene.camera == camera and stage.preview_camera(scene).name == "DP Camera"
    f = 120  # the cube's top cut both dancers at the waist here, through the startup camera
    counts = {}
    for hide in (False, True):
        if hide:
            assert bpy.ops.dancing_points.hide_in_previews() == {'FINISHED'}
            assert stage.obstacles(scene) == []
        assert bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / f"h{int(hide)}_"), file_format='PNG',
                                                     frame_start=f, frame_end=f, resolution_percentage=25,
                                                     burn_in=False) == {'FINISHED'}
        px = bsu.load_png(tmp_path / f"h{int(hide)}_{f:04d}.png")[..., :3]
        counts[hide] = int((px[..., 2] > px[..., 0] + 0.15).sum() + (px[..., 0] > px[..., 2] + 0.15).sum())
    print(f"\nstartup scene, frame {f}: the dancers' pixels {counts[False]} with the cube, {counts[True]} with it "
          f"hidden in previews")
    assert counts[True] > 1.5 * counts[False]  # the cube hid them; hidden in previews it does not
    # the scene's camera unchanged, the cube still there and shown in final renders
    assert scene.camera == camera and camera.data.lens == before[1]
    np.testing.assert_array_equal(np.array(camera.matrix_world), before[0])
    assert scene.objects.get("Cube") == cube and not cube.hide_render and not cube.hide_viewport
    # the preview's frames look like the README's: the couple whole, >= 55 % of the height, centred
    dp_cam = stage.preview_camera(scene)
    arms = _arms()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for frame in range(scene.frame_start, scene.frame_end + 1, 7):
        scene.frame_set(frame)
        pts = np.concatenate([_bone_points(arms[r], depsgraph) for r in ("leader", "follower")])
        v = np.array([world_to_camera_view(scene, dp_cam, Vector(p)) for p in pts])
        assert (v[:, 2] > 0).all() and v[:, :2].min() >= 0.0 and v[:, :2].max() <= 1.0, frame
        assert v[:, 1].max() - v[:, 1].min() >= 0.55, frame
        assert abs((v[:, 0].max() + v[:, 0].min()) / 2 - 0.5) <= 0.1, frame
    # the scene's own camera is a choice too
    scene.dancing_points.camera_mode = 'SCENE'
    assert stage.preview_camera(scene) == camera
    scene.dancing_points.camera_mode = 'FOLLOW'


def test_timing_24_and_60_fps_scenes():
    """The scene keeps its rate; the take's empties and the duet are keyed in scene
    time, so at scene time t the Head empty is at the take's head at t, and the
    leader's head at the command line's duet's head at t; synthesis still reads
    the take's own samples exactly."""
    runtime = import_from_extension("dancing_points_addon.runtime")
    take_collection = import_from_extension("operators.take_collection")
    take30 = resample_take(load_input(str(SAMPLE)), 30.0)
    ref = runtime.Synthesizer(runtime.SynthesisOptions(models=MODELS, foot_lock=True)).synthesize(take30)
    t30 = np.arange(take30.n_frames) / 30.0
    for fps in (24, 60):
        scene = bsu.fresh_scene()
        scene.render.fps, scene.render.fps_base = fps, 1.0
        _import_and_synthesize(update_scene_fps=False)
        assert (scene.render.fps, scene.render.fps_base) == (fps, 1.0)  # the project keeps its rate
        n = int(np.ceil((take30.n_frames - 1) * fps / 30.0 - 1e-6)) + 1
        assert (scene.frame_start, scene.frame_end) == (1, n)
        coll = bpy.data.collections[TAKE]
        back = take_collection.take_from_collection(bpy.context, coll)
        np.testing.assert_array_equal(back.positions, take30.positions)  # the take's own samples
        np.testing.assert_allclose(back.quats, take30.quats, rtol=0, atol=1e-12)
        head = bpy.data.objects["Head"]
        lead = _arms()["leader"]
        frames = np.arange(1, n + 1, 3)
        t = (frames - 1) / fps
        want_take = bm.to_blender(np.stack([np.interp(t, t30, take30.positions[:, 0, i]) for i in range(3)], 1))
        hj = JOINT_NAMES.index("head")
        want_head = bm.to_blender(np.stack([np.interp(t, t30, ref.leader_positions[:, hj, i]) for i in range(3)], 1))
        got_take, got_head = [], []
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for f in frames:
            scene.frame_set(int(f))
            got_take.append(np.array(head.matrix_world.translation))
            ev = lead.evaluated_get(depsgraph)
            got_head.append(np.array(ev.matrix_world @ ev.pose.bones["head"].tail))
        e_take = np.linalg.norm(np.array(got_take) - want_take, axis=1).max()
        e_head = np.linalg.norm(np.array(got_head) - want_head, axis=1).max()
        print(f"\n{fps} fps scene: Head empty off the take by <= {e_take * 1000:.3f} mm, leader's head off the "
              f"duet by <= {e_head * 1000:.3f} mm (over {len(frames)} frames)")
        assert e_take < 0.01 and e_head < 0.01


def test_rerun_keeps_one_stage_and_the_users_own_things(tmp_path):
    scene = bsu.fresh_scene()
    # the user's own camera, world and light
    cam = bpy.data.objects.new("MyCam", bpy.data.cameras.new("MyCam"))
    scene.collection.objects.link(cam)
    cam.location = (0.5, -9.0, 1.4)
    cam.rotation_euler = (np.deg2rad(88.0), 0.0, 0.0)
    scene.camera = cam
    world = bpy.data.worlds.new("MyWorld")
    world.color = (0.1, 0.2, 0.3)
    scene.world = world
    lamp = bpy.data.objects.new("MyLamp", bpy.data.lights.new("MyLamp", 'POINT'))
    lamp.data.energy = 123.0
    scene.collection.objects.link(lamp)

    def user_state():
        bpy.context.view_layer.update()
        return (scene.camera.name, np.array(cam.matrix_world).round(9).tolist(), cam.data.lens, cam.animation_data,
                scene.world.name, tuple(world.color), lamp.data.energy, np.array(lamp.matrix_world).tolist(),
                sorted(o.name for o in scene.objects if o.type == 'LIGHT'))

    state = user_state()
    _import_and_synthesize()
    ids = {k: _stage_ids(k) for k in ("collections", "objects", "cameras", "lights", "worlds", "materials",
                                      "meshes", "actions")}
    assert ids["collections"] == ["DP Stage"]
    assert ids["objects"] == ["DP Camera", "DP Camera Rig", "DP Floor"]  # no sun: the user has a light
    assert ids["lights"] == [] and ids["worlds"] == []  # nor a world
    assert user_state() == state  # the user's camera stays the scene camera, all as it was
    for _ in range(2):  # re-running synthesis and the preview
        assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=TAKE) == {'FINISHED'}
        assert bpy.ops.dancing_points.render_preview(filepath=str(tmp_path / "p_"), file_format='PNG',
                                                     frame_start=100, frame_end=100,
                                                     resolution_percentage=10) == {'FINISHED'}
    assert {k: _stage_ids(k) for k in ids} == ids  # nothing duplicated, the old floor and path replaced
    assert len([o for o in scene.objects if o.type == 'CAMERA']) == 2
    assert user_state() == state
    # removable: the stage goes, the user's things stay
    assert bpy.ops.dancing_points.remove_stage() == {'FINISHED'}
    assert not any(_stage_ids(k) for k in ids)
    assert user_state() == state

    # A scene with nothing: the stage brings its camera, a sun and a light world, once.
    scene = bsu.fresh_scene()
    assert scene.world is None and scene.camera is None
    _import_and_synthesize()
    assert bpy.ops.dancing_points.synthesize(model_dir=MODELS, take=TAKE) == {'FINISHED'}
    assert _stage_ids("objects") == ["DP Camera", "DP Camera Rig", "DP Floor", "DP Sun"]
    assert _stage_ids("worlds") == ["DP World"] and scene.world.name == "DP World"
    assert scene.camera.name == "DP Camera"
    assert len(_stage_ids("actions")) == 1  # the follow path of the newest duet only
    assert bpy.ops.dancing_points.remove_stage() == {'FINISHED'}
    assert scene.world is None and scene.camera is None
    with pytest.raises(RuntimeError, match="no DP Stage"):
        bpy.ops.dancing_points.remove_stage()
