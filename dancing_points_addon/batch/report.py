"""What a batch leaves behind: the JSON report and the summary line.

The report (``OUT_DIR/batch_report.json`` or ``--report``) holds the run
(``format, output_dir, jobs, models, started, seconds, interrupted``, the
``counts`` per status, ``error`` when the run could not go on) and per file
``input, output, outputs, status, error, frames, seconds``.
"""
from __future__ import annotations

import collections
import json

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
