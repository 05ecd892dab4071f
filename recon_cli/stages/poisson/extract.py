"""Extraction of the level set over the tree (the density trim is :mod:`.trim`).

:func:`extract_leaves` works at the leaves' own size (Kazhdan, Klein, Dalal & Hoppe 2007,
"Unconstrained isosurface extraction on arbitrary octrees"). ``gvals[d]`` holds the whole
``chi`` at level ``d``'s nodes, and a level's correction vanishes on the border of its region,
so ``chi`` is trilinear in every leaf and continuous across leaves of any sizes; moreover all
leaves with a corner at a point hold the same bits there (finer corrections are exactly 0 at
a coarser leaf's corners, the prolongation copies coincident nodes), so a point's sign never
depends on which leaf reads it.

- A *minimal edge* is an edge of a leaf that no leaf sharing it splits; ``chi`` is linear on
  it, so its root is the linear interpolation of its end values, one vertex per minimal edge,
  welded through the edge's key (lower end on the finest lattice, axis).
- A *minimal face* is the smaller of the two leaf faces that meet (the far side is looked up
  level by level where it has children); its boundary, walked counter-clockwise about its
  normal, runs over its minimal edges; its roots are paired without crossings by one rule
  computed from the face alone (the value at its centre: inside, the inside arcs are joined),
  so both leaves see the same segments, in opposite directions.
- Each leaf chains the segments of the minimal faces covering its boundary into closed loops
  (every root ends one segment and starts another), each loop a polygon: a triangle as it
  is; up to :data:`._extract.MAX_DP` vertices the minimal-area triangulation among diagonals
  joining roots on no common face of the leaf (only such a pair could be joined by another
  leaf too: edge-manifold), else a fan about a new vertex at the loop's centroid.
- Points on the cube's faces count as outside (``chi`` clamped to ``iso - FACE_MARGIN``), so a
  surface running into them is closed. Along a leaf edge that leaves the cube's face the
  clamp can put two roots, joined on both faces of the leaf there: that loop has no area and
  is left out, gluing the leaves across those faces directly.

:func:`extract_finest` (every straddling leaf refined to the finest lattice, then sparse
marching cubes) gives the same vertices when every leaf holding surface is a finest cell (a
dense closed shape), faster; :func:`extract` takes it then. Where coarser leaves hold
surface (open scans, sparse regions) it would give several times the faces.
"""

from __future__ import annotations

import numpy as np

from recon_cli.errors import StageFailed
from recon_cli.stages.mcubes import marching_cubes_sparse
from recon_cli.stages.poisson import _extract as E
from recon_cli.stages.poisson import _extract_finest as EF
from recon_cli.stages.poisson import _system as Y
from recon_cli.stages.poisson.octree import Level
from recon_cli.stages.poisson.system import chi_at

# how far below the iso-value chi is clamped on the cube's faces (chi jumps by about 1)
FACE_MARGIN = 1e-3
# roots are kept this fraction of a minimal edge away from its ends (no two at one point)
ROOT_CLAMP = 1e-3
# vertices refined at a time by refine_roots (its temporaries are ~0.5 kB a vertex)
ROOT_CHUNK = 1 << 16
# cells a chunk of leaf_polygons (fixed, so the chunks do not depend on the thread count; the
# weld makes the mesh independent of them anyway): many more chunks than threads balance them
LEAF_CHUNK = 1 << 16


