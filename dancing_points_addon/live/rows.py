"""The live loop's rows (:mod:`.session`): a row's values as a take file writes
and reads them back (:func:`as_written`, :func:`as_read`), the rows so far
(:class:`Rows`), and their 30 Hz frames made causally (:class:`CausalResampler`).
"""
from __future__ import annotations

import numpy as np

from ..formats.take import Take
from ..resample import NET_FPS, _bracket_rel, _tolerance, output_offsets
from ..rotations import quat_slerp

_IDENT = np.array([1.0, 0.0, 0.0, 0.0])


def as_written(positions, quats):
    """One row's ``(positions (3, 3), quats (3, 4))`` as
    :func:`~..formats.take.write_take` writes it (ten significant digits; a
    device with any non-finite value lost in all seven). Written again, the
    same text."""
    vals = np.concatenate([np.asarray(positions, np.float64), np.asarray(quats, np.float64)], axis=-1)
    dev = np.array([float("%.10g" % v) for v in vals.ravel().tolist()]).reshape(3, 7)
    dev[np.isnan(dev).any(-1)] = np.nan
    return dev[:, :3].copy(), dev[:, 3:].copy()


def as_read(quats):
    """Written quaternions ``(..., 4)`` as :func:`~..formats.take_read.read_take` gives them: normalised."""
    with np.errstate(invalid="ignore"):
        return quats / np.linalg.norm(quats, axis=-1)[..., None]


class CausalResampler:
    """The 30 Hz frames of :func:`~..resample.resample_take`, each made as soon
    as a row after it has come: output frame ``k`` at ``k / fps`` after the first
    row, positions linear and rotations slerped between the rows around it, lost
    where a row it takes weight from is lost. Rows are times relative to the
    first (which is 0), strictly increasing."""

    def __init__(self, fps: float = NET_FPS):
        self.fps = float(fps)
        self.k = 0  # the next frame to make
        self.prev = None  # (t, pos, quat, valid) of the row before the last
        self.last = None
        self.t_first = None

    def _row(self, t, pos, quat, valid):
        v = np.asarray(valid, dtype=bool)
        return (float(t), np.where(v[:, None], pos, 0.0), np.where(v[:, None], quat, _IDENT), v)

    def add(self, t, pos, quat, valid) -> list:
        """Rows in order; returns the frames now made: ``(k, pos (3, 3), quat (3, 4), valid (3,))``."""
        row = self._row(t, pos, quat, valid)
        if self.t_first is None:
            self.t_first = row[0]
        self.prev, self.last = self.last, row
        if self.prev is None:
            return []
        tol = _tolerance(np.array([self.t_first, row[0]]))
        out = []
        while self.k / self.fps + tol < row[0]:
            out.append(self._frame(self.k, self.prev, self.last, tol))
            self.k += 1
        return out

    def due(self, times) -> tuple:
        """The frames the rows so far make that are not made yet, read
        together (rows that come faster than the frames are coalesced: only
        the two rows around each frame's time are read). ``times``: every
        row's time so far (relative, strictly increasing). Returns ``(ks, i,
        a)``: the frames, their rows ``i, i + 1`` and the weight of ``i + 1``,
        as :meth:`add` would make them row by row (and
        :func:`~..resample.resample_take` over the whole take); the caller
        makes each (:meth:`interp`) and moves :attr:`k` on."""
        n = len(times)
        if n < 2:
            return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
        t_last = float(times[n - 1])
        tol = _tolerance(np.array([float(times[0]), t_last]))
        end = max(self.k, int(np.floor((t_last - tol) * self.fps)) - 2)
        while end / self.fps + tol < t_last:  # the frames add() makes once the row at t_last has come
            end += 1
        ks = np.arange(self.k, end)
        if not len(ks):
            return ks, ks, np.zeros(0)
        i, a = _bracket_rel(np.asarray(times[:n], dtype=np.float64), ks / self.fps, tol)
        return ks, i, a

    def interp(self, k, t0, p0, q0, t1, p1, q1, a):
        """Frame ``k`` between two rows (as read: NaN where a device is lost) with weight ``a`` on the second."""
        r0 = self._row(t0, p0, q0, np.isfinite(p0).all(-1) & np.isfinite(q0).all(-1))
        r1 = self._row(t1, p1, q1, np.isfinite(p1).all(-1) & np.isfinite(q1).all(-1))
        return self._interp(k, r0, r1, float(a))

    def _frame(self, k, r0, r1, tol):
        off = k / self.fps
        rel = np.array([r0[0], r1[0]])
        _, a = _bracket_rel(rel, np.array([off]), tol)
        return self._interp(k, r0, r1, float(a[0]))

    @staticmethod
    def _interp(k, r0, r1, a):
        _, p0, q0, v0 = r0
        _, p1, q1, v1 = r1
        ok = (v0 | (a >= 1.0)) & (v1 | (a <= 0.0))
        p = p0 + (p1 - p0) * a
        q = quat_slerp(q0, q1, np.full(3, a))
        p[~ok] = np.nan
        q[~ok] = np.nan
        return k, p, q, ok

    def finish(self, times, positions, quats) -> list:
        """The frames still to make at the end of a take of these rows (all of
        it, relative times): those :func:`~..resample.resample_take` makes up to
        the last row, bracketed over the whole take as it does."""
        times = np.asarray(times, dtype=np.float64)
        offs = output_offsets(times, self.fps)
        if self.k >= len(offs) or len(times) < 2:
            return []
        tol = _tolerance(times)
        ks = np.arange(self.k, len(offs))
        i, a = _bracket_rel(times - times[0], offs[ks], tol)
        valid = np.isfinite(positions).all(-1) & np.isfinite(quats).all(-1)
        out = []
        for k, ii, aa in zip(ks.tolist(), i.tolist(), a.tolist()):
            r0 = self._row(times[ii], positions[ii], quats[ii], valid[ii])
            r1 = self._row(times[ii + 1], positions[ii + 1], quats[ii + 1], valid[ii + 1])
            out.append(self._interp(k, r0, r1, aa))
        self.k = len(offs)
        return out


