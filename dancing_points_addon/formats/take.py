"""Three-point takes (SPEC §3): the leader's head and two hand devices over time.

Reading (:func:`read_take`) is vectorised: the header and the line structure are
validated first, the numbers are parsed in one C call, and the offending line
is only searched for (in Python) once something is known to be wrong. Writing
(:func:`write_take`) is atomic: a temporary file in the target folder replaced
onto the target, so a failure never leaves a half-written take behind.

:func:`load_input` turns any supported input (take ``.csv``, CMU ``.amc``,
``.bvh``) into a :class:`Take` at the source rate; it is what the command line
and the Blender import use.
"""
from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .files import atomic_output
from ..rotations import axis_rotation, matrix_to_quat
from ..skeleton import HEAD_BONE, TRACKED, Motion

DEVICES = ("head", "lhand", "rhand")
DEVICE_FIELDS = ("px", "py", "pz", "qw", "qx", "qy", "qz")
COLUMNS = ("time",) + tuple(f"{d}_{f}" for d in DEVICES for f in DEVICE_FIELDS)
MAX_DISTANCE_M = 1000.0  # SPEC §3: positions farther than 1 km are rejected
QUAT_NORM_RANGE = (0.5, 2.0)  # SPEC §3: other norms are rejected, these normalised

# The head device looks along its local -Z with +Y up (OpenXR); the CMU skull
# (ASF bone ``head``) faces +Z at rest. Device-to-world = R_head · Ry(180°), so a
# wearer facing +Z has device quaternion (0, 0, 1, 0).
HEAD_DEVICE_OFFSET = axis_rotation("Y", np.pi)


@dataclass
class Take:
    """``time (T,)`` seconds; ``positions (T, 3, 3)`` metres, motion space, device
    order head/lhand/rhand; ``quats (T, 3, 4)`` device-to-world ``(w, x, y, z)``.
    A device that lost tracking on a row has NaN in its position and quaternion.
    """

    time: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    meta: dict = field(default_factory=dict)
    source: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """``(T, 3)`` bool: device tracked on that row."""
        return np.isfinite(self.positions).all(-1) & np.isfinite(self.quats).all(-1)

    @property
    def height(self):
        h = self.meta.get("height_m")
        return float(h) if h not in (None, "") else None


# --------------------------------------------------------------------------- reading

_NUMBER = re.compile(
    r"[+-]?(?:\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|nan|inf|infinity)",
    re.IGNORECASE)
_META_KEY = re.compile(r"[A-Za-z_][\w.\-]*")
_NL_TO_COMMA = bytes.maketrans(b"\n", b",")


def read_take(path) -> Take:
    """Read a SPEC §3 take file. Every rejection is an :class:`InputError` naming
    the file and line; lost devices (an empty field or ``nan`` in any of their
    seven columns) come back as NaN in all seven; quaternions are normalised.
    """
    path = str(path)
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a take file") from None
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    return parse_take_bytes(raw, path)


def parse_take_bytes(raw: bytes, path="<take>") -> Take:
    """Parse the bytes of a take file (see :func:`read_take`)."""
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    if b"\r" in raw:
        raw = raw.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if b"\x00" in raw:
        raise InputError(path, "not a text file (contains NUL bytes)")
    buf = np.frombuffer(raw, dtype=np.uint8)
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate([[0], nl + 1])
    ends = np.concatenate([nl, [len(raw)]])
    # Commas per line, from the sorted comma positions (no per-byte cumsum).
    cpos = np.flatnonzero(buf == 44)
    n_commas = np.searchsorted(cpos, ends) - np.searchsorted(cpos, starts)
    # Blank lines: empty, or (only when the file has spaces or tabs) whitespace-only
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
    meta: dict = {}
    for i in hash_lines:
        text = raw[starts[i]:ends[i]].decode("utf-8", "replace").strip()
        if text.startswith("#"):
            comment[i] = True
            _parse_meta(path, int(i) + 1, text[1:], meta)
    other = np.flatnonzero(~blank & ~comment)
    if other.size == 0:
        raise InputError(path, "empty take file: no header line", int(len(starts)))
    header_i = int(other[0])
    columns = _parse_header(path, header_i + 1, raw[starts[header_i]:ends[header_i]])
    ncols = len(columns)
    rows = other[1:]
    n = int(rows.size)
    if n == 0:
        raise InputError(path, "no data rows; a take needs at least 2", header_i + 1)

    bad = np.flatnonzero(n_commas[rows] != ncols - 1)
    if bad.size:
        i = int(rows[bad[0]])
        raise InputError(path, f"row has {int(n_commas[i]) + 1} fields, the header has {ncols}", i + 1)

    if rows[-1] - rows[0] + 1 == n:  # contiguous block: no comments or blank lines between rows
        block = raw[starts[rows[0]]:ends[rows[-1]]]
    else:
        block = b"\n".join(raw[starts[i]:ends[i]] for i in rows)
    values = _parse_numbers(path, block, n, ncols, rows, starts, ends, raw, columns)
    data = np.empty((n, len(COLUMNS)))
    for j, name in enumerate(columns):
        data[:, COLUMNS.index(name)] = values[:, j]
    lines = rows + 1  # 1-based line number of each data row
    return _build_take(path, data, lines, meta, header_i + 1)


