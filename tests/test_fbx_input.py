"""FBX takes everywhere a take is read, and as exact as BVH.

A held-out segment (the leader's test frames of salsa take 08, SPEC §5) is
written as a BVH and a take CSV; Blender imports the BVH and exports it with
its own FBX exporter (default settings, the rig deforming a small mesh so that
the file carries the rest pose), and with its own BVH exporter. Then:

* Blender import (*Import Dancing Points take*), ``synthesize`` and ``batch``
  of the FBX give the CSV's duet: the leader within 2 mm (mean), as Blender's
  BVH export does; with the exporter's key simplification off, within 0.01 mm
  (the import loses nothing: the millimetres are the exporter's key
  simplification, up to 0.1 % of each Euler angle);
* ``extract`` of the FBX gives the CSV's three points;
* a folder mixing ``.fbx``, ``.bvh``, ``.csv`` and ``.amc`` takes converts in one
  ``batch`` run, locally and on a Dask cluster (``--cluster local:2``);
* without the ``bpy`` module: one line saying how, before any work;
* a file with several armatures (the batch's own duet FBX: ``DP Leader`` and
  ``DP Follower``) gives the dancer of the take's role, the armature read named
  in the take; armatures that say no role are refused, one line naming them;
* the batch's duet FBX re-imported with Blender's default settings lands on the
  .blend's frames, bones where the .blend has them.

An armature that deforms no mesh is exported by Blender without its rest pose
(the pose on the export frame stands in for it): its points are read, its head
and hand orientations are not (``orientations=none``, a warning says so).
"""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from conftest import MODELS, SALSA
from support.helpers import read_report, run_batch, run_cli, run_cli_long

bpy = pytest.importorskip("bpy")

from support import blender_scene_util as bsu  # noqa: E402
from support.ext_util import import_from_extension  # noqa: E402

from dancing_points_addon.errors import InputError  # noqa: E402
from dancing_points_addon.formats.bvh import write_bvh  # noqa: E402
from dancing_points_addon.inputs import load_input  # noqa: E402
from dancing_points_addon.formats.take import take_from_motion, take_orientations_usable, write_take  # noqa: E402
from dancing_points_addon.formats.take_read import read_take  # noqa: E402
from dancing_points_addon.runtime import Synthesizer  # noqa: E402
from dancing_points_addon.synthesis_options import SynthesisOptions  # noqa: E402

MM = 1e-3
# Blender's FBX exporter simplifies the keys: the duet of its file lies a few millimetres from the
# CSV's (2.7 mm mean over the leader's joints, measured 2026-12-02; the acceptance allows 25 mm).
FBX_SIMPLIFIED = 5 * MM


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    if not SALSA.exists():
        pytest.skip("shared data not found")
    from training.evaluate import test_segments

    d = tmp_path_factory.mktemp("fbx")
    seg = next(test_segments(str(SALSA), ("08",)))
    write_bvh(d / "seg.bvh", seg["lead60"])
    take = take_from_motion(seg["lead60"])
    take.time = take.time - take.time[0]
    write_take(d / "seg.csv", take)
    bsu.fresh_scene()
    assert bpy.ops.import_anim.bvh(filepath=str(d / "seg.bvh"), update_scene_fps=True,
                                   update_scene_duration=True) == {'FINISHED'}
    arm = bpy.context.active_object
    scene = bpy.context.scene
    # Blender's own BVH export of the motion (Z up)
    assert bpy.ops.export_anim.bvh(filepath=str(d / "blender.bvh"), frame_start=scene.frame_start,
                                   frame_end=scene.frame_end) == {'FINISHED'}
    # unskinned: Blender writes no rest pose
    assert bpy.ops.export_scene.fbx(filepath=str(d / "unskinned.fbx")) == {'FINISHED'}
    bpy.ops.mesh.primitive_cube_add(size=0.1)
    cube = bpy.context.active_object
    cube.vertex_groups.new(name="Hips").add(list(range(8)), 1.0, 'REPLACE')
    cube.modifiers.new("Armature", 'ARMATURE').object = arm
    cube.parent = arm
    assert bpy.ops.export_scene.fbx(filepath=str(d / "seg.fbx")) == {'FINISHED'}  # the default settings
    assert bpy.ops.export_scene.fbx(filepath=str(d / "exact.fbx"), bake_anim_simplify_factor=0.0) == {'FINISHED'}
    ref = Synthesizer(SynthesisOptions(models=MODELS)).synthesize(read_take(d / "seg.csv"))
    return {"dir": d, "ref": ref, "take": read_take(d / "seg.csv")}


