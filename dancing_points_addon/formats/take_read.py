"""Reading a three-point take file (SPEC §3, :class:`~.take.Take`).

:func:`read_take` streams and is vectorised: the file is taken in chunks of
whole lines; in each, the line structure is validated first, the numbers are
parsed in one C call into arrays allocated once for the take, and the
offending line is only searched for (in Python) once something is known to be
wrong. What the writer (:func:`~.take.write_take`) writes reads back as it was.
"""
from __future__ import annotations

import io
import os
import re
import warnings

import numpy as np

from ..audio import check_offset
from ..errors import InputError
from .devices import META_OFFSET_KEYS, META_TURN_KEYS, parse_offset, parse_turn
from .files import open_regular
from .limits import FLOOR_RANGE_M, MAX_ABS_TIME_S, MAX_DURATION_S, MAX_GAP_S, check_height
from .take import (COLUMNS, DEVICES, MAX_DISTANCE_M, META_KEY, ORIENTATION_VALUES, ORIENTATIONS_KEY, QUAT_NORM_RANGE,
                   Take)


_NUMBER = re.compile(
    r"[+-]?(?:\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|nan|inf|infinity)",
    re.IGNORECASE)
_NL_TO_COMMA = bytes.maketrans(b"\n", b",")
CHUNK_BYTES = 1 << 20  # the reader parses this much of a file at a time
MAX_LINE_BYTES = 1 << 20  # a longer line is not a take's (binary data, a wrong file)


def read_take(path) -> Take:
    """Read a SPEC §3 take file. Every rejection is an :class:`InputError` naming
    the file and line; lost devices (an empty field or ``nan`` in any of their
    seven columns) come back as NaN in all seven; quaternions are normalised.

    The file is read in chunks of lines (:data:`CHUNK_BYTES`) parsed into
    arrays allocated once for the whole take: the memory it takes is about the
    take's arrays (176 bytes a row, less than the file), not several copies of
    the file. Besides SPEC §3, it rejects times beyond ±:data:`MAX_ABS_TIME_S`,
    gaps over :data:`MAX_GAP_S` and takes over :data:`MAX_DURATION_S`, and a
    ``height_m`` outside :data:`HEIGHT_RANGE_M`.
    """
    path = str(path)
    with open_regular(path, "a take file") as f:
        try:
            size = os.fstat(f.fileno()).st_size
            return _TakeReader(path, size).read(f)
        except OSError as exc:
            raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None


def parse_take_bytes(raw: bytes, path="<take>") -> Take:
    """Parse the bytes of a take file (see :func:`read_take`)."""
    return _TakeReader(str(path), len(raw)).read(io.BytesIO(raw))


def _cut(buf: bytes) -> int:
    """Length of the complete lines at the start of ``buf`` (never splitting a
    ``\\r\\n``; the last byte is never taken as a line end), or -1."""
    n = len(buf)
    p = max(buf.rfind(b"\n", 0, n - 1), buf.rfind(b"\r", 0, n - 1))
    if p < 0:
        return -1
    if buf[p] == 13 and buf[p + 1] == 10:
        p += 1
    return p + 1


