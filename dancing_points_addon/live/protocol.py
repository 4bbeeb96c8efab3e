"""The two network layouts a live stream may use, read and written with
``python-osc`` (OSC 1.0 over UDP): the VMC protocol and this project's own.

Reading is two steps. :func:`osc_messages` turns one UDP datagram into its
``(address, arguments)`` in order, nested bundles included; a bundle's time tag
is ignored (senders get it wrong, and a sample's time is its arrival). A
decoder (:class:`VmcDecoder`, :class:`OscDecoder`) then turns the messages of
one datagram into a :class:`Packet`: the device poses it carries, in motion
space (SPEC §1), and what else it says (a sample number, the sender's clock,
take metadata).

**VMC** (``/VMC/Ext/...``; VirtualMotionCapture, SlimeVR and others): the
head is ``/VMC/Ext/Hmd/Pos``, the hands ``/VMC/Ext/Con/Pos`` (trackers,
``/VMC/Ext/Tra/Pos``, only when named as a hand), each ``s serial, f px py pz
qx qy qz qw`` in Unity's left-handed Y-up metres. Mirroring z turns that into
SPEC §1's right-handed Y-up: ``(x, y, z) -> (x, y, -z)`` and ``(qx, qy, qz, qw)
-> (w=qw, x=-qx, y=-qy, z=qz)``. A Unity device looks along its local +Z;
mirrored, along −Z with +Y up and +X right: the OpenXR view convention, so a
headset's pose is SPEC §3's ``devices=openxr`` view pose as it is.
``/VMC/Ext/T`` (the sender's clock) and ``/VMC/Ext/OK`` are read;
every other address is ignored.

Which controller is which hand: a serial given as left or right
(:class:`HandAssignment`), else one whose name says ``left`` or ``right``,
else the side of the head it is on when first seen (in the head's own frame,
from its +X, the wearer's right), then kept for the stream.

**The project's own layout** (``/dancing_points/...``, documented in the
README) carries motion-space poses as a take file has them: see
:class:`OscDecoder`.
"""
from __future__ import annotations

import logging
import math
import struct

import numpy as np

from . import OSC_PORT, VMC_PORT  # noqa: F401 - (the ports, for the modules that read this one)

DEVICES = ("head", "lhand", "rhand")
MAX_DISTANCE_M = 1000.0  # SPEC §3: a position farther than 1 km is not a pose
QUAT_NORM_RANGE = (0.5, 2.0)  # SPEC §3: a quaternion whose norm is outside is not a rotation

VMC_HMD, VMC_CON, VMC_TRA = "/VMC/Ext/Hmd/Pos", "/VMC/Ext/Con/Pos", "/VMC/Ext/Tra/Pos"
VMC_TIME, VMC_OK = "/VMC/Ext/T", "/VMC/Ext/OK"
OSC_PREFIX = "/dancing_points/"
OSC_DEVICE = {OSC_PREFIX + d: i for i, d in enumerate(DEVICES)}
OSC_FRAME = OSC_PREFIX + "frame"  # ,i: the sender's sample number
OSC_META = OSC_PREFIX + "meta"  # ,ss: a take metadata key and its value
META_KEYS = ("devices", "height_m", "floor_y", "role", "head_offset_m", "lhand_offset_m", "rhand_offset_m",
             "head_turn", "lhand_turn", "rhand_turn", "orientations")
# ``/dancing_points/meta ,ss "meta_keys" "devices,height_m,..."``: the keys of the metadata a sender sends
# (``stream`` puts it in every sample), so that a receiver knows to wait for metadata lost on the way; a
# receiver that does not know it ignores it as an unknown key.
META_ANNOUNCE = "meta_keys"
HAND_SIDE_M = 0.05  # a lone controller is given a side only this far to one side of the head


class MalformedPacket(ValueError):
    """A datagram that is no OSC packet (or one ``python-osc`` cannot read)."""


class BadMessage(ValueError):
    """An OSC message at a known address whose arguments are not what it carries."""


# --------------------------------------------------------------------------- OSC packets