def _diff(duet, ref):
    n = min(len(duet.time), len(ref.time))
    assert abs(len(duet.time) - len(ref.time)) <= 1
    return {r: float(np.linalg.norm(getattr(duet, r + "_positions")[:n] - getattr(ref, r + "_positions")[:n],
                                    axis=-1).mean()) for r in ("leader", "follower")}


def _npz_diff(path, ref):
    with np.load(path) as z:
        n = min(len(z["time"]), len(ref.time))
        return {r: float(np.linalg.norm(z[r + "_positions"][:n] - getattr(ref, r + "_positions")[:n],
                                        axis=-1).mean()) for r in ("leader", "follower")}


def _blender_import(path, **kw):
    take_collection = import_from_extension("operators.take_collection")
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(path), **kw) == {'FINISHED'}
    coll = next(c for c in bpy.data.collections if c.dancing_points.kind == 'TAKE')
    take = take_collection.take_from_collection(bpy.context, coll)
    return take, Synthesizer(SynthesisOptions(models=MODELS, height=take.height)).synthesize(take)


def test_blender_import_of_blenders_fbx_is_as_exact_as_bvh(files):
    d, ref = files["dir"], files["ref"]
    got = {}
    for name, path, kw in (("Blender's BVH export", d / "blender.bvh", dict(axis_up='Z', axis_forward='Y')),
                           ("Blender's FBX export", d / "seg.fbx", {}),
                           ("Blender's FBX export, keys not simplified", d / "exact.fbx", {}),
                           ("Blender's FBX export of an unskinned armature", d / "unskinned.fbx", {})):
        take, duet = _blender_import(path, **kw)
        got[name] = _diff(duet, ref)
        read = import_from_extension("operators.take_io").load_any(bpy.context, str(path), **kw)
        unread = not take_orientations_usable(read.meta)
        print(f"\n{name}: leader {got[name]['leader'] / MM:.3f} mm, follower {got[name]['follower'] / MM:.3f} mm "
              f"from the CSV's duet (mean){' (orientations not read)' if unread else ''}")
        # the file's rest pose is the SPEC's (exact rotations), but for the unskinned armature's
        assert unread == ("unskinned" in name)
    assert got["Blender's FBX export"]["leader"] < FBX_SIMPLIFIED
    assert max(got["Blender's FBX export, keys not simplified"].values()) < 0.01 * MM
    assert got["Blender's BVH export"]["leader"] < 2 * MM


def test_synthesize_and_extract_of_an_fbx(files, tmp_path):
    d, ref = files["dir"], files["ref"]
    for name in ("seg.fbx", "exact.fbx"):
        out = tmp_path / (name + ".npz")
        res = run_cli_long("synthesize", d / name, "-o", out, "--models", MODELS)
        assert res.returncode == 0, res.stderr
        diff = _npz_diff(out, ref)
        print(f"\nsynthesize {name}: leader {diff['leader'] / MM:.3f} mm, follower {diff['follower'] / MM:.3f} mm")
        assert diff["leader"] < (FBX_SIMPLIFIED if name == "seg.fbx" else 0.01 * MM)
    res = run_cli("extract", d / "exact.fbx", "-o", tmp_path / "x.csv", timeout=300)
    assert res.returncode == 0, res.stderr
    back, want = read_take(tmp_path / "x.csv"), files["take"]
    assert back.n_frames == want.n_frames
    np.testing.assert_allclose(back.positions, want.positions, atol=1e-5)
    np.testing.assert_allclose(back.time, want.time, atol=1e-9)
    # a file that is not an FBX: one line naming it, nothing written
    bad = tmp_path / "bad.fbx"
    bad.write_text("not an fbx")
    res = run_cli("synthesize", bad, "-o", tmp_path / "bad.npz", timeout=300)
    assert res.returncode == 2 and not (tmp_path / "bad.npz").exists()
    assert res.stderr.strip().count("\n") == 0 and str(bad) in res.stderr and "binary FBX" in res.stderr


