"""How and where a stage's work runs: workers, cluster, memory and temporary folder.

One object, :class:`Execution`, says it for every stage; the stages' own functions take data and
the algorithm's parameters only. A run sets it for a block of code::

    import recon_cli
    with recon_cli.run_on(memory="6GB"):
        mesh = recon_cli.poisson(cloud, depth=12)   # out of core in this process, in slabs
    with recon_cli.run_on(workers=2):
        mesh = recon_cli.poisson(cloud, depth=12)   # on a local Dask cluster of 2 processes

A command takes the same options (``--workers``, ``--scheduler``, ``--partitions``,
``--memory``, ``--temp-dir``) when its stage declares them (:attr:`StageSpec.execution
<recon_cli.params.StageSpec>`): they are declared here, once (:data:`PARAMS`).

This module imports nothing heavy.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

from recon_cli.errors import ParameterError
from recon_cli.params import Param

_UNITS = {
    "": 1,
    "b": 1,
    "k": 1000,
    "kb": 1000,
    "m": 1000**2,
    "mb": 1000**2,
    "g": 1000**3,
    "gb": 1000**3,
    "t": 1000**4,
    "tb": 1000**4,
    "kib": 1 << 10,
    "mib": 1 << 20,
    "gib": 1 << 30,
    "tib": 1 << 40,
}
_SIZE = re.compile(r"\s*([0-9]*\.?[0-9]+(?:e[+-]?[0-9]+)?)\s*([a-z]*)\s*$", re.IGNORECASE)
# below this a run holds hardly more than Python, numpy and numba themselves
MIN_MEMORY = 256 << 20


def parse_size(value: Any) -> int:
    """Bytes of a size: an integer, or text such as ``6GB``, ``6GiB``, ``500MB`` (``1e9``).

    Raises ValueError (with the expected form) on anything else.
    """
    if isinstance(value, bool):
        raise ValueError("a size such as 6GB, 6GiB or 500MB")
    if isinstance(value, (int, float)):
        n = float(value)
    else:
        m = _SIZE.match(str(value))
        if not m or m.group(2).lower() not in _UNITS:
            raise ValueError("a size such as 6GB, 6GiB or 500MB")
        n = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not n >= MIN_MEMORY or n != n or n == float("inf"):
        raise ValueError(f"a size of at least {MIN_MEMORY >> 20} MiB")
    return int(n)


#: the options of :class:`Execution`, declared once for every command that takes them
PARAMS: tuple[Param, ...] = (
    Param(
        "workers",
        "int",
        None,
        "Run on a local Dask cluster of N worker processes, the cloud in slabs; the workers "
        "read IN by chunks, no process holds it whole.",
        min=1,
        max=1024,
    ),
    Param(
        "scheduler",
        "any",
        None,
        "Run as --workers does on the existing Dask cluster at this address (tcp://host:8786); "
        "IN and the output folder must be on a file system its workers share.",
        metavar="ADDRESS",
    ),
    Param(
        "partitions",
        "int",
        None,
        "Slabs the cloud is cut into; more slabs, less memory each (default: the fewest whose "
        "one slab fits the memory; the report says how many and why).",
        min=1,
        max=64,
    ),
    Param(
        "memory",
        "any",
        None,
        "Memory the run may use on this machine, all its processes together (e.g. 6GB, 6GiB): "
        "a larger cloud is done in slabs through files in the temporary folder; a limit too "
        "small for one slab is refused up front (default: the memory available at start).",
        metavar="SIZE",
        words={"auto": None},
        validate=parse_size,
        allowed="a size of at least 256 MiB",
    ),
    Param(
        "temp_dir",
        "any",
        None,
        "Folder for the run's spill files (default: beside OUT, else the system's); removed "
        "when the run ends, whatever the outcome.",
        metavar="DIR",
    ),
)
_BY_NAME = {p.name: p for p in PARAMS}


@dataclass(frozen=True)
class Execution:
    """How and where a stage's work runs.

    Parameters
    ----------
    workers : int or None
        Local Dask worker processes; None: this process (in slabs when the memory needs them).
    scheduler : str or None
        Address of an existing Dask cluster (with ``workers`` None).
    partitions : int or None
        Slabs; None: as many as the memory needs.
    memory : int or None
        Bytes the run may use on this machine, all its processes together; None: the memory
        available when the run starts (:func:`recon_cli.memory.available_bytes`).
    temp_dir : str or None
        Parent folder of the run's spill folder; None: the output's folder when there is one,
        else the system's temporary folder.
    """

    workers: int | None = None
    scheduler: str | None = None
    partitions: int | None = None
    memory: int | None = None
    temp_dir: str | None = None

    def __post_init__(self) -> None:
        if self.scheduler is not None and self.workers is not None:
            raise ParameterError(
                "--workers makes a local cluster and --scheduler names one: give one of them"
            )
        if self.temp_dir is not None and not os.path.isdir(self.temp_dir):
            raise ParameterError(f"--temp-dir {self.temp_dir}: no such folder")

    @classmethod
    def from_values(cls, values: dict[str, Any], text_ok: bool = True) -> Execution:
        """An execution from option values (names of :data:`PARAMS`), checked by them."""
        out = {}
        for k, v in values.items():
            key = k.replace("-", "_")
            if key not in _BY_NAME:
                known = ", ".join(p.dashed for p in PARAMS)
                raise ParameterError(f"no execution option {k!r} (options: {known})")
            out[key] = _BY_NAME[key].coerce(v, text_ok=text_ok)
        return cls(**out)

    @property
    def distributed(self) -> bool:
        """Whether the work goes to a Dask cluster (local workers or a scheduler)."""
        return self.workers is not None or self.scheduler is not None

    def budget(self) -> int | None:
        """Bytes the run may use: ``memory``, else what is available now (None: unknown)."""
        if self.memory is not None:
            return self.memory
        from recon_cli.memory import available_bytes

        return available_bytes()

    def worker_memory(self) -> int | None:
        """Each local worker's memory limit: the workers share 4/5 of :meth:`budget`.

        The rest is the coordinating process's, which holds the coarse levels and the
        messages, not a slab. None without ``memory`` (Dask's own share of the machine).
        """
        if self.memory is None or self.workers is None:
            return None
        return int(self.memory * 0.8) // self.workers

    def cluster(self) -> contextlib.AbstractContextManager:
        """``with ex.cluster() as (client, info)``: the Dask cluster the work runs on.

        A local cluster of ``workers`` processes (closed at the end) or a client of
        ``scheduler``'s; in this process ``client`` is None. ``info`` has ``workers`` and
        ``memory`` (per worker, bytes; this process's budget without a cluster).
        """
        if not self.distributed:
            return contextlib.nullcontext((None, {"workers": 0, "memory": self.budget()}))
        from recon_cli.batch.cluster import open_client

        return open_client(self.scheduler, self.workers, self.worker_memory(), stealing=False)

    def spill_parent(self, output: str | None = None) -> str | None:
        """The folder the run's spill folder goes in (None: the system's temporary folder).

        ``temp_dir`` when given; else the output's folder (a regular file's), so spill files
        land on the disk the result goes to.
        """
        if self.temp_dir is not None:
            return self.temp_dir
        if output and output != "-" and not output.startswith("/dev/"):
            parent = os.path.dirname(os.path.abspath(output))
            if os.path.isdir(parent) and os.access(parent, os.W_OK):
                return parent
        return None

    def describe(self) -> dict[str, Any]:
        """The settings that differ from the defaults, for reports and provenance."""
        return {k: v for k, v in vars(self).items() if v is not None}


_DEFAULT = Execution()
_CURRENT: contextvars.ContextVar[Execution] = contextvars.ContextVar(
    "recon_execution",
    default=_DEFAULT,  # noqa: B039 (frozen: the default is never changed)
)


def current() -> Execution:
    """The execution in force (:func:`run_on`); by default this process, the available memory."""
    return _CURRENT.get()


@contextlib.contextmanager
def run_on(execution: Execution | None = None, **options: Any) -> Iterator[Execution]:
    """Run the block's stages as ``execution`` or ``options`` say (:class:`Execution`'s fields).

    Options given here replace those of ``execution`` (default: the execution in force).
    Values are checked as the command line's are: ``memory="6GB"`` or a number of bytes.
    """
    base = execution if execution is not None else current()
    if options:
        given = Execution.from_values(options)
        names = [k.replace("-", "_") for k in options]
        base = replace(base, **{k: getattr(given, k) for k in names})
    token = _CURRENT.set(base)
    try:
        yield base
    finally:
        _CURRENT.reset(token)
