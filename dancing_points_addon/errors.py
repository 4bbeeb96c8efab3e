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


def regular_file(path, what: str = "a file", missing: str | None = None):
    """``os.stat`` of ``path`` when it is a regular file (symbolic links
    followed); else an :class:`InputError` naming it: no such file (``missing``,
    default ``cannot read file (...)``), a symbolic link loop, a folder, or
    something that is not a regular file (a FIFO, a device such as
    ``/dev/zero``, a socket: reading one could block or never end).
    Call it before opening a file for reading."""
    import errno
    import os
    import stat

    try:
        st = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(path, "symbolic link loop (cannot resolve the path)") from None
        if missing is not None and exc.errno in (errno.ENOENT, errno.ENOTDIR):
            if os.path.islink(path):
                raise InputError(path, f"{missing} (broken symbolic link)") from None
            raise InputError(path, missing) from None
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    except ValueError as exc:  # e.g. an embedded NUL character in the name
        raise InputError(path, f"invalid file name ({exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(path, f"is a folder, not {what}")
    if not stat.S_ISREG(st.st_mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else
                "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                "a socket" if stat.S_ISSOCK(st.st_mode) else "not a plain file")
        raise InputError(path, f"not a regular file ({kind}); give {what}")
    return st


def open_regular(path, what: str = "a file", missing: str | None = None):
    """``path`` opened for binary reading after :func:`regular_file` accepted it
    (opened non-blocking and checked again, so a FIFO swapped in meanwhile
    neither blocks nor is read)."""
    import os
    import stat

    regular_file(path, what, missing)
    flags = os.O_RDONLY | getattr(os, "O_BINARY", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(path, f"not a regular file; give {what}")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_text(path) -> str:
    """A text file's contents (UTF-8, with or without BOM, else Latin-1); a file
    that cannot be read (missing, a folder, a FIFO or device, a symbolic link
    loop) is an :class:`InputError` naming it."""
    try:
        with open_regular(path, "a text file") as f:
            data = f.read()
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")
