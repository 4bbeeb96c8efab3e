"""The ``stream`` and ``live`` commands (SPEC §7), registered in :mod:`..cli`.

``live`` receives, runs the duet as the samples come with a one-line status,
and at the end (Ctrl-C, SIGTERM or ``--duration`` seconds after the dancer was
first seen) writes the take (``OUT.csv``, SPEC §3) and its duet (``OUT.npz``,
SPEC §4; what ``synthesize OUT.csv`` gives) together: both or neither.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

from ..argtypes import (CLI_SIGNALS, EXIT_OK, add_audio_arguments, add_calibration_arguments, calibration_options,
                        height_metres, port_number, positive_float, printable, share, thread_count)
from ..errors import InputError, UserError
from ..formats.files import check_output_path
from . import OSC_PORT, VMC_PORT
from .senders import FOLLOW_RESTART_S, parse_sender

STATUS_EVERY_S = 0.5  # on a terminal the status line is redrawn this often
STATUS_LOG_EVERY_S = 5.0  # elsewhere a status line is printed this often


def seconds_or_zero(text: str) -> float:
    """A number of seconds, 0 or more."""
    try:
        v = float(text)
    except ValueError:
        v = -1.0
    if not (math.isfinite(v) and v >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a number of seconds, 0 or more, got {text!r}")
    return v


def sender_address(text: str) -> str:
    """``ADDR[:PORT]``, checked (:func:`.senders.parse_sender`)."""
    try:
        parse_sender(text)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text.strip()


def _default_port(fmt: str) -> int:
    return VMC_PORT if fmt == "vmc" else OSC_PORT


# --------------------------------------------------------------------------- stream

MAX_STREAM_RATE_HZ = 1000.0  # beyond any tracker's rate (72-120 Hz); a sample is a packet or four


def stream_rate(text: str) -> float:
    v = positive_float(text)
    if v > MAX_STREAM_RATE_HZ:
        raise argparse.ArgumentTypeError(f"at most {MAX_STREAM_RATE_HZ:g} samples a second, got {text!r}")
    return v


def cmd_stream(args) -> int:
    from ..inputs import load_input
    from .stream import stream_take

    take = load_input(args.input)
    port = args.port or _default_port(args.format)
    rate = f"{args.rate:g} Hz" if args.rate else "the take's rate"
    print(printable(f"streaming {args.input} to {args.host}:{port} ({args.format}, {rate}"
                    f"{', looping' if args.loop else ''}); Ctrl-C stops"), flush=True)
    res = stream_take(take, port, args.host, args.format, args.rate, args.loop, args.duration, args.drop,
                      args.seed, bundle=not args.messages, source_port=args.source_port)
    line = (f"sent {res['sent']} packets ({res['samples']} samples, {res['dropped']} dropped on purpose) "
            f"in {res['seconds']:.2f} s to {args.host}:{port} from port {res['source_port']}")
    if res["errors"]:
        line += f"; {res['errors']} sends refused by the system"
    print(printable(line), flush=True)
    if res["sent"] == 0 and res["errors"]:
        raise UserError(f"nothing could be sent to {args.host}:{port} (every send was refused: is the address "
                        f"right and reachable?)")
    return EXIT_OK


def parser_stream(sub) -> None:
    p = sub.add_parser("stream", help="replay a take in real time over UDP (VMC or OSC)",
                       description="Send a take's head and hands in real time over UDP, as the VMC protocol "
                                   "(/VMC/Ext/Hmd/Pos, /VMC/Ext/Con/Pos) or this project's OSC layout "
                                   "(/dancing_points/head, lhand, rhand; see the README), to test the live "
                                   "receiver or drive it without a headset.")
    p.add_argument("input", metavar="TAKE", help="take file (.csv), BVH or CMU AMC file")
    p.add_argument("--port", type=port_number, default=None, metavar="P",
                   help=f"UDP port to send to (default {VMC_PORT} for vmc, {OSC_PORT} for osc)")
    p.add_argument("--host", default="127.0.0.1", metavar="ADDR", help="where to send (default 127.0.0.1)")
    p.add_argument("--format", choices=("vmc", "osc"), default="vmc", help="the layout (default vmc)")
    p.add_argument("--rate", type=stream_rate, default=None, metavar="HZ",
                   help=f"send the take resampled to HZ samples a second, at most {MAX_STREAM_RATE_HZ:g} "
                        f"(default: its own rows and times)")
    p.add_argument("--source-port", type=port_number, default=None, metavar="P",
                   help="send from this UDP port (default: any free one; the receiver's --sender ADDR:PORT names it)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C or --duration")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--drop", type=share, default=0.0, metavar="P",
                   help="leave out this share of the packets on purpose (a lossy network; default 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of --drop's choice (default 0)")
    p.add_argument("--messages", action="store_true",
                   help="osc: one message per device instead of one bundle per sample")
    p.set_defaults(func=cmd_stream)


# --------------------------------------------------------------------------- live

def _outputs(out):
    check_output_path(out)
    base, ext = os.path.splitext(out)
    if ext.lower() != ".npz":
        raise InputError(out, "output must end in .npz (the take is written beside it as .csv)")
    csv = base + ".csv"
    check_output_path(csv)
    return out, csv


def cmd_live(args) -> int:
    from ..formats.files import atomic_outputs, write_npz
    from ..formats.take import take_to_text
    from ..nets import check_models
    from .protocol import decoder_for
    from .receiver import Counters, UdpReceiver
    from .senders import SenderGate
    from .session import LiveSession
    from .options import LiveOptions, ignored_senders_text

    out, csv = _outputs(args.output)
    if args.audio:  # the song the dancer dances to: read once, before anything listens
        from ..audio import read_song
        read_song(args.audio)
    want = parse_sender(args.sender) if args.sender else None
    check_models(args.models, args.threads, args.role or "leader")
    port = args.port or _default_port(args.format)
    cal = calibration_options(args)
    options = LiveOptions(source=args.format, height=args.height, floor_y=cal["floor_y"], devices=cal["devices"],
                          head_offset=cal["head_offset"], hand_offset=cal["hand_offset"],
                          head_turn=cal["head_turn"], hand_turn=cal["hand_turn"],
                          role=args.role,  # None: the stream's role, else leader (the session checks both)
                          models=args.models, threads=args.threads, follow_devices=cal["follow_devices"])
    counters = Counters()
    sink = []  # the session, once its networks are loaded (the port is taken first: a clear error at once)
    gate = SenderGate(lambda: decoder_for(args.format, args.left, args.right), lambda s: sink[0].put(s), counters,
                      want=want, follow_s=args.follow_restart)
    rx = UdpReceiver(gate, port, args.bind)
    rx.open()
    try:
        session = LiveSession(options, counters=counters, describe=f"{args.format} :{rx.port} ")
    except BaseException:
        rx.stop()
        raise
    session.gate = gate
    sink.append(session)
    session.listen_to(rx)
    rx.start()
    session.start()
    tty = sys.stdout.isatty()
    next_log = time.perf_counter() + STATUS_LOG_EVERY_S
    warned = told = 0

    def warn(over_status: bool) -> None:  # the session's warnings and the gate's news not yet printed, a line each
        nonlocal warned, told
        for line in session.warnings[warned:]:
            print(("\r" + " " * 160 + "\r" if over_status else "") + printable(line), flush=True)
            warned += 1
        for line in gate.events[told:]:
            print(("\r" + " " * 160 + "\r" if over_status else "") + printable(line), flush=True)
            told += 1

    try:
        try:
            # (within the try: a signal that comes once this line is out ends the take as Ctrl-C does)
            ends = f"recording {args.duration:g} s" if args.duration else "Ctrl-C ends the take"
            print(printable(f"listening on UDP {args.bind}:{rx.port} ({args.format}) for "
                            f"{'the sender ' + args.sender if want else 'the first sender with a head'}; {ends}"),
                  flush=True)
            while True:
                time.sleep(0.05 if args.duration else STATUS_EVERY_S)
                for failed in (rx, session):
                    if failed.error is not None:
                        raise UserError(f"the live loop stopped: {failed.error}")
                warn(tty)
                now = time.perf_counter()
                if args.duration and session.t_first is not None and now - session.t_first >= args.duration:
                    break
                if tty:
                    print("\r" + printable(session.status_line(now))[:160].ljust(160), end="", flush=True)
                elif now >= next_log:
                    next_log = now + STATUS_LOG_EVERY_S
                    print(printable(session.status_line(now)), flush=True)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the end of the take
            CLI_SIGNALS.clear()  # handled: what fails from here on is reported as itself
        if tty:
            print()
    finally:
        rx.stop()
        session.stop()
    result = session.finish()
    warn(False)  # (a calibration made at the end)
    if result.duet is None:
        raise UserError("the recording is too short for a duet (under two 30 Hz frames)")
    if args.audio:
        from ..audio import record_song
        result.duet.song = record_song(result.take, args.audio, args.audio_offset or 0.0, csv)
    atomic_outputs([(csv, lambda f: f.write(take_to_text(result.take).encode("utf-8"))),
                    (out, lambda f: write_npz(f, result.duet.arrays()))], "wb")
    c = result.counters
    take = result.take
    ignored = gate.ignored()
    print(printable(f"received {c['datagrams']} packets: used {c['used']}, late {c['late']}, malformed "
                    f"{c['malformed']}, ignored {c['ignored']}, from other senders {c['others']}; "
                    f"lost on the way {c['lost']} samples"))
    print(printable(f"the take is the sender {gate.sender()}'s" + (f"; {ignored_senders_text(ignored)}:"
                                                                   if ignored else "; no other sender")))
    for name, packets in ignored:
        print(printable(f"  ignored sender {name}: {packets} packets"))
    med, p99 = result.latency_ms
    smed, sp99 = result.steady_ms
    print(printable(f"latency from a packet's arrival to its duet frame: median {med:.2f} ms, "
                    f"99th percentile {p99:.2f} ms; after the calibration's catch-up: median {smed:.2f} ms, "
                    f"99th percentile {sp99:.2f} ms"))
    print(printable(f"{result.duet.calibration.describe()}"))
    span = float(take.time[-1])
    print(printable(f"wrote {csv} ({take.n_frames} rows, {span:.2f} s, "
                    f"{(take.n_frames - 1) / span if span > 0 else 0.0:.0f} samples a second) and {out} "
                    f"({result.duet.n_frames} frames at 30 Hz)"))
    return EXIT_OK


def parser_live(sub) -> None:
    p = sub.add_parser("live", help="receive a live stream (VMC or OSC), synthesise the duet as it comes",
                       description="Receive a dancer's head and hands over UDP (the VMC protocol, e.g. from "
                                   "VirtualMotionCapture or SlimeVR, or this project's OSC layout), run the duet "
                                   "live with a one-line status, and at the end (Ctrl-C, or --duration) write the "
                                   "recorded take beside the output (OUT.csv) and the duet (OUT.npz), the one "
                                   "'synthesize OUT.csv' gives.")
    p.add_argument("-o", "--output", required=True, metavar="OUT.npz",
                   help="the duet (SPEC §4); the take is written beside it as OUT.csv (both replaced, both or "
                        "neither)")
    p.add_argument("--port", type=port_number, default=None, metavar="P",
                   help=f"UDP port to receive on (default {VMC_PORT} for vmc, {OSC_PORT} for osc)")
    p.add_argument("--bind", default="0.0.0.0", metavar="ADDR",
                   help="the address to receive on (default 0.0.0.0: every network; 127.0.0.1: this machine only)")
    p.add_argument("--format", choices=("vmc", "osc"), default="vmc", help="the layout (default vmc)")
    p.add_argument("--sender", type=sender_address, default=None, metavar="ADDR[:PORT]",
                   help="take only this sender's samples (default: the first sender whose samples carry a head); "
                        "every other sender is ignored and named with its packet count")
    p.add_argument("--follow-restart", type=seconds_or_zero, default=FOLLOW_RESTART_S, metavar="S",
                   help=f"when the sender has been silent S seconds, follow it to another port of its address "
                        f"(it started again; vmc: with the same head serial); 0: never (default "
                        f"{FOLLOW_RESTART_S:g})")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="end the take S seconds after the dancer is first seen (default: at Ctrl-C)")
    p.add_argument("--height", type=height_metres, default=None, metavar="H",
                   help="the dancer's standing height in metres (default: the stream's height_m, else estimated "
                        "from the first second, before the duet starts)")
    p.add_argument("--left", default=None, metavar="SERIAL", help="vmc: the serial of the left-hand controller "
                   "or tracker (default: a serial named left, else the controller on the head's left)")
    p.add_argument("--right", default=None, metavar="SERIAL", help="vmc: the serial of the right hand")
    p.add_argument("--threads", type=thread_count, default=1, metavar="N", help="onnxruntime threads (default 1)")
    p.add_argument("--models", default=None, metavar="DIR",
                   help="folder with the ONNX models (default: $DP_MODEL_DIR, else the bundled models/)")
    add_calibration_arguments(p)
    add_audio_arguments(p, live=True)
    p.set_defaults(func=cmd_live)
