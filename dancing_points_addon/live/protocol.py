"""The two network layouts a live stream may use, read and written with
``python-osc`` (OSC 1.0 over UDP): the VMC protocol and this project's own.

Reading is two steps. :func:`~.osc.osc_messages` turns one UDP datagram into
its ``(address, arguments)`` in order, nested bundles included; a bundle's time
tag is ignored (senders get it wrong, and a sample's time is its arrival). A
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

import math
import struct

import numpy as np

from . import OSC_PORT, VMC_PORT  # noqa: F401 - (the ports, for the modules that read this one)
from .osc import BUNDLE, IMMEDIATELY, INT32, OscMessage, padded

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


class BadMessage(ValueError):
    """An OSC message at a known address whose arguments are not what it carries."""


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
    w, x, y, z = q  # (divided as numpy would divide the array: the same doubles, one array made)
    return np.array(p, dtype=np.float64), np.array((w / n, x / n, y / n, z / n), dtype=np.float64)


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


_VMC_POSES = frozenset((VMC_HMD, VMC_CON, VMC_TRA))


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
                if address in _VMC_POSES:
                    pk.known += 1
                    if len(args) < 8 or not isinstance(args[0], str):
                        raise BadMessage(f"{address} needs a serial and 7 numbers")
                    nums = _numbers(args[1:8])
                    p, q = _pose(*unity_to_motion(nums[:3], nums[3:]))
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
    ``struct`` of the numbers: what :class:`OscMessage` writes."""
    key = (fmt, VMC_SERIALS)
    got = _PREFIXES.get(key)
    if got is None:
        if fmt == "vmc":
            heads = [padded(a.encode("utf-8")) + padded(b",sfffffff") + padded(VMC_SERIALS[d].encode("utf-8"))
                     for d, a in enumerate((VMC_HMD, VMC_CON, VMC_CON))]
            got = heads, struct.Struct(">7f")
        else:
            got = [padded((OSC_PREFIX + n).encode("utf-8")) + padded(b",ddddddd") for n in DEVICES], \
                struct.Struct(">7d")
        _PREFIXES[key] = got
    return got


def _sample(fmt, frame, clock, devices, meta, bundle, announce) -> list:
    msgs = []
    if announce:
        msgs.append(OscMessage(OSC_META, ("s", META_ANNOUNCE), ("s", ",".join(announce))).dgram)
    for k, v in reversed(list((meta or {}).items())):  # (each put first in turn: the last key first)
        msgs.append(OscMessage(OSC_META, ("s", str(k)), ("s", str(v))).dgram)
    if fmt == "vmc":
        msgs += [OscMessage(VMC_TIME, ("f", float(clock))).dgram, *devices, OscMessage(VMC_OK, ("i", 1)).dgram]
    else:
        msgs += devices
    number = OscMessage(OSC_FRAME, ("i", int(frame) & 0x7FFFFFFF)).dgram
    if fmt == "osc" and not bundle:
        # the sample number first: it opens the sample's group at the receiver
        return [number] + msgs
    msgs.append(number)
    return [BUNDLE + IMMEDIATELY + b"".join(INT32.pack(len(m)) + m for m in msgs)]
