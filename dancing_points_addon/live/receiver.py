"""The UDP receiver: a thread that reads datagrams, decodes them
(:mod:`.protocol`) and hands whole samples to the live loop.

A **sample** is what one sender sends for one instant: one bundle, or loose
messages taken together while they arrive within :data:`GROUP_WINDOW_S` of
the first, name each device at most once and no new sample number or sender
clock opens the next. Its time is the arrival of its first datagram (this
machine's monotonic clock), never a time tag.

Every datagram is counted once (:class:`Counters`): ``used`` (it carried
poses, a lost mark, a sample number or metadata), ``late`` (its sample came
after a later one, by the sender's sample number or clock, or after the live
loop had moved past its time), ``malformed`` (no OSC packet, or no message it
carries could be read), ``ignored`` (well formed, nothing this layout reads);
``lost``: samples the sender numbered that never came; ``others``: datagrams
of senders other than the dancer's (:class:`SenderGate`).

**One dancer, one sender.** Several programs may send to the same port (a
second headset, a VMC app left running). :class:`SenderGate` keeps one
:class:`SampleAssembler` per sender (address and port) until one sends a
sample with a head (one matching :attr:`SenderGate.want`, when the user chose
the sender): it **locks** onto that sender, and from then on only its samples
reach the live loop; every other sender's datagrams are counted under its
name and not even read. A locked sender that falls silent for
:attr:`SenderGate.follow_s` seconds and sends again from another port of the
same address (a sender that restarted; for VMC with the same head serial) is
followed.
"""
from __future__ import annotations

import errno
import math
import socket
import struct
import sys
import threading
import time

from ..errors import UserError
from .protocol import osc_messages

GROUP_WINDOW_S = 0.002
MAX_DATAGRAM = 65536
RECEIVE_BUFFER = 1 << 20
HOLD_POLL_S = 0.0005  # while the consumer makes a frame: how often datagrams are taken off the socket
# (where the kernel does not stamp them)
_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else None  # SO_TIMESTAMPNS = SCM_TIMESTAMPNS (Linux)
_TIMESPEC = struct.Struct("@qq")  # struct timespec (64-bit Linux)
_ANCILLARY = 64
MAX_STAMP_AGE_S = 1.0  # a kernel stamp older than this (a clock set meanwhile): taken as this old at most
# The system clock (the kernel's stamps) is put on the receiver's clock by one pair of
# readings taken within this many seconds of each other; a pair further apart (the
# thread was paused between them) keeps the offset read before.
STAMP_PAIR_S = 50e-6
STAMP_STEP_S = 2e-6  # a datagram's arrival is at least this after the one before (times are kept to the microsecond)
# A sample number this far back, or back at the start (0 to FRAME_FIRST), is a sender
# that started again (or a stray number far ahead before it), not a late sample: a
# sample arrives late by a few numbers (UDP reordering), 300 is 2.5 s at 120 Hz.
FRAME_RESTART, FRAME_FIRST = 300, 2
CLOCK_RESTART_S = 5.0  # the same for the sender's clock (/VMC/Ext/T)


class PortInUse(UserError):
    """The UDP port is taken (by another program or another live session)."""


class Counters:
    """Datagram accounting, shared by the receiver thread and the live loop."""

    FIELDS = ("datagrams", "used", "late", "malformed", "ignored", "lost", "bad_messages", "samples", "others")

    def __init__(self):
        self._lock = threading.Lock()
        for f in self.FIELDS:
            setattr(self, f, 0)

    def add(self, **kw) -> None:
        with self._lock:
            for k, v in kw.items():
                setattr(self, k, getattr(self, k) + v)

    def snapshot(self) -> dict:
        with self._lock:
            return {f: getattr(self, f) for f in self.FIELDS}

    @property
    def dropped(self) -> int:
        return self.late + self.malformed + self.ignored


class Sample:
    """One instant of the stream: ``time`` (arrival, seconds of the receiver's
    clock), ``poses {device: (position, quaternion) or None (lost)}``, the
    sender's ``frame`` number and ``clock``, take ``meta`` and how many
    ``datagrams`` made it."""

    __slots__ = ("time", "poses", "frame", "clock", "meta", "datagrams")

    def __init__(self, time, poses=None, frame=None, clock=None, meta=None, datagrams=1):
        self.time = time
        self.poses = dict(poses or {})
        self.frame = frame
        self.clock = clock
        self.meta = dict(meta or {})
        self.datagrams = datagrams


