"""Command-line conventions shared by every command: the exit statuses, the
one-line parser, the option types, :func:`printable` (file names as a terminal
may show them), :func:`exit_for` (the one line and exit status of a failed
command) and the environment that keeps numeric libraries on one thread.

Used by :mod:`.cli` (``python -m dancing_points_addon``), by :mod:`.batch` (its
options, shared by the ``batch`` subcommand and Blender's ``convert`` command)
and by the Blender side's ``convert`` command. Imports nothing of the package
but :mod:`.errors`, so that any of them can import it.
"""
from __future__ import annotations

import argparse
import math
import re
import unicodedata

from .errors import UserError, error_message, one_line
from .formats.limits import FLOOR_RANGE_M, HEIGHT_RANGE_M  # (imports no numpy)

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143
# Set to "1" before numpy loads (the benchmark, batch workers): one BLAS/OpenMP thread.
SINGLE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                     "VECLIB_MAXIMUM_THREADS")


class Terminated(KeyboardInterrupt):
    """SIGTERM: unwinds like Ctrl-C (the temporary file being written is removed)."""


# The signals the command line's handler has received (``cli.main``): a library may
# turn what the handler raised into an error of its own, which is then reported as
# the signal. A command that ends on a signal by design (``live``: the end of the
# take) clears it once it has caught the signal, so that what fails after (writing
# the take) is reported as itself.
CLI_SIGNALS: list = []


def after_imports(exception_for, received: list):
    """A signal handler that appends each signal to ``received`` and raises
    ``exception_for(signum)`` -- once any import under way has finished. Raised
    inside an import (numpy's, onnxruntime's), the exception may come back as the
    module's own ``ImportError`` (then reported as "onnxruntime is not installed")
    or with a traceback printed by the extension; so there the handler sends the
    signal to the process again in 50 ms instead. ``received`` tells a caller that
    a signal came even when a library swallowed what was raised."""
    import os
    import threading

    def handler(signum, frame):
        received.append(signum)
        f = frame
        while f is not None:
            if f.f_code.co_filename.startswith("<frozen importlib"):
                timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
                timer.daemon = True
                timer.start()
                return
            f = f.f_back
        raise exception_for(signum)

    return handler


# argparse's own matcher (``^-\d+$|^-\d*\.\d+$``), also for comma lists and exponents
_NEGATIVE_VALUES = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$")


class UsageError(UserError):
    """A bad command line (reported like bad input: one line, exit 2)."""


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are a :class:`UsageError`
    (one line) instead of the usage text and ``SystemExit``, and which takes a
    comma list that starts with a negative number (``--hand-offset -0.025,0.07,0``)
    as a value, as argparse does a single negative number."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_VALUES

    def error(self, message):  # argparse would print the usage too: keep it one line
        raise UsageError(f"{self.prog}: {message}")


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return v


def port_number(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a UDP port within 1..65535, got {text!r}")
    return v


def share(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = -1.0
    if not 0.0 <= v < 1.0:
        raise argparse.ArgumentTypeError(f"must be a share within [0, 1), got {text!r}")
    return v


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return v


MAX_THREADS = 64


def thread_count(text: str) -> int:
    """``--threads``: ONNX Runtime threads, 1 to :data:`MAX_THREADS`."""
    v = positive_int(text)
    if v > MAX_THREADS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_THREADS}, got {text!r}")
    return v


def printable(text) -> str:
    """``text`` safe to print as part of one line: control characters (newlines,
    escape codes), line and paragraph separators and undecodable bytes of a file
    name (lone surrogates) are written as Python escapes (``\\n``, ``\\x1b``,
    ``\\udcff``); everything else, accented letters included, is kept."""
    text = str(text)
    if text.isprintable():
        return text
    # (not printable but harmless: the other spaces, e.g. no-break, ideographic)
    return "".join(ch if ch.isprintable() or unicodedata.category(ch) == "Zs" else repr(ch)[1:-1]
                   for ch in text)


def height_metres(text: str) -> float:
    v = positive_float(text)
    lo, hi = HEIGHT_RANGE_M
    if not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"must be a height in metres between {lo} and {hi}, got {text!r}")
    return v


def offset_metres(text: str) -> tuple:
    """``x,y,z`` in metres (a body offset: each within half a metre)."""
    parts = text.split(",")
    try:
        v = tuple(float(p) for p in parts)
    except ValueError:
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise argparse.ArgumentTypeError(f"must be three numbers x,y,z in metres, got {text!r}")
    if max(abs(c) for c in v) > 0.5:
        raise argparse.ArgumentTypeError(f"must be within 0.5 m on each axis, got {text!r}")
    return v


def turn_quaternion(text: str) -> tuple:
    """``w,x,y,z``: a rotation quaternion (normalised; its norm within [0.5, 2])."""
    parts = text.split(",")
    try:
        q = tuple(float(p) for p in parts)
    except ValueError:
        q = ()
    if len(q) != 4 or not all(math.isfinite(c) for c in q):
        raise argparse.ArgumentTypeError(f"must be a quaternion w,x,y,z, got {text!r}")
    n = math.sqrt(sum(c * c for c in q))
    if not 0.5 <= n <= 2.0:
        raise argparse.ArgumentTypeError(f"is not a rotation (its norm {n:.3g} is not within [0.5, 2]): {text!r}")
    return tuple(c / n for c in q)