def _parse_meta(path, lineno, text, meta):
    key, eq, value = text.partition("=")
    key, value = key.strip(), value.strip()
    if not eq or not _META_KEY.fullmatch(key):
        return  # an ordinary comment
    if key == "height_m":
        try:
            h = float(value)
        except ValueError:
            raise InputError(path, f"height_m is not a number: {value!r}", lineno) from None
        if not np.isfinite(h) or h <= 0:
            raise InputError(path, f"height_m must be a positive number of metres, got {value!r}", lineno)
        meta[key] = h
    else:
        meta[key] = value


def _parse_header(path, lineno, line: bytes):
    text = line.decode("utf-8", "replace")
    names = [c.strip().lower() for c in text.split(",")]
    if names and _NUMBER.fullmatch(names[0]):
        raise InputError(path, "missing header line (expected " + ",".join(COLUMNS[:4]) + ",...)", lineno)
    seen = set()
    for c in names:
        if c not in COLUMNS:
            raise InputError(path, f"unknown header column {c!r}", lineno)
        if c in seen:
            raise InputError(path, f"header column {c!r} appears twice", lineno)
        seen.add(c)
    missing = [c for c in COLUMNS if c not in seen]
    if missing:
        raise InputError(path, "missing header column" + ("s " if len(missing) > 1 else " ")
                         + ", ".join(missing), lineno)
    return names


def _parse_numbers(path, block: bytes, n, ncols, rows, starts, ends, raw, columns):
    """All fields of the data rows as an ``(n, ncols)`` float array (empty = NaN)."""
    if b" " in block or b"\t" in block:
        # Whitespace-only fields are empty; whitespace inside a field is an error.
        if re.search(rb"[^ \t,\n][ \t]+[^ \t,\n]", block):
            _locate_non_numeric(path, rows, starts, ends, raw, columns)
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
        _locate_non_numeric(path, rows, starts, ends, raw, columns)
        raise InputError(path, "non-numeric value in the data rows")
    return values.reshape(n, ncols)


def _locate_non_numeric(path, rows, starts, ends, raw, columns):
    for i in rows:
        fields = raw[starts[i]:ends[i]].decode("utf-8", "replace").split(",")
        for name, f in zip(columns, fields):
            s = f.strip()
            if s and not _NUMBER.fullmatch(s):
                shown = s if len(s) <= 30 else s[:27] + "..."
                raise InputError(path, f"non-numeric value {shown!r} in column {name}", int(i) + 1)


