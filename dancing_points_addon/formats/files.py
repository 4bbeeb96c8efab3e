"""Files: reading only regular files (:func:`regular_file`, :func:`open_regular`,
:func:`read_text`: never a FIFO, a device or a symbolic link loop), and writing
output files atomically: a temporary file beside the output, renamed onto it
only when complete. Every writer of the core goes through
:func:`atomic_output` (one file) or :func:`atomic_outputs` (files that belong
together, e.g. a duet's two BVH files), so a failed or interrupted write never
leaves a half-written file and never replaces an existing one.

Also here: :func:`install_all` (rename finished temporaries onto their outputs,
all or none; the batch commits through it), :func:`write_npz` (an ``.npz``
writer that leaves nothing behind when the write fails) and :func:`same_file`.
"""
from __future__ import annotations

import contextlib
import os
import tempfile

from ..errors import InputError


def _check_target(path) -> str:
    path = os.fspath(path)
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        raise InputError(path, "output folder does not exist")
    if os.path.isdir(path):
        raise InputError(path, "output path is a folder")
    return path


def writable_folder(folder) -> str | None:
    """None when a file can be made in ``folder``, else why not: a file is made
    and removed (``os.access`` says yes to root on a read-only file system)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".dp_probe_"):
            return None
    except OSError as exc:
        return exc.strerror or str(exc)


def check_output_path(path) -> None:
    """Fail early, before any work, when ``path`` cannot be an output file:
    its folder missing or not writable, or the path a folder."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(path, "output folder does not exist")
    if os.path.isdir(path):
        raise InputError(path, "output path is a folder")
    why = writable_folder(folder)
    if why is not None:
        raise InputError(path, f"output folder is not writable ({why})")


def _temp_for(path) -> tuple:
    """``(fd, name)`` of a new hidden temporary file beside ``path``."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        return tempfile.mkstemp(dir=folder, prefix="." + os.path.basename(path) + ".", suffix=".part")
    except OSError as exc:
        raise InputError(path, f"cannot write output ({exc.strerror or exc})") from None


def _unlink(path) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


@contextlib.contextmanager
def atomic_output(path, mode="w", **kwargs):
    """Open a temporary file beside ``path`` and move it onto ``path`` on success.

    On any error the temporary file is removed and ``path`` is left untouched.
    OS errors (missing folder, no permission) become :class:`InputError`.
    """
    path = _check_target(path)
    fd, tmp = _temp_for(path)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode(path))  # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException as exc:
        _unlink(tmp)
        if isinstance(exc, OSError):
            raise InputError(path, f"cannot write output ({exc.strerror or exc})") from None
        raise


def atomic_outputs(writers, mode="w", **kwargs) -> None:
    """Write several files that belong together, all or none: ``writers`` is a
    list of ``(path, write)``, ``write(f)`` writing one file's contents to the
    open file ``f``. Each is written to a temporary file beside its path; only
    when every one is complete are they renamed into place (:func:`install_all`).
    On any error (a full disk, Ctrl-C) the temporary files are removed and no
    existing file is replaced; an OS error becomes an :class:`InputError` naming
    the file whose write failed."""
    paths = [_check_target(p) for p, _ in writers]
    temps = []
    try:
        for path, (_, write) in zip(paths, writers):
            fd, tmp = _temp_for(path)
            temps.append(tmp)
            try:
                with os.fdopen(fd, mode, **kwargs) as f:
                    write(f)
                    f.flush()
                    os.fsync(f.fileno())
                os.chmod(tmp, new_file_mode(path))
            except OSError as exc:
                raise InputError(path, f"cannot write output ({exc.strerror or exc})") from None
        try:
            install_all(list(zip(temps, paths)))
        except OSError as exc:
            raise InputError(getattr(exc, "filename", None) or paths[0],
                             f"cannot write output ({exc.strerror or exc})") from None
    finally:
        for tmp in temps:  # (gone already after a successful install)
            _unlink(tmp)


@contextlib.contextmanager
def _folder_lock(folder):
    """One installer of several files at a time in ``folder``: an ``flock`` on
    the folder itself (POSIX; elsewhere, or when it cannot be opened, none), so
    that two runs writing the same pair leave one run's whole pair."""
    try:
        import fcntl
        fd = os.open(folder, os.O_RDONLY)
    except (ImportError, OSError):
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # (releases the lock)