class _TakeReader:
    """One pass over a take file, chunk by chunk (see :func:`read_take`)."""

    def __init__(self, path: str, size: int):
        self.path = path
        self.size = max(int(size), 0)  # bytes expected: sizes the arrays
        self.meta: dict = {}
        self.lines_done = 0  # lines of the chunks already parsed
        self.bytes_done = 0
        self.columns = None
        self.perm = None  # file column of each COLUMNS entry (None: the same order)
        self.header_line = None
        self.first_line = None  # line of the first data row
        self.n = 0
        self.cap = 0
        self.time = self.pos = self.quat = None
        self.t_first = None
        self.t_last = None  # the previous row's time (rows of earlier chunks)

    # -- the file ----------------------------------------------------------
    def read(self, f) -> Take:
        buf = b""
        first = True
        while True:
            data = f.read(CHUNK_BYTES)
            if first:
                first = False
                if data.startswith(b"\xef\xbb\xbf"):
                    data = data[3:]
                    self.size -= 3
            if not data:
                self._chunk(buf)
                break
            buf = buf + data if buf else data
            cut = _cut(buf)
            if cut < 0:
                if len(buf) > MAX_LINE_BYTES:
                    raise InputError(self.path, f"line longer than {MAX_LINE_BYTES // 1024} KiB: "
                                                "not a take file", self.lines_done + 1)
                continue
            chunk, buf = (buf, b"") if cut == len(buf) else (buf[:cut], buf[cut:])
            self._chunk(chunk)
        return self._finish()

    def _finish(self) -> Take:
        path = self.path
        if self.columns is None:
            raise InputError(path, "empty take file: no header line", max(self.lines_done, 1))
        if self.n == 0:
            raise InputError(path, "no data rows; a take needs at least 2", self.header_line)
        if self.n < 2:
            raise InputError(path, "only 1 data row; a take needs at least 2", self.first_line)
        n = self.n
        return Take(self.time[:n], self.pos[:n], self.quat[:n], self.meta, path)

    # -- one chunk of whole lines -----------------------------------------
    def _chunk(self, raw: bytes) -> None:
        if not raw:
            return
        path = self.path
        self.bytes_done += len(raw)
        if b"\r" in raw:
            raw = raw.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
        if raw.endswith(b"\n"):
            raw = raw[:-1]
        base = self.lines_done  # line number of this chunk's first line, minus 1
        if b"\x00" in raw:
            raise InputError(path, "not a text file (contains NUL bytes)",
                             base + raw.count(b"\n", 0, raw.index(b"\x00")) + 1)
        buf = np.frombuffer(raw, dtype=np.uint8)
        nl = np.flatnonzero(buf == 10)
        starts = np.concatenate([[0], nl + 1])
        ends = np.concatenate([nl, [len(raw)]])
        self.lines_done += len(starts)
        # Commas per line, from the sorted comma positions (no per-byte cumsum).
        cpos = np.flatnonzero(buf == 44)
        n_commas = np.searchsorted(cpos, ends) - np.searchsorted(cpos, starts)
        del cpos
        # Blank lines: empty, or (only when the chunk has spaces or tabs) whitespace-only
        # lines, which have no comma.
        blank = ends == starts
        if b" " in raw or b"\t" in raw:
            for i in np.flatnonzero(~blank & (n_commas == 0)):
                if not raw[starts[i]:ends[i]].strip():
                    blank[i] = True
        # Comment lines: first non-blank character is '#' (checked in Python only for
        # the few lines that contain a '#').
        comment = np.zeros(len(starts), dtype=bool)
        hash_lines = np.unique(np.searchsorted(starts, np.flatnonzero(buf == 35), side="right") - 1)
        for i in hash_lines:
            text = raw[starts[i]:ends[i]].decode("utf-8", "replace").strip()
            if text.startswith("#"):
                comment[i] = True
                _parse_meta(path, base + int(i) + 1, text[1:], self.meta)
        other = np.flatnonzero(~blank & ~comment)
        if self.columns is None:
            if other.size == 0:
                return
            header_i = int(other[0])
            self.header_line = base + header_i + 1
            self.columns = _parse_header(path, self.header_line, raw[starts[header_i]:ends[header_i]])
            order = [self.columns.index(c) for c in COLUMNS]
            self.perm = None if order == list(range(len(COLUMNS))) else np.array(order)
            other = other[1:]
        rows = other
        k = int(rows.size)
        if k == 0:
            return
        ncols = len(self.columns)
        bad = np.flatnonzero(n_commas[rows] != ncols - 1)
        if bad.size:
            i = int(rows[bad[0]])
            raise InputError(path, f"row has {int(n_commas[i]) + 1} fields, the header has {ncols}",
                             base + i + 1)
        if rows[-1] - rows[0] + 1 == k:  # contiguous block: no comments or blank lines between rows
            block = raw[starts[rows[0]]:ends[rows[-1]]]
        else:
            block = b"\n".join(raw[starts[i]:ends[i]] for i in rows)
        values = _parse_numbers(path, block, k, ncols, rows, starts, ends, raw, self.columns, base)
        del block
        data = values if self.perm is None else values[:, self.perm]
        if self.first_line is None:
            self.first_line = base + int(rows[0]) + 1
        self._add(data, rows + (base + 1))

    # -- rows: checks, then into the take's arrays --------------------------
    def _reserve(self, k: int) -> None:
        need = self.n + k
        if need <= self.cap:
            return
        left = max(self.size - self.bytes_done, 0)
        per_row = self.bytes_done / need  # bytes of file per data row so far
        cap = max(need + int(left / max(per_row, 1.0) * 1.02) + 64, int(self.cap * 1.25) + 64)
        time, pos, quat = np.empty(cap), np.empty((cap, 3, 3)), np.empty((cap, 3, 4))
        if self.n:
            time[:self.n] = self.time[:self.n]
            pos[:self.n] = self.pos[:self.n]
            quat[:self.n] = self.quat[:self.n]
        self.time, self.pos, self.quat, self.cap = time, pos, quat, cap

    def _add(self, data: np.ndarray, lines: np.ndarray) -> None:
        """Check ``data`` (rows in :data:`COLUMNS` order, on file ``lines``) and
        append it; the earliest row with a problem is reported."""
        path = self.path
        k = data.shape[0]
        time = data[:, 0]
        dev = data[:, 1:].reshape(k, 3, 7)
        problems = []  # (row, order, message): the earliest row wins

        def first(mask):
            idx = np.flatnonzero(mask)
            return int(idx[0]) if idx.size else None

        with np.errstate(all="ignore"):  # overflowing norms and differences are reported, not warned
            r = first(np.isnan(time))
            if r is not None:
                problems.append((r, 0, "missing time value"))
            inf = np.isinf(data)
            r = first(inf.any(1))
            if r is not None:
                col = COLUMNS[int(np.flatnonzero(inf[r])[0])]
                problems.append((r, 1, f"infinite value in column {col}"))
            r = first(np.abs(time) > MAX_ABS_TIME_S)
            if r is not None:
                problems.append((r, 2, f"time {time[r]:.9g} is out of range (more than {MAX_ABS_TIME_S:g} s "
                                       f"from 0; time is in seconds)"))
            lost = np.isnan(dev).any(-1)  # (k, 3)
            dev = np.where(lost[..., None], np.nan, dev)
            dist = np.linalg.norm(dev[..., :3], axis=-1)
            qn = np.linalg.norm(dev[..., 3:], axis=-1)
            far = dist > MAX_DISTANCE_M
            badq = (qn < QUAT_NORM_RANGE[0]) | (qn > QUAT_NORM_RANGE[1])
            r = first(far.any(1))
            if r is not None:
                d = int(np.flatnonzero(far[r])[0])
                if np.isfinite(dist[r, d]):
                    problems.append((r, 3, f"{DEVICES[d]} position is {dist[r, d]:.6g} m from the origin "
                                           f"(more than {MAX_DISTANCE_M:g} m)"))
                else:
                    big = float(np.abs(dev[r, d, :3]).max())
                    problems.append((r, 3, f"{DEVICES[d]} position is out of range (a coordinate of "
                                           f"{big:.6g} m; more than {MAX_DISTANCE_M:g} m from the origin)"))
            r = first(badq.any(1))
            if r is not None:
                d = int(np.flatnonzero(badq[r])[0])
                lo, hi = QUAT_NORM_RANGE
                if np.isfinite(qn[r, d]):
                    problems.append((r, 4, f"{DEVICES[d]} quaternion norm {qn[r, d]:.6g} is not within "
                                           f"[{lo:g}, {hi:g}]"))
                else:
                    big = float(np.abs(dev[r, d, 3:]).max())
                    problems.append((r, 4, f"{DEVICES[d]} quaternion is out of range (a component of "
                                           f"{big:.6g}; its norm must be within [{lo:g}, {hi:g}])"))
            # Time order, gaps and the duration, also across the previous chunk's last row.
            prev = np.empty(k)
            prev[0] = np.nan if self.t_last is None else self.t_last
            prev[1:] = time[:-1]
            pair = np.isfinite(time) & np.isfinite(prev)
            dt = time - prev
            r = first(~(dt > 0) & pair)
            if r is not None:
                problems.append((r, 5, f"time {time[r]:.9g} is not after the previous row's "
                                       f"{prev[r]:.9g} (time must increase strictly)"))
            r = first((dt > MAX_GAP_S) & pair)
            if r is not None:
                problems.append((r, 6, f"gap of {dt[r]:.6g} s after the previous row's time {prev[r]:.9g} "
                                       f"(more than {MAX_GAP_S:g} s; split the take there)"))
            t_first = time[0] if self.t_first is None else self.t_first
            span = time - t_first
            r = first(span > MAX_DURATION_S)
            if r is not None:
                problems.append((r, 7, f"the take spans more than the maximum of {MAX_DURATION_S / 3600:g} "
                                       f"hours here ({span[r]:.6g} s after its first row; split it)"))
            if problems:
                row, _, msg = min(problems, key=lambda p: (p[0], p[1]))
                raise InputError(path, msg, int(lines[row]))
            self._reserve(k)
            a, b = self.n, self.n + k
            self.time[a:b] = time
            self.pos[a:b] = dev[..., :3]
            self.quat[a:b] = dev[..., 3:] / qn[..., None]
        self.n = b
        self.t_first = t_first
        self.t_last = float(time[-1])


