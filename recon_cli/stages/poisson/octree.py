"""The sparse multilevel grid of the Poisson solver (the octree, level by level).

Level ``d`` holds cells of the ``2**d`` lattice (keys sorted, see :mod:`._octree`), complete
in siblings, every cell up to ``full_depth``; a level's nodes are the corners of its cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_cli.stages.poisson import _octree as K

# cells kept around each occupied cell at every level (PoissonRecon keeps the B-spline support);
# build_levels builds this ring as the children of the parents within 1 of an occupied parent,
# which holds for 2 only
RING = 2


@dataclass
class Level:
    """One level of the grid (arrays are dropped as soon as the solve no longer needs them)."""

    depth: int
    # lookups are binary searches in the sorted keys: hash tables would double the memory
    cell_keys: np.ndarray  # (c,) int64 sorted keys
    node_keys: np.ndarray | None  # (m,) int64 sorted keys (dropped once the level is set up)
    n_nodes: int
    # (c, 4) int32: corners 0..3, corner q + 4 is node cell_nodes[c, q] + 1 (None until
    # set_corners when the levels were built without them)
    cell_nodes: np.ndarray | None
    unknown: np.ndarray | None  # (m,) bool: hat functions solved for at this level
    ncell: np.ndarray | None  # (m,) int8: cells incident to each node (the stiffness diagonal)
    cell_parent: np.ndarray | None = None  # (c,) int32 index in the coarser level
    # set by the solve, for the extraction: the nodes on the cube's faces and the leaf cells
    face_nodes: np.ndarray | None = None
    leaf: np.ndarray | None = None


def unique_keys(keys: np.ndarray) -> np.ndarray:
    """The sorted distinct values of 1-d ``keys``, as ``np.unique(keys)`` gives them.

    By a sort and a comparison of neighbours: numpy's hash-based ``unique`` is much slower on
    millions of int64 keys (docs/design/poisson.md).
    """
    s = np.sort(keys)
    if len(s) < 2:
        return s
    keep = np.empty(len(s), bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def _x_runs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """``points``' order along x and each box's run in it: a box tests only its x-range."""
    order = np.argsort(points[:, 0], kind="stable")
    xs = points[order, 0]
    return order, np.searchsorted(xs, lo[:, 0], side="left"), np.searchsorted(xs, hi[:, 0], "right")


def points_in_boxes(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """How many of ``points`` (n, 3) lie in each closed box ``lo``-``hi`` (k, 3): (k,) int.

    Through the points sorted along x, so a box tests only those in its x-range (thousands of
    small pieces of a noisy cloud of millions of points would otherwise cost k * n).
    """
    if not len(lo):
        return np.zeros(0, np.int64)
    order, start, stop = _x_runs(points, lo, hi)
    out = np.zeros(len(lo), np.int64)
    for k in range(len(lo)):
        yz = points[order[start[k] : stop[k]], 1:]
        out[k] = np.count_nonzero(np.all((yz >= lo[k, 1:]) & (yz <= hi[k, 1:]), axis=1))
    return out


def indices_in_boxes(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sorted indices of the ``points`` (n, 3) in any of the closed boxes ``lo``-``hi`` (k, 3).

    Only the points in the boxes' common bounding box are sorted (:func:`points_in_boxes`).
    """
    if not len(lo) or not len(points):
        return np.zeros(0, np.int64)
    near = np.flatnonzero(np.all((points >= lo.min(axis=0)) & (points <= hi.max(axis=0)), axis=1))
    sub = points[near]
    order, start, stop = _x_runs(sub, lo, hi)
    hit = np.zeros(len(sub), bool)
    for k in range(len(lo)):
        run = order[start[k] : stop[k]]
        hit[run[np.all((sub[run, 1:] >= lo[k, 1:]) & (sub[run, 1:] <= hi[k, 1:]), axis=1)]] = True
    return near[hit]


