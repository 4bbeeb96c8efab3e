"""Make ``docs/duet_avatars.png``: the synthesised duet on the two avatars of
``../shared/assets``, rendered headless by the add-on's own preview operator.

    .venv/bin/python docs/make_duet_avatars.py [models_dir]

Run from the checkout's root (the ``bpy`` module; the extension is enabled from
a temporary user repository, as the tests do). Seconds 10-15 of CMU salsa take
60_10 as a take -> ``synthesize`` -> ``retarget_duet`` onto White_M_1_Casual
(leader) and White_F_1_Casual (follower), loaded by ``load_rig_file``; the
default bodies hidden; the scene camera turned to the avatars' centre; frame 30
rendered with ``render_preview`` (Workbench, 50 %: 960 x 540).
"""
import os
import shutil
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), ROOT]

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from ext_util import import_from_extension  # noqa: E402

SHARED = os.path.join(ROOT, "..", "shared")
FRAME = 30


def main(models=os.path.join(ROOT, "models")):
    from dancing_points_addon.formats.asf_amc import load_amc
    from dancing_points_addon.skeleton import Motion
    from dancing_points_addon.formats.take import take_from_motion, write_take

    rmod = import_from_extension("operators.retarget")
    tmp = tempfile.mkdtemp(prefix="dp_docs_")
    try:
        m = load_amc(os.path.join(SHARED, "data", "cmu_salsa", "60_10.amc"))
        i0, i1 = int(10.0 * m.fps), int(15.0 * m.fps)
        m = Motion(m.positions[i0:i1], m.rotations[i0:i1], m.fps, m.bone_vectors, m.source, dict(m.meta))
        csv = os.path.join(tmp, "salsa_5s.csv")
        write_take(csv, take_from_motion(m))
        bpy.ops.wm.read_homefile(use_empty=True)
        assert bpy.ops.dancing_points.import_take(filepath=csv) == {'FINISHED'}
        assert bpy.ops.dancing_points.synthesize(model_dir=models) == {'FINISHED'}
        duet = next(c for c in bpy.data.collections if c.dancing_points.kind == 'DUET')
        rigs = [rmod.load_rig_file(os.path.join(SHARED, "assets", f))
                for f in ("White_M_1_Casual.glb", "White_F_1_Casual.glb")]
        assert bpy.ops.dancing_points.retarget_duet(duet=duet.name, leader_target=rigs[0].name,
                                                    follower_target=rigs[1].name) == {'FINISHED'}
        rmod.hide_duet_bodies(duet)
        scene = bpy.context.scene
        scene.frame_set(FRAME)
        # aim the camera at the centre of the avatars' deformed meshes at that frame
        deps = bpy.context.evaluated_depsgraph_get()
        pts = []
        for o in scene.objects:
            if o.type == 'MESH' and o.parent in rigs:
                ev = o.evaluated_get(deps)
                mw = np.array(ev.matrix_world)
                co = np.empty(3 * len(ev.data.vertices))
                ev.data.vertices.foreach_get("co", co)
                pts.append(co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3])
        c = np.concatenate(pts).mean(0)
        cam = scene.camera
        from mathutils import Vector
        cam.rotation_mode = 'QUATERNION'
        cam.rotation_quaternion = (Vector(c.tolist()) - cam.location).to_track_quat('-Z', 'Y')
        prefix = os.path.join(tmp, "frame_")
        assert bpy.ops.dancing_points.render_preview(filepath=prefix, frame_start=FRAME, frame_end=FRAME,
                                                     resolution_percentage=50) == {'FINISHED'}
        out = os.path.join(ROOT, "docs", "duet_avatars.png")
        shutil.copyfile(prefix + "%04d.png" % FRAME, out)
        print("wrote", out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
