"""Command line (SPEC §7): ``python -m dancing_points_addon <command> ...``.

Each subcommand is one ``cmd_<name>(args) -> int`` function plus one
``_parser_<name>(subparsers)`` block registered in :data:`PARSERS`. The option
types and the one-line parser are :mod:`.argtypes` (shared with :mod:`.batch`,
whose options the ``batch`` subcommand takes).

Errors never show a traceback: bad input (an :class:`InputError`, a bad option)
prints one line ``error: <file>:<line>: <what>`` on stderr and exits with 2;
an unexpected failure prints one line and exits with 1 (``DP_DEBUG=1`` shows
the traceback). Outputs are written atomically, so nothing half-written is
ever left at an output path and an existing file survives a failed run.
"""
from __future__ import annotations

import argparse
import os
import sys

from .argtypes import Parser, UsageError, height_metres, positive_float, positive_int
from .errors import InputError, UserError, error_message, one_line

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT = 0, 1, 2


# --------------------------------------------------------------------------- shared options

def add_input_arguments(p: argparse.ArgumentParser) -> None:
    """INPUT and the options every input-reading command takes (SPEC §7)."""
    p.add_argument("input", metavar="INPUT",
                   help="take file (.csv), BVH file (.bvh) or CMU AMC file (.amc)")
    p.add_argument("--input-fps", type=positive_float, default=None, metavar="F",
                   help="override the input's frame rate (for a .csv: ignore its time "
                        "column and use t0 + k/F)")
    p.add_argument("--asf", default=None, metavar="PATH",
                   help="ASF skeleton of an AMC input (default: found beside it)")
    p.add_argument("--height", type=height_metres, default=None, metavar="H",
                   help="the leader's height in metres (stored as height_m)")


