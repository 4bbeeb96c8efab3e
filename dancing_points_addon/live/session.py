"""The live loop: samples in, the duet out frame by frame, the take kept.

:class:`LiveSession` takes :class:`~.receiver.Sample` s from any source (the
UDP receiver's thread, Blender's VR session polled on the main thread) and, in
its own thread (or the caller's: :meth:`LiveSession.feed`, :meth:`tick`):

1. **rows**: each sample becomes a take row at its arrival time. A device the
   sample does not name keeps its last pose if that is at most
   :attr:`~.options.LiveOptions.gap_s` old, else it is lost (NaN, SPEC §3); a device the
   sender marks lost is lost at once. When nothing arrives for ``gap_s`` the
   loop adds rows of lost devices, one a frame, so the duet goes on (the
   runtime stands in for lost devices). A sample whose time is not after the
   last row's is late: dropped and counted. Times are kept to the microsecond
   and every value as a take file writes and reads it back
   (:func:`.rows.as_written`), so the rows *are* the take file.
2. **the start**: the take starts at the first row where all three devices
   are tracked, so it has no lost start to fill (offline synthesis fills one by
   looking ahead, which a live loop cannot).
3. **calibration**: with the height and the floor known (options, or the
   stream's metadata) the duet starts at once; otherwise the first
   :attr:`~.options.LiveOptions.calibration_s` seconds of rows are calibrated like a
   take (:meth:`~..runtime.Synthesizer.calibrate`: the height, and the floor
   when the height is given) and the duet starts then, from the first row. The
   values used are the ones the take's metadata carry (``height_m`` and
   ``floor_y`` to 0.1 mm), so the take reads back with the same calibration.
   A sender that announces its metadata's keys (``stream`` does:
   :data:`~.protocol.META_ANNOUNCE`) and whose metadata the calibration reads
   has not all come (lost on the way) is waited for, at most
   :data:`~.stream_meta.META_WAIT_S` seconds past the calibration window; then the
   calibration goes on without it and says so (:attr:`LiveSession.warnings`).
   A sender that announces nothing (any other VMC or OSC sender) is not waited
   for. The tracked dancer's ``role`` (SPEC §3) is the option's, else the
   stream's, else ``leader``; it is one of the keys waited for, and a role
   other than the synthesizer's switches it to that role's networks
   (preloaded, :meth:`LiveSession.__init__`) before the first frame; the rows
   that arrive meanwhile are caught up as those before the calibration are (no
   latency counted). A role given that the stream contradicts wins, with a
   warning.
4. **frames**: resampled causally to 30 Hz (:class:`.rows.CausalResampler`:
   the frames of :func:`~..resample.resample_take`, each made once the row
   after it has come) and synthesised
   (:meth:`~..runtime.Synthesizer.step`). Only the two rows around a
   frame's time are read for it, as the calibration says (as
   :func:`~..calibration.apply_calibration` reads a take): rows that come
   faster than the frames are coalesced, so a 1,000 Hz sender costs the loop
   its rows, not 1,000 readings a second. The loop's thread takes every
   sample that came while it made a frame at once, then makes the frames.

:meth:`LiveSession.finish` ends it: trailing rows of lost devices are dropped
(with the frames made from them) and it returns the take and the duet
(:class:`~.options.LiveResult`); ``synthesize`` of that take gives that duet.
"""
from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque

import numpy as np

from ..calibration import apply_calibration
from ..errors import UserError
from ..formats.take import Take
from ..resample import NET_FPS, output_offsets
from . import ROLES
from .receiver import Counters, Sample
from .options import LiveOptions, LiveResult, ignored_senders_text
from .rows import CausalResampler, Rows, as_read
from .stream_meta import StreamCalibration

RATE_WINDOW_S = 1.0  # the input rate is the samples of this last window
def _offset_text(v) -> str:
    return ",".join(repr(float(c)) for c in v)