def pack_keys(xyz: np.ndarray) -> np.ndarray:
    """(n,) int64 lattice keys of integer coordinates (n, 3) (:func:`._octree.lattice_key`)."""
    xyz = xyz.astype(np.int64)
    return (xyz[:, 0] << 42) | (xyz[:, 1] << 21) | xyz[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(n, 3) int64 coordinates of lattice keys (the inverse of :func:`pack_keys`)."""
    m = (1 << 21) - 1
    return np.stack([(keys >> 42) & m, (keys >> 21) & m, keys & m], axis=1)


def dilate(keys: np.ndarray, axis: int, lo: int, hi: int, limit: int) -> np.ndarray:
    """Unique keys within [lo, hi] of ``keys`` along ``axis`` (sorted along that axis)."""
    k = np.sort(K.rekey(keys, axis, False))
    return K.rekey(K.dilate_minor(k, lo, hi, limit), axis, True)


def corner_keys(cell_keys: np.ndarray, depth: int) -> np.ndarray:
    """Sorted unique keys of the corners of the cells ``cell_keys`` (level ``depth``).

    The nodes of a level whose cells these are (:func:`build_levels` makes them so for the
    complete levels; a slab makes those of the cells it keeps).
    """
    nodes = cell_keys
    for axis in range(3):
        nodes = dilate(nodes, axis, 0, 1, 1 << depth)
    return nodes


def build_levels(
    item_pos: np.ndarray,
    item_level: np.ndarray,
    depth: int,
    full_depth: int,
    boundary: str,
    corners: bool = True,
    own_ring: int = 2,
    finer: np.ndarray | None = None,
) -> list[Level]:
    """Levels 0..``depth``: complete up to ``full_depth``.

    Below it, at level ``d``, the cells within :data:`RING` of a cell holding a splat item of level
    ``d`` or finer (``item_pos`` (k, 3) unit-cube positions, ``item_level`` (k,)), completed in
    siblings: the tree stops where the samples stop.

    With ``own_ring`` 1 (the degree-2 solve), a level keeps the ring of 2 only around its
    cells over finer items, and around the cells holding its own items only the ring of 1
    the items' field reaches (their quadratic B-splines' 27 cells): as in PoissonRecon,
    whose finest nodes are those its splats make, their neighbours only made at the coarser
    depths (the B-splines' overlap around nodes with children). It takes a third of the
    finest unknowns and a seventh of the peak memory off at the same accuracy
    (``bench/calibration.md``).

    Each level's nodes, its cells' corner nodes and which nodes are unknowns under
    ``boundary`` (the corners and unknowns only if ``corners``: the degree-2 solve needs
    neither, and makes the corners after it with :func:`set_corners`, the largest arrays of
    the levels kept out of its peak).

    ``finer``: sorted unique keys of the level-``depth`` cells holding items finer than
    ``depth`` (a tree whose finer levels are built elsewhere: the distributed coarse tree). The
    levels are those the items themselves would give, without building the finer ones.
    """
    if own_ring not in (1, 2):
        raise ValueError(f"own_ring must be 1 or 2, got {own_ring}")
    levels: list[Level] = []
    occ: list[np.ndarray | None] = [None] * (depth + 1)
    near: list[np.ndarray | None] = [None] * (depth + 1)
    occ_keys = np.zeros(0, np.int64) if finer is None else np.asarray(finer, np.int64)
    for d in range(depth, full_depth, -1):
        sel = item_level == d
        own = pack_keys(np.floor(item_pos[sel] * (1 << d)).clip(0, (1 << d) - 1))
        if own_ring == 1:
            # ring 2 around the cells over finer items (occ), and the parents of the cells
            # within 1 of the level's own items (near)
            near[d] = _ring1_parents(unique_keys(own), (1 << (d - 1)) - 1)
            # halved from the finer level: the cells over finer items
            occ[d] = unique_keys(occ_keys)
            occ_keys = unique_keys(np.concatenate([occ_keys, own]))
        else:
            occ_keys = unique_keys(np.concatenate([occ_keys, own]))
            occ[d] = occ_keys
        occ_keys = K.halve(occ_keys)  # halving breaks the x-major order (sorted above)
    for d in range(depth + 1):
        top = (1 << d) - 1
        if d <= full_depth:
            r = np.arange(top + 1, dtype=np.int64)
            g = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
            keys = pack_keys(g)
        else:
            # the cells within RING (= 2) of an occupied cell, completed in siblings, are the
            # children of the parents within 1 of an occupied parent (floor((o +- 2) / 2) =
            # floor(o / 2) +- 1 for either parity): dilate at the coarser level, 8x fewer keys,
            # and emit the children already sorted, with their parent index
            keys = unique_keys(K.halve(occ[d]))
            for axis in range(3):
                keys = dilate(keys, axis, -1, 1, top >> 1)  # valid for RING == 2 only
            # (the last dilation, along z, leaves the keys sorted and unique)
            near_d = near[d]
            if near_d is not None:
                keys = unique_keys(np.concatenate([keys, near_d]))
            par_idx = K.merge_lookup(keys, levels[-1].cell_keys)
            # the nodes of the children of parent p are 2p + {0, 1, 2}^3
            nodes = K.double(keys)
            keys, cell_parent = K.children_sorted(keys, par_idx)
            del par_idx
            for axis in range(3):
                nodes = dilate(nodes, axis, 0, 2, top + 1)
        if d <= full_depth:
            nodes = corner_keys(keys, d)
        # sorted queries (a constant offset keeps the order): linear merges, no hashing;
        # int32 and 4 corners of 8: a quarter of (c, 8) int64, the largest array
        cell_nodes = ncell = unknown = None
        if corners:
            cell_nodes = K.corner_nodes(keys, nodes)
            ncell = K.node_cell_count(cell_nodes, len(nodes))
            unknown = K.unknown_nodes(nodes, ncell, top + 1, boundary == "dirichlet")
        lev = Level(d, keys, nodes, len(nodes), cell_nodes, unknown, ncell)
        if d > 0:
            lev.cell_parent = (
                cell_parent
                if d > full_depth
                else K.bsearch_many(levels[-1].cell_keys, K.halve(keys))
            )
        levels.append(lev)
    return levels


def set_corners(lev: Level, node_keys: np.ndarray) -> None:
    """The corner nodes of ``lev``'s cells (``cell_nodes``) from its sorted node keys."""
    lev.cell_nodes = K.corner_nodes(lev.cell_keys, node_keys)


def _ring1_parents(cells: np.ndarray, top: int) -> np.ndarray:
    """Sorted unique parents of the cells within 1 of ``cells``.

    The parents are on the level above, coordinates 0..``top``: per axis the parent and, on the side
    the cell touches, its neighbour.
    """
    xyz = unpack_keys(cells)
    par = xyz >> 1
    side = np.where((xyz & 1) == 1, 1, -1)
    out = []
    for m in range(8):
        q = par.copy()
        for a in range(3):
            if m >> a & 1:
                q[:, a] += side[:, a]
        ok = np.all((q >= 0) & (q <= top), axis=1)
        out.append(pack_keys(q[ok]))
    return unique_keys(np.concatenate(out))
