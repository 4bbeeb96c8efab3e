"""The worker protocol: how the parent (:mod:`.scheduler`) and its workers
(:mod:`.worker`) talk. Every message is a JSON object whose ``"type"`` is one of
the constants below; this module is the only place that builds or parses them.

* Parent -> worker, one JSON object per line on the worker's stdin: :func:`job`
  (convert one take), or a message of type :data:`EXIT` (stop; closing the
  worker's stdin does the same).
* Worker -> parent, JSON lines on the worker's stdout, each prefixed by
  :data:`PREFIX`, so that everything else a library prints there is ignored
  (the worker also moves its own stdout to stderr, which goes to a log file
  whose tail is reported if the worker dies): :func:`ready` once, then for each
  job any number of :func:`progress` and one :func:`done` or :func:`error`.
"""
from __future__ import annotations

import json

PREFIX = "@@dancing_points.batch@@ "

# parent -> worker
JOB = "job"  # convert one take: id, input, temps {kind: path}, needs_bpy, options
EXIT = "exit"  # stop
# worker -> parent
READY = "ready"  # started, waiting for jobs: pid
PROGRESS = "progress"  # of the job id: fraction in [0, 1]
DONE = "done"  # the job id wrote all its temporary files: frames, seconds
ERROR = "error"  # the job id failed: error (one line), seconds


# --------------------------------------------------------------------------- the messages

def job(task_id, path, temps, needs_bpy, options) -> dict:
    return {"type": JOB, "id": task_id, "input": path, "temps": temps, "needs_bpy": needs_bpy,
            "options": options}


def ready(pid) -> dict:
    return {"type": READY, "pid": pid}


def progress(job_id, fraction) -> dict:
    return {"type": PROGRESS, "id": job_id, "fraction": round(float(fraction), 4)}


def done(job_id, frames, seconds) -> dict:
    return {"type": DONE, "id": job_id, "frames": frames, "seconds": seconds}


def error(job_id, reason, seconds) -> dict:
    return {"type": ERROR, "id": job_id, "error": reason, "seconds": seconds}


# --------------------------------------------------------------------------- parent -> worker

def encode_request(msg) -> bytes:
    """The line the parent writes to a worker's stdin."""
    return (json.dumps(msg) + "\n").encode("utf-8")


def decode_request(line: str):
    """The message of a line a worker read from its stdin (None for a blank line)."""
    line = line.strip()
    return json.loads(line) if line else None


# --------------------------------------------------------------------------- worker -> parent

class Orphaned(BaseException):
    """The parent is gone (a write to it failed): unwind and exit."""


class Channel:
    """The worker's end: messages to the parent, on ``stream`` (the worker's original stdout)."""

    def __init__(self, stream):
        self.stream = stream

    def send(self, msg):
        try:
            self.stream.write(PREFIX + json.dumps(msg) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            raise Orphaned() from None


def decode_reply(raw: bytes):
    """The message of a line of a worker's stdout; None for anything that is not one."""
    line = raw.decode("utf-8", "replace")
    if not line.startswith(PREFIX):
        return None
    try:
        return json.loads(line[len(PREFIX):])
    except ValueError:
        return None
