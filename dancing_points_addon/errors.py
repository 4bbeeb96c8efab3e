"""User-facing errors: one base class, one formatter.

Every error whose message is written for the user (bad input, a rig that cannot
be retargeted, missing models, ...) is a :class:`UserError`: the command line,
the batch report and the Blender operators show its message as it is, on one
line, without a traceback. Anything else is unexpected and is shown with its
type by :func:`error_message`.
"""
from __future__ import annotations


class UserError(Exception):
    """An error whose message is the one line to show the user."""


class InputError(UserError, ValueError):
    """Bad user input: names the file, the line (when known) and what is wrong."""

    def __init__(self, path, message: str, line: int | None = None):
        self.path = str(path) if path is not None else None
        self.line = line
        self.reason = message
        where = self.path or "<input>"
        if line is not None:
            where = f"{where}:{line}"
        super().__init__(f"{where}: {message}")


def one_line(text) -> str:
    """``text`` (or an exception's message) with all whitespace runs as one space."""
    return " ".join(str(text).split())


def is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a :class:`UserError`, also of another copy of this
    module (a ``bpy`` batch worker runs the core both as ``dancing_points_addon``
    and as the enabled extension's package)."""
    return any(c.__name__ == "UserError" and c.__module__.endswith("dancing_points_addon.errors")
               for c in type(exc).__mro__)


def error_message(exc: BaseException, failed: str = "") -> str:
    """The one line to show for ``exc``: a :class:`UserError`'s message as it is;
    for anything else its type and the first line of its message, after
    ``failed`` (e.g. ``"retarget failed"``) when given."""
    text = str(exc).strip()
    if is_user_error(exc):
        return one_line(text) or type(exc).__name__
    first = text.splitlines()[0].strip() if text else ""
    detail = f"{type(exc).__name__}: {first}" if first else type(exc).__name__
    return f"{failed}: {detail}" if failed else detail
