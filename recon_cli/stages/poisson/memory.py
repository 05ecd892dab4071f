"""Screened Poisson's peak memory, predicted from the cloud's size and the depth before a run.

The solve's state grows with the samples (the points) and with the tree's finest cells: the
cells of level ``depth`` holding a sample, which follow the surface's area at that level (about
``4**depth`` times the share of the cube the surface covers), and never outnumber the points.
The figures are calibrated on noisy armadillo samples (``bench/memory_model.py``,
``bench/calibration.md``: "Memory model").
"""

from __future__ import annotations

import math

import numpy as np

from recon_cli.memory_model import BASE_BYTES

# per point and per finest cell of a run in one piece (bench/calibration.md, Memory model:
# POINT_BYTES, CELL_BYTES; bench/memory_model.py poisson)
POINT_BYTES = 440
CELL_BYTES = 900
# finest cells a surface has per 4**depth, from the header alone (points not read yet): the
# noisy armadillo's, a high figure (bench/calibration.md, Memory model: SURFACE_CELLS)
SURFACE_CELLS = 5.0
# a slab's own state per point and per cell of its own, its pads' included (bench/calibration.md,
# Memory model: SLAB_POINT_BYTES, SLAB_CELL_BYTES)
SLAB_POINT_BYTES = 900
SLAB_CELL_BYTES = 1400
# the coordinator's coarse levels: bytes per cell of the whole cube's coarse tree
COARSE_CELL_BYTES = 1200
# the in-memory cloud the stage holds beside its slabs (points, normals, a property)
CLOUD_BYTES = 64


def finest_cells(points: int, depth: int, cells: int | None = None) -> int:
    """The tree's finest cells: ``cells`` when counted, else estimated from the points alone.

    The estimate fills :data:`SURFACE_CELLS` ``* 4**depth`` surface cells with ``points``
    samples thrown at random: ``S (1 - exp(-points / S))``.
    """
    if cells is not None:
        return int(cells)
    surface = SURFACE_CELLS * 4.0 ** min(int(depth), 20)
    return int(surface * -math.expm1(-points / surface)) if points else 0


def count_cells(points: np.ndarray, depth: int, scale: float) -> int:
    """The cells of level ``depth`` of the solve's cube that hold a point (``points`` (n, 3))."""
    from recon_cli.stages.poisson.octree import pack_keys, unique_keys

    if len(points) == 0:
        return 0
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = float((hi - lo).max()) * scale
    if not size > 0:
        return 1
    origin = 0.5 * (lo + hi) - 0.5 * size
    n = 1 << int(depth)
    ijk = np.clip(((points - origin) * (n / size)).astype(np.int64), 0, n - 1)
    return len(unique_keys(pack_keys(ijk)))


def one_piece_bytes(points: int, depth: int, cells: int | None = None) -> int:
    """Peak resident bytes of a run in one piece (the process's, imports included)."""
    c = finest_cells(points, depth, cells)
    return int(BASE_BYTES + POINT_BYTES * points + CELL_BYTES * c)


def coarse_bytes(depth: int, coarse_depth: int) -> int:
    """The whole cube's coarse levels that the coordinator and every slab hold."""
    return int(COARSE_CELL_BYTES * finest_cells(1 << 62, min(depth, coarse_depth)))


def slab_bytes(points: int, depth: int, slabs: int, cells: int | None = None) -> int:
    """A slab's own state, pads included: the part a slab count divides (bytes)."""
    c = finest_cells(points, depth, cells)
    return int((SLAB_POINT_BYTES * points + SLAB_CELL_BYTES * c) / max(int(slabs), 1))


def slab_run_bytes(
    points: int, depth: int, slabs: int, cells: int | None = None, in_memory: bool = True
) -> int:
    """Peak resident bytes of a process running ``slabs`` slabs, one at a time.

    The process's base, the coarse levels, one slab's state and, with ``in_memory``, the cloud
    the stage was given (a run from files never holds it).
    """
    from recon_cli.stages.poisson.distributed import coarse_depth_for

    held = CLOUD_BYTES * points if in_memory else 0
    return int(
        BASE_BYTES
        + held
        + coarse_bytes(depth, coarse_depth_for(depth))
        + slab_bytes(points, depth, slabs, cells)
    )
