"""What the user sees while a batch runs: a progress bar on stderr (per-file and
overall progress, ETA; ``\\r`` updates on a terminal, plain lines otherwise) and
one result line per file on stdout (:func:`result_line`), in the order the files
finish (first those decided before any work: skipped, output exists), not the
input order (the report keeps the input order). File names are printed with
their control characters escaped (:func:`~..argtypes.printable`): one line each.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time

from ..argtypes import printable


def fmt_duration(seconds) -> str:
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "--:--"
    s = int(round(max(0.0, seconds)))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def eta(elapsed, fraction):
    """Seconds left at constant throughput (None before any progress)."""
    if fraction <= 0.0:
        return None
    return elapsed * (1.0 - min(fraction, 1.0)) / fraction


class Progress:
    """Overall and per-file progress with an ETA on ``stream`` (stderr): one line
    rewritten with ``\\r`` on a terminal, plain lines otherwise (at each finished
    file and every ``interval`` seconds). Result lines go to ``out`` (stdout)."""

    WIDTH = 24

    def __init__(self, total, stream=None, out=None, enabled=True, tty=None, interval=10.0):
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.out = out if out is not None else sys.stdout
        self.enabled = enabled and self.total > 0
        if tty is None:
            try:
                tty = self.stream.isatty()
            except (AttributeError, ValueError):
                tty = False
        self.tty = tty
        self.interval = interval
        self.t0 = time.perf_counter()
        self.done = 0
        self.running = []  # [(name, fraction)]
        self._shown = False
        self._last_draw = 0.0
        self._last_line = time.perf_counter()
        self._last_done = -1

    def fraction(self):
        if not self.total:
            return 1.0
        return min(1.0, (self.done + sum(f for _, f in self.running)) / self.total)

    def text(self, width=None):
        f = self.fraction()
        elapsed = time.perf_counter() - self.t0
        fill = int(round(self.WIDTH * f))
        bar = "#" * fill + "-" * (self.WIDTH - fill)
        run = ", ".join(f"{printable(n)} {100 * x:.0f}%" for n, x in self.running)
        left = eta(elapsed, f) if self.done < self.total else 0.0
        line = (f"[{bar}] {self.done}/{self.total} files {100 * f:3.0f}% "
                f"elapsed {fmt_duration(elapsed)} ETA {fmt_duration(left)}")
        if run:
            line += " | " + run
        if width and len(line) > width:
            line = line[:max(width - 3, 0)] + "..."
        return line

    def update(self, done, running, force=False):
        self.done, self.running = done, list(running)
        if not self.enabled:
            return
        now = time.perf_counter()
        if self.tty:
            if force or now - self._last_draw >= 0.1:
                cols = shutil.get_terminal_size((100, 20)).columns - 1
                self.stream.write("\r\x1b[K" + self.text(cols))
                self.stream.flush()
                self._shown = True
                self._last_draw = now
        elif done != self._last_done or now - self._last_line >= self.interval:
            self.stream.write("progress: " + self.text() + "\n")
            self.stream.flush()
            self._last_line = now
            self._last_done = done

    def _clear(self):
        if self.enabled and self.tty and self._shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._shown = False

    def result(self, line):
        """One result line (stdout), keeping the bar below it on a terminal."""
        self._clear()
        print(line, file=self.out, flush=True)

    def finish(self):
        self._clear()


def result_line(task, out_dir=None) -> str:
    """The stdout line of a task that is done (ok, failed, skipped, interrupted),
    control characters escaped."""

    def rel(p):
        if out_dir:
            with contextlib.suppress(ValueError):
                return os.path.join(os.path.basename(out_dir.rstrip(os.sep)), os.path.relpath(p, out_dir))
        return p

    if task.status == "ok":
        outs = ", ".join(rel(o) for o in task.outputs)
        line = f"ok      {task.input} -> {outs} ({task.frames} frames, {task.seconds:.2f} s)"
    elif task.status == "skipped":
        line = f"skipped {task.input} ({task.error})"
    else:
        err = str(task.error)  # a reader's message that names the input already: not twice
        line = f"{task.status.upper():7s} {err}" if err.startswith(f"{task.input}:") else \
            f"{task.status.upper():7s} {task.input}: {err}"
    return printable(line)  # a file name with a newline or escape codes stays on its line
