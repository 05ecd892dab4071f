"""The slabs of a job: how many, where the seams go, which sub-slab a point is in.

Shared by the stages that work in slabs (``recon_cli.stages.poisson.distributed``,
``recon_cli.stages.normals.distributed``): a job's cube is cut along one axis into slabs
whose seams lie on planes of a coarse lattice, balanced by point count; a slab's memory is its
points times a stage's bytes per point, and a run takes the fewest slabs whose one slab fits a
share of the memory a process may use (a Dask worker's limit, or this process's budget,
:class:`recon_cli.execution.Execution`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from recon_cli.errors import ParameterError

log = logging.getLogger("recon")

# the share of a process's memory one slab may take: the rest is the process's own (imports,
# compiled kernels, Dask's buffers or the coordinator's coarse levels) and the pads' growth with
# many slabs
SLAB_MEMORY_SHARE = 0.4


def choose_seams(counts: np.ndarray, parts: int) -> list[int]:
    """Seam positions that balance ``counts`` over ``parts`` slabs.

    In slabs of the seams' level, strictly increasing, 1..len(counts) - 1; ``counts`` are the
    points per slab of that level (32 of level 5, or 64 of level 6).
    """
    n = len(counts)
    if parts > n:
        raise ParameterError(f"at most {n} partitions (the seams' planes), got {parts}")
    cum = np.concatenate([[0], np.cumsum(counts)])
    total = cum[-1]
    seams: list[int] = []
    for k in range(1, parts):
        target = total * k / parts
        b = int(np.argmin(np.abs(cum[1:n] - target))) + 1
        lo = (seams[-1] + 1) if seams else 1
        hi = n - (parts - k)
        seams.append(min(max(b, lo), hi))
    return seams


def sub_slab(x_unit: np.ndarray, nsub: int) -> np.ndarray:
    """(n,) the sub-slab (of ``nsub`` along x) of each unit-cube x."""
    return np.clip(np.floor(x_unit * nsub), 0, nsub - 1).astype(np.int64)


def default_partitions(
    npoints: int,
    workers: int,
    memory_per_worker: float | None,
    bytes_per_point: float,
    cap: int = 64,
) -> int:
    """The slab count of a run whose ``--partitions`` is not given.

    Parameters
    ----------
    npoints : int
        Points of the cloud (those with a usable normal).
    workers : int
        Worker processes of the cluster (>= 1).
    memory_per_worker : float or None
        A worker's memory limit in bytes; None or 0 for no limit.
    bytes_per_point : float
        A slab's peak per point of its own (the stage's figure).
    cap : int
        The most slabs the stage's seams allow.

    Returns
    -------
    int
        The fewest slabs such that one slab, at ``bytes_per_point`` bytes per point of its share
        of ``npoints``, fits ``SLAB_MEMORY_SHARE`` of ``memory_per_worker``, rounded up to a
        multiple of ``workers`` (every worker runs as many), at least ``workers``; at most
        ``cap``, even when a slab does not fit then. Without a limit, one slab per worker.
    """
    if int(workers) < 1:
        raise ParameterError(f"workers must be >= 1, got {workers}")
    if int(npoints) < 0:
        raise ParameterError(f"npoints must be >= 0, got {npoints}")
    workers = int(workers)
    if not memory_per_worker or memory_per_worker <= 0:
        return min(workers, cap)
    need = math.ceil(npoints * bytes_per_point / (SLAB_MEMORY_SHARE * memory_per_worker))
    rounds = max(1, math.ceil(need / workers))
    return min(rounds * workers, cap)


def worker_memory(client: Any) -> tuple[int, int | None]:
    """The cluster's worker count and the smallest worker memory limit in bytes (None: no limit)."""
    workers = client.scheduler_info().get("workers", {})
    limits = [w.get("memory_limit") for w in workers.values()]
    limited = [float(m) for m in limits if m]
    return max(1, len(workers)), (int(min(limited)) if limited else None)


def _size(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB" if nbytes >= 2**30 else f"{nbytes / 2**20:.3g} MiB"


def slab_count(
    partitions: int | None,
    npoints: int,
    client: Any,
    bytes_per_point: float,
    cap: int,
    stage: str,
    cap_reason: str,
    budget: int | None = None,
) -> tuple[int, dict]:
    """The slabs of a run and the report's ``partitions`` entry (how many, and why).

    Parameters
    ----------
    partitions : int or None
        Given: that many. None: the fewest whose one slab fits (:func:`default_partitions`).
    npoints : int
        Points of the cloud.
    client : dask.distributed.Client or None
        The cluster, whose workers' count and memory limit size the slabs; None: this process,
        whose memory is ``budget``.
    bytes_per_point : float
        A slab's peak memory per point of its own, the stage's figure.
    cap : int
        The most slabs; ``cap_reason`` says why there is one.
    stage : str
        The stage, for messages.
    budget : int or None
        Bytes this process may use (no ``client``); None: no limit (one slab).

    Raises
    ------
    ParameterError
        A memory limit too small for one slab of the most slabs: the message gives the
        smallest limit that would do.
    """
    if client is not None:
        nworkers, memory = worker_memory(client)
        whose = "a worker's"
    else:
        nworkers, memory = 1, budget
        whose = "this process's"
    entry: dict[str, Any] = {
        "count": 0,
        "why": "",
        "workers": nworkers if client is not None else 0,
        "memory_per_worker" if client is not None else "memory": memory,
        "points": int(npoints),
    }
    if partitions is not None:
        entry.update(count=int(partitions), why="given (--partitions)")
        return int(partitions), entry
    parts = default_partitions(npoints, nworkers, memory, bytes_per_point, cap)
    slab_bytes = npoints / parts * bytes_per_point
    entry.update(count=parts, slab_bytes_estimate=int(slab_bytes))
    if memory is not None and slab_bytes > SLAB_MEMORY_SHARE * memory:
        need = math.ceil(slab_bytes / SLAB_MEMORY_SHARE / 2**20)  # MiB, rounded up: enough
        raise ParameterError(
            f"{stage}: {npoints} points need at least {need} MiB of memory per process in "
            f"{parts} slabs (the most: {cap_reason}); {whose} limit is {_size(memory)}"
        )
    if client is None:
        head = "one slab" if parts == 1 else f"{parts} slabs in this process"
    elif parts % nworkers == 0:
        head = "one per worker" if parts == nworkers else f"{parts // nworkers} per worker"
    else:
        head = f"{parts} slabs"
    if memory is None:
        why = f"{head}: no memory limit"
    else:
        share = f"{SLAB_MEMORY_SHARE:.0%} of {whose} {_size(memory)}"
        why = f"{head}: a slab (~{_size(slab_bytes)}) fits {share}"
    entry["why"] = why
    return parts, entry
