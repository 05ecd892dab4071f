"""A job's spill folder: made for the job, removed when it ends, however it ends.

The slabs' states, the chunks sorted by sub-slab and the mesh's parts wait there between the
steps of an out-of-core or distributed run. The folder is removed on success, on an error and on
SIGINT/SIGTERM (the command's handlers raise :class:`KeyboardInterrupt`: the ``finally`` below
runs); a write that fails for want of room is one line naming the folder.

Only SIGKILL (or a crash of the machine) leaves a folder behind. The folder's ``owner.lock``
holds its run's process id under an exclusive ``flock`` for as long as the run lives (the
kernel drops it when the process dies, however it dies), so the next run that makes a spill
folder in the same parent removes the folders whose lock nobody holds any more.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator

from recon_cli.errors import StageFailed

log = logging.getLogger("recon")

OWNER = "owner.lock"
"""The file in a spill folder its run holds locked while it lives."""


def _python_handlers() -> None:
    """Python's own SIGINT/SIGTERM handlers again, if a command put a machine-code one over them.

    A command runs a stage's computation with a handler that ends the process at once
    (``recon_cli.cli._signals.immediate``), which would leave the folder behind; Python's
    handler raises instead, so the folder's clean-up runs.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for s in (signal.SIGINT, signal.SIGTERM):
        h = signal.getsignal(s)
        if callable(h):
            signal.signal(s, h)


@contextlib.contextmanager
def spill_folder(parent: str | None, label: str) -> Iterator[str]:
    """A new folder in ``parent`` (None: the system's temporary folder), removed on exit.

    The folders that killed runs left in ``parent`` go first (:func:`remove_stale`).
    """
    _python_handlers()
    remove_stale(parent)
    try:
        path = tempfile.mkdtemp(prefix=f".recon-{label}-", dir=parent)
        owner = _own(path)
    except OSError as exc:
        where = parent or tempfile.gettempdir()
        raise StageFailed(f"cannot make the run's spill folder ({exc.strerror})", where) from None
    try:
        yield path
    except OSError as exc:
        if not _full(exc, path):
            raise
        where = parent or os.path.dirname(path)
        raise StageFailed("no space left on device for the run's spill files", where) from None
    finally:
        shutil.rmtree(path, ignore_errors=True)
        os.close(owner)


def _own(path: str) -> int:
    """Lock ``path``'s :data:`OWNER` file for this process; its open descriptor.

    The file is locked under another name, then renamed: no other run ever sees it unlocked.
    """
    tmp = os.path.join(path, f".{OWNER}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, f"{os.getpid()}\n".encode())
        os.rename(tmp, os.path.join(path, OWNER))
    except OSError:
        os.close(fd)
        raise
    return fd


def remove_stale(parent: str | None) -> list[str]:
    """Remove the spill folders in ``parent`` whose run has died; the folders removed.

    A spill folder is a ``.recon-*`` folder with an :data:`OWNER` file; its run is dead when
    nobody holds that file's lock. Anything else is left alone; so is a folder that cannot be
    looked at.
    """
    where = parent or tempfile.gettempdir()
    try:
        names = [n for n in os.listdir(where) if n.startswith(".recon-")]
    except OSError:
        return []
    removed = []
    for name in names:
        path = os.path.join(where, name)
        try:
            fd = os.open(os.path.join(path, OWNER), os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue  # its run is alive
        try:
            pid = os.read(fd, 32).decode(errors="replace").strip()
            shutil.rmtree(path, ignore_errors=True)
        finally:
            os.close(fd)
        log.info("removed %s, the spill folder of a run that was killed (process %s)", path, pid)
        removed.append(path)
    return removed


# below this much free space, a short write (numpy's "requested and written") is a full disk
_NEARLY_FULL = 64 << 20


def _full(exc: OSError, path: str) -> bool:
    """Whether ``exc`` is a write that failed for want of room under ``path``."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if exc.errno is None and "requested and" in str(exc):  # numpy's short write
        try:
            return shutil.disk_usage(path).free < _NEARLY_FULL
        except OSError:
            return False
    return False