class SampleAssembler:
    """Datagrams -> samples (see the module docstring), without the socket:
    :meth:`datagram` for each arrival, :meth:`flush` when the window passes.
    ``sink(sample)`` receives each whole sample that is not late."""

    def __init__(self, decoder, sink, counters: Counters | None = None, window: float = GROUP_WINDOW_S):
        self.decoder = decoder
        self.sink = sink
        self.counters = counters or Counters()
        self.window = float(window)
        self.pending = None
        self.last_frame = None
        self.last_clock = None

    def datagram(self, data: bytes, t: float, sender=None) -> None:
        """One datagram arrived at ``t`` (``sender``: its address, unused here)."""
        c = self.counters
        c.add(datagrams=1)
        try:
            msgs = osc_messages(data)
            pk = self.decoder.decode(msgs)
        except Exception:  # noqa: BLE001 - MalformedPacket, or a packet the decoder did not foresee: never fatal
            c.add(malformed=1)
            return
        if pk.bad:
            c.add(bad_messages=pk.bad)
        if not pk.known:
            c.add(ignored=1)
            return
        if pk.known == pk.bad:
            c.add(malformed=1)
            return
        if not pk.poses and pk.frame is None and not pk.meta:
            c.add(ignored=1)  # a sender's clock or status alone
            if pk.clock is not None and self.pending is None:
                self._check_clock(pk.clock)
            return
        p = self.pending
        bundle = data[:8] == b"#bundle\x00"
        if p is not None and (bundle or pk.frame is not None or pk.clock is not None or t - p.time > self.window
                              or any(d in p.poses for d in pk.poses)):
            self.flush()
            p = None
        if p is None:
            p = self.pending = Sample(t, pk.poses, pk.frame, pk.clock, pk.meta, 1)
        else:
            p.poses.update(pk.poses)
            p.meta.update(pk.meta)
            p.datagrams += 1
        if bundle or len(p.poses) == 3:
            self.flush()

    def due(self, now: float) -> float | None:
        """Seconds until the pending sample's window closes (None: nothing pending)."""
        return None if self.pending is None else max(0.0, self.pending.time + self.window - now)

    def flush_due(self, now: float) -> None:
        """Flush the pending sample when its window has passed."""
        if self.pending is not None and now - self.pending.time >= self.window:
            self.flush()

    def flush(self) -> None:
        s, self.pending = self.pending, None
        if s is None:
            return
        c = self.counters
        late = False
        if s.frame is not None:
            last = self.last_frame
            if last is not None and last - FRAME_RESTART < s.frame <= last and s.frame > FRAME_FIRST:
                late = True
            else:
                if last is not None and s.frame > last + 1:
                    c.add(lost=s.frame - last - 1)
                self.last_frame = s.frame
        elif s.clock is not None:
            late = not self._check_clock(s.clock)
        if late:
            c.add(late=s.datagrams)
            return
        c.add(used=s.datagrams)
        self.sink(s)

    def _check_clock(self, clock: float) -> bool:
        last = self.last_clock
        if last is not None and last - CLOCK_RESTART_S < clock <= last:
            return False
        self.last_clock = clock
        return True


