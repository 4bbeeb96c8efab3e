"""One dancer, one sender: the datagrams of several senders to one port told
apart, and only the dancer's read.

Several programs may send to the same port (a
second headset, a VMC app left running). :class:`SenderGate` keeps one
:class:`~.receiver.SampleAssembler` per sender (address and port) until one sends a
sample with a head (one matching :attr:`SenderGate.want`, when the user chose
the sender): it **locks** onto that sender, and from then on only its samples
reach the live loop; every other sender's datagrams are counted under its
name and not even read. A locked sender that falls silent for
:attr:`SenderGate.follow_s` seconds and sends again from another port of the
same address (a sender that restarted; for VMC with the same head serial) is
followed.
"""
from __future__ import annotations

import threading

from ..errors import UserError
from .receiver import GROUP_WINDOW_S, Counters, Sample, SampleAssembler

MAX_SENDERS = 64  # senders told apart by name; more (a flood of source ports) are counted together
FOLLOW_RESTART_S = 2.0  # the locked sender silent this long: a sender of its address on another port is followed


def sender_text(addr) -> str:
    """``host:port`` of a sender's address (``addr``: ``(host, port)``)."""
    return f"{addr[0]}:{addr[1]}" if addr else "other senders"


def parse_sender(text: str) -> tuple:
    """``ADDR[:PORT]`` -> ``(address, port or None)``; a :class:`UserError` unless
    ADDR is an IPv4 address and PORT a port number."""
    import ipaddress

    host, sep, port = str(text).strip().partition(":")
    try:
        host = str(ipaddress.IPv4Address(host))
        p = int(port) if sep else None
        if p is not None and not 1 <= p <= 65535:
            raise ValueError
    except ValueError:
        raise UserError(f"sender {text!r} is not ADDR or ADDR:PORT (an IPv4 address, a port 1-65535), "
                        f"e.g. 192.168.1.20 or 192.168.1.20:50123") from None
    return host, p


class SenderInfo:
    """One sender: its ``addr``, ``packets`` (all its datagrams), ``others``
    (those counted as another sender's: ignored), when it was first and last
    heard, its own :class:`~.receiver.SampleAssembler` while it is read and the metadata
    of its samples without a head before the lock."""

    __slots__ = ("addr", "packets", "others", "first", "last", "assembler", "meta")

    def __init__(self, addr, t):
        self.addr = addr
        self.packets = self.others = 0
        self.first = self.last = t
        self.assembler = None
        self.meta = {}  # the metadata of its samples before the lock