class _QuietPythonOsc(logging.Filter):
    """``python-osc`` logs a warning (on the root logger) for each bundle
    element or argument type it skips; a stream of bad packets would flood the
    log. Those records are dropped (the receiver counts the packets instead);
    nothing else is."""

    def filter(self, record):
        return not (record.name == "root" and record.module in ("osc_bundle", "osc_message"))


_QUIET = _QuietPythonOsc()


def _quiet_osc_logging() -> None:
    root = logging.getLogger()
    if _QUIET not in root.filters:
        root.addFilter(_QUIET)


MAX_BUNDLE_DEPTH = 16


def bundle_framing_ok(dgram: bytes, depth: int = 0) -> bool:
    """Whether each element size of a bundle (and of the bundles nested in it)
    lies within the datagram. ``python-osc`` 1.10.2 loops for ever on a
    negative size; this is checked before a bundle is handed to it (only the
    sizes: the elements themselves are ``python-osc``'s to read)."""
    if depth > MAX_BUNDLE_DEPTH or len(dgram) < 16:
        return False
    i, n = 16, len(dgram)  # "#bundle\0" and the 8-byte time tag
    while i < n:
        if i + 4 > n:
            return False
        size = struct.unpack_from(">i", dgram, i)[0]
        i += 4
        if size < 0 or i + size > n:
            return False
        if dgram.startswith(b"#bundle\x00", i) and not bundle_framing_ok(dgram[i:i + size], depth + 1):
            return False
        i += size
    return True


class _Unusual(Exception):
    """A datagram the fast reader leaves to ``python-osc``."""


_INT, _FLOAT, _DOUBLE = struct.Struct(">i"), struct.Struct(">f"), struct.Struct(">d")
_ARG_SIZE = {"i": 4, "f": 4, "d": 8}
_BUNDLE = b"#bundle\x00"


def _fast_string(d: bytes, i: int, start: int, end: int) -> tuple:
    """The string at ``i`` of the message ``d[start:end]`` and where the next
    item starts (its null, padded to 4 bytes from the message's start)."""
    j = d.find(b"\x00", i, end)
    if j < 0:
        raise _Unusual
    nxt = start + ((j - start + 4) & ~3)
    if nxt > end:
        raise _Unusual
    try:
        return d[i:j].decode("utf-8"), nxt
    except UnicodeDecodeError:
        raise _Unusual from None


_PLANS = {}  # a message's type tags -> how to read its arguments (see _plan)
_MAX_PLANS = 256  # (a fuzzing sender's odd tag strings are read without keeping their plan)


def _plan(tags: str) -> tuple:
    """The arguments of ``tags`` (``,`` then ``i f d s``) as steps: None (a
    string) or one ``struct`` for a run of numbers, read in one call."""
    plan = _PLANS.get(tags)
    if plan is not None:
        return plan
    steps, run = [], ""
    for c in tags[1:]:
        if c == "s":
            if run:
                steps.append(struct.Struct(">" + run))
                run = ""
            steps.append(None)
        elif c in _ARG_SIZE:
            run += c
        else:
            raise _Unusual
    if run:
        steps.append(struct.Struct(">" + run))
    plan = tuple(steps)
    if len(_PLANS) < _MAX_PLANS:
        _PLANS[tags] = plan
    return plan


def _fast_message(d: bytes, start: int, end: int) -> tuple:
    address, i = _fast_string(d, start, start, end)
    if i == end:
        return address, []
    if d[i:i + 1] != b",":
        raise _Unusual
    tags, i = _fast_string(d, i, start, end)
    args = []
    for step in _plan(tags):
        if step is None:
            v, i = _fast_string(d, i, start, end)
            args.append(v)
        else:
            if i + step.size > end:
                raise _Unusual
            args.extend(step.unpack_from(d, i))
            i += step.size
    return address, args


