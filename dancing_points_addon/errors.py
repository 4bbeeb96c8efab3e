"""The one error type that user-facing code catches and prints as one line."""
from __future__ import annotations


class InputError(ValueError):
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


def read_text(path) -> str:
    """A text file's contents (UTF-8, with or without BOM, else Latin-1); a file
    that cannot be read is an :class:`InputError` naming it."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")
