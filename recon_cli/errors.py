"""Error types of recon.

The library raises these; only :mod:`recon_cli.cli.main` maps them to exit codes, so
library code never calls ``sys.exit``.
"""

from __future__ import annotations


class ReconError(Exception):
    """Base class of every error recon raises on purpose.

    The message is one line meant for a user, ideally naming the file and the problem.
    """

    exit_code = 1


class InputError(ReconError):
    """Bad input data: malformed, truncated or inconsistent file, NaN coordinates, ..."""

    exit_code = 2

    def __init__(self, message: str, path: str | None = None):
        self.path = path
        super().__init__(f"{path}: {message}" if path else message)


class ParameterError(ReconError):
    """A parameter value that cannot be used (negative radius, unknown stage, ...)."""

    exit_code = 2


class BackendError(ReconError):
    """A reference backend is not installed or failed."""

    exit_code = 3


class StageFailed(ReconError):
    """A stage could not produce a result from valid input (e.g. nothing to reconstruct)."""

    exit_code = 1
