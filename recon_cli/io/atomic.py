"""Output files: regular files appear whole or not at all; special files are written as they are.

What :func:`atomic_open` does with an output path:

``-``
    standard output (an error if it is closed).
``/dev/stdout``, ``/dev/stderr``, ``/dev/fd/N``, ``/proc/self/fd/N``
    the open file descriptor itself (a pipe, a process substitution ``>(cmd)``, a file
    opened by the shell), written at its position, never reopened or replaced.
a character or block device, a FIFO (existing, not a regular file)
    opened and written directly: the node is never replaced (``/dev/null`` stays a device).
a regular file, or a path that does not exist yet
    written to an anonymous temporary file in the target's folder (Linux ``O_TMPFILE``:
    it has no name, so even ``kill -9`` leaves nothing behind), which is then given the
    target's name; where ``O_TMPFILE`` is not supported, a named ``.NAME.xxxx.tmp`` file
    beside the target, removed on any error or interruption. An existing file keeps its
    permission bits.
a symbolic link
    written through to the file it points to (as ``cp`` and the shell's ``>`` do); the link
    itself is kept.

Every failure (missing folder, a directory, a read-only or full file system, an immutable
file) is an :class:`~recon_cli.errors.OutputError` naming the path and the system's reason
(a full one a :class:`~recon_cli.errors.NoSpace`, exit 1); the target is then untouched and
no temporary file remains.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from typing import IO

from recon_cli.errors import NoSpace, OutputError

# paths that name an already open file descriptor
_FD_PATH = re.compile(r"^/(?:dev/fd|proc/self/fd)/(\d+)$")
_FD_ALIASES = {"/dev/stdin": 0, "/dev/stdout": 1, "/dev/stderr": 2}
# Linux only; None elsewhere (and in tests that exercise the named fallback)
_O_TMPFILE = getattr(os, "O_TMPFILE", None)
# O_TMPFILE is refused with one of these where the file system or kernel lacks it
_NO_TMPFILE = {errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT}


# names of the temporary files being written (only where O_TMPFILE is missing): removed on
# any error here, and by remove_temporaries() when a signal ends the process
_NAMED: set[str] = set()
# temporary folders of new folders being written (new_folder), removed the same ways
_FOLDERS: set[str] = set()


def remove_temporaries() -> None:
    """Remove the temporary files and folders of writes in progress (the process must end now)."""
    for name in list(_NAMED):
        with contextlib.suppress(OSError):
            os.unlink(name)
        _NAMED.discard(name)
    for folder in list(_FOLDERS):
        shutil.rmtree(folder, ignore_errors=True)
        _FOLDERS.discard(folder)


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _failed(exc: OSError, path: str) -> OutputError:
    """The error of a write to ``path`` that failed with ``exc``: no room is :class:`NoSpace`."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return NoSpace(_reason(exc), path)
    return OutputError(_reason(exc), path)


