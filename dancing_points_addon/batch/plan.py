"""Planning a batch: which files, which outputs, which temporary names.

* Inputs: files, or folders searched recursively by extension (``.csv``, ``.bvh``,
  ``.amc``, ``.fbx``: an FBX take is read by Blender's importer in a worker with
  ``bpy``, whatever the output format). Hidden files and folders and the output
  folder are not searched.
* Outputs: one per take, named after it (``take.npz``, ``take.blend``,
  ``take.fbx``; ``take_leader.bvh`` + ``take_follower.bvh``; ``--render`` adds
  ``take.mp4``), in the output folder, under the input's sub-folder when it was
  found inside a folder. Two takes that would get the same name get their
  source extension appended (``take_csv.npz``, ``take_bvh.npz``).
* Temporary files: a worker writes ``.NAME.part-PID.EXT`` beside each output
  (``PID``: the batch's own process, so that no two processes ever share one);
  the parent renames them into place only once a take is complete
  (:mod:`.scheduler`), and never over an existing file unless ``--overwrite``;
  with ``--resume`` the takes whose outputs all exist are skipped. The
  temporary files that a batch killed on the spot left beside this batch's
  outputs are removed at its start (:func:`remove_stale_temps`).
* Never over an input: an output (or the report) that is one of the inputs
  is refused before any work (:func:`check_not_inputs`).
"""
from __future__ import annotations

import collections
import contextlib
import os
import re
import shutil
import time

from ..errors import InputError

PART = ".part"


def discover(paths, exts, exclude=()):
    """``[(path, rel_dir)]``: the files among ``paths`` and, for folders, the files
    below them (recursively, sorted) whose extension is in ``exts``; ``rel_dir`` is
    the file's sub-folder relative to the folder it was found in ("" for a file
    given directly). A file given directly is kept whatever its extension (its
    conversion then reports the problem). Hidden entries, the folders in
    ``exclude`` and duplicates are left out."""
    exts = tuple(e.lower() for e in exts)
    excluded = {os.path.realpath(e) for e in exclude}
    out, seen = [], set()

    def add(path, rel):
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            out.append((os.path.abspath(path), rel))

    for p in paths:
        p = os.fspath(p)
        if os.path.isdir(p):
            for dirpath, dirnames, filenames in os.walk(p):
                dirnames[:] = sorted(d for d in dirnames if not d.startswith(".")
                                     and os.path.realpath(os.path.join(dirpath, d)) not in excluded)
                rel = os.path.relpath(dirpath, p)
                rel = "" if rel == "." else rel
                for f in sorted(filenames):
                    if not f.startswith(".") and os.path.splitext(f)[1].lower() in exts:
                        add(os.path.join(dirpath, f), rel)
        else:
            add(p, "")
    return out


def output_bases(entries):
    """Output base name (relative path without extension) of each ``(path, rel_dir)``:
    the input's stem; on a clash the source extension is appended, then a number."""
    bases = [os.path.join(rel, os.path.splitext(os.path.basename(p))[0]) for p, rel in entries]
    counts = collections.Counter(b.lower() for b in bases)
    for i, (p, _) in enumerate(entries):
        if counts[bases[i].lower()] > 1:
            ext = os.path.splitext(p)[1].lower().lstrip(".")
            if ext:
                bases[i] = f"{bases[i]}_{ext}"
    used, final = set(), []
    for b in bases:
        cand, k = b, 2
        while cand.lower() in used:
            cand, k = f"{b}_{k}", k + 1
        used.add(cand.lower())
        final.append(cand)
    return final


def output_kinds(fmt: str, render: bool):
    """``[(kind, suffix)]`` of the files one take produces."""
    kinds = {"npz": [("npz", ".npz")], "blend": [("blend", ".blend")], "fbx": [("fbx", ".fbx")],
             "bvh": [("bvh_leader", "_leader.bvh"), ("bvh_follower", "_follower.bvh")]}[fmt]
    return kinds + ([("mp4", ".mp4")] if render else [])


def temp_path(final: str, pid=None) -> str:
    """The temporary name a worker writes before the rename: ``.NAME.part-PID.EXT``
    beside ``final`` (``PID``: this process by default; the real extension kept
    last, which some writers need)."""
    folder, name = os.path.split(final)
    stem, ext = os.path.splitext(name)
    return os.path.join(folder, f".{stem}{PART}-{os.getpid() if pid is None else int(pid)}{ext}")


_TEMP_NAME = re.compile(r"(\..*" + re.escape(PART) + r"-)(\d+)(.*)", re.DOTALL)


def stale_temps(finals):
    """The temporary files (and what their writers left, :func:`temp_leftovers`)
    of the outputs ``finals`` whose batch process is no longer running, or is this
    one (which has none while it does not run): what a batch killed on the spot
    left. Each folder is listed once."""
    from .lock import pid_alive

    wanted = collections.defaultdict(dict)  # folder -> {".STEM.part-": {EXT}}
    for final in finals:
        folder, name = os.path.split(final)
        stem, ext = os.path.splitext(name)
        wanted[folder].setdefault(f".{stem}{PART}-", set()).add(ext)
    found, alive = [], {}
    for folder, prefixes in wanted.items():
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        for n in names:
            m = _TEMP_NAME.fullmatch(n)
            if not m or m.group(1) not in prefixes:
                continue
            pid, tail = int(m.group(2)), m.group(3)
            if not any(tail in (ext, ext + "@", ext + ".d") for ext in prefixes[m.group(1)]):
                continue
            if pid not in alive:
                alive[pid] = pid != os.getpid() and pid_alive(pid)
            if not alive[pid]:
                found.append(os.path.join(folder, n))
    return sorted(found)