def install_all(moves, replace=True) -> None:
    """Rename each finished temporary file onto its final path (``moves``: a list
    of ``(tmp, final)`` in one file system), all or none: when one rename fails
    the files renamed before it are put back as they were (an existing file from
    a hard-link backup taken first; a new one removed). ``replace=False``: never
    over an existing file (:class:`FileExistsError` naming it, also when it
    appears meanwhile). The temporary files of a failed call are the caller's.
    Several files are installed under a lock on the first one's folder
    (:func:`_folder_lock`)."""
    if len(moves) > 1:
        with _folder_lock(os.path.dirname(os.path.abspath(moves[0][1]))):
            _install_all(moves, replace)
    else:
        _install_all(moves, replace)


def _install_all(moves, replace) -> None:
    done = []  # (final, backup or None, replaced an existing file)
    try:
        for tmp, final in moves:
            if not replace:
                try:
                    os.link(tmp, final)  # fails if ``final`` exists: never overwrite
                except FileExistsError:
                    raise FileExistsError(17, "output exists", final) from None
                except OSError:  # no hard links on this file system
                    if os.path.lexists(final):
                        raise FileExistsError(17, "output exists", final) from None
                    os.replace(tmp, final)
                else:
                    os.unlink(tmp)
                done.append((final, None, False))
                continue
            existed = os.path.lexists(final)
            backup = _backup(final) if existed and len(moves) > 1 else None
            try:
                os.replace(tmp, final)
            except BaseException:
                if backup:
                    _unlink(backup)
                raise
            done.append((final, backup, existed))
    except BaseException:
        for final, backup, existed in reversed(done):
            with contextlib.suppress(OSError):
                if backup:
                    os.replace(backup, final)
                elif not existed:
                    os.unlink(final)
        raise
    for _, backup, _ in done:
        if backup:
            _unlink(backup)


def _backup(path):
    """A hard link to ``path`` under a hidden temporary name (None when the file
    system has no hard links)."""
    folder, name = os.path.split(os.path.abspath(path))
    for _ in range(100):
        cand = os.path.join(folder, f".{name}.{os.urandom(4).hex()}.old")
        try:
            os.link(path, cand)
            return cand
        except FileExistsError:
            continue
        except OSError:
            return None
    return None


class _Disarmable:
    """A binary file as :func:`numpy.savez` sees it (``read``,
    ``write``, ``tell``, ``seek``, ``flush`` pass through); after :meth:`disarm`
    it is a sink that only counts (writes go nowhere, positions stay
    consistent), so the zip writer that a failed write leaves unclosed can finish
    when it is collected without touching the file or printing a traceback."""

    def __init__(self, f):
        self._f = f
        self.name = getattr(f, "name", None)
        self._pos = self._end = 0

    def read(self, *args):  # (numpy takes an object without ``read`` for a path)
        return self._f.read(*args) if self._f is not None else b""

    def write(self, data):
        if self._f is not None:
            return self._f.write(data)
        self._pos += len(data)
        self._end = max(self._end, self._pos)
        return len(data)

    def tell(self):
        return self._f.tell() if self._f is not None else self._pos

    def seek(self, offset, whence=0):
        if self._f is not None:
            return self._f.seek(offset, whence)
        self._pos = max(0, offset + (0, self._pos, self._end)[whence])
        return self._pos

    def flush(self):
        if self._f is not None:
            self._f.flush()

    def disarm(self):
        if self._f is None:
            return
        try:
            self._pos = self._end = max(0, self._f.tell())
        except (OSError, ValueError):
            pass
        self._f = None


def write_npz(f, arrays) -> None:
    """``numpy.savez`` of ``arrays`` (a dict) into the open binary file ``f``, the
    same bytes; when the write fails (a full disk, Ctrl-C) the exception
    propagates and nothing more is written to ``f`` afterwards. Not compressed:
    a duet's float arrays deflate by about 8 %, at 17 times the writing time
    (0.51 s against 0.03 s for a minute of duet)."""
    import numpy as np

    out = _Disarmable(f)
    try:
        np.savez(out, **arrays)
    except BaseException:
        out.disarm()
        raise


def same_file(a, b) -> bool:
    """Whether the paths ``a`` and ``b`` are one file (the same inode when both
    exist: hard links, symbolic links; else the same real path)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b))


def new_file_mode(path) -> int:
    """The mode an ordinary ``open(path, 'w')`` would give: the existing file's, else
    0666 less the umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask


# --------------------------------------------------------------------------- reading

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