class SenderGate:
    """Datagrams of any number of senders -> the samples of one (see the module
    docstring); in :class:`~.receiver.UdpReceiver` in place of a :class:`~.receiver.SampleAssembler`.
    ``make_decoder()``: a new decoder (one per sender: a VMC decoder keeps its
    sender's serials); ``want``: ``(address, port or None)`` the user chose, or
    None (the first sender with a head); ``follow_s``: seconds of silence after
    which a restarted sender is followed (0: never). :attr:`events`: lines for
    the user (the lock, a sender followed)."""

    def __init__(self, make_decoder, sink, counters: Counters | None = None, window: float = GROUP_WINDOW_S,
                 want=None, follow_s: float = FOLLOW_RESTART_S):
        self.make_decoder = make_decoder
        self.sink = sink
        self.counters = counters or Counters()
        self.window = float(window)
        self.want = want
        self.follow_s = float(follow_s or 0.0)
        self.locked = None  # the address of the sender the samples come from
        self.senders = {}  # addr -> SenderInfo
        self.overflow = SenderInfo(None, 0.0)  # senders past MAX_SENDERS, counted together
        self.events = []
        self._lock = threading.Lock()  # senders and events, read by the status

    @property
    def pending(self):  # (UdpReceiver's interface: a sample waits for its window)
        return any(i.assembler is not None and i.assembler.pending is not None for i in self.senders.values())

    def due(self, now: float) -> float | None:
        waits = [i.assembler.due(now) for i in self.senders.values() if i.assembler is not None
                 and i.assembler.pending is not None]
        return min(waits) if waits else None

    def flush_due(self, now: float) -> None:
        for i in list(self.senders.values()):
            if i.assembler is not None:
                i.assembler.flush_due(now)

    def flush(self) -> None:
        for i in list(self.senders.values()):
            if i.assembler is not None:
                i.assembler.flush()

    def datagram(self, data: bytes, t: float, sender=None) -> None:
        info = self.senders.get(sender)
        if info is None:
            if len(self.senders) >= MAX_SENDERS:
                self.overflow.packets += 1
                self.overflow.others += 1
                self.overflow.last = t
                self.counters.add(datagrams=1, others=1)
                return
            with self._lock:
                info = self.senders[sender] = SenderInfo(sender, t)
        self.flush_due(t)  # loose messages of a sender whose window passed while others sent
        info.packets += 1
        if sender == self.locked:
            info.last = t
            info.assembler.datagram(data, t)
            return
        info.others += 1
        self.counters.add(datagrams=1, others=1)
        if self._candidate(sender, t):
            if info.assembler is None:
                info.assembler = SampleAssembler(self.make_decoder(), lambda s, i=info: self._sample(i, s),
                                                 Counters(), self.window)
            info.assembler.datagram(data, t)
        info.last = t

    def _candidate(self, sender, t) -> bool:
        """Whether this sender's datagrams are read: before the lock, any (the
        one chosen); after it, one on the locked sender's address that may be
        it started again, once the locked sender has been silent ``follow_s``."""
        want = self.want
        if want is not None and (sender is None or sender[0] != want[0] or want[1] not in (None, sender[1])):
            return False
        if self.locked is None:
            return True
        if not self.follow_s or (want is not None and want[1] is not None) or sender is None:
            return False
        old = self.senders.get(self.locked)
        return sender[0] == self.locked[0] and old is not None and t - old.last >= self.follow_s

    def _sample(self, info, s) -> None:
        """A sample of a sender not locked onto: the lock when it carries a head."""
        if s.poses.get(0) is None:  # no head (hands only, metadata): not the dancer's, or not yet
            if s.meta and len(info.meta) < 64:
                info.meta.update(s.meta)  # (its metadata comes to the loop if it is the dancer's)
            return
        if self.locked is not None and not self._candidate(info.addr, s.time):
            return  # (a sample left pending when another sender was locked onto)
        old = self.senders.get(self.locked) if self.locked is not None else None
        if old is not None:
            serial = getattr(old.assembler.decoder, "head_serial", None)
            if serial is not None and getattr(info.assembler.decoder, "head_serial", None) != serial:
                return  # another headset on that machine, not the dancer's restarted
        p = info.assembler.counters.snapshot()
        asm = info.assembler
        asm.counters = self.counters
        asm.sink = self.sink
        # its datagrams so far, counted as another sender's until now: counted as its own (those of samples
        # before this one carried no head: only their metadata is used)
        self.counters.add(others=-p["datagrams"], used=p["used"], ignored=p["ignored"], late=p["late"],
                          malformed=p["malformed"], bad_messages=p["bad_messages"], lost=p["lost"])
        with self._lock:
            info.others = 0
            self.locked = info.addr
            for other in self.senders.values():
                if other is not info:
                    other.assembler = None  # not read any more (a restarted sender gets a new one)
            if old is None:
                self.events.append(f"locked onto the sender {sender_text(info.addr)}{self._serials(asm.decoder)}: "
                                   f"its samples are the take, any other sender's are ignored")
            else:
                self.events.append(f"followed the sender to {sender_text(info.addr)} (it started again: "
                                   f"{sender_text(old.addr)} silent {s.time - old.last:.1f} s)")
        if info.meta:
            self.sink(Sample(s.time, meta=info.meta))
            info.meta = {}
        self.sink(s)

    @staticmethod
    def _serials(decoder) -> str:
        head = getattr(decoder, "head_serial", None)
        if head is None:
            return ""
        hands = getattr(decoder, "hands", None)
        sides = {v: k for k, v in (hands.sides.items() if hands is not None else ())}
        named = ", ".join(f"{side} hand {sides[n]!r}" for n, side in ((1, "left"), (2, "right")) if n in sides)
        return f" (head {head!r}{', ' + named if named else ''})"

    def sender(self) -> str:
        """The locked sender (``host:port``), or ""."""
        return sender_text(self.locked) if self.locked is not None else ""

    def ignored(self) -> list:
        """``(host:port, packets)`` of every sender whose datagrams were ignored, first heard first."""
        with self._lock:
            out = [(sender_text(i.addr), i.others) for i in self.senders.values() if i.others]
        if self.overflow.others:
            out.append((f"{sender_text(None)} (past {MAX_SENDERS})", self.overflow.others))
        return out
