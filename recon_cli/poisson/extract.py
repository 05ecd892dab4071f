"""Extraction of the level set over the tree."""

from __future__ import annotations

import numpy as np

from recon_cli.mcubes import marching_cubes_sparse
from recon_cli.poisson import _extract as E
from recon_cli.poisson.octree import Level

# how far below the iso-value chi is clamped on the cube's faces (chi jumps by about 1)
FACE_MARGIN = 1e-3


def extract(levels: list[Level], gvals: list[np.ndarray], iso: float, origin: np.ndarray, size: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (world units) and faces of the level set ``chi = iso``.

    Leaves of the tree are refined to the finest lattice where they straddle the iso-value
    (exactly: chi is trilinear in a leaf), every lattice value is computed once, so there are
    no cracks between cells of different sizes. Consumes ``levels`` and ``gvals`` (emptied,
    finest first, to free memory). The cube's faces count as outside (chi clamped to
    ``iso - FACE_MARGIN`` there), so a surface running into them is closed.
    """
    depth = len(levels) - 1
    res = 1 << depth

    # only leaves whose corner range reaches the iso-value can hold surface: count their
    # finest cells first, then write them straight into arrays of the exact size (per-level
    # parts and their concatenation would hold the cells twice)
    none_xyz, none_val = np.zeros((0, 3), np.int64), np.zeros((0, 8))
    counts = [E.refine_leaves(lev.cell_keys, lev.cell_nodes, lev.leaf, g, lev.depth, depth, iso, 1e-9, FACE_MARGIN, none_xyz, none_val)
              for lev, g in zip(levels, gvals)]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cells = np.empty((int(offsets[-1]), 3), np.int64)
    vals = np.empty((int(offsets[-1]), 8))
    # finest first, freeing each level once written: it holds most of the memory
    for d in range(depth, -1, -1):
        lev = levels.pop()
        E.refine_leaves(lev.cell_keys, lev.cell_nodes, lev.leaf, gvals.pop(), d, depth, iso, 1e-9, FACE_MARGIN,
                        cells[offsets[d]:offsets[d + 1]], vals[offsets[d]:offsets[d + 1]])
    del levels, gvals, lev
    # one value per lattice point whichever leaf computed it (they agree up to rounding)
    ckeys = E.corner_keys(cells)
    # one unstable argsort and a linear pass: np.unique's stable sort and inverse cost 4x more
    order = np.argsort(ckeys)
    E.unify_corner_values(vals, ckeys[order], order)
    del ckeys, order
    verts, faces = marching_cubes_sparse(cells, vals, -iso, origin=tuple(origin), spacing=size / res)
    del cells, vals
    return verts, faces
