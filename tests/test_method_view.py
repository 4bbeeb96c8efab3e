"""The method made visible (``operators/method_view.py``).

Core (no bpy): ``Synthesizer(record_predictions=True)`` records the mapping
network's 1 s predictions of both dancers' three points and changes no output
bit; the leader's first predicted head position is the take's next head sample
to a few cm.

Blender (the extension enabled as an extension): synthesising the embedded
sample take builds "DP Method <take>" in the duet collection: a predicted
trajectories curve whose points are the stored predictions of the current
frame (also after save + reload), input markers on the take's empties, floor
discs only under feet in contact, everything hidden in renders unless asked;
a BVH or AMC import with "Keep Source Body" keeps the source body as a ghost
whose head is on the take's head empty.
"""
from __future__ import annotations

import pathlib
import shutil

import numpy as np
import pytest

from conftest import MODELS, SALSA
from dancing_points_addon.features import FUTURE
from dancing_points_addon.inputs import load_input
from dancing_points_addon.resample import resample_take
from dancing_points_addon.runtime import Synthesizer
from dancing_points_addon.synthesis_options import SynthesisOptions
from dancing_points_addon.skeleton import FEET

ROOT = pathlib.Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "dancing_points_addon" / "samples" / "sample_take.csv"
CM = 0.01

try:
    import bpy
except ImportError:  # the core test still runs
    bpy = None

needs_bpy = pytest.mark.skipif(bpy is None, reason="needs the bpy module")


@pytest.fixture(scope="module")
def sample():
    return load_input(str(SAMPLE))


@pytest.fixture(scope="module")
def core_duet(sample):
    """The sample's duet with predictions, as the Blender path makes it."""
    synth = Synthesizer(SynthesisOptions(models=MODELS), record_predictions=True)
    return synth.synthesize(sample)


# --------------------------------------------------------------------------- core

@pytest.mark.parametrize("height", [None, "auto"])
def test_recording_changes_no_output(sample, height):
    plain = Synthesizer(SynthesisOptions(models=MODELS, height=height))
    rec = Synthesizer(SynthesisOptions(models=MODELS, height=height), nets=plain.nets, record_predictions=True)
    a, b = plain.synthesize(sample), rec.synthesize(sample)
    assert a.predictions is None
    for key, value in a.arrays().items():
        assert np.array_equal(value, b.arrays()[key]), key
    for role in ("leader", "follower"):
        assert np.array_equal(a.bone_vectors[role], b.bone_vectors[role])
    if height == "auto":
        assert rec.scale() != 1.0  # the scale is undone in the recorded positions too
    p = b.predictions
    assert p.dtype == np.float32 and p.shape == (b.n_frames, 2, FUTURE, 3, 3)
    assert np.isfinite(p).all()
    # the mapping predicts the leader's own next second: its first frame is the take's next sample
    head = resample_take(sample, 30.0).positions[:, 0]
    err = np.linalg.norm(p[:-1, 0, 0, 0] - head[1:], axis=-1)
    print(f"\nheight={height}: leader head, first predicted frame vs next sample: median "
          f"{np.median(err) * 100:.2f} cm, p90 {np.percentile(err, 90) * 100:.2f} cm, max {err.max() * 100:.2f} cm")
    assert np.median(err) < 3 * CM and np.percentile(err, 90) < 5 * CM, (np.median(err), np.percentile(err, 90))
    # and further ahead it drifts away, as a prediction of 1 s does (the trajectories are not the input)
    far = np.linalg.norm(p[:-FUTURE, 0, FUTURE - 1, 0] - head[FUTURE:], axis=-1)
    assert np.median(far) > np.median(err)
    # the follower's predicted points are somewhere near her, in the same world (not the leader's)
    d = np.linalg.norm(p[:, 1, 0, 0] - p[:, 0, 0, 0], axis=-1)
    assert np.median(d) > 0.2