def test_a_folder_mixing_fbx_bvh_csv_amc_in_one_batch(files, tmp_path):
    d, ref = files["dir"], files["ref"]
    takes = tmp_path / "takes"
    takes.mkdir()
    shutil.copy(d / "seg.fbx", takes / "a.fbx")
    shutil.copy(d / "seg.bvh", takes / "b.bvh")
    shutil.copy(d / "seg.csv", takes / "c.csv")
    from support.helpers import trim_amc
    trim_amc(SALSA / "60_08.amc", takes / "d.amc", 240)
    shutil.copy(SALSA / "60.asf", takes / "d.asf")
    for extra, out in (((), tmp_path / "out"), (("--cluster", "local:2"), tmp_path / "out_cluster")):
        res = run_batch(takes, out, "npz", *extra)
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
        report = read_report(out)
        assert sorted((os.path.basename(f["input"]), f["status"]) for f in report["files"]) == [
            ("a.fbx", "ok"), ("b.bvh", "ok"), ("c.csv", "ok"), ("d.amc", "ok")]
        diff = {k: _npz_diff(out / f"{k}.npz", ref) for k in "abc"}
        print(f"\nbatch{' ' + ' '.join(extra) if extra else ''}: " + ", ".join(
            f"{k}: leader {v['leader'] / MM:.3f} mm" for k, v in diff.items()))
        assert diff["a"]["leader"] < FBX_SIMPLIFIED and diff["c"]["leader"] < 1e-6


def test_without_bpy_one_line_says_how(files, tmp_path, monkeypatch):
    import importlib.util

    from dancing_points_addon import batch
    from dancing_points_addon.formats import fbx

    monkeypatch.setattr(fbx, "bpy_available", lambda: False)
    with pytest.raises(InputError, match="install the bpy module") as exc:
        load_input(files["dir"] / "seg.fbx")
    assert str(files["dir"] / "seg.fbx") in str(exc.value)
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "bpy" else real(name, *a))
    from dancing_points_addon.argtypes import Parser

    p = Parser(prog="batch")
    batch.add_arguments(p)
    args = p.parse_args([str(files["dir"]), "-o", str(tmp_path / "out"), "--format", "npz", "--models", MODELS])
    with pytest.raises(InputError, match="FBX takes are read by Blender's importer: install the bpy module"):
        batch.run(args)
    assert not (tmp_path / "out").exists()  # checked before any work


# --------------------------------------------------------------------------- duet FBX (several armatures)

def _short_take(files, path, rows=120):
    from dancing_points_addon.formats.take import Take

    t = files["take"]
    write_take(path, Take(t.time[:rows], t.positions[:rows], t.quats[:rows], dict(t.meta), t.source))
    return read_take(path)


@pytest.fixture(scope="module")
def duet(files, tmp_path_factory):
    """A short take converted as ``batch --format blend`` and ``--format fbx`` convert it (one job)."""
    d = tmp_path_factory.mktemp("duet_fbx")
    take = _short_take(files, d / "short.csv")
    bsu.fresh_scene()
    batch_cli = import_from_extension("operators.batch_cli")
    batch_cli.convert_job({"input": str(d / "short.csv"), "options": {"models": MODELS},
                           "temps": {"blend": str(d / "duet.blend"), "fbx": str(d / "duet.fbx")}}, lambda p: None)
    scene = bpy.context.scene
    after = (scene.frame_start, scene.frame_end, _arm_probe())  # the scene after the export (a video follows it)
    bsu.fresh_scene()
    return {"dir": d, "take": take, "blend": d / "duet.blend", "fbx": d / "duet.fbx", "after": after}