class UdpReceiver:
    """A thread receiving on UDP ``host:port`` into a :class:`SampleAssembler`.
    :meth:`start` binds (a :class:`PortInUse` when the port is taken);
    :meth:`stop` ends the thread and closes the socket.

    ``hold``: a lock the consumer holds while it makes a frame (the live
    session's :attr:`~.session.LiveSession.busy`). A datagram that comes
    meanwhile is read into the assembler once the lock is free, with the time
    it arrived: the kernel's stamp (Linux), else the socket is looked at every
    :data:`HOLD_POLL_S` and each datagram stamped as it is taken off. A fast
    sender's datagrams then do not take the interpreter from a frame being
    made, and a frame's latency does not grow with the input rate."""

    def __init__(self, assembler: SampleAssembler, port: int, host: str = "0.0.0.0", clock=time.perf_counter,
                 hold=None):
        self.assembler = assembler
        self.hold = hold if hold is not None else threading.Lock()
        self.kernel_stamps = False  # the system stamps each datagram's arrival (Linux), set when bound
        self._last_t = -math.inf
        self._offset = None  # the receiver's clock minus the system's (kernel stamps)
        self.port = int(port)
        self.host = host
        self.clock = clock
        self.sock = None
        self.thread = None
        self._stop = threading.Event()
        self.error = None  # an unexpected failure of the thread (it ends; the loop reports it)

    def open(self) -> None:
        """Bind the socket (datagrams wait in it until :meth:`start`)."""
        if self.sock is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            if exc.errno in (errno.EADDRINUSE, errno.EACCES, getattr(errno, "WSAEADDRINUSE", -1)):
                raise PortInUse(f"UDP port {self.port} is already in use on {self.host} (another program, or "
                                f"another live session, receives on it): close it or choose another port") from None
            raise UserError(f"cannot receive on UDP {self.host}:{self.port}: {exc.strerror or exc}") from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        except OSError:
            pass
        if _SO_TIMESTAMPNS is not None and hasattr(sock, "recvmsg"):
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self.kernel_stamps = True
            except OSError:
                pass
        self.port = sock.getsockname()[1]  # the port actually bound (port 0: any free one)
        self.sock = sock

    def start(self) -> None:
        """Bind (unless :meth:`open` did) and start the thread."""
        self.open()
        self.thread = threading.Thread(target=self._run, name=f"dancing_points_live_udp_{self.port}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        sock, asm, clock, hold, kernel = self.sock, self.assembler, self.clock, self.hold, self.kernel_stamps
        stamped = []  # (datagram, arrival, sender) not yet read into the assembler
        try:
            while not self._stop.is_set():
                if stamped:
                    # the kernel stamps the datagrams that come meanwhile: wait for the frame, not a moment longer
                    # (without its stamps they are taken off the socket every HOLD_POLL_S, stamped as they are)
                    if hold.acquire(timeout=0.05) if kernel else hold.acquire(blocking=False):
                        try:
                            for data, t, addr in stamped:
                                asm.datagram(data, t, addr)
                            stamped.clear()
                        finally:
                            hold.release()
                    elif kernel:
                        continue
                wait = asm.due(clock())
                wait = 0.05 if wait is None else max(wait, 1e-4)
                sock.settimeout(min(wait, HOLD_POLL_S) if stamped else wait)
                try:
                    got = self._receive(sock, clock)
                except socket.timeout:
                    if not stamped:
                        with hold:
                            asm.flush_due(clock())
                    continue
                except OSError:
                    if self._stop.is_set():
                        break
                    continue
                stamped.append(got)
            with hold:
                for data, t, addr in stamped:
                    asm.datagram(data, t, addr)
                asm.flush()
        except Exception as exc:  # noqa: BLE001 - kept for the loop to report; never a traceback in a thread
            self.error = exc

    def _receive(self, sock, clock) -> tuple:
        """One datagram: ``(data, arrival on clock, sender)``. The arrival is
        the kernel's stamp where the system gives one (put on ``clock`` by
        :meth:`_clock_offset`: a datagram read late keeps its time), else the
        moment it is read. Always after the previous datagram's
        (:data:`STAMP_STEP_S`): two samples never share a time."""
        if self.kernel_stamps:
            data, anc, _flags, addr = sock.recvmsg(MAX_DATAGRAM, _ANCILLARY)
            now, offset = self._clock_offset(clock)
            t = now
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(cdata) == _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack(cdata)
                    t = min(max(sec + nsec * 1e-9 + offset, now - MAX_STAMP_AGE_S), now)
        else:
            data, addr = sock.recvfrom(MAX_DATAGRAM)
            t = clock()
        t = self._last_t = max(t, self._last_t + STAMP_STEP_S)
        return data, t, addr

    def _clock_offset(self, clock) -> tuple:
        """``(now on clock, clock minus the system clock)``. The offset is read
        between two readings of ``clock`` no more than :data:`STAMP_PAIR_S`
        apart; when the thread was paused between them the last good offset
        stands (a pause there would otherwise date the datagram too early)."""
        a = clock()
        real = time.time()
        b = clock()
        if b - a <= STAMP_PAIR_S or self._offset is None:
            self._offset = 0.5 * (a + b) - real
        return b, self._offset

    @property
    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self.thread is not None:
            self.thread.join(timeout)
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self.thread = None


# --------------------------------------------------------------------------- one dancer, one sender

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
    heard, its own :class:`SampleAssembler` while it is read and the metadata
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
    docstring); in :class:`UdpReceiver` in place of a :class:`SampleAssembler`.
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
