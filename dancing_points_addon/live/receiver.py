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
of senders other than the dancer's (:class:`~.senders.SenderGate`).

One dancer among several senders to one port: :mod:`.senders`.
"""
from __future__ import annotations

import errno
import math
import select
import socket
import struct
import sys
import threading
import time

from ..errors import UserError
from .osc import osc_messages

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
        self._stamped = []  # datagrams taken off the socket during a frame, not yet read
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
        stamped = self._stamped  # (datagram, arrival, sender) not yet read into the assembler
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

    def waiting(self) -> bool:
        """Whether datagrams have arrived that the assembler has not read yet
        (in the socket, or taken off it during a frame): whoever would say
        that nothing came (the live loop's silence) waits for them."""
        if self._stamped:
            return True
        sock = self.sock
        if sock is None:
            return False
        try:
            return bool(select.select([sock], [], [], 0)[0])
        except (OSError, ValueError):  # (closed meanwhile)
            return False

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