def test_planted_states_are_what_the_locks_hold(sample, core_duet):
    """The discs' source (``Duet.planted``): the foot points the foot lock holds.
    A held point stays put (its lock blends in over a few frames); a free one
    moves; they differ from the contact probabilities at 0.5 (her lock switches
    on at 0.4, his reads kinematic evidence too); none without foot locking."""
    from dancing_points_addon.skeleton import FEET

    planted = core_duet.planted
    assert planted.dtype == bool and planted.shape == (core_duet.n_frames, 2, 4)
    for d, role in enumerate(("leader", "follower")):
        held = planted[:, d]
        assert 0.2 < held.mean() < 0.9, (role, held.mean())
        pos = getattr(core_duet, f"{role}_positions")[:, FEET]
        step = np.linalg.norm((pos[1:] - pos[:-1])[..., [0, 2]], axis=-1)  # horizontal, per frame
        both = held[1:] & held[:-1]
        print(f"\n{role}: held {held.mean():.2f} of foot-frames; held point moves median "
              f"{np.median(step[both]) * 1000:.2f} mm, p95 {np.percentile(step[both], 95) * 1000:.1f} mm; "
              f"free points median {np.median(step[~both]) * 1000:.1f} mm")
        assert np.median(step[both]) < 0.5e-3 and np.percentile(step[both], 95) < 1 * CM
        assert np.median(step[~both]) > 1 * CM
        probs = getattr(core_duet, f"{role}_contacts") >= 0.5
        assert (held != probs).mean() > 0.1  # the view shows the locks, not the probabilities
    free = Synthesizer(SynthesisOptions(models=MODELS, foot_lock=False)).synthesize(sample)
    assert free.planted is None


# --------------------------------------------------------------------------- Blender

def _mv():
    from support.ext_util import import_from_extension
    return import_from_extension("operators.method_view")


@pytest.fixture(scope="module")
def scene_duet(core_duet):
    """The sample take imported and synthesised by the operators."""
    if bpy is None:
        pytest.skip("needs the bpy module")
    from support import blender_scene_util as bsu

    scene = bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(SAMPLE)) == {'FINISHED'}
    take = scene.dancing_points.take
    assert bpy.ops.dancing_points.synthesize(take=take.name, model_dir=MODELS) == {'FINISHED'}
    (duet,) = [c for c in bpy.data.collections if c.name.startswith("DP Duet")]
    (method,) = [c for c in duet.children if c.name.startswith("DP Method")]
    objs = {o.get("dp_method"): [] for o in method.objects}
    for o in method.objects:
        objs[o.get("dp_method")].append(o)
    return {"scene": scene, "take": take, "duet": duet, "method": method, "objs": objs,
            "f0": take.dancing_points.frame_start, "T": core_duet.n_frames}


def _points(curve_obj):
    out = []
    for sp in curve_obj.data.splines:
        co = np.empty(4 * len(sp.points), dtype=np.float32)
        sp.points.foreach_get("co", co)
        out.append(co.reshape(-1, 4)[:, :3])
    return np.stack(out)  # (6, FUTURE, 3)


def _stored(obj, prop, shape):
    return np.array(obj[prop], dtype=np.float32).reshape(shape)


@needs_bpy
def test_method_objects_built(scene_duet, core_duet):
    objs = scene_duet["objs"]
    assert set(objs) == {"predictions", "inputs", "contacts"}
    assert len(objs["predictions"]) == 1 and len(objs["contacts"]) == 1 and len(objs["inputs"]) == 3
    (pred,) = objs["predictions"]
    assert pred.type == 'CURVE' and pred.data.bevel_depth > 0  # renders (Workbench included)
    assert len(pred.data.splines) == 6 and all(len(s.points) == FUTURE for s in pred.data.splines)
    colours = [tuple(m.diffuse_color)[:3] for m in pred.data.materials]
    assert colours[0][2] > colours[0][0] and colours[1][0] > colours[1][2]  # leader blue, follower red
    assert [s.material_index for s in pred.data.splines] == [0, 0, 0, 1, 1, 1]
    from dancing_points_addon import blender_math as bm
    expect = bm.to_blender(core_duet.predictions.transpose(0, 1, 3, 2, 4))
    stored = _stored(pred, "dp_predictions", (-1, 2, 3, FUTURE, 3))
    assert stored.shape[0] == core_duet.n_frames
    assert np.abs(stored - expect).max() < 1e-5  # the operator's duet is the core's


