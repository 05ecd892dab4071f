"""Screened Poisson's peak memory, predicted from the cloud and the depth before a run.

The solve's state grows with the samples (the points) and with the tree's nodes at its finest
level: the children of the parents within one cell of a cell that holds a sample (the tree is
complete in siblings, each node's neighbours made), the "ring parents". The tree is only as deep
as the samples' density supports (``samples_per_node``, :func:`.splat.make_splats`): its depth is
estimated from the points per cell of a coarse level. With the points at hand both are counted
(:func:`tree_of`); from the point count alone (a file's header), estimated at the calibration
cloud's coverage (:func:`tree_estimate`). The figures: ``bench/memory_model.py``,
``bench/calibration.md`` ("Memory model").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from recon_cli.memory import JIT_BASE

# a run in one piece: bytes per point and per ring parent of the finest level
# (bench/calibration.md, Memory model: poisson POINT_BYTES, RING_BYTES)
POINT_BYTES = 245
RING_BYTES = 700
# a slab's own state per point and per ring parent, its pads' included (bench/calibration.md,
# Memory model: SLAB_POINT_BYTES, SLAB_RING_BYTES)
SLAB_POINT_BYTES = 20
SLAB_RING_BYTES = 720
# the whole cube's coarse levels every slab and the coordinator hold, per ring parent of the coarse
# depth (bench/calibration.md, Memory model: COARSE_RING_BYTES)
COARSE_RING_BYTES = 1500
# a Dask worker running one slab (bench/calibration.md, Memory model: WORKER_STATE_FACTOR): its
# steps' peak over the slab's state of one process's model (the state read back from its file
# beside the step's arrays, the coarse levels' arguments unpickled), and the share of its memory
# limit the plan lets it reach (the nanny restarts a worker past 95 %)
WORKER_STATE_FACTOR = 1.5
WORKER_PEAK_SHARE = 0.9
# the cloud a run in slabs was given in memory, held beside them (points, normals, a property)
CLOUD_BYTES = 64
# what a run in slabs holds of every point beside the slab's state (bench/calibration.md,
# Memory model: SLABS_POINT_BYTES)
SLABS_POINT_BYTES = 170
# a run in one piece keeps its freed memory for reuse when its budget is this many times its
# predicted peak, and the kept heap's holes raise the part of the peak beyond the base by
# HEAP_GROWTH (bench/calibration.md, Memory model: HEAP_ROOM)
HEAP_ROOM = 3.0
HEAP_GROWTH = 1.5
# the level whose points per cell set the tree's depth, and the levels the densest samples go
# beyond the mean's (bench/calibration.md, Memory model: TREE_DEPTH_MARGIN)
DENSITY_LEVEL = 6
TREE_DEPTH_MARGIN = 1.0
# without the points (a header's count): the calibration cloud's cells of level DENSITY_LEVEL and
# ring parents per 4**level, and its ring parents per point at most (noisy armadillo samples)
SURFACE_CELLS = 3.0
SURFACE_RINGS = 11.0
RINGS_PER_POINT = 3.5


@dataclass(frozen=True)
class Tree:
    """The tree a solve builds: its finest ``depth`` and ``rings``, that level's ring parents."""

    depth: int
    rings: int


def _keys(points: np.ndarray, level: int, origin: np.ndarray, size: float) -> np.ndarray:
    from recon_cli.stages.poisson.octree import pack_keys, unique_keys

    n = 1 << level
    ijk = np.clip(((points - origin) * (n / size)).astype(np.int64), 0, n - 1)
    return unique_keys(pack_keys(ijk))


def _ring(keys: np.ndarray, n: int) -> int:
    """The cells within one cell (27-neighbourhood) of ``keys`` (packed, level of side ``n``)."""
    from recon_cli.stages.poisson.octree import unique_keys

    mask = (1 << 21) - 1
    for shift in (42, 21, 0):
        c = (keys >> shift) & mask
        step = np.int64(1) << np.int64(shift)
        keys = unique_keys(np.concatenate([keys, keys[c > 0] - step, keys[c < n - 1] + step]))
    return len(keys)


def tree_depth(points: int, depth: int, coarse_cells: float, samples_per_node: float) -> int:
    """The tree's depth, at most ``depth``.

    Where the mean points per cell of :data:`DENSITY_LEVEL` (``coarse_cells`` of them hold a
    point), a quarter of them a level finer, reach ``samples_per_node``; plus
    :data:`TREE_DEPTH_MARGIN` (the densest samples').
    """
    level = min(DENSITY_LEVEL, depth)
    per = max(points / max(coarse_cells, 1.0), 1e-9)
    est = level + 0.5 * math.log2(max(per / samples_per_node, 1e-9)) + TREE_DEPTH_MARGIN
    return int(min(depth, max(level, math.ceil(est))))


def tree_of(points: np.ndarray, depth: int, scale: float, samples_per_node: float) -> Tree:
    """The tree of the cloud ``points`` (n, 3): its depth estimated, its ring parents counted."""
    if len(points) == 0:
        return Tree(0, 0)
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = float((hi - lo).max()) * scale
    if not size > 0:
        return Tree(0, 1)
    origin = 0.5 * (lo + hi) - 0.5 * size
    coarse = len(_keys(points, min(DENSITY_LEVEL, depth), origin, size))
    d = tree_depth(len(points), depth, coarse, samples_per_node)
    if d < 1:
        return Tree(d, 1)
    finest = _keys(points, d, origin, size)
    from recon_cli.stages.poisson.octree import pack_keys, unique_keys, unpack_keys

    parents = unique_keys(pack_keys(unpack_keys(finest) >> 1))
    return Tree(d, _ring(parents, 1 << (d - 1)))


