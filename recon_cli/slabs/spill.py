"""A job's spill folder: made for the job, removed when it ends, however it ends.

The slabs' states, the chunks sorted by sub-slab and the mesh's parts wait there between the
steps of an out-of-core or distributed run. The folder is removed on success, on an error and on
SIGINT/SIGTERM (the command's handlers raise :class:`KeyboardInterrupt`: the ``finally`` below
runs); a write that fails for want of room is one line naming the folder.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator

from recon_cli.errors import StageFailed


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
    """A new folder in ``parent`` (None: the system's temporary folder), removed on exit."""
    _python_handlers()
    try:
        path = tempfile.mkdtemp(prefix=f".recon-{label}-", dir=parent)
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