def check_output_path(path) -> None:
    """Fail early, before any work, when ``path`` cannot be an output file."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(path, "output folder does not exist")
    if os.path.isdir(path):
        raise InputError(path, "output path is a folder")
    if not os.access(folder, os.W_OK):
        raise InputError(path, "output folder is not writable")


def load_input_from_args(args):
    from .formats.take import load_input
    return load_input(args.input, asf=args.asf, input_fps=args.input_fps, height=args.height)


# --------------------------------------------------------------------------- extract

def cmd_extract(args) -> int:
    from .formats.take import write_take

    check_output_path(args.output)
    take = load_input_from_args(args)
    write_take(args.output, take)
    dur = float(take.time[-1] - take.time[0])
    rate = (take.n_frames - 1) / dur if dur > 0 else float("nan")
    print(f"wrote {args.output}: {take.n_frames} rows, {dur:.2f} s, {rate:.1f} Hz")
    return EXIT_OK


def _parser_extract(sub) -> None:
    p = sub.add_parser("extract", help="full-body motion -> three-point take at the source rate",
                       description="Write the three-point take (SPEC §3) of a motion file: "
                                   "head and wrist positions, head-device and wrist orientations, "
                                   "at the input's own frame rate.")
    add_input_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="TAKE.csv", help="output take file")
    p.set_defaults(func=cmd_extract)


# --------------------------------------------------------------------------- synthesize

def cmd_synthesize(args) -> int:
    import time

    from .runtime import SynthesisOptions, Synthesizer, duet_motions, save_npz

    out = args.output
    check_output_path(out)
    base, ext = os.path.splitext(out)
    ext = ext.lower()
    if ext not in (".npz", ".bvh"):
        raise InputError(out, "output must end in .npz or .bvh")
    take = load_input_from_args(args)
    t0 = time.perf_counter()
    synth = Synthesizer(SynthesisOptions(models=args.models, threads=args.threads, height=args.height or take.height,
                                         foot_lock=not args.no_foot_lock, hand_ik=not args.no_hand_ik))
    duet = synth.synthesize(take)
    if ext == ".npz":
        save_npz(duet, out)
        written = [out]
    else:
        from .formats.bvh import bvh_text
        from .formats.files import atomic_output

        written = []
        try:
            for role, motion in duet_motions(duet).items():
                path = f"{base}_{role}.bvh"
                existed = os.path.exists(path)
                with atomic_output(path, "w", newline="\n") as f:
                    f.write(bvh_text(motion))
                if not existed:
                    written.append(path)
        except BaseException:
            for path in written:  # never leave one dancer without the other
                os.remove(path)
            raise
        written = [f"{base}_{r}.bvh" for r in ("leader", "follower")]
    dt = time.perf_counter() - t0
    print(f"wrote {', '.join(written)}: {duet.n_frames} frames at 30 Hz, "
          f"{duet.n_frames / 30.0:.1f} s of duet in {dt:.2f} s")
    return EXIT_OK


def _parser_synthesize(sub) -> None:
    p = sub.add_parser("synthesize", help="three-point take (or full-body motion) -> leader + follower duet",
                       description="Synthesise both dancers' full-body motion at 30 Hz from the leader's "
                                   "three points. OUT.npz: SPEC §4 arrays; OUT.bvh: writes OUT_leader.bvh "
                                   "and OUT_follower.bvh on the CMU skeleton (Y up, metres).")
    add_input_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.npz|OUT.bvh", help="output file")
    p.add_argument("--threads", type=positive_int, default=1, metavar="N", help="onnxruntime threads (default 1)")
    p.add_argument("--models", default=None, metavar="DIR", help="folder with the ONNX models")
    p.add_argument("--no-foot-lock", action="store_true", help="turn contact-based foot locking off")
    p.add_argument("--no-hand-ik", action="store_true",
                   help="leave the leader's head and wrists where the network puts them (no IK onto the input)")
    p.set_defaults(func=cmd_synthesize)


# --------------------------------------------------------------------------- benchmark

def cmd_benchmark(args) -> int:
    from .benchmark import report, run

    res = run(frames=args.frames, threads=args.threads, model_dir=args.models,
              foot_lock=not args.no_foot_lock, hand_ik=not args.no_hand_ik)
    print(report(res))
    return EXIT_OK


def _parser_benchmark(sub) -> None:
    p = sub.add_parser("benchmark", help="per character-frame latency of the frame-by-frame loop",
                       description="Time the frame-by-frame loop on the embedded sample take (batch 1): "
                                   "median and p99 per character-frame, split into features, networks "
                                   "and pose recovery, beside the compute floor of the same weights.")
    p.add_argument("--frames", type=positive_int, default=2000, metavar="N", help="timed duet frames (default 2000)")
    p.add_argument("--threads", type=positive_int, default=1, metavar="N", help="onnxruntime threads (default 1)")
    p.add_argument("--models", default=None, metavar="DIR", help="folder with the ONNX models")
    p.add_argument("--no-foot-lock", action="store_true")
    p.add_argument("--no-hand-ik", action="store_true")
    p.set_defaults(func=cmd_benchmark)


# --------------------------------------------------------------------------- batch

def cmd_batch(args) -> int:
    from .batch import run

    return run(args)


def _parser_batch(sub) -> None:
    from .batch import add_arguments

    p = sub.add_parser("batch", help="many takes (files or folders) -> one duet each, in parallel",
                       description="Convert every take (.csv, .bvh, .amc; folders are searched "
                                   "recursively) to a baked duet, one output per take named after it, "
                                   "on --jobs worker processes. A bad file is reported and skipped; the "
                                   "exit status is 1 if any file failed, 130 when interrupted (Ctrl-C: "
                                   "no partial outputs are left; --resume finishes the rest). "
                                   "--format blend/fbx and --render need the bpy module.")
    add_arguments(p)
    p.set_defaults(func=cmd_batch)


# --------------------------------------------------------------------------- main

PARSERS = [_parser_extract, _parser_synthesize, _parser_benchmark, _parser_batch]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="python -m dancing_points_addon",
                     description="Dancing Points: a salsa duet from three tracked points.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for add in PARSERS:
        add(sub)
    return parser


def main(argv=None) -> int:
    debug = os.environ.get("DP_DEBUG", "") not in ("", "0")
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except UserError as exc:
        if debug and not isinstance(exc, UsageError):
            raise
        print(f"error: {error_message(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - never a raw traceback for users
        if debug:
            raise
        print(f"error: internal error ({type(exc).__name__}: {one_line(exc)}); "
              f"run with DP_DEBUG=1 for details", file=sys.stderr)
        return EXIT_FAILURE
