"""What a batch leaves behind: the JSON report and the summary line.

The report (``OUT_DIR/batch_report.json`` or ``--report``) holds the run
(``format, output_dir, jobs, models, started, seconds, interrupted``, the
``counts`` per status, ``error`` when the run could not go on) and per file
``input, output, outputs, status, error, frames, seconds``, in input order.

The report path is checked before any work (:func:`check_report_path`): never
one of the inputs, and an existing file there is replaced only when it is a
batch report itself (or with ``--overwrite``).
"""
from __future__ import annotations

import collections
import json
import os

from ..errors import InputError
from ..formats.files import writable_folder

REPORT_NAME = "batch_report.json"
STATUSES = ("ok", "failed", "skipped", "interrupted", "pending")


def build_report(tasks, fmt, out_dir, jobs, model_dir, started, seconds, outcome, fatal=None) -> dict:
    counts = collections.Counter(t.status for t in tasks)
    report = {"format": fmt, "output_dir": out_dir, "jobs": jobs, "models": model_dir,
              "started": started, "seconds": round(seconds, 3), "interrupted": outcome != "done",
              "counts": {k: counts.get(k, 0) for k in STATUSES},
              "files": [t.record() for t in tasks]}
    if fatal:
        report["error"] = fatal
    return report


def summary_line(report, outcome, seconds, report_path) -> str:
    """The last stdout line: the counts, the time and where the report is."""
    c = report["counts"]
    jobs = report["jobs"]
    return (f"{len(report['files'])} file(s): {c['ok']} ok, {c['failed']} failed, {c['skipped']} skipped"
            + (f", {c['interrupted'] + c['pending']} not done" if outcome != "done" else "")
            + f" in {seconds:.1f} s ({jobs} job{'s' if jobs != 1 else ''})"
            + (f"; report: {report_path}" if report_path else ""))


def write_report(path, data) -> None:
    from ..formats.files import atomic_output

    with atomic_output(path, "w", encoding="utf-8", newline="\n") as f:
        json.dump(data, f, indent=1)
        f.write("\n")


REPORT_KEYS = ("format", "output_dir", "counts", "files")


def is_report(path) -> bool:
    """Whether the file ``path`` holds a batch report (a JSON object with the keys
    of :func:`build_report`)."""
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(data, dict) and all(k in data for k in REPORT_KEYS) and isinstance(data["files"], list)


def check_report_path(path, overwrite=False, explicit=True) -> None:
    """Before any work: an :class:`InputError` (one line) when the report cannot go
    to ``path``: a folder; an existing file that is not a batch report (unless
    ``overwrite``); for an ``explicit`` ``--report``, a missing folder. (That it
    is no input: :func:`.plan.check_not_inputs`.)"""
    flag = "--report: " if explicit else ""
    if os.path.isdir(path):
        raise InputError(path, f"{flag}the report path is a folder")
    if explicit and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        raise InputError(path, f"{flag}the report's folder does not exist")
    if os.path.lexists(path) and not overwrite and not is_report(path):
        raise InputError(path, f"{flag}exists and is not a Dancing Points batch report (use --overwrite to "
                               f"replace it, or choose another --report path)")
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(folder):  # (the output folder may be made later; its own check is the outputs')
        why = writable_folder(folder)  # what writing the report at the end will need
        if why is not None:
            raise InputError(path, f"{flag}cannot write the report there ({why})")