def _arm_probe(frames_of=None):
    """Per armature: its action's frame range and the world heads of a few bones
    at the first, a middle and the last frame (of ``frames_of``, else its own)."""
    scene = bpy.context.scene
    out = {}
    for o in bpy.data.objects:
        if o.type != 'ARMATURE':
            continue
        f0, f1 = (int(round(x)) for x in o.animation_data.action.frame_range)
        if frames_of:
            f0, f1 = frames_of[o.name][0]
        pts = []
        for f in (f0, (f0 + f1) // 2, f1):
            scene.frame_set(f)
            pts.append([list(o.matrix_world @ o.pose.bones[b].head) for b in ("head", "lhand", "rfoot", "root")])
        out[o.name] = ((f0, f1), np.array(pts))
    return out


def test_batch_fbx_reimports_on_the_blends_frames(duet):
    bpy.ops.wm.open_mainfile(filepath=str(duet["blend"]))
    want = _arm_probe()
    assert set(want) == {"DP Leader", "DP Follower"} and want["DP Leader"][0][0] == 1, want
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.import_scene.fbx(filepath=str(duet["fbx"])) == {'FINISHED'}  # Blender's defaults
    keyed = {o.name: tuple(int(round(x)) for x in o.animation_data.action.frame_range)
             for o in bpy.data.objects if o.type == 'ARMATURE'}
    got = _arm_probe(want)
    bsu.fresh_scene()
    assert keyed == {name: rng for name, (rng, _) in want.items()}, (keyed, want)
    for name, (_, pts) in want.items():
        err = np.abs(got[name][1] - pts).max()
        assert err < 1e-4, (name, err)
    # the export leaves the scene's keys and range as they were
    f0, f1, after = duet["after"]
    assert (f0, f1) == want["DP Leader"][0]
    for name, (rng, pts) in want.items():
        assert after[name][0] == rng and np.abs(after[name][1] - pts).max() < 1e-6, name


def test_a_duet_fbx_gives_the_dancer_of_the_takes_role(duet, tmp_path):
    take_rig = import_from_extension("operators.take_rig")
    ExtInputError = import_from_extension("dancing_points_addon.errors").InputError
    take_collection = import_from_extension("operators.take_collection")
    head0 = duet["take"].positions[0, 0]
    read = {}
    for role in (None, "leader", "follower"):
        bsu.fresh_scene()
        read[role] = take_rig.read_rig_take(bpy.context, str(duet["fbx"]), ".fbx", role=role)
    assert read[None].meta["source_armature"] == read["leader"].meta["source_armature"] == "DP Leader"
    assert read[None].meta["role"] == "leader"  # the armature's, when none is asked for
    assert read["follower"].meta["source_armature"] == "DP Follower"
    # the leader's head is the take's (the duet follows the devices); the follower stands apart
    assert np.linalg.norm(read[None].positions[0, 0] - head0) < 0.05
    assert np.linalg.norm(read["follower"].positions[0, 0] - head0) > 0.5
    # named as in the file, whatever Blender renamed them to (a scene with the duet already in it)
    bpy.ops.wm.open_mainfile(filepath=str(duet["blend"]))
    again = take_rig.read_rig_take(bpy.context, str(duet["fbx"]), ".fbx", role="follower")
    assert again.meta["source_armature"] == "DP Follower"
    np.testing.assert_allclose(again.positions, read["follower"].positions, atol=1e-6)
    named = take_rig.read_rig_take(bpy.context, str(duet["fbx"]), ".fbx", armature="DP Follower")
    assert named.meta["role"] == "follower" and named.meta["source_armature"] == "DP Follower"
    with pytest.raises(ExtInputError, match=r"no armature named 'Nobody' in the file \(armatures: 'DP Follower', "
                                         r"'DP Leader'\)"):
        take_rig.read_rig_take(bpy.context, str(duet["fbx"]), ".fbx", armature="Nobody")
    # Blender's import of the take: the leader's points, marked leader
    bsu.fresh_scene()
    assert bpy.ops.dancing_points.import_take(filepath=str(duet["fbx"])) == {'FINISHED'}
    coll = bpy.context.scene.dancing_points.take
    take = take_collection.take_from_collection(bpy.context, coll)
    assert coll.dancing_points.role == "leader" and np.linalg.norm(take.positions[0, 0] - head0) < 0.05
    bsu.fresh_scene()
    # the command line reads the same armature (the standalone reader) and says which
    res = run_cli("extract", duet["fbx"], "-o", tmp_path / "x.csv", timeout=300)
    assert res.returncode == 0, res.stderr
    back = read_take(tmp_path / "x.csv")
    assert back.meta["source_armature"] == "DP Leader" and back.meta["role"] == "leader"
    np.testing.assert_allclose(back.positions, read[None].positions, atol=1e-5)
    res = run_cli("extract", duet["fbx"], "-o", tmp_path / "y.csv", "--role", "follower", timeout=300)
    assert res.returncode == 0, res.stderr
    back = read_take(tmp_path / "y.csv")  # --role picks the dancer, not only the label
    assert back.meta["source_armature"] == "DP Follower" and back.meta["role"] == "follower"
    np.testing.assert_allclose(back.positions, read["follower"].positions, atol=1e-5)


def test_several_armatures_saying_no_role_are_refused(files, tmp_path):
    take_rig = import_from_extension("operators.take_rig")
    ExtInputError = import_from_extension("dancing_points_addon.errors").InputError
    bsu.fresh_scene()
    for _ in range(2):  # two copies of one rig: "seg" and "seg.001"
        assert bpy.ops.import_anim.bvh(filepath=str(files["dir"] / "seg.bvh"), update_scene_fps=True,
                                       update_scene_duration=True) == {'FINISHED'}
    two = tmp_path / "two.fbx"
    assert bpy.ops.export_scene.fbx(filepath=str(two)) == {'FINISHED'}
    bsu.fresh_scene()
    why = (r"2 armatures have a Head bone and hand bones \('seg', 'seg\.001'\) and none is the leader's; name "
           r"the one to read in the import's Armature option, or keep only that one in the file")
    for role in (None, "follower"):
        with pytest.raises(ExtInputError, match=why.replace("leader", role or "leader")):
            take_rig.read_rig_take(bpy.context, str(two), ".fbx", role=role)
    assert not [o for o in bpy.data.objects]  # nothing left behind
    got = take_rig.read_rig_take(bpy.context, str(two), ".fbx", armature="seg.001")
    assert got.meta["source_armature"] == "seg.001" and "role" not in got.meta
    with pytest.raises(RuntimeError, match=why):
        bpy.ops.dancing_points.import_take(filepath=str(two))
    with pytest.raises(InputError, match=why) as exc:  # the command line's reader: the same line
        load_input(two)
    assert str(two) in str(exc.value) and "\n" not in str(exc.value)


def test_import_take_role_and_armature_option_pick_the_dancer(duet, capfd):
    """*Import Dancing Points take* of the duet FBX: Role (and the batch's --role)
    and the Armature option choose the dancer; the INFO line names the armature."""
    take_rig = import_from_extension("operators.take_rig")
    take_collection = import_from_extension("operators.take_collection")
    bsu.fresh_scene()
    want = {r: take_rig.read_rig_take(bpy.context, str(duet["fbx"]), ".fbx", role=r).positions[0]
            for r in ("leader", "follower")}
    for kw, role, arm in (({}, "leader", "DP Leader"), ({"role": 'follower'}, "follower", "DP Follower"),
                          ({"armature": "DP Follower"}, "follower", "DP Follower"),
                          ({"armature": "DP Leader", "role": 'follower'}, "follower", "DP Leader")):
        bsu.fresh_scene()
        capfd.readouterr()
        assert bpy.ops.dancing_points.import_take(filepath=str(duet["fbx"]), **kw) == {'FINISHED'}
        assert "30 fps, armature '{:s}')".format(arm) in capfd.readouterr().out, kw
        coll = bpy.context.scene.dancing_points.take
        take = take_collection.take_from_collection(bpy.context, coll)
        assert coll.dancing_points.role == role, kw
        np.testing.assert_allclose(take.positions[0], want["leader" if arm == "DP Leader" else "follower"],
                                   atol=1e-4, err_msg=str(kw))
    # the batch's --role: the follower's points, marked follower
    batch_cli = import_from_extension("operators.batch_cli")
    props = import_from_extension("operators.props")
    batch_cli.convert_job({"input": str(duet["fbx"]), "options": {"models": MODELS, "role": "follower"},
                           "temps": {}}, lambda p: None)
    coll = props.active_take(bpy.context)
    take = take_collection.take_from_collection(bpy.context, coll)
    assert coll.dancing_points.role == "follower"
    np.testing.assert_allclose(take.positions[0], want["follower"], atol=1e-4)
    bsu.fresh_scene()
