"""One batch per output folder: the lock file ``OUT_DIR/.dancing_points_batch.lock``.

A batch holds it from its start to its end (:func:`acquire`, then
:meth:`OutputLock.release`, which removes the file); a second batch writing into
the same folder meanwhile is refused with one line (it would replace the first
one's outputs under its feet). The file holds the owner's process id, for that
line. On POSIX systems the lock itself is an ``flock`` on the file, which the
system releases when its process ends however it ends: the file a killed batch
left is simply taken over. Elsewhere (or where the file system has no
``flock``) the file is created with ``O_EXCL`` and a file whose process is no
longer running is taken over.

Also here: :func:`pid_alive` (the batch's temporary files carry their
process id, see :mod:`.plan`).
"""
from __future__ import annotations

import contextlib
import errno
import os
import time

from ..errors import InputError

LOCK_NAME = ".dancing_points_batch.lock"

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` is running (this one included)."""
    if pid <= 0:
        return False
    if pid == os.getpid():
        return True
    if os.name == "nt":
        import ctypes

        k32 = ctypes.WinDLL("kernel32", use_last_error=True)
        handle = k32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return ctypes.get_last_error() == 5  # access denied: it exists
        try:
            code = ctypes.c_ulong()
            return bool(k32.GetExitCodeProcess(handle, ctypes.byref(code))) and code.value == 259  # STILL_ACTIVE
        finally:
            k32.CloseHandle(handle)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's
    except OSError:
        return False
    return True


def _read_pid(fd_or_path):
    try:
        if isinstance(fd_or_path, int):
            os.lseek(fd_or_path, 0, os.SEEK_SET)
            data = os.read(fd_or_path, 64)
        else:
            with open(fd_or_path, "rb") as f:
                data = f.read(64)
        return int(data.decode("ascii").strip())
    except (OSError, ValueError):
        return None


def _busy(out_dir, pid):
    who = f"another batch (process {pid})" if pid else "another batch"
    return InputError(out_dir, f"{who} is writing into this output folder; wait for it to finish or choose "
                               f"another folder (-o)")


class OutputLock:
    """A held lock; :meth:`release` (also at the end of a ``with`` block) removes it."""

    def __init__(self, path, fd, flocked):
        self.path, self.fd, self.flocked = path, fd, flocked

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            if self.flocked or _read_pid(self.path) == os.getpid():
                with contextlib.suppress(OSError):
                    os.unlink(self.path)  # (still locked: a waiting batch sees the file replaced)
        finally:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def acquire(out_dir) -> OutputLock:
    """Lock the output folder ``out_dir`` (it exists) for this batch; an
    :class:`InputError` (one line) when another running batch holds it."""
    path = os.path.join(out_dir, LOCK_NAME)
    try:
        for _ in range(50):
            lock = _try_flock(out_dir, path) if fcntl is not None else None
            if lock is None:
                lock = _try_exclusive(out_dir, path)
            if lock is not False:
                return lock
            time.sleep(0.01)  # the file was replaced meanwhile: again
    except OSError as exc:
        raise InputError(out_dir, f"cannot write into the output folder ({exc.strerror or exc})") from None
    raise _busy(out_dir, _read_pid(path))


def _try_flock(out_dir, path):
    """The lock through ``flock``; None where the file system has none; False: try again."""
    try:
        fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
    except FileExistsError:
        try:
            fd, created = os.open(path, os.O_RDWR), False
        except FileNotFoundError:
            return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise _busy(out_dir, _read_pid(fd)) from None
            os.close(fd)
            if created:  # (the O_EXCL way must not find our empty file)
                with contextlib.suppress(OSError):
                    os.unlink(path)
            return None  # no flock here (ENOLCK, ENOTSUP...)
        # The previous holder may have removed the file between our open and our lock.
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            return False
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        return OutputLock(path, fd, True)
    except BaseException:
        with contextlib.suppress(OSError):
            os.close(fd)
        raise


def _try_exclusive(out_dir, path):
    """The lock as a file created with ``O_EXCL``; False: a stale one was removed, try again."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        pid = _read_pid(path)
        if pid is None:  # being written, or garbage: stale once it is a few seconds old
            with contextlib.suppress(OSError):
                if time.time() - os.path.getmtime(path) < 5.0:
                    raise _busy(out_dir, None)
        elif pid_alive(pid):
            raise _busy(out_dir, pid)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)  # the lock of a batch that was killed: take it over
        return False
    os.write(fd, f"{os.getpid()}\n".encode("ascii"))
    return OutputLock(path, fd, False)
