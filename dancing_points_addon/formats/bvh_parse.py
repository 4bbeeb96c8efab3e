"""BVH files, reading the text: :func:`parse_bvh` to :class:`BvhData` (the
hierarchy, channels and frames, in the file's units). Conventions, namings and
the kinematics are in :mod:`.bvh`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .files import read_text
from .limits import check_duration, check_rate
from .naming import bone_key

_CHANNELS = {
    "xposition": "Xposition", "yposition": "Yposition", "zposition": "Zposition",
    "xrotation": "Xrotation", "yrotation": "Yrotation", "zrotation": "Zrotation",
}


@dataclass
class BvhData:
    """A parsed BVH file, numbers as in the file (file units, degrees).

    Joints are in file (depth-first) order; ``parents[j] < j`` (root: -1).
    ``channels[j]`` are canonical names (``'Xposition'``, ``'Zrotation'``, ...)
    whose values are ``values[:, channel_start[j] + k]``.
    ``end_parents[e]`` is the joint that End Site ``e`` belongs to.
    """

    path: str
    names: list
    parents: np.ndarray
    offsets: np.ndarray  # (J, 3)
    channels: list  # [tuple of str]
    channel_start: np.ndarray  # (J,)
    end_parents: np.ndarray  # (E,)
    end_offsets: np.ndarray  # (E, 3)
    frame_time: float  # seconds, as used (input_fps override applied)
    values: np.ndarray  # (T, C)
    joint_lines: list = field(default_factory=list)  # line of each ROOT/JOINT keyword
    frames_line: int | None = None
    warnings: list = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def fps(self) -> float:
        """``1 / frame_time``, snapped to a whole rate when the frame time is that
        rate rounded to 6 decimals (``0.016667`` -> 60), as exporters write it."""
        return _snap_fps(self.frame_time)

    def index(self, name: str) -> int:
        """Index of a joint by exact name, else by normalised name (namespace,
        case, ``_-. `` ignored). ``KeyError`` if absent."""
        if name in self.names:
            return self.names.index(name)
        key = bone_key(name)
        for i, n in enumerate(self.names):
            if bone_key(n) == key:
                return i
        raise KeyError(name)

    def children(self, j: int) -> list:
        return [int(c) for c in np.nonzero(self.parents == j)[0]]


def _read_lines(path):
    return read_text(path).replace("\r\n", "\n").replace("\r", "\n").split("\n")


def frame_line(path, index: int) -> int | None:
    """The line of the ``index``-th frame row (from 0) of a BVH file (the
    non-blank lines after ``Frame Time:``), for a message about that frame
    found after parsing; None if there is no such row."""
    k, rows = -1, False
    for lineno, line in enumerate(_read_lines(path), 1):
        if not rows:
            rows = re.match(r"^\s*frame\s*time\s*:", line, re.IGNORECASE) is not None
        elif line.strip():
            k += 1
            if k == index:
                return lineno
    return None


def _snap_fps(frame_time: float) -> float:
    fps = 1.0 / frame_time if frame_time > 1e-300 else float("inf")
    if not np.isfinite(fps) or fps > 1e12:
        return fps
    r = round(fps)
    if r >= 1 and abs(frame_time - 1.0 / r) <= 5.01e-7:
        return float(r)
    return fps


def _float(path, tok, lineno, what):
    try:
        v = float(tok)
    except ValueError:
        raise InputError(path, f"non-numeric value {tok!r} in {what}", lineno) from None
    if not np.isfinite(v):
        raise InputError(path, f"non-finite value {tok!r} in {what}", lineno)
    return v


class _Tokens:
    """Whitespace tokens of the hierarchy section, each with its line number."""

    def __init__(self, path, lines):
        self.path = path
        self.lines = lines
        self.toks = []
        for i, line in enumerate(lines, 1):
            parts = line.split()
            if parts and parts[0].upper() == "MOTION":
                self.motion_line = i
                break
            # Braces glued to words ("JOINT Hips{", "}}") become their own tokens.
            for p in parts:
                for t in re.findall(r"[{}]|[^{}]+", p):
                    self.toks.append((t, i))
        else:
            self.motion_line = None
        self.pos = 0

    def peek(self):
        return self.toks[self.pos] if self.pos < len(self.toks) else (None, self.last_line)

    def next(self):
        t = self.peek()
        self.pos += 1
        return t

    @property
    def last_line(self):
        if self.motion_line is not None:
            return self.motion_line
        n = len(self.lines)
        while n > 1 and not self.lines[n - 1].strip():
            n -= 1
        return max(n, 1)


def parse_bvh(path, input_fps: float | None = None) -> BvhData:
    """Parse a BVH file. ``input_fps`` overrides the file's ``Frame Time``.

    Rejects with :class:`InputError` (file and line): a missing HIERARCHY or
    MOTION section, more than one ROOT, unbalanced braces, malformed OFFSET or
    CHANNELS, a missing or malformed ``Frames:`` / ``Frame Time:`` line, a
    frame time that is not positive or not a rate within
    ``limits.INPUT_FPS_RANGE`` (unless ``input_fps`` is given, which must be), a
    motion longer than ``limits.MAX_DURATION_S`` (checked before its rows are
    read), a non-regular file (FIFO, device), a frame
    row with the wrong number of values, non-numeric or non-finite values,
    fewer frame rows than ``Frames:`` declares. More rows than declared are
    accepted (all are used) with a note in ``BvhData.warnings``.
    """

    path = str(path)
    if input_fps is not None:
        input_fps = check_rate(path, input_fps)
    lines = _read_lines(path)
    tk = _Tokens(path, lines)

    tok, ln = tk.next()
    if tok is None or tok.upper() != "HIERARCHY":
        raise InputError(path, "not a BVH file: it must start with HIERARCHY", ln if tok else 1)

    names, parents, offsets, channels, joint_lines = [], [], [], [], []
    end_parents, end_offsets = [], []

    def read_offset(owner):
        tok, ln = tk.next()
        if tok is None or tok.upper() != "OFFSET":
            raise InputError(path, f"{owner}: expected OFFSET, found {tok or 'end of hierarchy'!r}", ln)
        vals = []
        for _ in range(3):
            t, l2 = tk.next()
            if t is None or t in "{}" or l2 != ln:
                raise InputError(path, f"{owner}: OFFSET needs 3 numbers", ln)
            vals.append(_float(path, t, ln, "OFFSET"))
        return vals

    def read_name(kw_line, what):
        parts = []
        while True:
            t, l2 = tk.peek()
            if t is None or l2 != kw_line or t in "{}":
                break
            parts.append(t)
            tk.next()
        if not parts:
            raise InputError(path, f"{what} without a name", kw_line)
        return "_".join(parts)

    def expect_open(owner, kw_line):
        t, l2 = tk.next()
        if t != "{":
            raise InputError(path, f"{owner}: expected '{{', found {t or 'end of hierarchy'!r}", l2 if t else kw_line)
        return l2

    def read_channels(owner, l2):
        nt, _ = tk.next()
        try:
            n = int(nt)
        except (TypeError, ValueError):
            raise InputError(path, f"{owner}: CHANNELS needs a count, found {nt!r}", l2) from None
        if n < 0 or n > 6:
            raise InputError(path, f"{owner}: CHANNELS count must be 0 to 6, got {n}", l2)
        lst = []
        for _ in range(n):
            ct, cl = tk.peek()
            canon = _CHANNELS.get((ct or "").lower())
            if canon is None:
                raise InputError(path, f"{owner}: CHANNELS declares {n} channels but lists {len(lst)}"
                                 + (f" (unknown channel {ct!r})" if ct and ct not in "{}" and
                                    ct.upper() not in ("JOINT", "END", "OFFSET") else ""), l2)
            tk.next()
            if canon in lst:
                raise InputError(path, f"{owner}: channel {canon} listed twice", cl)
            lst.append(canon)
        return tuple(lst)

    def parse_joint(kw_line, parent, depth=0):
        if depth > 200:
            raise InputError(path, "hierarchy nested more than 200 joints deep", kw_line)
        name = read_name(kw_line, "ROOT/JOINT")
        owner = f"joint {name!r}"
        open_line = expect_open(owner, kw_line)
        j = len(names)
        names.append(name)
        parents.append(parent)
        joint_lines.append(kw_line)
        offset, chans = None, None
        while True:  # OFFSET and CHANNELS, in either order, before any child
            t, l2 = tk.peek()
            u = (t or "").upper()
            if u == "OFFSET" and offset is None:
                offset = read_offset(owner)
            elif u == "CHANNELS" and chans is None:
                tk.next()
                chans = read_channels(owner, l2)
            elif u in ("OFFSET", "CHANNELS"):
                raise InputError(path, f"{owner}: {t} given twice", l2)
            else:
                break
        if offset is None:
            raise InputError(path, f"{owner} has no OFFSET (found {t or 'end of hierarchy'!r} "
                             f"at line {l2})", kw_line)
        offsets.append(offset)
        chans = chans or ()
        channels.append(chans)
        while True:
            t, l2 = tk.next()
            if t is None:
                raise InputError(path, f"unbalanced braces: '{{' of {owner} (line {open_line}) is never closed"
                                 + ("" if tk.motion_line is None else " before MOTION"), open_line)
            u = t.upper()
            if t == "}":
                return
            if u == "JOINT":
                parse_joint(l2, j, depth + 1)
            elif u == "END":
                s, _ = tk.next()
                if s is None or s.upper() != "SITE":
                    raise InputError(path, f"expected 'End Site', found 'End {s or ''}'", l2)
                while True:  # an optional name after "End Site"
                    t3, l3 = tk.peek()
                    if t3 is None or l3 != l2 or t3 == "{":
                        break
                    tk.next()
                eo = expect_open(f"End Site of {owner}", l2)
                end_offsets.append(read_offset(f"End Site of {owner}"))
                end_parents.append(j)
                t4, l4 = tk.next()
                if t4 != "}":
                    raise InputError(path, f"unbalanced braces: End Site of {owner} (line {eo}) "
                                     f"must close after its OFFSET, found {t4 or 'end of hierarchy'!r}",
                                     l4 if t4 else eo)
            elif u == "ROOT":
                raise InputError(path, "several roots: ROOT inside a joint", l2)
            elif u in ("OFFSET", "CHANNELS"):
                raise InputError(path, f"{owner}: {t} must come first in the joint, before JOINT/End Site", l2)
            else:
                raise InputError(path, f"{owner}: unexpected {t!r} in the hierarchy", l2)

    root_seen = False
    while True:
        tok, ln = tk.next()
        if tok is None:
            break
        u = tok.upper()
        if u == "ROOT":
            if root_seen:
                raise InputError(path, "several roots: a second ROOT (only one skeleton per file is supported)", ln)
            root_seen = True
            parse_joint(ln, -1)
        elif tok == "}":
            raise InputError(path, "unbalanced braces: '}' without a matching '{'", ln)
        elif tok == "{":
            raise InputError(path, "unbalanced braces: '{' outside any joint", ln)
        else:
            raise InputError(path, f"unexpected {tok!r} in the hierarchy", ln)
    if not root_seen:
        raise InputError(path, "no ROOT joint in the HIERARCHY", tk.last_line)
    if tk.motion_line is None:
        raise InputError(path, "no MOTION section after the hierarchy", tk.last_line)

    # ----------------------------------------------------------------- MOTION
    i = tk.motion_line  # 0-based index of the line after MOTION
    after = lines[i - 1].split()[1:]
    if after:
        raise InputError(path, f"unexpected {' '.join(after)!r} after MOTION", i)

    def next_line(i, what):
        start = i
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise InputError(path, f"missing '{what}' line in MOTION (end of file)", start)
        return i

    i = next_line(i, "Frames:")
    m = re.match(r"^\s*frames\s*:\s*(\S+)\s*$", lines[i], re.IGNORECASE)
    if not m:
        raise InputError(path, f"expected 'Frames: N', found {lines[i].strip()[:40]!r}", i + 1)
    frames_line = i + 1
    try:
        n_declared = int(m.group(1))
    except ValueError:
        raise InputError(path, f"frame count must be a whole number, found {m.group(1)!r}", frames_line) from None
    if n_declared < 1:
        raise InputError(path, f"no frames (Frames: {n_declared})", frames_line)
    i = next_line(i + 1, "Frame Time:")
    m = re.match(r"^\s*frame\s*time\s*:\s*(\S+)\s*$", lines[i], re.IGNORECASE)
    if not m:
        raise InputError(path, f"expected 'Frame Time: SECONDS', found {lines[i].strip()[:40]!r}", i + 1)
    ft_line = i + 1
    try:
        frame_time = float(m.group(1))
    except ValueError:
        raise InputError(path, f"non-numeric frame time {m.group(1)!r}", ft_line) from None
    if input_fps is not None:
        frame_time = 1.0 / float(input_fps)
        dur_line = frames_line
    elif not np.isfinite(frame_time) or frame_time <= 0:
        raise InputError(path, f"frame time must be positive, got {m.group(1)} (override with --input-fps)",
                         ft_line)
    else:
        check_rate(path, _snap_fps(frame_time), ft_line,
                   f"frame rate (Frame Time {m.group(1)} s; override with --input-fps)")
        dur_line = ft_line
    # Before reading the rows: the declared frames must fit the maximum duration.
    check_duration(path, (n_declared - 1) * frame_time, dur_line,
                   f"the motion ({n_declared} frames of {frame_time:g} s)")

    n_ch = sum(len(c) for c in channels)
    row_lines, tokens = [], []
    for k in range(i + 1, len(lines)):
        parts = lines[k].split()
        if not parts:
            continue
        if len(parts) != n_ch:
            raise InputError(path, f"frame {len(row_lines) + 1} has {len(parts)} values, expected {n_ch} "
                             "(one per channel)", k + 1)
        row_lines.append(k + 1)
        tokens.extend(parts)
    n_rows = len(row_lines)
    warnings = []
    if n_rows < n_declared:
        raise InputError(path, f"Frames: declares {n_declared} frames but only {n_rows} frame rows follow "
                         "(truncated file?)", frames_line)
    if n_rows > n_declared:
        check_duration(path, (n_rows - 1) * frame_time, frames_line,
                       f"the motion ({n_rows} frame rows of {frame_time:g} s)")
        warnings.append(f"Frames: declares {n_declared} frames but {n_rows} rows follow; all rows are used")
    try:
        values = np.array(tokens, dtype=np.float64).reshape(n_rows, n_ch)
    except ValueError:
        for r, lnum in enumerate(row_lines):
            for t in lines[lnum - 1].split():
                _float(path, t, lnum, f"frame {r + 1}")
        raise  # pragma: no cover (the loop above always finds the culprit)
    if not np.all(np.isfinite(values)):
        r = int(np.argwhere(~np.isfinite(values))[0, 0])
        raise InputError(path, f"non-finite value in frame {r + 1}", row_lines[r])

    starts = np.concatenate([[0], np.cumsum([len(c) for c in channels])[:-1]]).astype(np.int64)
    return BvhData(
        path=path, names=names, parents=np.asarray(parents, dtype=np.int64),
        offsets=np.asarray(offsets, dtype=np.float64).reshape(-1, 3), channels=channels,
        channel_start=starts, end_parents=np.asarray(end_parents, dtype=np.int64),
        end_offsets=np.asarray(end_offsets, dtype=np.float64).reshape(-1, 3),
        frame_time=float(frame_time), values=values, joint_lines=joint_lines,
        frames_line=frames_line, warnings=warnings)


# --------------------------------------------------------------------------- kinematics