class Rows:
    """The take's rows so far, in arrays that grow by doubling. A row is kept
    as it came and made :func:`as_written` when it is first read
    (:meth:`settle`): a fast sender's rows that no frame reads cost their
    formatting only once, at the end, not as they come."""

    def __init__(self):
        self.n = 0
        self.time = np.empty(1024)
        self.pos = np.empty((1024, 3, 3))
        self.quat = np.empty((1024, 3, 4))
        self.arrival = np.empty(1024)  # this machine's clock when the row was made (for latency)
        self.raw = np.zeros(1024, dtype=bool)  # not yet as written

    def _room(self) -> None:
        if self.n == len(self.time):
            m = 2 * self.n
            for name in ("time", "pos", "quat", "arrival", "raw"):
                old = getattr(self, name)
                new = np.zeros((m,) + old.shape[1:], dtype=old.dtype)
                new[:self.n] = old[:self.n]
                setattr(self, name, new)

    def stage(self, got) -> np.ndarray:
        """Write the next row's devices (``got``: per device ``(position,
        quaternion)``, or None: lost, NaN) without adding it yet; returns which
        are whole (finite). :meth:`commit` adds it."""
        self._room()
        pos, quat = self.pos[self.n], self.quat[self.n]
        for d, v in enumerate(got):
            if v is None:
                pos[d] = quat[d] = np.nan
            else:
                pos[d], quat[d] = v
        return np.isfinite(pos).all(-1) & np.isfinite(quat).all(-1)

    def commit(self, t, arrival) -> None:
        """Add the row :meth:`stage` wrote, at ``t`` (arrived at ``arrival``)."""
        n = self.n
        self.time[n], self.arrival[n], self.raw[n] = t, arrival, True
        self.n = n + 1

    def settle(self, rows=None) -> None:
        """Make the rows (indices; None: all so far) as written (:func:`as_written`), once each."""
        idx = np.flatnonzero(self.raw[:self.n]) if rows is None else np.asarray(rows)[self.raw[rows]]
        for i in idx.tolist():
            self.pos[i], self.quat[i] = as_written(self.pos[i], self.quat[i])
        self.raw[idx] = False

    def take(self, n=None, meta=None) -> Take:
        """The first ``n`` rows as a take file reads them back."""
        n = self.n if n is None else n
        self.settle(np.arange(n))
        return Take(self.time[:n].copy(), self.pos[:n].copy(), as_read(self.quat[:n]), dict(meta or {}))