@needs_bpy
def test_trajectories_follow_the_frame(scene_duet):
    scene, f0 = scene_duet["scene"], scene_duet["f0"]
    (pred,) = scene_duet["objs"]["predictions"]
    stored = _stored(pred, "dp_predictions", (-1, 6, FUTURE, 3))
    seen = []
    for t in (40, 41, 200):
        scene.frame_set(f0 + t)
        pts = _points(pred)
        assert np.abs(pts - stored[t]).max() < 1e-6, t
        seen.append(pts)
    assert np.abs(seen[1] - seen[0]).max() > 1e-3  # they move from one frame to the next
    # the leader's head path starts near the leader's head empty at that frame
    head = np.array(scene_duet["take"].all_objects["Head"].matrix_world.translation)
    assert np.linalg.norm(seen[2][0, 0] - head) < 0.15
    scene.frame_set(f0 + scene_duet["T"] + 10)  # past the take: nothing to see
    assert np.abs(_points(pred)).max() == 0.0


@needs_bpy
def test_markers_follow_the_empties(scene_duet):
    scene, f0 = scene_duet["scene"], scene_duet["f0"]
    from support.ext_util import import_from_extension
    props = import_from_extension("operators.props")
    empties = props.device_objects(scene_duet["take"])
    markers = {o["dp_marks"]: o for o in scene_duet["objs"]["inputs"]}
    assert set(markers) == {"head", "lhand", "rhand"}
    for t in (0, 90, 250):
        scene.frame_set(f0 + t)
        for dev, m in markers.items():
            a = np.array(m.matrix_world.translation)
            b = np.array(empties[dev].matrix_world.translation)
            assert np.linalg.norm(a - b) < 1e-5, (t, dev)
    # the markers moved with the take
    scene.frame_set(f0)
    p0 = np.array(markers["head"].matrix_world.translation)
    scene.frame_set(f0 + 250)
    assert np.linalg.norm(np.array(markers["head"].matrix_world.translation) - p0) > 0.05


@needs_bpy
def test_contact_marks_only_on_contact(scene_duet, core_duet):
    scene, f0 = scene_duet["scene"], scene_duet["f0"]
    (obj,) = scene_duet["objs"]["contacts"]
    me = obj.data
    assert len(me.polygons) == 8
    from dancing_points_addon import blender_math as bm
    contact = core_duet.planted.reshape(len(core_duet.planted), 8)  # (T, 8): the points the locks hold
    feet = np.concatenate([core_duet.leader_positions[:, FEET], core_duet.follower_positions[:, FEET]], axis=1)
    floor = _mv().stage_floor(scene)  # on the stage's floor when there is one, else on the lowest foot
    if floor is None:
        floor = min(core_duet.leader_positions[:, FEET, 1].min(), core_duet.follower_positions[:, FEET, 1].min())
    floor_objs = [o for o in scene.objects if o.get("dp_stage") == "floor" and o.type == 'MESH']
    for o in floor_objs:  # the discs lie just above the stage's floor, not under it
        z = np.array([(o.matrix_world @ v.co).z for v in o.data.vertices])
        assert 0.0 < floor + 0.002 - z.max() < 0.0025
    # frames with and without contacts, for both dancers
    frames = sorted({int(t) for t in np.linspace(0, len(contact) - 1, 25)}
                    | {int(np.argmin(contact.sum(1))), int(np.argmax(contact.sum(1)))})
    assert contact[frames].any() and not contact[frames].all()
    print(f"\ncontacts: {contact.mean():.2f} of foot-frames in contact; floor {floor:.4f} m "
          f"({'stage' if floor_objs else 'lowest foot'}); {len(frames)} frames checked")
    for t in frames:
        scene.frame_set(f0 + t)
        area = np.empty(8, dtype=np.float32)
        me.polygons.foreach_get("area", area)
        assert np.array_equal(area > 1e-5, contact[t]), t
        centre = np.empty(3 * 8, dtype=np.float32)
        me.polygons.foreach_get("center", centre)
        centre = centre.reshape(8, 3)
        for d in np.flatnonzero(contact[t]):
            want = bm.to_blender(np.array([feet[t, d, 0], floor + 0.002, feet[t, d, 2]]))
            assert np.linalg.norm(centre[d] - want) < 1e-4, (t, d)


@needs_bpy
def test_visibility_settings(scene_duet):
    scene = scene_duet["scene"]
    s = scene.dancing_points_method
    every = [o for objs in scene_duet["objs"].values() for o in objs]
    assert not s.method_in_render
    assert all(o.hide_render for o in every)  # off in final renders by default
    assert not any(o.hide_viewport for o in every)
    try:
        s.method_in_render = True
        assert not any(o.hide_render for o in every)
        s.show_predictions = False
        (pred,) = scene_duet["objs"]["predictions"]
        assert pred.hide_viewport and pred.hide_render
        assert not any(o.hide_viewport or o.hide_render for o in scene_duet["objs"]["contacts"])
    finally:
        s.show_predictions = True
        s.method_in_render = False
    assert all(o.hide_render for o in every) and not any(o.hide_viewport for o in every)