def _parse_meta(path, lineno, text, meta):
    key, eq, value = text.partition("=")
    key, value = key.strip(), value.strip()
    if not eq or not META_KEY.fullmatch(key):
        return  # an ordinary comment
    if key == "height_m":
        try:
            h = float(value)
        except ValueError:
            raise InputError(path, f"height_m is not a number: {value!r}", lineno) from None
        if not np.isfinite(h) or h <= 0:
            raise InputError(path, f"height_m must be a positive number of metres, got {value!r}", lineno)
        meta[key] = check_height(path, h, lineno, "height_m")
    elif key == "role" and value.lower() not in ("leader", "follower"):
        raise InputError(path, f"unknown role {value!r} (expected leader or follower)", lineno)
    elif key == "devices" and value.lower() not in ("joints", "openxr"):
        raise InputError(path, f"unknown devices value {value!r} (expected joints or openxr)", lineno)
    elif key == "floor_y":
        try:
            f = float(value)
        except ValueError:
            raise InputError(path, f"floor_y is not a number: {value!r}", lineno) from None
        if not (np.isfinite(f) and abs(f) <= FLOOR_RANGE_M):
            raise InputError(path, f"floor_y must be a height in metres within ±{FLOOR_RANGE_M:g}, got {value!r}",
                             lineno)
        meta[key] = value
    elif key in META_OFFSET_KEYS:
        parse_offset(value, key, path, lineno)
        meta[key] = value
    elif key in META_TURN_KEYS:
        parse_turn(value, key, path, lineno)
        meta[key] = value
    elif key == ORIENTATIONS_KEY and value.lower() not in ORIENTATION_VALUES:
        raise InputError(path, f"unknown orientations value {value!r} (expected {' or '.join(ORIENTATION_VALUES)})",
                         lineno)
    elif key == "audio_offset_s":
        check_offset(value, path, lineno)
        meta[key] = value
    else:
        meta[key] = value.lower() if key in ("role", "devices", ORIENTATIONS_KEY) else value