def _fd_of(path: str) -> int | None:
    if path in _FD_ALIASES:
        return _FD_ALIASES[path]
    m = _FD_PATH.match(path)
    return int(m.group(1)) if m else None


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike) -> Iterator[IO[bytes]]:
    """Open ``path`` for binary writing (see the module docstring for what each kind of path gets).

    Raises
    ------
    OutputError
        The path cannot be written (its message names the path and the reason); the
        target is left as it was and no temporary file remains.
    """
    if str(path) == "-":
        with _open_stdout() as f:
            yield f
        return
    path = os.fspath(path)
    if not path:
        raise OutputError("output path is empty", "''")
    fd = _fd_of(path)
    if fd is not None:
        with _open_fd(path, fd) as f:
            yield f
        return
    if path.endswith(os.sep) or path.endswith("/."):
        raise OutputError("is a folder path (ends with '/'); give a file name", path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise _failed(exc, path) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError("is a directory", path)
    if st is not None and not stat.S_ISREG(st.st_mode):
        with _open_special(path) as f:
            yield f
        return
    # a regular file or a new one; through symbolic links to the file they name
    final = os.path.realpath(path) if os.path.islink(path) else os.path.abspath(path)
    folder = os.path.dirname(final)
    if not os.path.isdir(folder):
        raise OutputError("output folder does not exist", path)
    with _open_replacing(path, final, folder, st) as f:
        yield f


@contextlib.contextmanager
def _open_stdout() -> Iterator[IO[bytes]]:
    if sys.stdout is None:
        raise OutputError("standard output is closed", "<stdout>")
    out = sys.stdout.buffer
    try:
        sys.stdout.flush()
        yield out
        out.flush()
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise _failed(exc, "<stdout>") from None


@contextlib.contextmanager
def _open_fd(path: str, fd: int) -> Iterator[IO[bytes]]:
    """An open descriptor named by path (``/dev/fd/63`` of ``>(cmd)``): written where it stands."""
    try:
        mode = os.fstat(fd).st_mode
    except OSError as exc:
        raise OutputError(f"{_reason(exc)} (not an open file)", path) from None
    if stat.S_ISDIR(mode):
        raise OutputError("is a directory", path)
    if fd == 1 and sys.stdout is not None:
        sys.stdout.flush()
    try:
        with open(fd, "wb", closefd=False) as f:
            yield f
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise _failed(exc, path) from None


@contextlib.contextmanager
def _open_special(path: str) -> Iterator[IO[bytes]]:
    """A device or FIFO: opened and written as it is, never replaced by a regular file."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise _failed(exc, path) from None
    try:
        with open(fd, "wb") as f:
            yield f
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise _failed(exc, path) from None


@contextlib.contextmanager
def _open_replacing(
    path: str, final: str, folder: str, st: os.stat_result | None
) -> Iterator[IO[bytes]]:
    """Write a regular file to an unnamed (else hidden) temporary file, then name it ``final``."""
    named = None  # the temporary file's name while it has one
    try:
        try:
            if _O_TMPFILE is None:
                raise OSError(errno.EOPNOTSUPP, "no O_TMPFILE")
            fd = os.open(folder, _O_TMPFILE | os.O_WRONLY | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            if exc.errno not in _NO_TMPFILE:
                raise
            fd, named = tempfile.mkstemp(
                prefix="." + os.path.basename(final) + ".", suffix=".tmp", dir=folder
            )
            _NAMED.add(named)
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)
        with open(fd, "wb") as f:
            if st is not None:
                os.fchmod(fd, stat.S_IMODE(st.st_mode))
            yield f
            f.flush()
            os.fsync(fd)
            if named is None:
                named = _link_anonymous(fd, final, folder)
            if named is not None:
                os.replace(named, final)
                _NAMED.discard(named)
                named = None
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            raise
        raise _failed(exc, path) from None
    finally:
        if named is not None:
            with contextlib.suppress(OSError):
                os.unlink(named)
            _NAMED.discard(named)


def _link_anonymous(fd: int, final: str, folder: str) -> str | None:
    """Give the ``O_TMPFILE`` file ``fd`` a name.

    ``final`` itself when it does not exist (nothing else ever appears), else a hidden temporary
    name returned for the caller to rename.
    """
    dir_fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        source = f"/proc/self/fd/{fd}"
        # dst_dir_fd makes os.link use linkat(AT_SYMLINK_FOLLOW), which links the open file
        try:
            os.link(source, os.path.basename(final), dst_dir_fd=dir_fd, follow_symlinks=True)
            return None
        except FileExistsError:
            pass
        while True:
            name = f".{os.path.basename(final)}.{os.urandom(4).hex()}.tmp"
            full = os.path.join(folder, name)
            try:
                os.link(source, name, dst_dir_fd=dir_fd, follow_symlinks=True)
                _NAMED.add(full)
                return full
            except FileExistsError:
                continue
    finally:
        os.close(dir_fd)


def check_output(path: str | os.PathLike) -> None:
    """Refuse an output path that cannot be written before any work is done.

    Catches what can be known up front (empty path, a folder, a missing folder, a closed
    standard output or descriptor); a full or read-only file system shows when writing.

    Raises
    ------
    OutputError
    """
    if str(path) == "-":
        if sys.stdout is None:
            raise OutputError("standard output is closed", "<stdout>")
        return
    path = os.fspath(path)
    if not path:
        raise OutputError("output path is empty", "''")
    fd = _fd_of(path)
    if fd is not None:
        try:
            os.fstat(fd)
        except OSError as exc:
            raise OutputError(f"{_reason(exc)} (not an open file)", path) from None
        return
    if path.endswith(os.sep) or path.endswith("/."):
        raise OutputError("is a folder path (ends with '/'); give a file name", path)
    if os.path.isdir(path):
        raise OutputError("is a directory", path)
    if os.path.exists(path):
        return
    final = os.path.realpath(path) if os.path.islink(path) else os.path.abspath(path)
    if not os.path.isdir(os.path.dirname(final)):
        raise OutputError("output folder does not exist", path)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` as :func:`atomic_open` does (``-``: standard output)."""
    with atomic_open(path) as f:
        _write_all(f, data)


def write_pieces(
    path: str | os.PathLike, produce: Callable[[Callable[[bytes | memoryview], None]], None]
) -> None:
    """Write what ``produce(put)`` puts, piece by piece, as :func:`atomic_open` does.

    Each piece is written before ``put`` returns, so ``produce`` may reuse its buffer. A
    regular file appears whole or not at all, whatever ``produce`` raises.
    """
    with atomic_open(path) as f:
        produce(lambda data: _write_all(f, data))


def _write_all(f: IO[bytes], data: bytes | memoryview) -> None:
    """``f.write`` until every byte is out.

    To a pipe whose reader left, a buffered write can return a short count with no error (the next
    write then raises BrokenPipeError).
    """
    view = memoryview(data).cast("B")
    while len(view):
        n = f.write(view)
        if not n:
            raise OSError(errno.EIO, "the output accepts no more data")
        view = view[n:]


def check_new_folder(path: str | os.PathLike) -> None:
    """Refuse a path a new folder cannot be written at, before any work is done.

    Raises
    ------
    OutputError
        Standard output, an existing path (never replaced or merged into) or a missing parent.
    """
    if str(path) in ("-", ""):
        raise OutputError(
            "a folder is written here: give a path that does not exist yet", str(path)
        )
    path = os.fspath(path)
    if os.path.lexists(path):
        raise OutputError("exists: give a path that does not exist yet (nothing is replaced)", path)
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise OutputError("output folder does not exist", path)


@contextlib.contextmanager
def new_folder(path: str | os.PathLike) -> Iterator[str]:
    """A hidden temporary folder beside ``path``, renamed to ``path`` when the block ends.

    The folder appears whole or not at all: on any error, or an interruption, the temporary
    folder is removed and ``path`` is not created.

    Raises
    ------
    OutputError
        As :func:`check_new_folder`, the file system's refusal, or ``path`` created meanwhile.
    """
    check_new_folder(path)
    final = os.path.abspath(os.fspath(path))
    try:
        tmp = tempfile.mkdtemp(
            prefix="." + os.path.basename(final) + ".", suffix=".tmp", dir=os.path.dirname(final)
        )
    except OSError as exc:
        raise _failed(exc, os.fspath(path)) from None
    _FOLDERS.add(tmp)
    try:
        yield tmp
        if os.path.lexists(final):
            raise OutputError("was created meanwhile: nothing is replaced", os.fspath(path))
        os.rename(tmp, final)
    except OSError as exc:
        raise _failed(exc, os.fspath(path)) from None
    finally:
        if os.path.isdir(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
        _FOLDERS.discard(tmp)
