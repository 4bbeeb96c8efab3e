"""What a batch is asked to do: formats, input types, exit statuses, and the
options each job carries to its worker.

The parent turns the parsed command line into one plain dict, :func:`job_options`
(sent with every job, see :mod:`.messages`); a worker turns it back into
:class:`~..synthesis_options.SynthesisOptions` with :func:`synthesis_options` (the core
converter and the Blender side's ``convert_job`` alike).
"""
from __future__ import annotations

import os
import sys

from ..errors import InputError

FORMATS = ("npz", "bvh", "blend", "fbx")
BPY_FORMATS = ("blend", "fbx")  # (and --render) need Blender's bpy in the workers
CORE_INPUTS = (".csv", ".bvh", ".amc")
BPY_INPUTS = CORE_INPUTS + (".fbx",)  # every input type: an .fbx take is read by Blender in a bpy worker


def input_needs_bpy(path) -> bool:
    """Whether a take file is read through Blender (an FBX: its importer)."""
    return os.path.splitext(os.fspath(path))[1].lower() == ".fbx"


def task_needs_bpy(fmt, task) -> bool:
    """Whether a task runs in a worker with Blender's ``bpy``: a blend/fbx output,
    the preview video, or an FBX input (whatever the output format)."""
    return fmt in BPY_FORMATS or "mp4" in task.kinds or input_needs_bpy(task.input)
RIG_TYPES = (".blend", ".glb", ".gltf", ".fbx")


def default_jobs() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def resolve_model_dir(explicit=None):
    from ..nets import resolve_model_dir

    try:
        return resolve_model_dir(explicit)
    except InputError as exc:
        raise InputError(exc.path, exc.reason + "; give the folder with --models") from None


def _abs(path):
    return os.path.abspath(os.path.expanduser(path)) if path else None


def check_rigs(args, needs_bpy) -> None:
    """The ``--leader-rig`` / ``--follower-rig`` files exist, have a rig file type
    and come with an output that holds armatures (blend, fbx, --render)."""
    for opt in ("leader_rig", "follower_rig"):
        path = getattr(args, opt, None)
        if not path:
            continue
        flag = "--" + opt.replace("_", "-")
        if not os.path.isfile(os.path.expanduser(path)):
            raise InputError(path, f"no such file ({flag})")
        if os.path.splitext(path)[1].lower() not in RIG_TYPES:
            raise InputError(path, f"{flag} takes a {', '.join(RIG_TYPES)} file")
        if not needs_bpy:
            raise InputError(path, f"{flag} works with the blend and fbx formats or --render "
                                   f"(npz and bvh hold the Dancing Points skeleton only)")


def job_options(args, model_dir) -> dict:
    """The options of every job (a JSON-able dict) from the parsed command line."""
    return {"models": model_dir, "threads": int(args.threads or 1),
            "height": args.height, "input_fps": args.input_fps,
            "asf": os.path.abspath(args.asf) if args.asf else None,
            "no_foot_lock": bool(args.no_foot_lock), "no_hand_ik": bool(args.no_hand_ik),
            "role": getattr(args, "role", None), "devices": getattr(args, "devices", None),
            "floor_y": getattr(args, "floor_y", None),
            "head_offset": getattr(args, "head_offset", None), "hand_offset": getattr(args, "hand_offset", None),
            "head_turn": getattr(args, "head_turn", None), "hand_turn": getattr(args, "hand_turn", None),
            "no_device_follow": bool(getattr(args, "no_device_follow", False)),
            "audio": _abs(getattr(args, "audio", None)), "audio_offset": getattr(args, "audio_offset", None),
            "leader_rig": _abs(getattr(args, "leader_rig", None)),
            "follower_rig": _abs(getattr(args, "follower_rig", None))}


def job_song(o: dict, take):
    """The song of a job's take (``--audio``, else the take's; see :func:`..audio.take_song`);
    a song the take names that cannot be read is a warning on the worker's stderr."""
    from ..audio import take_song

    def warn(text):
        print("warning: " + text, file=sys.stderr, flush=True)

    return take_song(take, o.get("audio"), o.get("audio_offset"), warn=warn)


def synthesis_options(o: dict, take_height=None):
    """The :class:`~..synthesis_options.SynthesisOptions` of a job's options (``job_options``)."""
    from ..argtypes import calibration_options
    from ..synthesis_options import SynthesisOptions

    return SynthesisOptions(models=o["models"], threads=int(o.get("threads") or 1),
                            height=o.get("height") or take_height, foot_lock=not o.get("no_foot_lock"),
                            hand_ik=not o.get("no_hand_ik"), **calibration_options(o))
