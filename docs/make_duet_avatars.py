"""Make ``docs/duet_avatars.png``: the synthesised duet on the two avatars of
``../shared/assets``, rendered headless by the add-on's own preview operator.

    .venv/bin/python docs/make_duet_avatars.py [models_dir]

Run from the checkout's root (the ``bpy`` module; the extension is enabled from
a temporary user repository, as the tests do). Seconds 10-15 of CMU salsa take
60_10 as a take -> ``synthesize`` -> ``retarget_duet`` onto White_M_1_Casual
(leader) and White_F_1_Casual (follower), loaded by ``load_rig_file``; the
default bodies hidden; a camera of its own ("Docs Camera", from the side the
follow camera sees the couple from) framing the avatars' deformed meshes at
frame 30 (``blender_math.frame_camera``); that frame rendered with
``render_preview`` (Workbench, 50 %: 960 x 540), written as 8-bit RGB.
"""
import os
import shutil
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), ROOT]

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Matrix  # noqa: E402

from ext_util import import_from_extension  # noqa: E402

SHARED = os.path.join(ROOT, "..", "shared")
FRAME = 30


def main(models=os.path.join(ROOT, "models")):
    from dancing_points_addon import blender_math as bm
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
        # the avatars' deformed meshes at that frame, world space
        deps = bpy.context.evaluated_depsgraph_get()
        pts = []
        for o in scene.objects:
            if o.type == 'MESH' and o.parent in rigs:
                ev = o.evaluated_get(deps)
                mw = np.array(ev.matrix_world)
                co = np.empty(3 * len(ev.data.vertices))
                ev.data.vertices.foreach_get("co", co)
                pts.append(co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3])
        pts = np.concatenate(pts)
        # the avatars' own camera (the DP Camera is keyed on its rig, framing the
        # synthesised joints): from the follow camera's side at that frame, the
        # avatars' deformed meshes framed by the add-on's framing maths
        dp_cam = scene.camera
        view = np.array(dp_cam.matrix_world.translation) - pts.mean(0)
        r = scene.render
        loc, rot = bm.frame_camera(pts, view, dp_cam.data.angle, r.resolution_x / r.resolution_y, margin=1.05)
        cam = bpy.data.objects.new("Docs Camera", dp_cam.data.copy())
        scene.collection.objects.link(cam)
        mw = np.eye(4)
        mw[:3, :3], mw[:3, 3] = rot, loc
        cam.matrix_world = Matrix(mw.tolist())
        scene.camera = cam
        prefix = os.path.join(tmp, "frame_")
        assert bpy.ops.dancing_points.render_preview(filepath=prefix, frame_start=FRAME, frame_end=FRAME,
                                                     resolution_percentage=50) == {'FINISHED'}
        out = os.path.join(ROOT, "docs", "duet_avatars.png")
        src = bpy.data.images.load(prefix + "%04d.png" % FRAME, check_existing=False)
        w, h = src.size
        px = np.empty(len(src.pixels), dtype=np.float32)
        src.pixels.foreach_get(px)
        bpy.data.images.remove(src)
        px = px.reshape(h, w, -1)
        px[..., 3] = 1.0
        img = bpy.data.images.new("dp_docs_out", w, h, alpha=False)  # 8-bit RGB
        img.pixels.foreach_set(px.ravel())
        img.filepath_raw, img.file_format = out, 'PNG'
        img.save()
        bpy.data.images.remove(img)
        print("wrote", out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
