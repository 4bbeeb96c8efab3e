# SPDX-License-Identifier: GPL-3.0-or-later
"""Read an FBX file as a take in a ``bpy``-module process (Blender side, standalone).

``python operators/fbx_take.py INPUT.fbx OUT.npz [--input-fps F] [--role R]``: the core's
``formats.fbx.load_fbx`` runs this for ``synthesize`` and ``extract`` of an
``.fbx`` (the core never imports ``bpy``). It enables this checkout as the
extension (``batch_worker.enable_extension_in_bpy``), reads the file in an
empty scene with ``take_rig.read_rig_take`` (Blender's FBX importer; the rig's head
and wrists, exactly as *Import Dancing Points take* reads them: in a file with
several armatures, the one ``take_rig.choose_armature`` picks for ``--role``, the
take's role, else the leader's) and writes the
take's arrays to ``OUT.npz``. A bad file: one line ``error: FILE: what`` on
stderr and exit status 2; nothing written.
"""

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def main(argv) -> int:
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != HERE]
    sys.path.insert(0, ROOT)
    import argparse

    ap = argparse.ArgumentParser(prog="fbx_take.py")
    ap.add_argument("input")
    ap.add_argument("output")
    ap.add_argument("--input-fps", type=float, default=0.0)
    ap.add_argument("--role", choices=("leader", "follower"), default=None)
    args = ap.parse_args(argv)
    from dancing_points_addon.errors import error_message

    module = None
    import importlib

    try:
        import bpy
        import numpy as np

        sys.path.insert(0, HERE)
        from batch_worker import enable_extension_in_bpy

        module = enable_extension_in_bpy()
        bpy.ops.wm.read_homefile(use_empty=True)
        take_rig = importlib.import_module(module + ".operators.take_rig")
        fbx = importlib.import_module(module + ".dancing_points_addon.formats.fbx")
        check_take = importlib.import_module(module + ".dancing_points_addon.inputs").check_take
        check_rate = importlib.import_module(module + ".dancing_points_addon.formats.limits").check_rate
        path = os.path.abspath(args.input)
        fps = check_rate(path, args.input_fps) if args.input_fps > 0 else 0.0
        take = check_take(take_rig.read_rig_take(bpy.context, path, ".fbx", fps, role=args.role), path)
        tmp = args.output + ".part"
        with open(tmp, "wb") as f:
            np.savez(f, **fbx.take_arrays(take))
        os.replace(tmp, args.output)
        return 0
    except Exception as exc:  # noqa: BLE001 - one line, never a traceback
        if module is not None:  # the extension's own errors (its copy of the core)
            error_message = importlib.import_module(module + ".dancing_points_addon.errors").error_message
        if os.environ.get("DP_DEBUG", "") not in ("", "0"):
            import traceback
            traceback.print_exc()
        print("error: " + error_message(exc).replace("\n", " "), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