def _build_take(path, data, lines, meta, header_line) -> Take:
    n = data.shape[0]
    time = data[:, 0]
    dev = data[:, 1:].reshape(n, 3, 7)
    problems = []  # (row, order, message): the earliest row wins

    def first(mask):
        idx = np.flatnonzero(mask)
        return int(idx[0]) if idx.size else None

    r = first(np.isnan(time))
    if r is not None:
        problems.append((r, 0, "missing time value"))
    inf = np.isinf(data)
    r = first(inf.any(1))
    if r is not None:
        col = COLUMNS[int(np.flatnonzero(inf[r])[0])]
        problems.append((r, 1, f"infinite value in column {col}"))
    lost = np.isnan(dev).any(-1)  # (n, 3)
    dev = np.where(lost[..., None], np.nan, dev)
    with np.errstate(invalid="ignore"):
        dist = np.linalg.norm(dev[..., :3], axis=-1)
        qn = np.linalg.norm(dev[..., 3:], axis=-1)
        far = dist > MAX_DISTANCE_M
        badq = (qn < QUAT_NORM_RANGE[0]) | (qn > QUAT_NORM_RANGE[1])
    r = first(far.any(1))
    if r is not None:
        d = int(np.flatnonzero(far[r])[0])
        problems.append((r, 2, f"{DEVICES[d]} position is {dist[r, d]:.6g} m from the origin "
                               f"(more than {MAX_DISTANCE_M:g} m)"))
    r = first(badq.any(1))
    if r is not None:
        d = int(np.flatnonzero(badq[r])[0])
        problems.append((r, 3, f"{DEVICES[d]} quaternion norm {qn[r, d]:.6g} is not within "
                               f"[{QUAT_NORM_RANGE[0]:g}, {QUAT_NORM_RANGE[1]:g}]"))
    with np.errstate(invalid="ignore"):
        r = first(~(np.diff(time) > 0) & np.isfinite(time[1:]) & np.isfinite(time[:-1]))
    if r is not None:
        problems.append((r + 1, 4, f"time {time[r + 1]:.9g} is not after the previous row's "
                                   f"{time[r]:.9g} (time must increase strictly)"))
    if problems:
        row, _, msg = min(problems, key=lambda p: (p[0], p[1]))
        raise InputError(path, msg, int(lines[row]))
    if n < 2:
        raise InputError(path, "only 1 data row; a take needs at least 2", int(lines[0]))
    positions = np.ascontiguousarray(dev[..., :3])
    quats = dev[..., 3:] / qn[..., None]
    return Take(time.copy(), positions, np.ascontiguousarray(quats), meta, str(path))


# --------------------------------------------------------------------------- writing

def take_to_text(take: Take) -> str:
    """The CSV text of a take (lost devices as empty fields)."""
    n = take.n_frames
    data = np.empty((n, len(COLUMNS)))
    data[:, 0] = take.time
    dev = np.concatenate([np.asarray(take.positions, dtype=np.float64),
                          np.asarray(take.quats, dtype=np.float64)], axis=-1)
    lost = ~np.isfinite(dev).all(-1)
    dev[lost] = np.nan
    data[:, 1:] = dev.reshape(n, 21)
    fmt = "%.12g" + ",%.10g" * 21
    body = "\n".join([fmt % tuple(r) for r in data.tolist()])
    body = body.replace("nan", "")
    head = []
    for k, v in take.meta.items():
        v = str(v)
        if _META_KEY.fullmatch(str(k)) and "\n" not in v and "\r" not in v:
            head.append(f"# {k}={v}")
    head.append(",".join(COLUMNS))
    return "\n".join(head) + "\n" + body + "\n"


def write_take(path, take: Take) -> None:
    """Write ``take`` as a SPEC §3 file, atomically; metadata become ``# key=value``.

    Time is written with 12 significant digits, positions and quaternions with
    10 (better than 1e-6 m anywhere within the 1 km limit).
    """
    text = take_to_text(take)
    with atomic_output(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)


# --------------------------------------------------------------------------- extraction

def head_device_quat(head_rotations: np.ndarray) -> np.ndarray:
    """Head device quaternions from global rotations of the skull (SPEC §2 ``head``)."""
    return matrix_to_quat(np.asarray(head_rotations) @ HEAD_DEVICE_OFFSET)


def take_from_tracked(time, positions, head_rot, lhand_rot, rhand_rot, meta=None, source="") -> Take:
    """A take from tracked-point positions ``(T, 3, 3)`` and global rotations of the
    skull and the two wrists ``(T, 3, 3)`` each (SPEC §2 rest-pose convention)."""
    quats = np.stack([head_device_quat(head_rot), matrix_to_quat(lhand_rot),
                      matrix_to_quat(rhand_rot)], axis=1)
    return Take(np.asarray(time, dtype=np.float64), np.array(positions, dtype=np.float64),
                quats, dict(meta or {}), str(source))


