"""Full-body files of other rigs against the take CSV (run by hand, with ``bpy``).

``.venv/bin/python benchmarks/eval_rig_orientations.py [--seconds 5] [--namings mixamo,unreal,rigify,asf,vrm]
[--paths cli,batch,blender] [--out DIR]``

One held-out salsa segment (the leader's test frames of take 08, SPEC §5) is
the ground truth. Its take CSV is what ``extract`` writes of it; the CSV's duet
is ``synthesize`` of that CSV (device follow on, the default). The same motion
is put on rigs named as Mixamo, Unreal, Rigify (``DEF-``), VRoid and ASF rigs
(``tests/support/rig_builder.py``), resting in a T-pose and in an A-pose, with
random bone rolls, and written with Blender's own BVH and FBX exporters
(default settings). Each file then goes through

* ``cli``: ``python -m dancing_points_addon synthesize FILE -o out.npz``;
* ``batch``: one ``batch`` run of all the files (``--format npz``);
* ``blender``: ``bpy.ops.dancing_points.import_take`` (Blender-exported BVH
  with ``axis_up='Z'``, ``axis_forward='Y'``), its take synthesised.

Printed per file and path: the duet's distance from the CSV's duet (mean over
frames: the leader over all joints, his elbows, the follower over all joints;
mm) and the read orientations' angle from the CSV take's (mean over frames;
head, left hand, right hand; degrees; ``cli``/``batch``: the core reader's
take, ``blender``: the import's).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import numpy as np  # noqa: E402

MM = 1e-3
ELBOWS = ("lhumerus", "rhumerus")


def _duet_diff(leader, follower, ref):
    from dancing_points_addon.skeleton import JOINT_INDEX

    n = min(len(leader), len(ref["leader"]))
    dl = np.linalg.norm(leader[:n] - ref["leader"][:n], axis=-1)
    df = np.linalg.norm(follower[:n] - ref["follower"][:n], axis=-1)
    el = [JOINT_INDEX[e] for e in ELBOWS]
    return {"leader": float(dl.mean()) / MM, "elbows": float(dl[:, el].mean()) / MM,
            "follower": float(df.mean()) / MM}


def _angles(take, ref_take):
    from support.helpers import quat_angle_deg

    n = min(take.n_frames, ref_take.n_frames)
    return [float(x) for x in quat_angle_deg(take.quats[:n], ref_take.quats[:n]).mean(0)]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--namings", default="mixamo,unreal,rigify,asf,vrm")
    ap.add_argument("--poses", default="T,A")
    ap.add_argument("--exts", default="bvh,fbx")
    ap.add_argument("--paths", default="cli,batch,blender")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    import bpy
    from support import blender_scene_util as bsu
    from support.ext_util import import_from_extension
    from support.helpers import cut
    from support.rig_builder import build_rig, export_rig
    from dancing_points_addon.inputs import load_input
    from dancing_points_addon.formats.take import take_from_motion, write_take
    from dancing_points_addon.formats.take_read import read_take
    from dancing_points_addon.runtime import Synthesizer
    from dancing_points_addon.synthesis_options import SynthesisOptions
    from training.evaluate import test_segments

    models = os.environ.get("DP_MODEL_DIR") or str(ROOT / "models")
    shared = pathlib.Path(os.environ.get("DP_SHARED", ROOT.parent / "shared"))
    out = pathlib.Path(args.out or tempfile.mkdtemp(prefix="dp-rig-eval-"))
    out.mkdir(parents=True, exist_ok=True)
    seg = next(test_segments(str(shared / "data" / "cmu_salsa"), ("08",)))
    motion = cut(seg["lead60"], 0, int(round(args.seconds * seg["lead60"].fps)))
    take = take_from_motion(motion)
    write_take(out / "take.csv", take)
    csv = read_take(out / "take.csv")
    duet = Synthesizer(SynthesisOptions(models=models)).synthesize(csv)
    ref = {"leader": duet.leader_positions, "follower": duet.follower_positions}

    files = []
    for naming in args.namings.split(","):
        for pose in args.poses.split(","):
            for ext in args.exts.split(","):
                bsu.fresh_scene()
                arm = build_rig(motion, naming, pose, roll_seed=len(files) + 1)
                path = out / f"{naming}_{pose}_{ext}.{ext}"
                export_rig(arm, path)
                files.append((naming, pose, ext, path))
    rows = {}
    paths = args.paths.split(",")
    for naming, pose, ext, path in files:
        key = path.stem
        rows[key] = {"naming": naming, "pose": pose, "ext": ext}
        t0 = time.time()
        core = load_input(str(path))
        rows[key]["read"] = _angles(core, csv)
        rows[key]["read_orientations"] = core.meta.get("orientations", "")
        if "cli" in paths:
            res = subprocess.run([sys.executable, "-m", "dancing_points_addon", "synthesize", str(path), "-o",
                                  str(out / (key + "_cli.npz")), "--models", models], cwd=ROOT, capture_output=True,
                                 text=True)
            assert res.returncode == 0, res.stderr
            with np.load(out / (key + "_cli.npz")) as z:
                rows[key]["cli"] = _duet_diff(z["leader_positions"], z["follower_positions"], ref)
        if "blender" in paths:
            take_collection = import_from_extension("operators.take_collection")
            bsu.fresh_scene()
            kw = dict(axis_up='Z', axis_forward='Y') if ext == "bvh" else {}
            assert bpy.ops.dancing_points.import_take(filepath=str(path), **kw) == {'FINISHED'}
            coll = next(c for c in bpy.data.collections if c.dancing_points.kind == 'TAKE')
            btake = take_collection.take_from_collection(bpy.context, coll)
            bduet = Synthesizer(SynthesisOptions(models=models, height=btake.height)).synthesize(btake)
            rows[key]["blender"] = _duet_diff(bduet.leader_positions, bduet.follower_positions, ref)
            take_rig = import_from_extension("operators.take_rig")
            bsu.fresh_scene()
            rows[key]["blender_read"] = _angles(take_rig.read_rig_take(bpy.context, str(path), "." + ext, **kw), csv)
        print(key, json.dumps(rows[key]), f"({time.time() - t0:.0f} s)", flush=True)
    if "batch" in paths:
        bout = out / "batch"
        res = subprocess.run([sys.executable, "-m", "dancing_points_addon", "batch", *[str(f[3]) for f in files],
                              "-o", str(bout), "--format", "npz", "--jobs", "2", "--models", models, "--no-progress"],
                             cwd=ROOT, capture_output=True, text=True)
        assert res.returncode == 0, res.stderr[-3000:]
        for _, _, _, path in files:
            found = sorted(bout.rglob(path.stem + "*.npz"))
            with np.load(found[0]) as z:
                rows[path.stem]["batch"] = _duet_diff(z["leader_positions"], z["follower_positions"], ref)
    print(f"\nagainst the take CSV's duet (mm, mean over frames) and its orientations (deg, mean over frames); "
          f"{motion.n_frames} frames at {motion.fps:g} Hz; files in {out}")
    print(f"{'file':16s} {'path':8s} {'leader':>8s} {'elbows':>8s} {'follower':>8s}   head  lhand  rhand")
    for key, r in rows.items():
        for p in paths:
            if p not in r:
                continue
            ang = r["blender_read"] if p == "blender" else r["read"]
            d = r[p]
            print(f"{key:16s} {p:8s} {d['leader']:8.3f} {d['elbows']:8.3f} {d['follower']:8.3f}   "
                  + " ".join(f"{a:5.2f}" for a in ang))
    (out / "eval.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
