"""Writing output files atomically: a temporary file beside the output, renamed
onto it only when complete. Every writer of the core goes through
:func:`atomic_output`, so a failed or interrupted write never leaves a
half-written file and never replaces an existing one.
"""
from __future__ import annotations

import contextlib
import os
import tempfile

from ..errors import InputError


@contextlib.contextmanager
def atomic_output(path, mode="w", **kwargs):
    """Open a temporary file beside ``path`` and move it onto ``path`` on success.

    On any error the temporary file is removed and ``path`` is left untouched.
    OS errors (missing folder, no permission) become :class:`InputError`.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(path, "output folder does not exist")
    if os.path.isdir(path):
        raise InputError(path, "output path is a folder")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix="." + os.path.basename(path) + ".",
                                   suffix=".part")
    except OSError as exc:
        raise InputError(path, f"cannot write output ({exc.strerror or exc})") from None
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode(path))  # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise InputError(path, f"cannot write output ({exc.strerror or exc})") from None
        raise


def new_file_mode(path) -> int:
    """The mode an ordinary ``open(path, 'w')`` would give: the existing file's, else
    0666 less the umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask
