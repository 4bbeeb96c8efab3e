# SPDX-License-Identifier: GPL-3.0-or-later
"""Headless batch conversion inside Blender.

``blender --background --command dancing_points convert IN... -o OUT_DIR
[--format blend|fbx|bvh|npz] [--jobs N] [--render] [--overwrite] [--resume] ...``

The command is registered with ``bpy.utils.register_cli_command`` (Blender 4.2+)
when the extension is enabled. The orchestration (file discovery, worker
processes, progress, report, atomic outputs) is the bpy-free
``dancing_points_addon.batch``; this module adds the part that needs Blender:
:func:`convert_job`, the per-file conversion a worker runs for the blend and
fbx formats and ``--render`` (import the take with
``dancing_points.import_take``, synthesise, bake as ``dancing_points.synthesize``
does, then save the .blend / export the FBX / render the preview video to the
temporary paths the parent renames into place).

Inside the Blender binary the workers are ``blender --background --command
dancing_points worker`` processes (the extension enabled from the user's
preferences, as in the parent): :func:`cli` hands :func:`convert_job` to the
core's worker loop. With the ``bpy`` module (``python -m dancing_points_addon
batch``) they are ``operators/batch_worker.py`` processes, which enable the
checkout as an extension themselves and then use :func:`convert_job` too.
"""

import contextlib
import os
import shutil
import sys

import bpy
import numpy as np

from ..dancing_points_addon import batch as core_batch
from ..dancing_points_addon.argtypes import Parser, exit_for
from ..dancing_points_addon.batch.options import synthesis_options
from ..dancing_points_addon.batch.worker import worker_main, write_duet_files
from ..dancing_points_addon.errors import UserError, error_message
from . import compat
from .batch_worker import enable_extension_in_bpy

COMMAND_ID = "dancing_points"
PROG = "blender --background --command " + COMMAND_ID

USAGE = """usage: {prog} convert IN... -o OUT_DIR [--format blend|fbx|bvh|npz] [--jobs N] [--render]
                 [--overwrite] [--resume] [--report PATH] [--models DIR] ...

Convert takes (.csv, .bvh, .amc, .fbx files, or folders searched recursively)
into baked duets, one output per take, on --jobs worker processes.
Run '{prog} convert --help' for every option.""".format(prog=PROG)

_handle = None


# --------------------------------------------------------------------------- the command

def cli(argv):
    """``blender --command dancing_points ...``: the ``convert`` subcommand (and the
    internal ``worker``). Returns the exit status."""
    argv = list(argv)
    if argv and argv[0] == "worker":  # internal: one worker process of a batch
        return worker_main(bpy_converter=convert_job)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return 0 if argv else 2
    if argv[0] != "convert":
        print("error: {:s}: unknown subcommand {!r} (expected 'convert')".format(PROG, argv[0]), file=sys.stderr)
        return 2
    parser = Parser(prog=PROG + " convert",
                    description="Convert takes into baked duets in parallel (see the batch command of "
                                "python -m dancing_points_addon).")
    core_batch.add_arguments(parser, default_format="blend")
    debug = os.environ.get("DP_DEBUG", "") not in ("", "0")
    try:
        args = parser.parse_args(argv[1:])
        binary = bpy.app.binary_path
        worker_cmd = [binary, "--background", "--command", COMMAND_ID, "worker"] if binary else None
        return core_batch.run(args, worker_cmd=worker_cmd, in_blender=True)
    except SystemExit as exc:  # --help
        return int(exc.code or 0) if isinstance(exc.code, int) else 0
    except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - one line, never a traceback
        return exit_for(exc, debug=debug)


# --------------------------------------------------------------------------- one take

def _op_error(exc, path=None):
    """The one-line message of an operator's error report (see
    :func:`~.compat.operator_error_text`), naming the take."""
    msg = compat.operator_error_text(exc)
    if path and path not in msg:
        msg = "{:s}: {:s}".format(path, msg)
    return UserError(msg)


