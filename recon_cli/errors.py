"""Error types of recon.

The library raises these; only ``recon_cli.cli.main`` maps them to exit codes, so
library code never calls ``sys.exit``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


class ReconError(Exception):
    """Base class of every error recon raises on purpose.

    The message is one line meant for a user, naming the file and the problem: ``path``
    (when given) is put in front of ``message``.
    """

    exit_code = 1

    def __init__(self, message: str = "", path: str | None = None):
        self.message = message
        self.path = path
        super().__init__(f"{path}: {message}" if path else message)


class InputError(ReconError):
    """Bad input data: malformed, truncated or inconsistent file, NaN coordinates, ..."""

    exit_code = 2


class OutputError(ReconError):
    """An output path that cannot be written.

    Missing folder, a directory, read-only file system, closed standard output (a full one:
    :class:`NoSpace`). ``path`` is the output path as given.
    """

    exit_code = 2


class NoSpace(OutputError):
    """A write that failed for want of room: a full file system or an exhausted quota.

    Exit 1, as a run that failed on valid input (the spill folder's full disk is the same
    exit): nothing was wrong with what the user gave. ``path`` is the output path as given.
    """

    exit_code = 1


class ParameterError(ReconError):
    """A parameter value that cannot be used (negative radius, unknown stage, ...)."""

    exit_code = 2


class BackendError(ReconError):
    """A reference backend is not installed or failed."""

    exit_code = 3


class StageFailed(ReconError):
    """A stage could not produce a result from valid input (e.g. nothing to reconstruct)."""

    exit_code = 1


@contextlib.contextmanager
def naming(path: str | os.PathLike | None) -> Iterator[None]:
    """Put ``path`` in front of the errors raised inside that do not name a file yet.

    Those are the :class:`InputError` and :class:`StageFailed` of a stage that checks its data,
    where the caller knows the file.

    ``-`` is named ``<stdin>``.
    """
    try:
        yield
    except (InputError, StageFailed) as exc:
        if exc.path is not None or path is None:
            raise
        where = "<stdin>" if str(path) == "-" else os.fspath(path)
        raise type(exc)(exc.message, where) from exc
