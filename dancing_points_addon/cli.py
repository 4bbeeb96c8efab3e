"""Command line (SPEC §7): ``python -m dancing_points_addon <command> ...``.

Each subcommand is one ``cmd_<name>(args) -> int`` function plus one
``_parser_<name>(subparsers)`` block registered in :data:`PARSERS`. The option
types and the one-line parser are :mod:`.argtypes` (shared with :mod:`.batch`,
whose options the ``batch`` subcommand takes).

Errors never show a traceback: bad input (an :class:`InputError`, a bad option,
missing or damaged models) prints one line ``error: <file>:<line>: <what>`` on
stderr and exits with 2; an unexpected failure prints one line and exits with 1
(``DP_DEBUG=1`` shows the traceback). Ctrl-C exits with 130, SIGTERM with 143,
both after removing the temporary file being written.

Outputs: ``extract`` and ``synthesize`` replace an existing output file (never
their input: an output that is the input file is refused). They are written
atomically, so nothing half-written is ever left at an output path and an
existing file survives a failed run; ``synthesize -o OUT.bvh``'s two files
(``OUT_leader.bvh``, ``OUT_follower.bvh``) are replaced both or neither.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading

from .argtypes import (CLI_SIGNALS, EXIT_OK, Parser, Terminated, add_audio_arguments, add_calibration_arguments,
                       after_imports, calibration_options, exit_for, height_metres, offset_metres, positive_float,
                       positive_int, printable, thread_count)
from .errors import InputError
from .formats.files import check_output_path
from .live.cli import parser_live, parser_stream



# --------------------------------------------------------------------------- shared options

def add_input_arguments(p: argparse.ArgumentParser) -> None:
    """INPUT and the options every input-reading command takes (SPEC §7)."""
    p.add_argument("input", metavar="INPUT",
                   help="take file (.csv), BVH file (.bvh), CMU AMC file (.amc) or FBX file (.fbx, read by "
                        "Blender's importer: needs the bpy module)")
    p.add_argument("--input-fps", type=positive_float, default=None, metavar="F",
                   help="override the input's frame rate (for a .csv: ignore its time "
                        "column and use t0 + k/F)")
    p.add_argument("--asf", default=None, metavar="PATH",
                   help="ASF skeleton of an AMC input (default: found beside it)")
    p.add_argument("--height", type=height_metres, default=None, metavar="H",
                   help="the tracked dancer's standing height in metres (stored as height_m; default: the "
                        "take's, else estimated from the take)")


def check_not_input(args, outputs) -> None:
    """Refuse (before any work) an output that is one of the command's input
    files (the same file, also through a link): it would be overwritten."""
    from .formats.files import same_file

    inputs = [args.input] + ([args.asf] if getattr(args, "asf", None) else [])
    for out in outputs:
        if not os.path.lexists(out):
            continue
        for inp in inputs:
            if os.path.lexists(inp) and same_file(out, inp):
                raise InputError(out, f"this output is the input file {inp}: it would be overwritten; "
                                      f"choose another output path")


def warn(text) -> None:
    """One warning line on stderr."""
    print(printable("warning: " + text), file=sys.stderr, flush=True)


def song_from_args(take, args):
    """The take's song (``--audio``/``--audio-offset``, else its metadata), analysed;
    said on one line. A ``--audio`` that cannot be read is an :class:`InputError`,
    one named by the take a warning."""
    from .audio import take_song

    song = take_song(take, getattr(args, "audio", None), getattr(args, "audio_offset", None), warn=warn)
    if song is not None:
        print(printable(f"song {song.path}: {song.duration_s:.1f} s, {song.tempo_bpm:.1f} bpm, "
                        f"{len(song.beats)} beats, offset {song.offset_s:g} s"))
    return song


def load_input_from_args(args):
    from .inputs import load_input
    return load_input(args.input, asf=args.asf, input_fps=args.input_fps, height=args.height,
                      role=getattr(args, "role", None))


# --------------------------------------------------------------------------- extract

def cmd_extract(args) -> int:
    from .formats.take import write_take

    check_output_path(args.output)
    if os.path.splitext(args.output)[1].lower() != ".csv":
        raise InputError(args.output, "output must end in .csv (a take file, SPEC §3)")
    check_not_input(args, [args.output])
    if args.devices == "openxr":
        from .formats.devices import offsets_for
        from .inputs import load_headset_input

        offsets = offsets_for({}, args.head_offset, args.hand_offset)
        take = load_headset_input(args.input, asf=args.asf, input_fps=args.input_fps, height=args.height,
                                  role=getattr(args, "role", None),
                                  offsets=offsets)
    else:
        take = load_input_from_args(args)
        if args.devices == "joints" and take.meta.get("devices") == "openxr":
            take = _joints_take(take, args)
    if args.role:
        take.meta["role"] = args.role
    if take.meta.get("audio"):  # the song stays the same file, named relative to the new take
        from .audio import song_reference, take_song_path
        take.meta["audio"] = song_reference(take_song_path(take), args.output)
    write_take(args.output, take)
    dur = float(take.time[-1] - take.time[0])
    rate = (take.n_frames - 1) / dur if dur > 0 else float("nan")
    print(printable(f"wrote {args.output}: {take.n_frames} rows, {dur:.2f} s, {rate:.1f} Hz"))
    return EXIT_OK


def _joints_take(take, args):
    """A headset's take (``devices=openxr``) as the SPEC §2 points it gives
    (``devices=joints``): the body offsets (the take's, or the options') at the
    wearer's height (given, the take's, else estimated)."""
    from .calibration import calibrate
    from .formats.devices import openxr_to_points
    from .formats.take import Take

    calib = calibrate(take, height=args.height, devices="openxr", head_offset=args.head_offset,
                      hand_offset=args.hand_offset)
    pos, quats = openxr_to_points(take.positions, take.quats, calib.offsets.at(calib.height))
    meta = {k: v for k, v in take.meta.items() if not k.endswith("_offset_m")}
    meta["devices"] = "joints"
    return Take(take.time, pos, quats, meta, take.source)


def _parser_extract(sub) -> None:
    p = sub.add_parser("extract", help="full-body motion -> three-point take at the source rate",
                       description="Write the three-point take (SPEC §3) of a motion file: "
                                   "head and wrist positions, head-device and wrist orientations, "
                                   "at the input's own frame rate.")
    add_input_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="TAKE.csv",
                   help="output take file (an existing file is replaced; never the input)")
    p.add_argument("--devices", choices=("joints", "openxr"), default=None,
                   help="joints: the SPEC §2 points (default for a motion file; a headset's take is turned "
                        "into them with its body offsets); openxr: as a headset and two controllers record "
                        "the dancer (view pose, grip poses), placed with the body offsets below; default for a "
                        "take: its own devices")
    p.add_argument("--role", choices=("leader", "follower"), default=None,
                   help="whose part the dancer dances (SPEC §3 role, written to the take; default: the "
                        "input take's, else none: leader)")
    p.add_argument("--head-offset", type=offset_metres, default=None, metavar="X,Y,Z",
                   help="openxr: the base of the skull from the view pose (default: 0,-0.075,0.08 for a 1.70 m "
                        "dancer, scaled)")
    p.add_argument("--hand-offset", type=offset_metres, default=None, metavar="X,Y,Z",
                   help="openxr: the left wrist from its grip pose, the right's mirrored (default: "
                        "-0.025,0.07,0 for a 1.70 m dancer, scaled)")
    p.set_defaults(func=cmd_extract)


# --------------------------------------------------------------------------- synthesize

def cmd_synthesize(args) -> int:
    import time

    from .nets import check_models
    from .duet import duet_motions, save_npz
    from .runtime import Synthesizer
    from .synthesis_options import SynthesisOptions

    out = args.output
    check_output_path(out)
    base, ext = os.path.splitext(out)
    ext = ext.lower()
    if ext not in (".npz", ".bvh"):
        raise InputError(out, "output must end in .npz or .bvh")
    outputs = [out] if ext == ".npz" else [f"{base}_{r}.bvh" for r in ("leader", "follower")]
    for path in outputs:
        check_output_path(path)
    check_not_input(args, outputs)
    if args.audio:
        from .audio import check_song_file
        check_song_file(args.audio)  # before the take's work
    take = load_input_from_args(args)
    t0 = time.perf_counter()
    song = song_from_args(take, args)
    role = args.role or take.meta.get("role") or "leader"
    check_models(args.models, args.threads, role)  # --models, else $DP_MODEL_DIR, else the bundled ones
    synth = Synthesizer(SynthesisOptions(models=args.models, threads=args.threads, height=args.height or take.height,
                                         foot_lock=not args.no_foot_lock, hand_ik=not args.no_hand_ik,
                                         **calibration_options(args)))
    duet = synth.synthesize(take)
    duet.song = song
    print(printable(f"{take.source}: {duet.calibration.describe()}"))
    if duet.calibration.notice():
        warn(f"{take.source}: {duet.calibration.notice()}")
    if ext == ".npz":
        save_npz(duet, out)
    else:
        from .formats.bvh import bvh_text
        from .formats.files import atomic_outputs

        motions = duet_motions(duet)
        # both or neither: never one dancer without the other, nor a new leader beside an old follower
        atomic_outputs([(path, lambda f, m=motions[role]: f.write(bvh_text(m)))
                        for path, role in zip(outputs, ("leader", "follower"))], "w", newline="\n")
    dt = time.perf_counter() - t0
    print(printable(f"wrote {', '.join(outputs)}: {duet.n_frames} frames at 30 Hz, "
                    f"{duet.n_frames / 30.0:.1f} s of duet in {dt:.2f} s"))
    return EXIT_OK


def _parser_synthesize(sub) -> None:
    p = sub.add_parser("synthesize", help="three-point take (or full-body motion) -> leader + follower duet",
                       description="Synthesise both dancers' full-body motion at 30 Hz from the leader's "
                                   "three points. OUT.npz: SPEC §4 arrays; OUT.bvh: writes OUT_leader.bvh "
                                   "and OUT_follower.bvh on the CMU skeleton (Y up, metres).")
    add_input_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.npz|OUT.bvh",
                   help="output file (existing files are replaced, the two BVH files both or neither; "
                        "never the input)")
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="onnxruntime threads (default 1, at most 64)")
    p.add_argument("--models", default=None, metavar="DIR",
                   help="folder with the ONNX models (default: $DP_MODEL_DIR, else the bundled models/)")
    p.add_argument("--no-foot-lock", action="store_true", help="turn contact-based foot locking off")
    p.add_argument("--no-hand-ik", action="store_true",
                   help="leave the tracked dancer's head and wrists where the network puts them (no IK onto the "
                        "input)")
    add_calibration_arguments(p)
    add_audio_arguments(p)
    p.set_defaults(func=cmd_synthesize)


# --------------------------------------------------------------------------- benchmark

def cmd_benchmark(args) -> int:
    from .benchmark import report, run

    res = run(frames=args.frames, threads=args.threads, model_dir=args.models,
              foot_lock=not args.no_foot_lock, hand_ik=not args.no_hand_ik, compute=args.compute)
    print(report(res))
    return EXIT_OK


def _parser_benchmark(sub) -> None:
    p = sub.add_parser("benchmark", help="per character-frame latency of the frame-by-frame loop",
                       description="Time the frame-by-frame loop on the embedded sample take (batch 1): "
                                   "median and p99 per character-frame, split into features, networks "
                                   "and pose recovery, beside the compute floor of the same weights.")
    p.add_argument("--frames", type=positive_int, default=2000, metavar="N", help="timed duet frames (default 2000)")
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="onnxruntime threads (default 1, at most 64)")
    p.add_argument("--models", default=None, metavar="DIR",
                   help="folder with the ONNX models (default: $DP_MODEL_DIR, else the bundled models/)")
    p.add_argument("--no-foot-lock", action="store_true")
    p.add_argument("--no-hand-ik", action="store_true")
    p.add_argument("--compute", choices=("float", "int8"), default="float",
                   help="how the int8 networks multiply: float (the default everywhere) or int8 (ONNX Runtime's "
                        "int8 input quantisation)")
    p.set_defaults(func=cmd_benchmark)


# --------------------------------------------------------------------------- batch

def cmd_batch(args) -> int:
    from .batch import run

    return run(args)


def _parser_batch(sub) -> None:
    from .batch import add_arguments

    p = sub.add_parser("batch", help="many takes (files or folders) -> one duet each, in parallel",
                       description="Convert every take (.csv, .bvh, .amc, .fbx; folders are searched "
                                   "recursively) to a baked duet, one output per take named after it, "
                                   "on --jobs worker processes, with a result line per file as it "
                                   "finishes (the report lists them in input order). A bad file is "
                                   "reported and skipped; the exit status is 1 if any file failed, 130 "
                                   "when interrupted (Ctrl-C: no partial outputs are left; --resume "
                                   "finishes the rest), 2 for a bad command line or when another batch "
                                   "is writing into OUT_DIR. Existing outputs are replaced only with "
                                   "--overwrite, inputs never. --format blend/fbx and --render need the "
                                   "bpy module.")
    add_arguments(p)
    p.set_defaults(func=cmd_batch)


# --------------------------------------------------------------------------- main

PARSERS = [_parser_extract, _parser_synthesize, _parser_benchmark, _parser_batch, parser_stream, parser_live]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="python -m dancing_points_addon",
                     description="Dancing Points: a salsa duet from three tracked points.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for add in PARSERS:
        add(sub)
    return parser


# SIGTERM raises Terminated, Ctrl-C KeyboardInterrupt, once any import under way has finished
_on_signal = after_imports(lambda signum: Terminated() if signum == signal.SIGTERM else KeyboardInterrupt(),
                           CLI_SIGNALS)


def _install_handlers() -> dict:
    """:func:`_on_signal` for SIGTERM and (where Python's own handler has it) SIGINT;
    the handlers replaced, to put back. Only the main thread may set them."""
    old = {}
    if threading.current_thread() is not threading.main_thread():
        return old
    for sig in (signal.SIGTERM, signal.SIGINT):
        if sig == signal.SIGINT and signal.getsignal(sig) is not signal.default_int_handler:
            continue
        with contextlib.suppress(ValueError, OSError):
            old[sig] = signal.signal(sig, _on_signal)
    return old


def main(argv=None) -> int:
    debug = os.environ.get("DP_DEBUG", "") not in ("", "0")
    CLI_SIGNALS.clear()
    old = _install_handlers()
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - one line, never a raw traceback
        if CLI_SIGNALS and not isinstance(exc, KeyboardInterrupt):  # a signal a library made its own error
            exc = Terminated() if signal.SIGTERM in CLI_SIGNALS else KeyboardInterrupt()
        return exit_for(exc, debug=debug)
    finally:
        for sig, handler in old.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
