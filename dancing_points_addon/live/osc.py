"""OSC 1.0 packets over UDP: one datagram read into its ``(address,
arguments)`` in order, nested bundles included (:func:`osc_messages`; a
bundle's time tag is ignored: senders get it wrong, and a sample's time is its
arrival), and messages written byte for byte as ``python-osc`` writes them
(:class:`OscMessage`). The common packets are read in place with ``struct``;
anything unusual goes through ``python-osc`` itself, and the tests hold the
two to the same results."""
from __future__ import annotations

import logging
import struct


class MalformedPacket(ValueError):
    """A datagram that is no OSC packet (or one ``python-osc`` cannot read)."""


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


INT32, FLOAT32, FLOAT64 = struct.Struct(">i"), struct.Struct(">f"), struct.Struct(">d")
_ARG_SIZE = {"i": 4, "f": 4, "d": 8}
BUNDLE = b"#bundle\x00"


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


def _fast_message(d: bytes, start: int, end: int, runs=None) -> tuple:
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
            if runs is not None:  # where the numbers lie, for a template (_Template)
                runs.append((i, step, len(args)))
            args.extend(step.unpack_from(d, i))
            i += step.size
    return address, args


def _fast_messages(d: bytes, out: list, start: int, end: int, depth: int = 0, layout=None) -> None:
    """The common datagrams (messages of ``i f d s`` arguments, bundles of
    them) read with ``struct``, as ``python-osc`` reads them; anything else
    raises :class:`_Unusual` (then ``python-osc`` reads it). ``d[start:end]``:
    the packet (a bundle's element is read in place). ``layout``: two lists,
    ``(tags, runs)``, to which each bundle adds the offset of its time tag
    (which the reader ignores) and each message the list of its runs of
    numeric arguments, ``(offset, struct, index of its first argument)``."""
    if d.startswith(BUNDLE, start, end):
        if depth > MAX_BUNDLE_DEPTH or end - start < 16:
            raise _Unusual
        if layout is not None:
            layout[0].append(start + 8)
        i = start + 16
        while i < end:
            if i + 4 > end:
                raise _Unusual
            size = INT32.unpack_from(d, i)[0]
            i += 4
            if size <= 0 or i + size > end:
                raise _Unusual
            _fast_messages(d, out, i, i + size, depth + 1, layout)
            i += size
    elif d[start:start + 1] == b"/":
        runs = None if layout is None else []
        out.append(_fast_message(d, start, end, runs))
        if layout is not None:
            layout[1].append(runs)
    else:
        raise _Unusual


class _Template:
    """The layout of one datagram (:func:`_fast_messages` read it): its bytes
    outside the numeric arguments, which must match, and where the numbers
    lie. A sender sends the same layout sample after sample with other
    numbers: a datagram whose every byte outside the numbers is the
    template's is parsed alike (the numbers steer nothing), so its messages
    are the template's strings with its own numbers, read in one call."""

    __slots__ = ("size", "consts", "const_bytes", "numbers", "plan")

    def __init__(self, d: bytes, messages: list, tags: list, runs: list):
        spans = []  # (offset, end) of each run of numbers, in the datagram's order
        fmt, plan, n, pos = ">", [], 0, None
        for (address, args), msg_runs in zip(messages, runs):
            pieces, k = [], 0  # the arguments: a string as it is, a run as (first, end) in the numbers
            for offset, step, first in msg_runs:
                pieces.extend(args[k:first])
                count = len(step.unpack_from(d, offset))
                pieces.append((n, n + count))
                if pos is not None:
                    fmt += f"{offset - pos}x" if offset > pos else ""
                fmt += step.format.lstrip(">")
                pos = offset + step.size
                spans.append((offset, pos))
                n, k = n + count, first + count
            pieces.extend(args[k:])
            plan.append((address, tuple(pieces)))
        self.size = len(d)
        skipped = sorted(spans + [(t, t + 8) for t in tags])  # the numbers, and the time tags: any bytes
        edges = [0] + [e for span in skipped for e in span] + [len(d)]
        self.consts = tuple((a, b) for a, b in zip(edges[0::2], edges[1::2]) if b > a)
        self.const_bytes = b"".join(d[a:b] for a, b in self.consts)
        self.numbers = (spans[0][0], struct.Struct(fmt)) if spans else None
        self.plan = tuple(plan)

    def read(self, d: bytes):
        """``d``'s messages, or None when ``d`` is not of this layout."""
        if len(d) != self.size or b"".join([d[a:b] for a, b in self.consts]) != self.const_bytes:
            return None
        nums = self.numbers[1].unpack_from(d, self.numbers[0]) if self.numbers else ()
        out = []
        for address, pieces in self.plan:
            args = []
            for p in pieces:
                if p.__class__ is tuple:
                    args.extend(nums[p[0]:p[1]])
                else:
                    args.append(p)
            out.append((address, args))
        return out


_TEMPLATES = {}  # a datagram's size -> the layouts seen of that size, the latest first
_MAX_SIZES, _PER_SIZE = 64, 4  # (a fuzzing sender's odd datagrams are read without keeping their layout)


def osc_messages(dgram: bytes) -> list:
    """The ``(address, arguments)`` of one datagram, in the order they were
    sent (a bundle's elements depth first; time tags ignored).
    :class:`MalformedPacket` when it is no OSC packet. A datagram of a layout
    seen before is read by its :class:`_Template`; the other common datagrams
    by a small ``struct`` reader (a fifth of ``python-osc``'s time), the rest
    by ``python-osc``; all give the same."""
    for tpl in _TEMPLATES.get(len(dgram), ()):
        got = tpl.read(dgram)
        if got is not None:
            return got
    out, tags, runs = [], [], []
    try:
        _fast_messages(dgram, out, 0, len(dgram), layout=(tags, runs))
    except (_Unusual, struct.error, RecursionError):
        return _python_osc_messages(dgram)
    seen = _TEMPLATES.get(len(dgram))
    if seen is not None or len(_TEMPLATES) < _MAX_SIZES:  # (a new tuple: another receiver's thread may read it)
        _TEMPLATES[len(dgram)] = (_Template(dgram, out, tags, runs),) + (seen or ())[:_PER_SIZE - 1]
    return out


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


# --------------------------------------------------------------------------- writing

IMMEDIATELY = b"\x00" * 7 + b"\x01"  # the OSC time tag "immediately" (python-osc's IMMEDIATELY)


def padded(b: bytes) -> bytes:
    return b + b"\x00" * (4 - len(b) % 4)


class OscMessage:
    """One OSC message, written with ``struct`` as ``python-osc``'s builder
    writes it (``i``, ``f``, ``d``, ``s`` arguments; the tests hold them to the
    same bytes)."""

    __slots__ = ("dgram",)

    def __init__(self, address, *typed):
        parts = [padded(address.encode("utf-8")), padded(("," + "".join(t for t, _ in typed)).encode("ascii"))]
        for t, v in typed:
            parts.append(padded(v.encode("utf-8")) if t == "s" else
                         (INT32 if t == "i" else FLOAT32 if t == "f" else FLOAT64).pack(v))
        self.dgram = b"".join(parts)