def remove_stale_temps(tasks) -> list:
    """Remove :func:`stale_temps` of the tasks' outputs; returns what was removed."""
    stale = stale_temps([o for t in tasks for o in t.outputs])
    for p in stale:
        if os.path.isdir(p) and not os.path.islink(p):
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(p)
    return stale


def temp_leftovers(tmp: str):
    """Everything a writer may leave for the temporary ``tmp``: the file itself,
    Blender's ``tmp@`` save file, a render folder ``tmp.d``."""
    return [tmp, tmp + "@", tmp + ".d"]


def remove_temps(tmps) -> None:
    for tmp in tmps:
        for p in temp_leftovers(tmp):
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError, IsADirectoryError, PermissionError):
                    os.unlink(p)


class Task:
    """One input take and what became of it."""

    def __init__(self, index, path, outputs, kinds):
        self.index = index
        self.input = path
        self.outputs = list(outputs)  # final paths, in kind order
        self.kinds = list(kinds)
        self.temps = [temp_path(o) for o in self.outputs]
        self.status = "pending"  # ok | failed | skipped | interrupted | pending
        self.error = None
        self.frames = None
        self.seconds = None
        self.replace = False  # may replace existing outputs
        self.fraction = 0.0
        self.started = None
        try:
            self.size = os.path.getsize(path)
        except OSError:
            self.size = 0

    @property
    def name(self):
        return os.path.basename(self.input)

    def finish(self, status, error=None, frames=None, seconds=None):
        """Record the outcome; ``seconds`` default: since :attr:`started`."""
        self.status, self.error = status, error
        if frames is not None:
            self.frames = int(frames)
        self.seconds = seconds if seconds is not None else (
            time.perf_counter() - self.started if self.started else None)

    def record(self):
        return {"input": self.input, "output": self.outputs[0] if self.outputs else None,
                "outputs": self.outputs, "status": self.status, "error": self.error,
                "frames": self.frames, "seconds": None if self.seconds is None else round(self.seconds, 3)}


def settle_unfinished(tasks, fatal=None, signal_stop=None) -> str:
    """After a batch run: a started task still pending was interrupted; with a
    ``fatal`` error every pending or interrupted task failed with it. Returns
    the run's ending: "terminated" / "interrupted" for ``signal_stop``
    (SIGTERM / another signal number), else "done"."""
    import signal

    for t in tasks:
        if t.status == "pending" and t.started is not None:
            t.status, t.error = "interrupted", "interrupted before it finished"
            t.seconds = None
    if fatal:
        for t in tasks:
            if t.status in ("pending", "interrupted"):
                t.status, t.error = "failed", fatal
    if signal_stop is not None:
        return "terminated" if signal_stop == getattr(signal, "SIGTERM", None) else "interrupted"
    return "done"


def output_paths(entries, out_dir, fmt, render=False):
    """The output paths of each of ``entries`` (see :func:`discover`), in kind order."""
    kinds = output_kinds(fmt, render)
    return [[os.path.join(out_dir, base + suffix) for _, suffix in kinds] for base in output_bases(entries)]


def check_not_inputs(entries, paths, what="output") -> None:
    """An :class:`InputError` when one of ``paths`` (outputs, the report) is one of
    the input files of ``entries`` (the same file: also a hard or symbolic link)."""
    ids = {}
    for p, _ in entries:
        with contextlib.suppress(OSError):
            st = os.stat(p)
            ids[(st.st_dev, st.st_ino)] = p
    for p in paths:
        try:
            st = os.stat(p)
        except OSError:
            continue  # (an output that does not exist is no input)
        inp = ids.get((st.st_dev, st.st_ino))
        if inp is not None:
            raise InputError(p, f"this {what} is the input {inp}: it would be overwritten; choose another "
                                f"{'output folder (-o)' if what == 'output' else 'path'}")


def plan(entries, out_dir, fmt, render=False, overwrite=False, resume=False):
    """Tasks for ``entries`` (see :func:`discover`); outputs that already exist make a
    task ``skipped`` (``resume``) or ``failed`` (neither ``resume`` nor ``overwrite``)."""
    kinds = output_kinds(fmt, render)
    tasks = []
    for i, ((path, _), outs) in enumerate(zip(entries, output_paths(entries, out_dir, fmt, render))):
        t = Task(i, path, outs, [k for k, _ in kinds])
        exist = [o for o in outs if os.path.lexists(o)]
        if resume and exist and len(exist) == len(outs):
            t.status, t.error = "skipped", "output exists"
        elif exist and (overwrite or resume):
            t.replace = True  # --overwrite; or --resume over an incomplete set of outputs
        elif exist:
            t.status = "failed"
            t.error = (f"{exist[0]}: output exists (use --overwrite to replace it or --resume to "
                       f"skip this take)")
        tasks.append(t)
    return tasks


def _makedirs(folder):
    """``os.makedirs``; returns the folders it created."""
    new = []
    d = os.path.abspath(folder)
    while not os.path.isdir(d):
        new.append(d)
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    os.makedirs(folder, exist_ok=True)
    return new


def make_output_dirs(tasks):
    """Create the folders of the pending tasks' outputs; returns the folders it
    made (for :func:`remove_empty_dirs`)."""
    made = []
    for t in tasks:
        if t.status == "pending":
            for o in t.outputs:
                try:
                    made.extend(_makedirs(os.path.dirname(o)))
                except OSError as exc:
                    raise InputError(os.path.dirname(o), f"cannot create the output folder "
                                                         f"({exc.strerror or exc})") from None
    return made


def remove_empty_dirs(made) -> None:
    """Remove the folders of ``made`` (deepest first) that stayed empty."""
    for d in sorted(set(made), key=len, reverse=True):
        with contextlib.suppress(OSError):
            os.rmdir(d)  # only if empty