def finest_cells(
    levels: list[Level],
    gvals: list[np.ndarray],
    iso: float,
    masks: list[np.ndarray] | None = None,
    consume: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The finest-lattice cells of the leaves that straddle ``iso``, one value per lattice point.

    Parameters
    ----------
    levels, gvals : list
        The tree's levels and chi at each level's nodes.
    iso : float
        The iso-value.
    masks : list of (c_d,) bool, optional
        Per level, the leaves to refine (default: every leaf; a slab's own leaves).
    consume : bool
        Empty ``levels`` and ``gvals`` (finest first, each freed once written: they hold most of
        the memory).

    Returns
    -------
    cells : (c, 3) int64
        Finest-lattice cells, level by level.
    vals : (c, 8) float
        Chi at their corners, the same at a lattice point whichever leaf computed it (they agree
        up to rounding); the cube's faces at ``iso - FACE_MARGIN``.
    ckeys : (8c,) int64
        The corners' packed lattice keys.
    """
    depth = len(levels) - 1
    if masks is None:
        masks = [np.asarray(lev.leaf) for lev in levels]
    # only leaves whose corner range reaches the iso-value can hold surface: count their
    # finest cells first, then write them straight into arrays of the exact size (per-level
    # parts and their concatenation would hold the cells twice)
    none_xyz, none_val = np.zeros((0, 3), np.int64), np.zeros((0, 8))
    counts = [
        EF.refine_leaves(
            lev.cell_keys,
            lev.cell_nodes,
            m,
            g,
            lev.depth,
            depth,
            iso,
            1e-9,
            FACE_MARGIN,
            none_xyz,
            none_val,
        )
        for lev, m, g in zip(levels, masks, gvals, strict=True)
    ]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    cells = np.empty((int(offsets[-1]), 3), np.int64)
    vals = np.empty((int(offsets[-1]), 8))
    for d in range(depth, -1, -1):
        lev = levels[d]
        EF.refine_leaves(
            lev.cell_keys,
            lev.cell_nodes,
            masks[d],
            gvals[d],
            d,
            depth,
            iso,
            1e-9,
            FACE_MARGIN,
            cells[offsets[d] : offsets[d + 1]],
            vals[offsets[d] : offsets[d + 1]],
        )
        if consume:
            levels.pop()
            gvals.pop()
            masks.pop()
    del lev, masks
    ckeys = EF.corner_keys(cells)
    # one unstable argsort and a linear pass: np.unique's stable sort and inverse cost 4x more
    order = np.argsort(ckeys)
    EF.unify_corner_values(vals, ckeys, order)
    return cells, vals, ckeys


def extract_finest(
    levels: list[Level], gvals: list[np.ndarray], iso: float, origin: np.ndarray, size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (world units) and faces of the level set ``chi = iso`` on the finest lattice.

    Leaves of the tree are refined to the finest lattice where they straddle the iso-value
    (exactly: chi is trilinear in a leaf), every lattice value is computed once, so there are
    no cracks between cells of different sizes. Consumes ``levels`` and ``gvals`` (emptied,
    finest first, to free memory). The cube's faces count as outside (chi clamped to
    ``iso - FACE_MARGIN`` there), so a surface running into them is closed.
    """
    res = 1 << (len(levels) - 1)
    cells, vals, ckeys = finest_cells(levels, gvals, iso, consume=True)
    del ckeys
    verts, faces = marching_cubes_sparse(
        cells, vals, -iso, origin=tuple(origin), spacing=size / res
    )
    del cells, vals
    return verts, faces


def extract(
    levels: list[Level], gvals: list[np.ndarray], iso: float, origin: np.ndarray, size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (world units) and faces of the level set ``chi = iso``.

    Over the leaves at their own size (:func:`extract_leaves`) when a leaf coarser than the
    finest cells holds surface; when none does (a dense closed shape), both ways give the same
    vertices, and marching cubes on the finest cells (:func:`extract_finest`) is faster, needs
    less memory and its triangles follow the surface a little closer (its tables against the
    minimal-area triangulation: 2-3 % on smooth shapes).
    """
    depth = len(levels) - 1
    coarse = any(
        EF.straddles(
            lev.cell_keys, lev.cell_nodes, lev.leaf, g, lev.depth, depth, iso, 1e-9, FACE_MARGIN
        )
        for lev, g in zip(levels[:-1], gvals[:-1], strict=True)
    )
    if coarse:
        return extract_leaves(levels, gvals, iso, origin, size)
    return extract_finest(levels, gvals, iso, origin, size)


def extract_leaves(
    levels: list[Level],
    gvals: list[np.ndarray],
    iso: float,
    origin: np.ndarray,
    size: float,
    x_range: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (world units) and faces of the level set ``chi = iso`` at the leaves' own size.

    Closed, edge- and vertex-manifold, consistently oriented (outward), no two vertices at one
    point (module docstring). Consumes ``levels`` and ``gvals`` (emptied, to free memory):
    the coarser levels are concatenated for the kernel, the finest (the largest) is passed
    as it is. ``x_range``: only the leaves whose lower x (finest-lattice units) is in
    [lo, hi) (a slab's part: :mod:`.distributed`); all by default.
    """
    depth = len(levels) - 1
    # the levels but the finest concatenated (each freed once copied); the finest, the
    # largest, passed as it is
    fine = levels.pop()
    fg = gvals.pop()
    coff = np.concatenate([[0], np.cumsum([len(lev.cell_keys) for lev in levels])]).astype(np.int64)
    goff = np.concatenate([[0], np.cumsum([len(x) for x in gvals])]).astype(np.int64)
    keys = np.empty(coff[-1], np.int64)
    leaf = np.empty(coff[-1], np.bool_)
    nodes = np.empty((coff[-1], 4), np.int32)
    g = np.empty(goff[-1])
    for d in range(depth - 1, -1, -1):
        lev = levels.pop()
        keys[coff[d] : coff[d + 1]] = lev.cell_keys
        leaf[coff[d] : coff[d + 1]] = lev.leaf
        nodes[coff[d] : coff[d + 1]] = lev.cell_nodes
        g[goff[d] : goff[d + 1]] = gvals.pop()
        del lev
    tree = (keys, leaf, nodes, g, coff, goff, fine.cell_keys, fine.cell_nodes, fg, depth)
    surface = (iso, 1e-9, FACE_MARGIN, ROOT_CLAMP)
    args = (tree, surface, *((0, (1 << depth) + 1) if x_range is None else x_range))
    tri, vpos, broken = _leaf_polygons(args, int(coff[-1]) + len(fine.cell_keys))
    del args, tree, keys, leaf, nodes, g, fine, fg
    if broken:
        raise StageFailed(
            f"poisson extraction: {broken} iso-segment chains did not close (please report "
            "this input)"
        )
    vpos *= size / (1 << depth)
    vpos += origin
    return vpos, tri


def _leaf_polygons(args: tuple, n_cells: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The leaves' triangles, vertices and broken chains, chunk by chunk in threads.

    :func:`._extract.leaf_polygons` over chunks of :data:`LEAF_CHUNK` cells in numba's thread
    count of threads, welded in chunk order: the mesh of one chunk of all cells, for any count.
    """
    import numba

    bounds = [(a, min(a + LEAF_CHUNK, n_cells)) for a in range(0, max(n_cells, 1), LEAF_CHUNK)]
    threads = min(numba.get_num_threads(), len(bounds))
    if threads == 1:
        parts = [E.leaf_polygons(*args, a, b) for a, b in bounds]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(threads) as pool:  # the kernel releases the GIL
            parts = list(pool.map(lambda ab: E.leaf_polygons(*args, *ab), bounds))
    if len(parts) == 1:
        return parts[0][0], parts[0][1], parts[0][3]
    voff = np.cumsum([0] + [len(p[2]) for p in parts], dtype=np.int64)
    toff = np.cumsum([0] + [len(p[0]) for p in parts], dtype=np.int64)
    vkey = np.concatenate([p[2] for p in parts])
    tri, first = E.weld_chunks(vkey, voff, np.concatenate([p[0] for p in parts]), toff)
    vpos = np.concatenate([p[1] for p in parts])[first]
    return tri, vpos, sum(p[3] for p in parts)


def _edge_steps(verts: np.ndarray, axis: np.ndarray, chi: list, depth: int) -> np.ndarray:
    """Length (finest-lattice units) of the minimal edge each vertex lies on.

    The size of the finest leaf around the edge, found as the finest level holding one of the four
    cells that meet along it (the finest cell holding a point is a leaf).
    """
    res = 1 << depth
    n = len(verts)
    step = np.zeros(n, np.int64)
    todo = np.arange(n)
    offs = [(-0.25, -0.25), (-0.25, 0.25), (0.25, -0.25), (0.25, 0.25)]
    for lv, cell_keys, _nodes, _g in chi[::-1]:
        if not len(todo):
            break
        hit = np.zeros(len(todo), bool)
        r = np.arange(len(todo))
        b = (axis[todo] + 1) % 3
        c = (axis[todo] + 2) % 3
        for ob, oc in offs:
            p = verts[todo].copy()
            p[r, b] += ob
            p[r, c] += oc
            hit |= Y.sample_cells(p / res, lv, cell_keys)[0] >= 0
        step[todo[hit]] = 1 << (depth - lv)
        todo = todo[~hit]
    step[todo] = 1 << depth
    return step


def refine_roots(verts: np.ndarray, chi: list, iso: float, depth: int) -> int:
    """Move each vertex to the root of a quadratic fit of chi along its lattice edge.

    In finest-lattice units, in place; returns how many were moved.

    ``chi`` is :func:`recon_cli.stages.poisson.system.chi_levels`'s list. chi is trilinear in the
    leaves, so the extracted vertices are the roots of a piecewise linear function; the indicator it
    stands for is smooth. As PoissonRecon's non-linear fit (the default in it and in Open3D), the
    root is taken on the quadratic through the edge's end values whose end slopes are in the ratio
    of chi's slopes there (central differences one lattice step beyond the ends:
    :func:`._extract.fit_roots`). The edge is the vertex's minimal edge, at the size of the finest
    leaf around it (:func:`_edge_steps`), and the central differences are one edge length beyond its
    ends (the finest step on a coarse leaf's edge fitted worse than the linear roots; figures in
    ``docs/design/poisson.md``). A vertex stays within its edge (so the topology is unchanged);
    vertices whose four values would reach the cube's faces (clamped in the extraction) stay where
    they are.
    """
    # in chunks: each vertex's fit is its own, and the fit's temporaries (four lattice points
    # per vertex, their cells and local coordinates at every level) are ~0.5 kB a vertex
    moved = 0
    for s in range(0, len(verts), ROOT_CHUNK):
        moved += _refine_chunk(verts[s : s + ROOT_CHUNK], chi, iso, depth)
    return moved


def _refine_chunk(verts: np.ndarray, chi: list, iso: float, depth: int) -> int:
    """:func:`refine_roots` on ``verts`` (a view, moved in place)."""
    res = 1 << depth
    if not len(verts):
        return 0
    near = np.abs(verts - np.round(verts))
    axis = np.argmax(near, axis=1)
    rows = np.arange(len(verts))
    frac_ok = near[rows, axis] > 0
    other = np.ones(len(verts), bool)
    for a in range(3):
        c = np.round(verts[:, a]).astype(np.int64)
        # the two coordinates off the edge's axis must be inside the cube, not on its faces
        other &= (axis == a) | ((c > 0) & (c < res))
    cand = np.flatnonzero(frac_ok & other)
    if not len(cand):
        return 0
    # the step of each vertex's minimal edge: the size of the finest leaf around it
    step = _edge_steps(verts[cand], axis[cand], chi, depth)
    ax = axis[cand]
    r = np.arange(len(cand))
    la = np.floor(verts[cand, ax] / step).astype(np.int64) * step
    base = np.round(verts[cand]).astype(np.int64)
    base[r, ax] = la
    # the fit's four values lie inside the cube, the far ones off its faces
    keep = (la - step >= 0) & (la + 2 * step <= res - 1)
    for a in range(3):
        keep &= (ax == a) | (base[:, a] % step == 0)
    sel = cand[keep]
    if not len(sel):
        return 0
    base, ax, step, la = base[keep], ax[keep], step[keep], la[keep]
    r = np.arange(len(sel))
    pts = np.empty((4, len(sel), 3))
    for k, m in enumerate((-1, 0, 1, 2)):
        pts[k] = base
        pts[k, r, ax] += m * step
    vals = chi_at(chi, pts.reshape(-1, 3) / res).reshape(4, len(sel))
    t = E.fit_roots(vals[0], vals[1], vals[2], vals[3], iso, ROOT_CLAMP)
    ok = t >= 0
    moved = sel[ok]
    verts[moved, axis[moved]] = la[ok] + t[ok] * step[ok]
    return int(ok.sum())