class LiveSession(StreamCalibration):
    """See the module docstring. ``synthesizer``: a
    :class:`~..runtime.Synthesizer` (default: one made from the options);
    ``counters``: the receiver's (shared accounting); ``clock``: the clock the
    samples' times are on."""

    def __init__(self, options: LiveOptions, synthesizer=None, counters: Counters | None = None,
                 clock=time.perf_counter, describe: str = ""):
        if options.role is not None and options.role not in ROLES:
            raise UserError(f"role {options.role!r} cannot be streamed yet (roles: {', '.join(ROLES)})")
        if synthesizer is None:
            from ..runtime import Synthesizer
            synthesizer = Synthesizer(options.synthesis_options())
        self.options = options
        self.synth = synthesizer
        self.record = bool(options.record_predictions)
        if self.record:
            synthesizer.record_predictions = True
        self.counters = counters or Counters()
        self.clock = clock
        self.describe = describe
        self.rows = Rows()
        self.t_first = None  # the clock's time of the take's first row
        self.stream_meta = {}
        self.calibration = None
        self.warnings = []  # lines for the user (the calibration went on without the announced metadata)
        self.resampler = CausalResampler()
        self._last_dev = [None, None, None]  # per device: (clock time, (position, quat)) last heard
        self._catchup = 0  # rows read when the calibration came (not live: no latency counted)
        self._calibrated_t = 0.0  # the take's time of the row the calibration came with
        self._silent = False  # the last row was made of silence
        self._frames = {k: [] for k in ("lp", "lr", "lc", "fp", "fr", "fc", "pred", "planted")}
        self.latest = None  # (k, leader DuetFrame, follower DuetFrame, arrival of the row that made it)
        self.latency = []  # (frame, seconds from a row's arrival to the frame), frames made live (not catching up)
        self.compute_s = []  # seconds of synthesis per frame
        self._recent = deque(maxlen=64)  # (clock time, latency) of the last frames
        self._arrivals = deque()  # clock times of the samples of the last second (the input rate)
        self.gate = None  # the receiver's SenderGate (the sender and the senders ignored), when there is one
        self._queue = queue.SimpleQueue()
        self._thread = None
        self._stop = threading.Event()
        self.error = None
        self._lock = threading.Lock()  # feed/tick/finish: one at a time
        self.busy = threading.Lock()  # held while a live frame is made (a receiver's ``hold``: it reads between)
        self.waiting = None  # () -> whether a receiver has datagrams not yet read (:meth:`listen_to`)
        self._live_after = -math.inf  # rows that arrived before this clock time are caught up (a role switch)
        self.role_switch_s = None  # seconds the switch to the stream's role took (None: none made)
        self._role_warned = False
        self._hold_calibration = False  # (rows read without calibrating: :meth:`received_take`)
        self._unavailable = {}  # role -> why its networks cannot be used (checked up front)
        if options.role is None:  # the stream may name either role: the other's networks checked and loaded now
            from ..nets import check_models

            for role in ROLES:
                if role != synthesizer.role:
                    try:
                        check_models(synthesizer.options.models, synthesizer.options.threads, role)
                    except UserError as exc:  # needed only if the stream says this role
                        self._unavailable[role] = str(exc)

    # -- input -------------------------------------------------------------------
    def listen_to(self, receiver) -> None:
        """Take ``receiver``'s samples (a :class:`~.receiver.UdpReceiver`, not
        yet started): it reads its datagrams between live frames, not during
        one (its ``hold`` is :attr:`busy`), and no silence is declared while
        it has datagrams it has not read (their arrival may be before the
        silence: they would come late)."""
        receiver.hold = self.busy
        self.waiting = receiver.waiting

    def put(self, sample: Sample) -> None:
        """From one thread (the receiver's, or the caller's): one sample for the
        loop; counted at once for the input rate, read or not."""
        arrivals = self._arrivals
        arrivals.append(sample.time)
        while arrivals and sample.time - arrivals[0] > RATE_WINDOW_S:
            arrivals.popleft()
        self._queue.put(sample)

    # -- the thread ------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="dancing_points_live_loop", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    s = self._queue.get(timeout=self._wait())
                except queue.Empty:
                    self.tick(self.clock())
                    continue
                with self._lock:  # this sample and all that came meanwhile, then their frames
                    self._ingest(s)
                    self._drain()
                    self._work(None)
            while True:  # what came before the stop
                try:
                    self.feed(self._queue.get_nowait())
                except queue.Empty:
                    break
        except Exception as exc:  # noqa: BLE001 - reported by whoever owns the session
            self.error = exc

    def _wait(self) -> float:
        if self.t_first is None:
            return 0.05
        due = self._last_abs + (1.0 / NET_FPS if self._silent else self.options.gap_s)
        return min(0.05, max(1e-4, due - self.clock()))

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """End the thread (samples already put are read first)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    # -- the loop (one caller at a time) ------------------------------------------------
    def feed(self, s: Sample) -> None:
        """One sample (see the module docstring), and the frames it makes."""
        with self._lock:
            self._ingest(s)
            self._work(None)

    def tick(self, now: float) -> None:
        """Nothing has come: after ``gap_s`` (then every frame) a row of lost devices
        (the samples put meanwhile read first: they may be older than now)."""
        with self._lock:
            self._drain()
            self._silence(now)
            self._work(None)

    def pump(self, now: float, budget_s: float | None = None) -> int:
        """For a caller that runs the loop itself (Blender's main thread, no
        loop thread): the samples put so far, silence up to ``now``, then
        their frames; the first second's catch-up for at most ``budget_s``
        seconds a call (the rest on the next calls: it never blocks long).
        Returns the rows still to read into frames."""
        with self._lock:
            self._drain()
            self._silence(now)
            return self._work(budget_s)

    def _drain(self) -> None:
        """Read what was put and not yet read (under the lock)."""
        while True:
            try:
                self._ingest(self._queue.get_nowait())
            except queue.Empty:
                break

    def _ingest(self, s: Sample) -> None:
        if s.meta:
            self.stream_meta.update(s.meta)
        if not s.poses:
            return
        poses, last_dev, gap = s.poses, self._last_dev, self.options.gap_s
        got = [None, None, None]
        for d in range(3):
            if d in poses:
                v = poses[d]
                last_dev[d] = None if v is None else (s.time, v)
            else:
                last = last_dev[d]
                v = last[1] if last is not None and s.time - last[0] <= gap else None
            got[d] = v
        self._row(s.time, got, s.datagrams)

    def _silence(self, now: float) -> None:
        if self.t_first is None:
            return
        due = self._last_abs + (1.0 / NET_FPS if self._silent else self.options.gap_s)
        if now < due or self.waiting is not None and self.waiting():
            return
        got = [None, None, None]
        for d in range(3):
            last = self._last_dev[d]
            if last is not None and now - last[0] <= self.options.gap_s:
                got[d] = last[1]
        self._row(now, got, 0, silent=True)

    def _row(self, t_abs, got, datagrams, silent=False):
        """One row at ``t_abs``: ``got``, per device its (position, quaternion) or None (lost)."""
        rows = self.rows
        valid = rows.stage(got)
        if self.t_first is None:
            if not valid.all():
                return  # the take starts where the dancer is first seen whole
            self.t_first = t_abs
        t = round(t_abs - self.t_first, 6)
        if rows.n and t <= rows.time[rows.n - 1]:
            if datagrams:
                self.counters.add(late=datagrams, used=-datagrams)
            return
        rows.commit(t, t_abs)  # (as written when it is read: Rows.settle)
        self._last_abs = t_abs
        self._silent = silent and not valid.any()
        if datagrams or not silent:
            self.counters.add(samples=1)
        if self.calibration is None and self._can_calibrate(t):
            self._calibrate(rows.n)

    def _work(self, budget_s) -> int:
        """Make the frames the rows so far allow (the catch-up's for at most
        ``budget_s`` seconds; None: all); returns how many are left. Rows that
        came faster than the frames are coalesced: each frame reads only the
        two rows around its time (:meth:`.rows.CausalResampler.due`), so the
        work a second does not grow with the input rate."""
        c = self.calibration
        rows = self.rows
        if c is None:
            return 0
        if rows.n < 2 or rows.time[rows.n - 1] <= self.resampler.k / self.resampler.fps:
            return 0  # no frame's time has passed (most rows of a fast sender)
        t0 = self.clock() if budget_s is not None else 0.0
        ks, idx, a = self.resampler.due(rows.time[:rows.n])
        if not len(ks):
            return 0
        need = np.unique(np.concatenate([idx, idx + 1]))
        rows.settle(need)
        one = Take(rows.time[need], rows.pos[need], as_read(rows.quat[need]), {})
        with np.errstate(invalid="ignore", divide="ignore"):  # lost devices: NaN in, NaN out
            read = apply_calibration(one, c, fill_start=False)
        j = np.searchsorted(need, idx)
        for m, k in enumerate(ks.tolist()):
            j0, j1, upper = int(j[m]), int(j[m]) + 1, int(idx[m]) + 1
            _, pk, qk, ok = self.resampler.interp(k, rows.time[upper - 1], read.positions[j0], read.quats[j0],
                                                  rows.time[upper], read.positions[j1], read.quats[j1], a[m])
            live = upper >= self._catchup and rows.arrival[upper] >= self._live_after
            if live:  # (a catch-up's frames let the receiver read between them: no silence seen meanwhile)
                with self.busy:
                    self._step(k, pk, qk, ok, rows.arrival[upper])
            else:
                self._step(k, pk, qk, ok, None)
            self.resampler.k = k + 1
            if budget_s is not None and upper < self._catchup and self.clock() - t0 >= budget_s:
                return len(ks) - m - 1
        return 0

    def _step(self, k, pos, quat, ok, arrival) -> None:
        t0 = self.clock()
        a, b = self.synth.step(pos, quat, ok)
        self.compute_s.append(self.clock() - t0)
        f = self._frames
        f["lp"].append(a.positions), f["lr"].append(a.rotations), f["lc"].append(a.contacts)
        f["fp"].append(b.positions), f["fr"].append(b.rotations), f["fc"].append(b.contacts)
        if self.record:
            f["pred"].append(self.synth.last_prediction)
            pl = self.synth.planted()
            f["planted"].append(pl if pl is not None else [[False] * 4] * 2)
        now = self.clock()
        self.latest = (k, a, b, arrival if arrival is not None else now)
        if arrival is not None:
            self.latency.append((k, now - arrival))
            self._recent.append((now, now - arrival))

    # -- status ------------------------------------------------------------------------
    def status(self, now: float | None = None) -> dict:
        """Input rate (samples received a second over the last second, whether
        the loop has read them yet or not), frames made, the
        counters, the latency (ms, median of the last frames), the state."""
        now = self.clock() if now is None else now
        recent = [t for t in list(self._arrivals) if now - t <= 1.0]
        lat = [v for t, v in list(self._recent) if now - t <= 2.0]
        c = self.counters.snapshot()
        if self.t_first is None:
            state = "waiting for the dancer (head and both hands)"
        elif self.calibration is None:
            waiting = self.missing_meta() and now - self.t_first >= self.options.calibration_s
            state = "waiting for the stream's metadata" if waiting else "calibrating"
        else:
            state = "dancing"
        gate = self.gate
        sender = gate.sender() if gate is not None else ""
        ignored = gate.ignored() if gate is not None else []
        if gate is not None and not sender and self.t_first is None:
            state = "waiting for a sender with a head" + (f" at {gate.want[0]}" if gate.want else "")
        return {"rate_hz": float(len(recent)), "frames": len(self._frames["lp"]), "state": state,
                "latency_ms": 1000.0 * float(np.median(lat)) if lat else math.nan,
                "seconds": 0.0 if self.t_first is None else max(0.0, now - self.t_first), **c,
                "dropped": c["late"] + c["malformed"] + c["ignored"], "sender": sender, "ignored_senders": ignored}

    def status_line(self, now: float | None = None) -> str:
        s = self.status(now)
        lat = "-" if math.isnan(s["latency_ms"]) else f"{s['latency_ms']:.1f} ms"
        line = (f"{self.describe}{s['state']} {s['seconds']:.1f} s | in {s['rate_hz']:.0f} Hz"
                f"{' from ' + s['sender'] if s['sender'] else ''} | duet frame {s['frames']} | "
                f"latency {lat} | dropped {s['dropped']} (late {s['late']}, bad {s['malformed']}, "
                f"other {s['ignored']}) | lost {s['lost']}")
        if s["ignored_senders"]:
            line += f" | {ignored_senders_text(s['ignored_senders'])}"
        return line

    # -- the end -------------------------------------------------------------------------
    def take_meta(self) -> dict:
        """The take file's metadata: the calibration's (with the role the duet
        was made for), its body offsets and how it was recorded."""
        c = self.calibration
        return self._finish_meta(dict(c.meta()), c.offsets)

    def _finish_meta(self, meta, offsets) -> dict:
        from ..formats.devices import META_OFFSET_KEYS

        for key, v in zip(META_OFFSET_KEYS, (offsets.head, offsets.lhand, offsets.rhand)):
            if v is not None:
                meta[key] = _offset_text(v)
        if self.describe:
            meta["recorded"] = self.describe.strip().rstrip(":")
        return meta

    def finish(self) -> LiveResult:
        """The take and its duet (call after :meth:`stop`, or when feeding by
        hand). A :class:`UserError` when nothing was recorded."""
        self.stop()
        with self._lock:
            self._drain()  # what was put and not yet read (a caller that pumps)
            rows = self.rows
            n = self._recorded()
            if n < 2:
                raise UserError("nothing recorded: no sample with the head and both hands tracked came"
                                if self.t_first is None else "the recording is too short (fewer than 2 samples)")
            if self.calibration is None:
                self._calibrate(n)
            self._warn_role()  # (a role that came after the calibration)
            self._work(None)
            rows.settle()
            times, pos, quat = rows.time[:n], rows.pos[:n], rows.quat[:n]
            with np.errstate(invalid="ignore", divide="ignore"):
                read = apply_calibration(Take(times, pos, as_read(quat), {}), self.calibration, fill_start=False)
            for k, pk, qk, ok in self.resampler.finish(times, read.positions, read.quats):
                self._step(k, pk, qk, ok, None)
            T = len(output_offsets(times))
            take = Take(times.copy(), pos.copy(), quat.copy(), self.take_meta())
            duet = self._duet(T)
            return LiveResult(take, duet, self.counters.snapshot(), self._latency_stats(0.0),
                              self._latency_stats(self._calibrated_t + 1.0))

    def _recorded(self) -> int:
        """Rows of the take: up to the last with a device tracked (under the lock)."""
        rows = self.rows
        valid = np.isfinite(rows.pos[:rows.n]).all(-1).any(-1) if rows.n else np.zeros(0, bool)
        return int(np.flatnonzero(valid)[-1]) + 1 if valid.any() else 0

    def received_take(self) -> Take | None:
        """Every row received, as the take file keeps them, whether or not a
        duet can be made: what a caller keeps when :meth:`finish` failed (the
        calibration or the synthesis). The metadata are the calibration's when
        it was made, else the options' and the stream's own values a take file
        may carry. None: fewer than two rows with a device tracked."""
        self.stop()
        with self._lock:
            self._hold_calibration = True  # it failed, and would again on each row read now
            try:
                self._drain()
            finally:
                self._hold_calibration = False
            n = self._recorded()
            if n < 2:
                return None
            if self.calibration is not None:
                meta = self.take_meta()
            else:
                from ..formats.devices import offsets_for

                o = self.options
                meta = self._meta()
                for key, v in (("height_m", o.height), ("floor_y", o.floor_y), ("devices", o.devices)):
                    if v is not None:
                        meta[key] = v
                meta = self._finish_meta(meta, offsets_for(meta, o.head_offset, o.hand_offset))
            rows = self.rows
            rows.settle()
            return Take(rows.time[:n].copy(), rows.pos[:n].copy(), rows.quat[:n].copy(), meta)

    def _latency_stats(self, after_s):
        """(median, 99th percentile) ms of the latency of the frames made live from ``after_s`` into the take."""
        lat = np.array([v for k, v in self.latency if k / NET_FPS >= after_s]) * 1000.0
        return (float(np.median(lat)), float(np.percentile(lat, 99))) if lat.size else (math.nan, math.nan)

    def _duet(self, T):
        from ..duet import Duet

        f = self._frames
        if T < 2 or len(f["lp"]) < T:  # (a take of one 30 Hz frame is one synthesize refuses)
            return None
        c = self.calibration
        stack = lambda key: np.array(f[key][:T])  # noqa: E731
        preds = stack("pred") if self.record and f["pred"] and f["pred"][0] is not None else None
        if preds is not None and c.floor_y:  # on the take's floor, as synthesize keeps them
            preds[..., 1] += np.float32(c.floor_y)
        planted = np.array(f["planted"][:T], dtype=bool) if self.record else None
        return Duet(np.arange(T) / NET_FPS, stack("lp"), stack("lr"), stack("lc"), stack("fp"), stack("fr"),
                    stack("fc"), bone_vectors=self.synth.output_bone_vectors(), predictions=preds,
                    planted=planted, calibration=c, tracked_role=c.role)