def _fast_messages(d: bytes, out: list, start: int, end: int, depth: int = 0) -> None:
    """The common datagrams (messages of ``i f d s`` arguments, bundles of
    them) read with ``struct``, as ``python-osc`` reads them; anything else
    raises :class:`_Unusual` (then ``python-osc`` reads it). ``d[start:end]``:
    the packet (a bundle's element is read in place)."""
    if d.startswith(_BUNDLE, start, end):
        if depth > MAX_BUNDLE_DEPTH or end - start < 16:
            raise _Unusual
        i = start + 16
        while i < end:
            if i + 4 > end:
                raise _Unusual
            size = _INT.unpack_from(d, i)[0]
            i += 4
            if size <= 0 or i + size > end:
                raise _Unusual
            _fast_messages(d, out, i, i + size, depth + 1)
            i += size
    elif d[start:start + 1] == b"/":
        out.append(_fast_message(d, start, end))
    else:
        raise _Unusual


def osc_messages(dgram: bytes) -> list:
    """The ``(address, arguments)`` of one datagram, in the order they were
    sent (a bundle's elements depth first; time tags ignored).
    :class:`MalformedPacket` when it is no OSC packet. The common datagrams
    are read by a small ``struct`` reader (a fifth of ``python-osc``'s time:
    a 1,000 Hz sender), the rest by ``python-osc``; both give the same."""
    out = []
    try:
        _fast_messages(dgram, out, 0, len(dgram))
        return out
    except (_Unusual, struct.error, RecursionError):
        pass
    return _python_osc_messages(dgram)


def _python_osc_messages(dgram: bytes) -> list:
    from pythonosc.osc_bundle import OscBundle
    from pythonosc.osc_message import OscMessage

    _quiet_osc_logging()
    out = []
    try:
        if OscBundle.dgram_is_bundle(dgram):
            if not bundle_framing_ok(dgram):
                raise MalformedPacket("a bundle element's size runs outside the packet")
            stack = [iter(OscBundle(dgram))]
            while stack:
                item = next(stack[-1], None)
                if item is None:
                    stack.pop()
                elif isinstance(item, OscBundle):
                    stack.append(iter(item))
                else:
                    out.append((item.address, item.params))
        elif OscMessage.dgram_is_message(dgram):
            m = OscMessage(dgram)
            out.append((m.address, m.params))
        else:
            raise MalformedPacket("not an OSC message or bundle")
    except MalformedPacket:
        raise
    except Exception as exc:  # noqa: BLE001 - python-osc's ParseError, or anything a broken packet raises
        raise MalformedPacket(f"{type(exc).__name__}: {exc}") from None
    return out