def tree_estimate(points: int, depth: int, samples_per_node: float = 1.5) -> Tree:
    """The tree of a cloud of ``points`` points, its cells not counted (a header's count)."""
    level = min(DENSITY_LEVEL, depth)
    d = tree_depth(points, depth, SURFACE_CELLS * 4.0**level, samples_per_node)
    rings = min(RINGS_PER_POINT * points, SURFACE_RINGS * 4.0 ** max(d - 1, 0))
    return Tree(d, int(rings))


def one_piece_bytes(points: int, tree: Tree) -> int:
    """Peak resident bytes of a run in one piece (the process's, imports included)."""
    return int(JIT_BASE + POINT_BYTES * points + RING_BYTES * tree.rings)


def heap_room(points: int, depth: int, budget: int | None) -> bool:
    """Whether a run in one piece may keep its freed memory (:func:`recon_cli.memory.heap_kept`).

    When ``budget`` bytes hold :data:`HEAP_ROOM` times its predicted peak (its own estimate
    of the tree); never when the budget is unknown.
    """
    if budget is None:
        return False
    return HEAP_ROOM * one_piece_bytes(points, tree_estimate(points, depth)) <= budget


def kept_heap_bytes(one_piece: int) -> int:
    """The peak of a run in one piece predicted at ``one_piece`` bytes, its freed heap kept."""
    return int(JIT_BASE + HEAP_GROWTH * max(one_piece - JIT_BASE, 0))


def coarse_depth(depth: int) -> int:
    """The levels the coordinator solves for the whole cube at ``depth`` (up to 32 slabs).

    As :func:`.distributed.coarse_depth_for` (not imported: that module imports this one).
    """
    from recon_cli.stages.poisson.slab import COARSE_MAX, COARSE_OFFSET, PARTITION_DEPTH

    return min(depth, max(PARTITION_DEPTH, min(depth - COARSE_OFFSET, COARSE_MAX)))


def read_share(depth: int, slabs: int) -> float:
    """The share of the cube's width the widest of ``slabs`` slabs reads: its own and its pads.

    The pads: :data:`.slab.PAD_CELLS` cells of the first level below the coarse depth beyond
    each seam (:func:`coarse_depth` of the tree's ``depth``), and the
    density's :data:`.slab.DENSITY_REACH` cells of that level beyond them.
    """
    if slabs <= 1:
        return 1.0
    from recon_cli.stages.poisson.slab import DENSITY_REACH, PAD_CELLS

    pad = (PAD_CELLS + DENSITY_REACH) / 2.0 ** (coarse_depth(depth) + 1)
    return min(1.0, 1.0 / slabs + 2.0 * pad)


def slab_bytes(points: int, tree: Tree, slabs: int) -> int:
    """A slab's own state, pads included: the part a slab count divides (bytes).

    The whole cloud's at one slab; at more, the share the widest reads (:func:`read_share`).
    """
    share = read_share(tree.depth, int(slabs))
    return int((SLAB_POINT_BYTES * points + SLAB_RING_BYTES * tree.rings) * share)


def slab_run_bytes(points: int, tree: Tree, slabs: int, in_memory: bool = True) -> int:
    """Peak resident bytes of a process running ``slabs`` slabs, one at a time.

    The process's base, the whole cube's coarse levels, one slab's state and, with
    ``in_memory``, the cloud the stage was given (a run from files never holds it).
    """
    held = (CLOUD_BYTES if in_memory else 0) + SLABS_POINT_BYTES
    return int(held * points + slab_peak_bytes(points, tree, read_share(tree.depth, int(slabs))))


def slab_peak_bytes(points: int, tree: Tree, share: float) -> int:
    """Peak resident bytes of a process running one slab that reads ``share`` of the points.

    A worker's (:func:`worker_bytes`), or a process running slabs one at a time without what it
    holds of every point (:func:`slab_run_bytes`): its base, the whole cube's coarse levels and
    the slab's state, its pads included, at ``share`` of the cloud's (points and ring parents).
    """
    coarse = coarse_depth(tree.depth)
    coarse_rings = min(tree.rings, SURFACE_RINGS * 4.0 ** max(coarse - 1, 0))
    state = (SLAB_POINT_BYTES * points + SLAB_RING_BYTES * tree.rings) * min(share, 1.0)
    return int(JIT_BASE + COARSE_RING_BYTES * coarse_rings + state)


def worker_bytes(points: int, tree: Tree, share: float) -> int:
    """Peak resident bytes of a Dask worker running a slab that reads ``share`` of the points.

    :func:`slab_peak_bytes` with the slab's state :data:`WORKER_STATE_FACTOR` times its size;
    ``share``: the largest slab's points read (its pads' included) over the cloud's, from the
    points per sub-slab (:func:`.distributed.fitted_slab_count`).
    """
    base = slab_peak_bytes(points, tree, 0.0)
    return int(base + WORKER_STATE_FACTOR * (slab_peak_bytes(points, tree, share) - base))