def _fresh_scene():
    """An empty scene, the extension still enabled (``read_homefile`` keeps the preferences)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    if not hasattr(bpy.types, "DANCING_POINTS_OT_import_take"):
        enable_extension_in_bpy()
    return bpy.context


def _render_video(context, tmp, n_frames, progress, f0, f1):
    """Render the preview video into the folder ``tmp.d``, then move it to ``tmp``."""
    folder = tmp + ".d"
    os.makedirs(folder, exist_ok=True)
    done = [0]

    def on_frame(scene, *args):
        done[0] += 1
        progress(f0 + (f1 - f0) * done[0] / max(n_frames, 1))

    bpy.app.handlers.render_write.append(on_frame)
    try:
        try:
            res = bpy.ops.dancing_points.render_preview(filepath=folder + os.sep, file_format='FFMPEG')
        except RuntimeError as exc:
            raise _op_error(exc) from None
        if 'FINISHED' not in res:
            raise UserError("the preview render did not finish")
        videos = sorted(f for f in os.listdir(folder) if not f.startswith("."))
        if not videos:
            raise UserError("the preview render wrote no video")
        os.replace(os.path.join(folder, videos[0]), tmp)
    finally:
        if on_frame in bpy.app.handlers.render_write:
            bpy.app.handlers.render_write.remove(on_frame)
        shutil.rmtree(folder, ignore_errors=True)


def _retarget_onto_rigs(context, duet_coll, opts, path):
    """Import the ``--leader-rig`` / ``--follower-rig`` files and bake the duet onto
    them (``dancing_points.retarget_duet``'s path: rest alignment, proportions,
    foot locking on the rigs' legs, held hands closed); the default bodies are hidden."""
    from . import retarget

    rigs = {}
    try:
        for role in ("leader", "follower"):
            rig_path = opts.get(role + "_rig")
            if rig_path:
                rigs[role] = retarget.load_rig_file(rig_path, context)
        retarget.retarget_duet_onto(rigs.get("leader"), rigs.get("follower"), duet_coll, context,
                                    foot_lock=not opts.get("no_foot_lock"))
    except UserError as exc:
        raise UserError("{:s}: retarget: {:s}".format(path, error_message(exc))) from None


# Blender's FBX importer puts FBX time 0 on this frame by default (its Animation Offset).
FBX_IMPORT_OFFSET = 1


@contextlib.contextmanager
def _keys_shifted(scene, by):
    """Every action keyed on the scene's objects moved ``by`` frames (and the
    scene's frame range with it) for a while; the keys are put back exactly."""
    saved = []
    seen = set()
    for obj in scene.objects:
        action, slot = compat.assigned_action(obj)
        if action is None or (action, slot) in seen:
            continue
        seen.add((action, slot))
        for fc in compat.fcurves_of(action, slot):
            kp = fc.keyframe_points
            co = {}
            for attr in ("co", "handle_left", "handle_right"):
                co[attr] = np.empty(2 * len(kp), dtype=np.float32)
                kp.foreach_get(attr, co[attr])
            saved.append((fc, co))
    rng = (scene.frame_start, scene.frame_end, scene.frame_current)
    try:
        for fc, co in saved:
            for attr, arr in co.items():
                moved = arr.copy()
                moved[0::2] += by
                fc.keyframe_points.foreach_set(attr, moved)
            fc.update()
        scene.frame_start, scene.frame_end = rng[0] + by, rng[1] + by
        yield
    finally:
        for fc, co in saved:
            for attr, arr in co.items():
                fc.keyframe_points.foreach_set(attr, arr)
            fc.update()
        scene.frame_start, scene.frame_end = rng[0], rng[1]
        scene.frame_set(rng[2])


def export_fbx(context, filepath, path=None):
    """The scene's duet (armatures and bodies, not the stage) as an FBX at
    ``filepath``: one animation stack, every bone keyed on every frame. The
    exporter writes the scene's time (frame ``f`` at ``f / fps``) and Blender's
    importer adds one frame by default, so the keys are written one frame early:
    a re-import with the default settings lands on the frames of the .blend."""
    from . import stage

    scene = context.scene
    by = -FBX_IMPORT_OFFSET if scene.frame_start >= FBX_IMPORT_OFFSET else 0
    try:
        with stage.excluded(context), _keys_shifted(scene, by):  # the duet, not the preview's floor
            # the scene's one stack: per-action stacks would pair each armature with every action its bones fit
            res = bpy.ops.export_scene.fbx(
                filepath=filepath, check_existing=False, use_selection=False,
                object_types={'ARMATURE', 'MESH'}, add_leaf_bones=False, bake_anim=True,
                bake_anim_use_all_bones=True, bake_anim_use_nla_strips=False,
                bake_anim_use_all_actions=False, bake_anim_force_startend_keying=True,
                bake_anim_simplify_factor=0.0)
    except RuntimeError as exc:
        raise _op_error(exc, path) from None
    if 'FINISHED' not in res:
        raise UserError("{:s}: the FBX export failed".format(path or filepath))


def convert_job(job, progress):
    """One take of a batch in this Blender process: write the outputs of
    ``job["temps"]`` (``{kind: temporary path}``; kinds ``blend``, ``fbx``, ``mp4``,
    ``npz``, ``bvh_leader``, ``bvh_follower``). Returns ``{"frames": n}``; raises
    on a bad take (the worker reports it and removes the temporary files)."""
    from .props import active_take
    from .song import song_of
    from .synthesize import make_synthesizer
    from .take_collection import take_from_collection
    from . import bake

    path = job["input"]
    opts = job["options"]
    temps = job["temps"]
    context = _fresh_scene()
    try:
        song_opts = {"audio": opts["audio"]} if opts.get("audio") else {}
        if opts.get("audio_offset") is not None:
            song_opts["audio_offset"] = float(opts["audio_offset"])
        res = bpy.ops.dancing_points.import_take(filepath=path, input_fps=float(opts.get("input_fps") or 0.0),
                                                 height=float(opts.get("height") or 0.0),
                                                 role=opts.get("role") or 'FILE', **song_opts)
    except RuntimeError as exc:
        raise _op_error(exc, path) from None
    if 'FINISHED' not in res:
        raise UserError("{:s}: the take could not be imported".format(path))
    progress(0.1)
    coll = active_take(context)
    if coll is None:
        raise UserError("{:s}: the import made no take".format(path))
    if job.get("source"):  # a cluster worker's scratch copy: the take's Source is the client's file
        coll.dancing_points.source = job["source"]
    take = take_from_collection(context, coll)
    try:
        synth = make_synthesizer(synthesis_options(opts, take.height))
    except UserError as exc:
        raise UserError(error_message(exc)) from None
    duet = synth.synthesize(take, progress=lambda i, n: progress(0.1 + 0.6 * i / max(n, 1)))
    duet.song = song_of(coll)
    write_duet_files(temps, duet)
    if any(k in temps for k in ("blend", "fbx", "mp4")):
        duet_coll, _ = bake.bake_duet(context, duet, coll.name, coll.dancing_points.frame_start)
        if opts.get("leader_rig") or opts.get("follower_rig"):
            _retarget_onto_rigs(context, duet_coll, opts, path)
    progress(0.8)
    if "blend" in temps:
        from . import method_view
        # the .blend carries the method view (hidden in renders); the FBX and the video do not
        method = method_view.build_method_view(context, duet_coll, duet, coll, coll.dancing_points.frame_start)
        try:
            res = bpy.ops.wm.save_as_mainfile(filepath=temps["blend"], copy=True, check_existing=False)
        except RuntimeError as exc:
            raise _op_error(exc, path) from None
        finally:
            method_view.remove_method_view(method)
        if 'FINISHED' not in res:
            raise UserError("{:s}: saving the .blend failed".format(path))
    if "fbx" in temps:
        export_fbx(context, temps["fbx"], path)
    if "mp4" in temps:
        _render_video(context, temps["mp4"], duet.n_frames, progress, 0.85, 1.0)
    return {"frames": int(duet.n_frames)}


# --------------------------------------------------------------------------- registration

def register():
    global _handle
    if _handle is None and hasattr(bpy.utils, "register_cli_command"):  # Blender 4.2+
        _handle = bpy.utils.register_cli_command(COMMAND_ID, cli)


def unregister():
    global _handle
    if _handle is not None:
        bpy.utils.unregister_cli_command(_handle)
        _handle = None