@needs_bpy
def test_method_panel(scene_duet):
    from support import blender_scene_util as bsu
    cls = bpy.types.Panel.bl_rna_get_subclass_py("VIEW3D_PT_dancing_points_method")
    assert cls is not None and cls.bl_parent_id == "VIEW3D_PT_dancing_points"
    fake = type("Fake", (), {"layout": bsu.RecordingLayout()})
    cls.draw(fake, bpy.context)
    shown = {c[1][1] for c in fake.layout.calls if c[0] == "prop"}
    assert shown == {"show_inputs", "show_predictions", "show_contacts", "show_ghost", "method_in_render"}


@needs_bpy
def test_workbench_render_shows_the_method_when_asked(scene_duet, tmp_path):
    from support import blender_scene_util as bsu
    scene = scene_duet["scene"]
    mid = scene_duet["f0"] + 200
    px = {}
    try:
        for on in (False, True):
            scene.dancing_points_method.method_in_render = on
            out = tmp_path / "m{:d}_".format(on)
            assert bpy.ops.dancing_points.render_preview(filepath=str(out), file_format='PNG', frame_start=mid,
                                                         frame_end=mid, resolution_percentage=25) == {'FINISHED'}
            px[on] = bsu.load_png(tmp_path / "m{:d}_{:04d}.png".format(on, mid))
    finally:
        scene.dancing_points_method.method_in_render = False
    changed = np.abs(px[True] - px[False]).max(-1) > 0.05
    rgb = px[True][..., :3]
    yellow = changed & (rgb[..., 0] > 0.5) & (rgb[..., 1] > 0.35) & (rgb[..., 2] < 0.3)
    light_blue = changed & (rgb[..., 2] > rgb[..., 0] + 0.1)
    print(f"\nmethod in render: {changed.sum()} pixels changed, {yellow.sum()} marker-yellow, "
          f"{light_blue.sum()} leader-blue")
    assert changed.sum() > 30 and light_blue.sum() > 5


@needs_bpy
def test_survives_save_and_reload(scene_duet, tmp_path):
    """Last of the scene tests: it replaces the file."""
    scene, f0 = scene_duet["scene"], scene_duet["f0"]
    (pred,) = scene_duet["objs"]["predictions"]
    name = pred.name
    stored = _stored(pred, "dp_predictions", (-1, 6, FUTURE, 3))
    path = tmp_path / "method.blend"
    scene.frame_set(f0 + 10)
    assert bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True) == {'FINISHED'}
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.wm.open_mainfile(filepath=str(path)) == {'FINISHED'}
    assert any(getattr(h, "__name__", "") == "_on_frame_change" for h in bpy.app.handlers.frame_change_pre)
    scene = bpy.context.scene
    pred = bpy.data.objects[name]
    assert np.array_equal(_stored(pred, "dp_predictions", (-1, 6, FUTURE, 3)), stored)
    for t in (10, 120):
        scene.frame_set(f0 + t)
        assert np.abs(_points(pred) - stored[t]).max() < 1e-6, t
    # robust to missing objects: the handler skips what is gone
    bpy.data.objects.remove(pred)
    scene.frame_set(f0 + 121)
    assert _mv().update_scene(scene) == 1  # the contacts only


@needs_bpy
def test_scene_frame_rate_other_than_30(core_duet):
    """A 60 fps project that keeps its rate: a sample every two scene frames (the
    take's keys), the trajectories on the nearest sample."""
    from support import blender_scene_util as bsu
    scene = bsu.fresh_scene()
    scene.render.fps, scene.render.fps_base = 60, 1.0
    assert bpy.ops.dancing_points.import_take(filepath=str(SAMPLE), update_scene_fps=False) == {'FINISHED'}
    take = scene.dancing_points.take
    step = take.dancing_points.frame_step
    assert step == 2.0
    assert bpy.ops.dancing_points.synthesize(take=take.name, model_dir=MODELS) == {'FINISHED'}
    (pred,) = [o for o in scene.objects if o.get("dp_method") == "predictions"]
    stored = _stored(pred, "dp_predictions", (-1, 6, FUTURE, 3))
    f0 = take.dancing_points.frame_start
    for t in (20, 21):
        scene.frame_set(int(f0 + step * t))
        assert np.abs(_points(pred) - stored[t]).max() < 1e-6
    (con,) = [o for o in scene.objects if o.get("dp_method") == "contacts"]
    assert con["dp_frame_step"] == step