def floor_metres(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and abs(v) <= FLOOR_RANGE_M):
        raise argparse.ArgumentTypeError(f"must be a height in metres within ±{FLOOR_RANGE_M:g}, got {text!r}")
    return v


def add_calibration_arguments(p: argparse.ArgumentParser) -> None:
    """How a take is read (SPEC §3, §7): its devices, the floor, the wearer's body
    offsets, and whether the head and hands follow the devices. Each overrides
    the take's own metadata; ``--height`` is added with the input options."""
    p.add_argument("--role", choices=("leader", "follower"), default=None,
                   help="whose three points the take holds: the leader's (the follower is synthesised) or the "
                        "follower's (the leader is synthesised); default: the take's role, else leader")
    p.add_argument("--devices", choices=("joints", "openxr"), default=None,
                   help="what the take's poses are: the SPEC §2 points (joints) or a headset's view and "
                        "controllers' grip poses (openxr); default: the take's devices, else joints")
    p.add_argument("--floor-y", type=floor_metres, default=None, metavar="Y",
                   help="height of the real floor in the take's frame, metres (default: the take's floor_y, "
                        "else estimated when the height is known, else 0)")
    p.add_argument("--head-offset", type=offset_metres, default=None, metavar="X,Y,Z",
                   help="openxr: the base of the skull from the view pose, in its axes (x right, y up, "
                        "z back), metres (default: 0,-0.075,0.08 for a 1.70 m wearer, scaled)")
    p.add_argument("--hand-offset", type=offset_metres, default=None, metavar="X,Y,Z",
                   help="openxr: the left wrist from its grip pose, in the grip's axes (the right hand's is its "
                        "mirror image), metres (default: -0.025,0.07,0 for a 1.70 m wearer, scaled)")
    p.add_argument("--head-turn", type=turn_quaternion, default=None, metavar="W,X,Y,Z",
                   help="a headset whose pose is turned from SPEC §3's (worn tilted, another sender's axes): the "
                        "constant rotation in its own axes, reported = true · turn (default: the take's head_turn)")
    p.add_argument("--hand-turn", type=turn_quaternion, default=None, metavar="W,X,Y,Z",
                   help="controllers in another convention (a raw controller pose, a wrist tracker): the left "
                        "one's constant rotation in its own axes, the right one's its mirror image (default: the "
                        "take's lhand_turn, rhand_turn)")
    p.add_argument("--no-device-follow", action="store_true",
                   help="leave the head and hands turned as the network has them (default: as the devices are)")


def audio_offset_seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and abs(v) <= 3600):
        raise argparse.ArgumentTypeError(f"must be seconds within ±3600, got {text!r}")
    return v


def add_audio_arguments(p: argparse.ArgumentParser, live: bool = False) -> None:
    """The song the take was danced to (SPEC §3 ``audio``, ``audio_offset_s``; §7)."""
    what = "the take it writes records" if live else "the npz records its path, offset, beats and tempo"
    p.add_argument("--audio", default=None, metavar="FILE",
                   help=f"the song danced to (WAV, FLAC, OGG or MP3; overrides the take's audio); {what}. "
                        "The synthesis does not read it")
    p.add_argument("--audio-offset", type=audio_offset_seconds, default=None, metavar="S",
                   help="the time in the song (s) at the take's time 0 (overrides the take's audio_offset_s; "
                        "default 0)")


def calibration_options(o) -> dict:
    """The :class:`~.synthesis_options.SynthesisOptions` fields of :func:`add_calibration_arguments`'
    options (parsed arguments or a batch job's dict)."""
    get = o.get if isinstance(o, dict) else (lambda k, d=None: getattr(o, k, d))
    tup = lambda v: None if v is None else tuple(float(c) for c in v)  # noqa: E731
    return {"role": get("role"), "devices": get("devices"), "floor_y": get("floor_y"),
            "head_offset": tup(get("head_offset")), "hand_offset": tup(get("hand_offset")),
            "head_turn": tup(get("head_turn")), "hand_turn": tup(get("hand_turn")),
            "follow_devices": not get("no_device_follow", False)}


def exit_for(exc: BaseException, err=None, debug: bool = False) -> int:
    """Print the one line of a command that ended with ``exc`` on ``err``
    (stderr) and return its exit status: 2 for a :class:`UserError`, 130 for
    Ctrl-C, 143 for SIGTERM, 1 for anything unexpected (re-raised when
    ``debug``: ``DP_DEBUG=1``)."""
    import sys

    err = sys.stderr if err is None else err
    if isinstance(exc, UserError):
        if debug and not isinstance(exc, UsageError):
            raise exc
        print(printable(f"error: {error_message(exc)}"), file=err)
        return EXIT_BAD_INPUT
    if isinstance(exc, KeyboardInterrupt):
        terminated = isinstance(exc, Terminated)
        print("error: terminated" if terminated else "error: interrupted", file=err)
        return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    if debug:
        raise exc
    print(printable(f"error: internal error ({type(exc).__name__}: {one_line(exc)}); "
                    f"run with DP_DEBUG=1 for details"), file=err)
    return EXIT_FAILURE