def take_from_motion(motion: Motion) -> Take:
    """The three-point take of a full-body clip at its own rate (time ``k / fps``).

    Positions are the SPEC §2 tracked points; the head device is rigid on the
    skull (bone ``head``, device-to-world ``R_head · Ry(180°)``); the hand
    devices carry the wrists' (``lwrist``, ``rwrist``) global rotations.
    No ``height_m`` is written: the user's height is an input (``--height``).
    """
    rot = motion.rotations
    lw, rw = int(TRACKED[1]), int(TRACKED[2])
    time = np.arange(motion.n_frames) / float(motion.fps)
    return take_from_tracked(time, motion.positions[:, TRACKED], rot[:, HEAD_BONE],
                             rot[:, lw], rot[:, rw], {}, motion.source)


INPUT_TYPES = (".csv", ".amc", ".bvh")


# --------------------------------------------------------------------------- any input

def load_input(path, asf=None, input_fps=None, height=None) -> Take:
    """Any supported input as a take at its source rate.

    * ``.csv`` take file (SPEC §3). ``input_fps`` replaces the time column by
      ``t0 + k / input_fps`` (``t0`` the first row's time): the rows are taken
      as regular samples at that rate.
    * ``.amc`` CMU motion (ASF beside it or ``asf``); ``input_fps`` overrides
      the default rate (60 Hz for subjects 60/61, else 120 Hz).
    * ``.bvh`` motion; ``input_fps`` overrides its Frame Time.

    ``height`` (metres) is stored as ``meta['height_m']``. Anything wrong with the
    input is an :class:`InputError`, including unexpected failures of a parser
    on a malformed file.
    """
    path = os.fspath(path)
    if input_fps is not None:
        input_fps = float(input_fps)
        if not (np.isfinite(input_fps) and input_fps > 0):
            raise InputError(path, f"input frame rate must be positive, got {input_fps:g}")
    if not os.path.exists(path):
        raise InputError(path, "no such file")
    if os.path.isdir(path):
        raise InputError(path, "is a folder, not an input file")
    ext = os.path.splitext(path)[1].lower()
    if ext not in INPUT_TYPES:
        raise InputError(path, f"unsupported input type {ext or '(no extension)'!r} "
                               f"(expected {', '.join(INPUT_TYPES)})")
    try:
        if ext == ".csv":
            take = read_take(path)
            if input_fps is not None:
                take.time = take.time[0] + np.arange(take.n_frames) / input_fps
        elif ext == ".amc":
            if asf is not None and not os.path.isfile(os.fspath(asf)):
                raise InputError(asf, "no such ASF file")
            from .asf_amc import load_amc
            take = take_from_motion(load_amc(path, asf, fps=input_fps))
        else:
            take = _take_from_bvh(path, input_fps)
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "file too large to load") from None
    except Exception as exc:  # a parser tripped over a malformed file
        raise InputError(path, f"cannot read {ext[1:].upper()} file "
                               f"({type(exc).__name__}: {exc})") from None
    if take.n_frames < 2:
        raise InputError(path, f"only {take.n_frames} frame(s); a take needs at least 2")
    if height is not None:
        h = float(height)
        if not (np.isfinite(h) and h > 0):
            raise InputError(path, f"height must be a positive number of metres, got {h:g}")
        take.meta["height_m"] = h
    take.source = path
    return take


def _take_from_bvh(path, input_fps=None) -> Take:
    from . import bvh

    data = bvh.parse_bvh(path, input_fps=input_fps)
    tp = bvh.tracked_points(data)
    positions = np.asarray(tp.positions, dtype=np.float64)
    rotations = np.asarray(tp.rotations, dtype=np.float64)
    # tp.fps is 1 / Frame Time, snapped to a whole rate when the file rounded it.
    time = np.arange(positions.shape[0]) / float(tp.fps)
    return take_from_tracked(time, positions, rotations[:, 0], rotations[:, 1], rotations[:, 2],
                             {}, path)