# --------------------------------------------------------------------------- ghosts

@pytest.fixture(scope="module")
def short_amc(tmp_path_factory):
    if not SALSA.exists():
        pytest.skip(f"shared data not found at {SALSA}")
    from support.helpers import trim_amc
    d = tmp_path_factory.mktemp("dp_ghost")
    shutil.copy(SALSA / "60.asf", d / "60.asf")
    trim_amc(SALSA / "60_10.amc", d / "60_10.amc", 150)  # 2.5 s at 60 Hz
    return d / "60_10.amc"


def _ghost_head_error(take, ghost_arm, head_bone, frames):
    """Largest distance (m) between the ghost's head joint and the take's Head empty."""
    scene = bpy.context.scene
    f0 = take.dancing_points.frame_start
    head = [o for o in take.all_objects if o.get("dp_device") == "head"][0]
    err = 0.0
    for t in frames:
        scene.frame_set(f0 + t)
        pb = ghost_arm.pose.bones[head_bone]
        p = np.array(ghost_arm.matrix_world @ pb.head if head_bone == "Head" else ghost_arm.matrix_world @ pb.tail)
        err = max(err, float(np.linalg.norm(p - np.array(head.matrix_world.translation))))
    return err


def _import_kept(path):
    before = {c.name for c in bpy.data.collections}
    assert bpy.ops.dancing_points.import_take(filepath=str(path), keep_source=True) == {'FINISHED'}
    (take,) = [c for c in bpy.data.collections if c.name not in before]
    return take


@needs_bpy
def test_amc_ghost(short_amc):
    from support import blender_scene_util as bsu
    bsu.fresh_scene()
    plain = bpy.ops.dancing_points.import_take(filepath=str(short_amc))
    assert plain == {'FINISHED'}
    assert not any(o.get("dp_ghost") for o in bpy.data.objects)  # only when asked
    take = _import_kept(short_amc)
    ghosts = [o for o in take.all_objects if o.get("dp_ghost")]
    (arm,) = [o for o in ghosts if o.type == 'ARMATURE']
    assert any(o.type == 'MESH' and o.display_type == 'WIRE' for o in ghosts)
    assert all(o.hide_render and not o.hide_viewport for o in ghosts)  # shown, but not in final renders
    # the source body's head (end of upperneck) is the take's head point on every frame tried
    err = _ghost_head_error(take, arm, "upperneck", (0, 30, 74))
    print(f"\nAMC ghost head vs take head: {err * 1000:.2f} mm")
    assert err < 1 * CM
    s = bpy.context.scene.dancing_points_method
    s.show_ghost = False
    assert all(o.hide_viewport for o in ghosts)
    s.show_ghost = True
    assert not any(o.hide_viewport for o in ghosts) and all(o.hide_render for o in ghosts)


@needs_bpy
def test_bvh_ghost(short_amc, tmp_path):
    from support import blender_scene_util as bsu
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.formats.bvh import write_bvh
    bvh = tmp_path / "ghost.bvh"
    write_bvh(bvh, load_amc(short_amc))
    bsu.fresh_scene()
    before = set(bpy.data.objects)
    take = _import_kept(bvh)
    ghosts = [o for o in take.all_objects if o.get("dp_ghost")]
    (arm,) = [o for o in ghosts if o.type == 'ARMATURE']
    assert {o for o in bpy.data.objects if o not in before} == set(take.all_objects)  # nothing elsewhere
    assert all(o.hide_render for o in ghosts) and arm.display_type == 'WIRE'
    assert take.dancing_points.n_frames == 75 and bpy.context.scene.render.fps == 30
    # retimed to the take's 30 Hz frames and scaled like the take: its Head joint is the head empty
    err = _ghost_head_error(take, arm, "Head", (0, 30, 74))
    print(f"\nBVH ghost head vs take head: {err * 1000:.2f} mm")
    assert err < 1 * CM