def _number(v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadMessage(f"not a number: {type(v).__name__}")
    x = float(v)
    if not math.isfinite(x):
        raise BadMessage("not a finite number")
    return x


_FLOAT_ONLY = {float}


def _numbers(vals) -> list:
    """``vals`` as floats; :class:`BadMessage` unless each is a finite number
    (floats, as OSC's ``f`` and ``d`` arrive, checked at once)."""
    vals = list(vals)
    if {*map(type, vals)} == _FLOAT_ONLY and math.isfinite(sum(vals)):
        return vals
    return [_number(v) for v in vals]


def check_pose(p, q) -> tuple:
    """``(position (3,), quaternion (4,) w,x,y,z)`` as float64 arrays, the
    quaternion normalised; :class:`BadMessage` unless SPEC §3 would read it
    (finite, within 1 km, a quaternion norm within [0.5, 2])."""
    return _pose(_numbers(p), _numbers(q))


def _pose(p, q) -> tuple:
    """:func:`check_pose` of numbers already checked finite."""
    if math.hypot(*p) > MAX_DISTANCE_M:
        raise BadMessage("position more than 1 km from the origin")
    n = math.hypot(*q)
    if not QUAT_NORM_RANGE[0] <= n <= QUAT_NORM_RANGE[1]:
        raise BadMessage(f"quaternion norm {n:.3g} not within [0.5, 2]")
    return np.array(p, dtype=np.float64), np.array(q, dtype=np.float64) / n


def unity_to_motion(p, q_xyzw) -> tuple:
    """A Unity pose (left-handed, Y up: position, quaternion x,y,z,w) in
    motion space (right-handed, Y up; quaternion w,x,y,z): z mirrored."""
    x, y, z = p
    qx, qy, qz, qw = q_xyzw
    return (x, y, -z), (qw, -qx, -qy, qz)


def motion_to_unity(p, q_wxyz) -> tuple:
    """The inverse of :func:`unity_to_motion`."""
    x, y, z = p
    w, qx, qy, qz = q_wxyz
    return (x, y, -z), (-qx, -qy, qz, w)


class Packet:
    """What one datagram (or a few loose messages taken together) says.

    ``poses``: ``{device index: (position, quaternion)}``, motion space; a
    device the sender marks as lost (NaN, our layout) has ``None``.
    ``frame``: the sender's sample number, ``clock``: the sender's time
    (``/VMC/Ext/T``), ``meta``: take metadata; ``bad``: messages at a known
    address that could not be read; ``known``: messages this layout reads."""

    __slots__ = ("poses", "frame", "clock", "meta", "bad", "known")

    def __init__(self):
        self.poses = {}
        self.frame = None
        self.clock = None
        self.meta = {}
        self.bad = 0
        self.known = 0


# --------------------------------------------------------------------------- VMC

def _right_axis(head):
    """The head's +X (the wearer's right) in motion space; ``head``: (position, quaternion)."""
    from ..rotations import quat_to_matrix

    return quat_to_matrix(np.asarray(head[1]))[:, 0]


class HandAssignment:
    """Which VMC serial is which hand (see the module docstring). ``left`` /
    ``right``: serials given by the user (then trackers may be hands too)."""

    def __init__(self, left: str | None = None, right: str | None = None):
        self.given = {s: side for s, side in ((left, 1), (right, 2)) if s}
        self.sides = dict(self.given)  # serial -> 1 (left) or 2 (right)

    def side(self, serial: str, kind: str, pos, head) -> int | None:
        """1 (left), 2 (right) or None (not a hand, or not yet known).
        ``head``: the head's (position, quaternion) in motion space, or None."""
        if serial in self.sides:
            return self.sides[serial]
        if kind != VMC_CON or self.given and len(self.given) == 2:
            return None
        taken = set(self.sides.values())
        name = serial.lower()
        guess = 1 if "left" in name else 2 if "right" in name else None
        if guess is None and head is not None:
            right = float(np.dot(_right_axis(head), np.asarray(pos) - head[0]))
            if abs(right) >= HAND_SIDE_M:
                guess = 2 if right > 0 else 1
        if guess is None or guess in taken:
            return None
        self.sides[serial] = guess
        return guess

    def pair(self, serials_pos: list, head) -> None:
        """Two unassigned controllers seen together with the head: the one more
        to the wearer's right is the right hand."""
        if head is None or len(serials_pos) != 2 or self.sides:
            return
        (s0, p0), (s1, p1) = serials_pos
        if "left" in s0.lower() + s1.lower() or "right" in s0.lower() + s1.lower():
            return
        x = _right_axis(head)
        r0, r1 = float(np.dot(x, np.asarray(p0) - head[0])), float(np.dot(x, np.asarray(p1) - head[0]))
        if r0 != r1:
            self.sides[s0], self.sides[s1] = (2, 1) if r0 > r1 else (1, 2)


class VmcDecoder:
    """VMC messages -> :class:`Packet` (see the module docstring)."""

    kind = "vmc"
    default_devices = "openxr"

    def __init__(self, left: str | None = None, right: str | None = None):
        self.hands = HandAssignment(left, right)
        self.head_serial = None
        self.head = None  # the last head pose: (position, quaternion)

    def decode(self, messages) -> Packet:
        pk = Packet()
        hands = []  # (kind, serial, p, q) of this packet's controllers and trackers
        for address, args in messages:
            try:
                if address in (VMC_HMD, VMC_CON, VMC_TRA):
                    pk.known += 1
                    if len(args) < 8 or not isinstance(args[0], str):
                        raise BadMessage(f"{address} needs a serial and 7 numbers")
                    nums = _numbers(args[1:8])
                    up, uq = unity_to_motion(nums[:3], nums[3:])
                    p, q = _pose(up, uq)
                    serial = args[0]
                    if address == VMC_HMD:
                        if self.head_serial is None:
                            self.head_serial = serial
                        if serial == self.head_serial:
                            pk.poses[0] = (p, q)
                            self.head = (p, q)
                    else:
                        hands.append((address, serial, p, q))
                elif address == VMC_TIME:
                    pk.known += 1
                    if len(args) < 1:
                        raise BadMessage("/VMC/Ext/T needs a time")
                    pk.clock = _number(args[0])
                elif address == VMC_OK:
                    pk.known += 1
                elif address == OSC_FRAME or address == OSC_META:
                    _read_extra(pk, address, args)
            except BadMessage:
                pk.bad += 1
        if hands:
            self.hands.pair([(s, p) for k, s, p, q in hands if k == VMC_CON and s not in self.hands.sides], self.head)
            for kind, serial, p, q in hands:
                side = self.hands.side(serial, kind, p, self.head)
                if side is not None:
                    pk.poses[side] = (p, q)
        return pk


def _read_extra(pk: Packet, address, args) -> None:
    """Our sample number and take metadata (also read beside VMC messages)."""
    pk.known += 1
    if address == OSC_FRAME:
        if len(args) != 1 or isinstance(args[0], bool) or not isinstance(args[0], int):
            raise BadMessage("frame needs one integer")
        pk.frame = int(args[0])
    else:
        if len(args) != 2 or not all(isinstance(a, str) for a in args):
            raise BadMessage("meta needs a key and a value (two strings)")
        key, value = args
        if (key in META_KEYS or key == META_ANNOUNCE) and len(value) <= 100 and value.isprintable():
            pk.meta[key] = value


# --------------------------------------------------------------------------- our layout

class OscDecoder:
    """This project's layout -> :class:`Packet`.

    ``/dancing_points/head``, ``/dancing_points/lhand``, ``/dancing_points/rhand``:
    seven numbers ``px py pz qw qx qy qz`` (``f`` or ``d``; motion space, as a
    take file's columns); seven NaN: that device is lost. ``/dancing_points/frame
    ,i``: the sender's sample number; ``/dancing_points/meta ,ss``: a take
    metadata key and value (``devices``, ``height_m``, ``floor_y``, ``role``,
    the offsets); ``/dancing_points/meta ,ss meta_keys devices,height_m,...``:
    the keys of the metadata the sender sends (see :data:`META_ANNOUNCE`)."""

    kind = "osc"
    default_devices = "joints"

    def decode(self, messages) -> Packet:
        pk = Packet()
        for address, args in messages:
            try:
                d = OSC_DEVICE.get(address)
                if d is not None:
                    pk.known += 1
                    if len(args) != 7:
                        raise BadMessage(f"{address} needs 7 numbers, got {len(args)}")
                    if all(isinstance(a, float) and math.isnan(a) for a in args):
                        pk.poses[d] = None
                        continue
                    pk.poses[d] = check_pose(args[:3], args[3:])
                elif address == OSC_FRAME or address == OSC_META:
                    _read_extra(pk, address, args)
            except BadMessage:
                pk.bad += 1
        return pk


def decoder_for(fmt: str, left: str | None = None, right: str | None = None):
    """The decoder of ``fmt`` (``vmc`` or ``osc``)."""
    if fmt == "vmc":
        return VmcDecoder(left, right)
    if fmt == "osc":
        return OscDecoder()
    raise ValueError(f"unknown stream format {fmt!r} (expected vmc or osc)")


# --------------------------------------------------------------------------- writing

VMC_SERIALS = ("DP_Head", "DP_LeftHand", "DP_RightHand")


def sample_datagrams(fmt: str, frame: int, clock: float, positions, quats, meta=None, bundle=True,
                     announce=None) -> list:
    """The datagrams of one sample (what ``stream`` sends): ``positions (3, 3)``,
    ``quats (3, 4)`` w,x,y,z motion space, NaN where a device is lost; ``meta``:
    take metadata to send with it; ``announce``: the metadata keys the sender
    sends (:data:`META_ANNOUNCE`), for every sample. VMC: one bundle
    (``/VMC/Ext/T``, the head, the two controllers, ``/VMC/Ext/OK``, our sample
    number; a lost device is left out). Ours: one bundle, or (``bundle=False``)
    one message each."""
    return _sample(fmt, frame, clock, device_messages(fmt, positions, quats), meta, bundle, announce)


def device_messages(fmt: str, positions, quats) -> list:
    """The messages (bytes) that carry one sample's device poses (see
    :func:`sample_datagrams`): a message's address, type tags and serial are
    written once (:func:`_device_prefixes`), its numbers packed in one call."""
    vmc = fmt == "vmc"
    if not vmc and fmt != "osc":
        raise ValueError(f"unknown stream format {fmt!r}")
    prefixes, numbers = _device_prefixes(fmt)
    out = []
    for d in range(3):
        vals = [float(v) for v in (*positions[d], *quats[d])]
        finite = all(math.isfinite(v) for v in vals)
        if vmc:
            if not finite:
                continue  # a lost device is left out
            up, uq = motion_to_unity(vals[:3], vals[3:])
            vals = [*up, *uq]
        elif not finite:
            vals = [math.nan] * 7
        out.append(prefixes[d] + numbers.pack(*vals))
    return out


_PREFIXES = {}


def _device_prefixes(fmt: str) -> tuple:
    """Per device, the bytes of its message before the numbers, and the
    ``struct`` of the numbers: what :class:`_Message` writes."""
    key = (fmt, VMC_SERIALS)
    got = _PREFIXES.get(key)
    if got is None:
        if fmt == "vmc":
            heads = [_padded(a.encode("utf-8")) + _padded(b",sfffffff") + _padded(VMC_SERIALS[d].encode("utf-8"))
                     for d, a in enumerate((VMC_HMD, VMC_CON, VMC_CON))]
            got = heads, struct.Struct(">7f")
        else:
            got = [_padded((OSC_PREFIX + n).encode("utf-8")) + _padded(b",ddddddd") for n in DEVICES], \
                struct.Struct(">7d")
        _PREFIXES[key] = got
    return got


def _sample(fmt, frame, clock, devices, meta, bundle, announce) -> list:
    msgs = []
    if announce:
        msgs.append(_Message(OSC_META, ("s", META_ANNOUNCE), ("s", ",".join(announce))).dgram)
    for k, v in reversed(list((meta or {}).items())):  # (each put first in turn: the last key first)
        msgs.append(_Message(OSC_META, ("s", str(k)), ("s", str(v))).dgram)
    if fmt == "vmc":
        msgs += [_Message(VMC_TIME, ("f", float(clock))).dgram, *devices, _Message(VMC_OK, ("i", 1)).dgram]
    else:
        msgs += devices
    number = _Message(OSC_FRAME, ("i", int(frame) & 0x7FFFFFFF)).dgram
    if fmt == "osc" and not bundle:
        # the sample number first: it opens the sample's group at the receiver
        return [number] + msgs
    msgs.append(number)
    return [_BUNDLE + _IMMEDIATELY + b"".join(_INT.pack(len(m)) + m for m in msgs)]


_IMMEDIATELY = b"\x00" * 7 + b"\x01"  # the OSC time tag "immediately" (python-osc's IMMEDIATELY)


def _padded(b: bytes) -> bytes:
    return b + b"\x00" * (4 - len(b) % 4)


class _Message:
    """One OSC message, written with ``struct`` as ``python-osc``'s builder
    writes it (``i``, ``f``, ``d``, ``s`` arguments; the tests hold them to the
    same bytes)."""

    __slots__ = ("dgram",)

    def __init__(self, address, *typed):
        parts = [_padded(address.encode("utf-8")), _padded(("," + "".join(t for t, _ in typed)).encode("ascii"))]
        for t, v in typed:
            parts.append(_padded(v.encode("utf-8")) if t == "s" else
                         (_INT if t == "i" else _FLOAT if t == "f" else _DOUBLE).pack(v))
        self.dgram = b"".join(parts)
