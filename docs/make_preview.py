"""Make ``docs/preview.png`` and ``docs/preview_strip.png``: the embedded sample
take synthesised and rendered headless by the add-on's own preview operator.

    .venv/bin/python docs/make_preview.py [models_dir]

Run from the checkout's root (the ``bpy`` module; the extension is enabled from
a temporary user repository, as the tests do). The sample take
``dancing_points_addon/samples/sample_take.csv`` -> ``import_take`` ->
``synthesize`` (which builds the stage: checker floor, follow camera, and the
method view) -> ``render_preview`` (Workbench, studio look, burn-in):

- ``preview.png``: frame ``FRAME`` at 960 x 540 with the method in the render
  (``Scene.dancing_points_method.method_in_render``): the leader's three input
  points (yellow), both dancers' predicted next second of head and wrists
  (light blue: leader, light red: follower) and the foot contacts (discs);
- ``preview_strip.png``: frames ``STRIP_FRAMES`` at 480 x 270, final-render
  look (method hidden), tiled 3 x 2 with numpy (4 px white gutters) and written with bpy's image API.

Both are written as 8-bit RGB PNG.
"""
import os
import shutil
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), ROOT]

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from ext_util import import_from_extension  # noqa: E402

SAMPLE = os.path.join(ROOT, "dancing_points_addon", "samples", "sample_take.csv")
FRAME = 160  # the still (scene frame): both dancers apart, hands' predictions looping between them
STRIP_FRAMES = (40, 100, 160, 245, 300, 340)  # across the take (1-343), neither dancer hidden
STRIP_COLS = 3
GUTTER = 4  # px of white between the strip's frames


def read_png(path):
    """An image file as float RGB rows, top row first: ``(h, w, 3)``."""
    img = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = img.size
        px = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    return px.reshape(h, w, -1)[::-1, :, :3]


def write_png(path, rgb):
    """Write ``rgb (h, w, 3)`` (0..1, top row first) as an 8-bit RGB PNG."""
    h, w = rgb.shape[:2]
    img = bpy.data.images.new("dp_docs_out", w, h, alpha=False)
    try:
        px = np.ones((h, w, 4), dtype=np.float32)
        px[..., :3] = np.clip(rgb[::-1], 0.0, 1.0)
        img.pixels.foreach_set(px.ravel())
        img.filepath_raw = path
        img.file_format = 'PNG'
        img.save()
    finally:
        bpy.data.images.remove(img)
    if not os.path.isfile(path) or os.path.getsize(path) == 0:
        raise RuntimeError("not written: " + path)


def tile(images, cols, gutter=GUTTER):
    """Equal-sized ``(h, w, 3)`` images in a grid of ``cols`` columns, row by
    row, ``gutter`` white pixels between them."""
    h, w = images[0].shape[:2]
    rows = -(-len(images) // cols)
    out = np.ones((rows * h + (rows - 1) * gutter, cols * w + (cols - 1) * gutter, 3), dtype=np.float32)
    for k, img in enumerate(images):
        y, x = (k // cols) * (h + gutter), (k % cols) * (w + gutter)
        out[y:y + h, x:x + w] = img
    return out


def method_objects(scene):
    """The method view's objects (predictions, contacts, input markers)."""
    return [o for o in scene.objects if o.get("dp_method") in ("predictions", "inputs", "contacts")]


def render(tmp, frame, percentage, burn_in=True):
    prefix = os.path.join(tmp, "f{:d}_".format(percentage))
    assert bpy.ops.dancing_points.render_preview(filepath=prefix, frame_start=frame, frame_end=frame,
                                                 resolution_percentage=percentage,
                                                 burn_in=burn_in) == {'FINISHED'}
    return read_png(prefix + "%04d.png" % frame)


def main(models=os.path.join(ROOT, "models")):
    import_from_extension()
    t0 = time.perf_counter()
    tmp = tempfile.mkdtemp(prefix="dp_docs_")
    try:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        scene.render.resolution_x, scene.render.resolution_y = 1920, 1080  # 50 %: 960 x 540, 25 %: 480 x 270
        assert bpy.ops.dancing_points.import_take(filepath=SAMPLE) == {'FINISHED'}
        assert bpy.ops.dancing_points.synthesize(model_dir=models) == {'FINISHED'}
        assert all(scene.frame_start <= f <= scene.frame_end for f in (FRAME,) + STRIP_FRAMES)
        print("frames {:d}-{:d}, synthesised in {:.1f} s".format(scene.frame_start, scene.frame_end,
                                                                 time.perf_counter() - t0))
        method = scene.dancing_points_method
        # (a) the still, the method shown
        method.show_inputs = method.show_predictions = method.show_contacts = True
        method.method_in_render = True
        assert method_objects(scene) and all(not o.hide_render for o in method_objects(scene))
        out = os.path.join(ROOT, "docs", "preview.png")
        write_png(out, render(tmp, FRAME, 50))
        print("wrote", out)
        # (b) the strip, final-render look
        method.method_in_render = False
        assert all(o.hide_render for o in method_objects(scene))
        tiles = [render(tmp, f, 25) for f in STRIP_FRAMES]
        out = os.path.join(ROOT, "docs", "preview_strip.png")
        write_png(out, tile(tiles, STRIP_COLS))
        print("wrote", out)
        print("done in {:.1f} s".format(time.perf_counter() - t0))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