def _parse_header(path, lineno, line: bytes):
    text = line.decode("utf-8", "replace")
    names = [c.strip().lower() for c in text.split(",")]
    if names and _NUMBER.fullmatch(names[0]):
        raise InputError(path, "missing header line (expected " + ",".join(COLUMNS[:4]) + ",...)", lineno)
    seen = set()
    for c in names:
        if c not in COLUMNS:
            shown = c if len(c) <= 40 else c[:37] + "..."
            raise InputError(path, f"unknown header column {shown!r}", lineno)
        if c in seen:
            raise InputError(path, f"header column {c!r} appears twice", lineno)
        seen.add(c)
    missing = [c for c in COLUMNS if c not in seen]
    if missing:
        raise InputError(path, "missing header column" + ("s " if len(missing) > 1 else " ")
                         + ", ".join(missing), lineno)
    return names


def _parse_numbers(path, block: bytes, n, ncols, rows, starts, ends, raw, columns, base=0):
    """All fields of the data rows as an ``(n, ncols)`` float array (empty = NaN)."""
    if b" " in block or b"\t" in block:
        # Whitespace-only fields are empty; whitespace inside a field is an error.
        if re.search(rb"[^ \t,\n][ \t]+[^ \t,\n]", block):
            _locate_non_numeric(path, rows, starts, ends, raw, columns, base)
        block = block.translate(None, b" \t")
    # Empty fields -> nan (',,' twice for runs; line starts and ends).
    if b",," in block:
        block = block.replace(b",,", b",nan,").replace(b",,", b",nan,")
    if b",\n" in block:
        block = block.replace(b",\n", b",nan\n")
    if b"\n," in block:
        block = block.replace(b"\n,", b"\nnan,")
    if block.startswith(b","):
        block = b"nan" + block
    if block.endswith(b","):
        block = block + b"nan"
    block = block.translate(_NL_TO_COMMA)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.fromstring(block, dtype=np.float64, sep=",")
    except (ValueError, DeprecationWarning):
        values = None
    if values is None or values.size != n * ncols:
        _locate_non_numeric(path, rows, starts, ends, raw, columns, base)
        raise InputError(path, "non-numeric value in the data rows")
    return values.reshape(n, ncols)


def _locate_non_numeric(path, rows, starts, ends, raw, columns, base=0):
    for i in rows:
        fields = raw[starts[i]:ends[i]].decode("utf-8", "replace").split(",")
        for name, f in zip(columns, fields):
            s = f.strip()
            if s and not _NUMBER.fullmatch(s):
                shown = s if len(s) <= 30 else s[:27] + "..."
                raise InputError(path, f"non-numeric value {shown!r} in column {name}", base + int(i) + 1)


