"""Every per-point property of the input carried onto the surface's vertices.

This is ``--attributes`` (PoissonRecon's ``--colors`` and ``--data``), without bleeding across
nearby surfaces.

Each vertex takes its values from the input points near it *on its own side*: among its
:data:`NEIGHBOURS` nearest points, those whose normal agrees with the surface's normal at the
vertex (positive dot product), weighted by a Gaussian of their distance (sigma one finest
cell of the tree, the nearest agreeing point always counting). Points on the other side of a
thin part face the other way and give nothing, so the two faces of a plate coloured
differently keep their colours (PoissonRecon#312: its colours are splatted into the tree
and averaged per node, across the plate). A vertex with no agreeing point among
:data:`FALLBACK_NEIGHBOURS` takes its nearest point's values (counted in the report:
``attribute_fallback_vertices``).

- Numeric properties (floats, colours, and integers whose name says a measurement:
  :data:`MEASURES`, such as ``intensity``) are the weighted mean, rounded and clipped to
  the type for integers.
- Integer codes (LAS ``classification``, ``return_number``, ``point_source_id``, any other
  integer or boolean property) take the value with the largest summed weight (ties: the
  smallest value), so no vertex gets a code no point has.

Every property keeps its dtype.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M. PoissonRecon issue #312 (colour bleeding through thin parts).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import ParameterError

# nearest input points read per vertex; more for the vertices none of them agrees with
NEIGHBOURS = 16
FALLBACK_NEIGHBOURS = 64
# vertices per block of the transfer (the neighbours' tables: ~40 bytes a neighbour)
CHUNK = 1 << 16
# points per occupied cell of the nearest-point search's grid (flat 4-32: bench/calibration.md)
GRID_POINTS = 8
# shells of cells read around a vertex before a k-d tree finds its nearest points
GRID_SHELLS = 4
# integer properties that are measurements (averaged), by lower-case name; the others are codes
MEASURES = frozenset(
    {
        "intensity",
        "amplitude",
        "reflectance",
        "deviation",
        "scan_angle",
        "scan_angle_rank",
        "red",
        "green",
        "blue",
        "alpha",
        "nir",
        "infrared",
        "range",
        "distance",
        "confidence",
        "quality",
        "density",
        "height",
        "elevation",
        "temperature",
    }
)
# the names ``--attributes`` accepts for the colours
COLOR_NAMES = ("colors", "color", "colours", "colour", "rgb")


def is_code(name: str, values: np.ndarray) -> bool:
    """Whether a property is a code (majority) rather than a measurement (mean)."""
    kind = values.dtype.kind
    if kind == "b":
        return True
    return kind in "iu" and name.lower() not in MEASURES


def select(spec, names: list[str], has_colors: bool) -> tuple[list[str], bool]:
    """The properties ``--attributes`` asks for.

    ``all`` (every one, the default), ``none``, or names separated by commas (``colors`` for the
    colours); returns (names, colours).

    Raises
    ------
    ParameterError
        A name the input does not have (the message lists what it has).
    """
    if isinstance(spec, (list, tuple)):  # a pipeline's list of names
        spec = ",".join(str(x) for x in spec) or "none"
    text = "all" if spec is None else str(spec).strip()
    if text.lower() == "all":
        return list(names), has_colors
    if text.lower() == "none":
        return [], False
    asked = [w.strip() for w in text.split(",") if w.strip()]
    if not asked:
        raise ParameterError("--attributes must be all, none or names separated by commas")
    out, colors = [], False
    for w in asked:
        if w.lower() in COLOR_NAMES and has_colors:
            colors = True
        elif w in names:
            if w not in out:
                out.append(w)
        else:
            have = [*names, *(["colors"] if has_colors else [])]
            listed = ", ".join(have) if have else "none"
            raise ParameterError(
                f"--attributes: the input has no property {w!r} (it has: {listed})"
            )
    return out, colors


@dataclass
class Transfer:
    """What :func:`transfer` returns."""

    values: dict[str, np.ndarray] = field(default_factory=dict)
    colors: np.ndarray | None = None
    fallback: int = 0  # vertices with no agreeing point near: their nearest point's values
    # (m,) per vertex, the distance of the farthest point its values read (None: no vertex)
    reach: np.ndarray | None = None


def vertex_normal_sums(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The faces' normals (twice their areas long) summed at each vertex."""
    from recon_cli.stages.poisson._attributes import face_normal_sums

    vn = np.zeros(verts.shape)
    face_normal_sums(
        np.ascontiguousarray(verts, np.float64), np.ascontiguousarray(faces, np.int64), vn
    )
    return vn


def unit_rows(vn: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (0 where zero)."""
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, ln, out=np.zeros_like(vn), where=ln > 0)


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit area-weighted normals of the faces around each vertex (0 where none)."""
    vn = vertex_normal_sums(verts, faces)
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, ln, out=np.zeros_like(vn), where=ln > 0)


def transfer(
    points: np.ndarray,
    normals: np.ndarray,
    values: dict[str, np.ndarray],
    colors: np.ndarray | None,
    verts: np.ndarray,
    faces: np.ndarray | None,
    cell: float,
    vertex_unit_normals: np.ndarray | None = None,
) -> Transfer:
    """Each vertex's properties from the input points near it on its side (module docstring).

    Parameters
    ----------
    points : (n, 3) float
        The input points (world units) the surface was made from.
    normals : (n, 3) float
        Their (outward) normals.
    values : dict of str to (n,) array
        The properties to carry.
    colors : (n, c) array or None
        The points' colours.
    verts, faces
        The surface.
    cell : float
        The Gaussian's sigma (one finest cell of the tree, world units).
    vertex_unit_normals : (m, 3) float, optional
        The surface's unit normals at ``verts`` (default: :func:`vertex_normals` of
        ``faces``; a slab of a distributed run gives them, summed over both slabs at a seam).

    Returns
    -------
    Transfer
        Per-vertex arrays in the properties' dtypes.
    """
    out = Transfer()
    m = len(verts)
    if m == 0 or (not values and colors is None):
        out.values = {k: v[:0].copy() for k, v in values.items()}
        out.colors = None if colors is None else colors[:0].copy()
        return out
    if vertex_unit_normals is not None:
        vn = vertex_unit_normals
    elif faces is not None:
        vn = vertex_normals(verts, faces)
    else:
        raise ValueError("transfer needs the faces or the vertices' unit normals")
    grid = _Grid(np.asarray(points, np.float64))
    normals = np.ascontiguousarray(normals, np.float64)
    vn = np.ascontiguousarray(vn, np.float64)
    verts = np.ascontiguousarray(verts, np.float64)
    out.reach = np.empty(m)
    res = {k: np.empty(m, v.dtype) for k, v in values.items()}
    col = None if colors is None else np.empty((m, colors.shape[1]), colors.dtype)
    for a in range(0, m, CHUNK):
        b = min(m, a + CHUNK)
        nb = _weights(grid, normals, verts[a:b], vn[a:b], cell)
        out.fallback += nb.fallback
        out.reach[a:b] = nb.reach
        for k, v in values.items():
            res[k][a:b] = nb.apply(_majority if is_code(k, v) else _mean, v)
        if colors is not None:
            assert col is not None  # made with the colours
            for c in range(colors.shape[1]):
                col[a:b, c] = nb.apply(_mean, colors[:, c])
    out.values, out.colors = res, col
    return out


class _Grid:
    """The points sorted into cubic cells, for :func:`._attributes.grid_knn`.

    A k-d tree of the points (made when first needed) answers for the vertices far from them.
    """

    def __init__(self, points: np.ndarray) -> None:
        from recon_cli._kernels.hashtable import build_table

        self.points = points
        n = len(points)
        self.lo = points.min(axis=0)
        extent = points.max(axis=0) - self.lo
        span = float(extent.max())
        self.h = _grid_side(points, self.lo, span)
        self.dims = (extent // self.h).astype(np.int64) + 1
        key = _cell_keys(points, self.lo, self.h, self.dims)
        order = np.argsort(key)  # the order within a cell is of no matter: ties go by index
        key = key[order]
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        self.starts = np.append(first, n).astype(np.int64)
        self.tk, self.tv, self.bits = build_table(key[first])
        self.spts = np.take(points, order, axis=0)
        self.sidx = order.astype(np.int64)
        # a point's cell is rounded: the search's bound is this much short
        self.slack = 1e-9 * self.h + 16 * np.finfo(np.float64).eps * (
            float(np.abs(self.lo).max()) + span
        )
        self._tree: Any = None

    def query(self, verts: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(m, k) distances and indices of each vertex's ``k`` nearest points, nearest first."""
        from recon_cli.stages.poisson._attributes import grid_knn

        m = len(verts)
        dist = np.empty((m, k))
        idx = np.empty((m, k), np.int64)
        far = np.empty(m, np.bool_)
        # the vertices sorted by cell (one past the grid at most): a cell's share their look-ups
        qcell = np.floor((verts - self.lo) / self.h)
        np.clip(qcell, -1, self.dims, out=qcell)
        qcell = qcell.astype(np.int64)
        dq = self.dims + 2
        key = ((qcell[:, 0] + 1) * dq[1] + qcell[:, 1] + 1) * dq[2] + qcell[:, 2] + 1
        order = np.argsort(key)
        key = key[order]
        groups = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True]).astype(np.int64)
        grid = (
            self.spts, self.sidx, self.starts, self.tk, self.tv, self.bits, self.lo, self.h,
            self.dims, self.slack,
        )  # fmt: skip
        grid_knn(grid, (verts, qcell, order, groups), k, GRID_SHELLS, (dist, idx, far))
        if far.any():
            if self._tree is None:
                from scipy.spatial import cKDTree

                # only rows far from the points reach it: a tree of uncompacted, unbalanced nodes
                # answers those several times faster (bench/calibration.md)
                self._tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)
            rows = np.flatnonzero(far)
            d, i = self._tree.query(verts[rows], k=k, workers=-1)
            dist[rows], idx[rows] = d.reshape(len(rows), k), i.reshape(len(rows), k)
        return dist, idx


def _cell_keys(points: np.ndarray, lo: np.ndarray, h: float, dims: np.ndarray) -> np.ndarray:
    """Each point's grid cell as one int64, ``(x * dims[1] + y) * dims[2] + z``."""
    c = np.floor((points - lo) / h).astype(np.int64)
    np.clip(c, 0, dims - 1, out=c)
    return (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]


def _grid_side(points: np.ndarray, lo: np.ndarray, span: float) -> float:
    """A cell side giving about :data:`GRID_POINTS` points per occupied cell.

    Estimated on a subsample of a surface's points: every s-th point in cells sqrt(s) times
    wider holds as many per cell.
    """
    if not span > 0.0:
        return 1.0
    n = len(points)
    least = span / (1 << 20)  # keys fit an int64
    step = max(1, n // 65536)
    sub = points[::step]
    h = max(least, span * np.sqrt(GRID_POINTS / n))
    for _ in range(3):
        hs = h * np.sqrt(step)
        dims = ((sub.max(axis=0) - lo) // hs).astype(np.int64) + 1
        per_cell = len(sub) / len(np.unique(_cell_keys(sub, lo, hs, dims)))
        h = max(least, h * float(np.clip(np.sqrt(GRID_POINTS / per_cell), 0.25, 4.0)))
    return h


@dataclass
class _Neighbours:
    """A block of vertices' neighbours and weights (rows sum to 1).

    ``rows``: the vertices none of whose :data:`NEIGHBOURS` agrees; theirs are ``idx2``,
    ``w2`` among :data:`FALLBACK_NEIGHBOURS`.
    """

    idx: np.ndarray
    w: np.ndarray
    rows: np.ndarray
    idx2: np.ndarray
    w2: np.ndarray
    fallback: int
    reach: np.ndarray  # the distance of each row's farthest neighbour read

    def apply(self, f, v: np.ndarray) -> np.ndarray:
        """``f(v, idx, w)`` per row, the fallback rows' from their wider neighbourhood."""
        out = f(v, self.idx, self.w)
        if len(self.rows):
            out[self.rows] = f(v, self.idx2, self.w2)
        return out


def _weights(grid: _Grid, normals: np.ndarray, verts: np.ndarray, vn: np.ndarray, cell: float):
    """The vertices' neighbours among the points and their weights (:class:`_Neighbours`)."""
    n = len(grid.points)
    k = min(NEIGHBOURS, n)
    dist, idx = grid.query(verts, k)
    w, none = _side_weights(normals, vn, dist, idx, cell)
    reach = dist[:, -1].copy()
    rows = np.flatnonzero(none)
    k2 = min(FALLBACK_NEIGHBOURS, n)
    i2, w2 = np.zeros((0, k2), np.int64), np.zeros((0, k2))
    fallback = 0
    if len(rows):
        d2, i2 = grid.query(verts[rows], k2)
        w2, none2 = _side_weights(normals, vn[rows], d2, i2, cell)
        # the nearest point alone where no point agrees (the surface's far sheets)
        w2[none2] = 0.0
        w2[none2, 0] = 1.0
        fallback = int(none2.sum())
        reach[rows] = d2[:, -1]
    return _Neighbours(idx, w, rows, i2, w2, fallback, reach)


def _side_weights(normals, vn, dist, idx, cell):
    """Gaussian weights of the neighbours on the vertex's side, rows normalised.

    And the rows with no such neighbour.
    """
    from recon_cli.stages.poisson._attributes import agreeing

    agree = np.empty(idx.shape, np.bool_)
    agreeing(normals, idx, vn, agree)
    w = np.exp(-0.5 * (dist / cell) ** 2) * agree
    # the nearest agreeing point always counts (far from the samples every weight underflows)
    first = np.argmax(agree, axis=1)
    rows = np.arange(len(vn))
    has = agree[rows, first]
    w[rows[has], first[has]] = np.maximum(w[rows[has], first[has]], 1e-300)
    s = w.sum(axis=1)
    w[has] /= s[has, None]
    return w, ~has


def _mean(v: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted mean per row, in ``v``'s dtype (integers rounded and clipped)."""
    x = (v[idx].astype(np.float64) * w).sum(axis=1)
    if v.dtype.kind in "iu":
        info = np.iinfo(v.dtype)
        return np.clip(np.round(x), info.min, info.max).astype(v.dtype)
    return x.astype(v.dtype)


def _majority(v: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The value with the largest summed weight per row (ties.

    The smallest): each row's values sorted, equal ones summed, the first largest sum taken.
    """
    vals = v[idx]
    out = vals[:, 0].copy()
    # rows whose neighbours all agree (most, away from class borders) need no vote
    mixed = np.flatnonzero((vals != vals[:, :1]).any(axis=1))
    if len(mixed):
        out[mixed] = _vote(vals[mixed], w[mixed])
    return out


def _vote(vals: np.ndarray, w: np.ndarray) -> np.ndarray:
    """:func:`_majority` on rows of values (m, k) and weights (codes as int64 in the kernel.

    One compiled signature for every dtype).
    """
    from recon_cli.stages.poisson._attributes import weighted_mode

    out = np.empty(len(vals), np.int64)
    weighted_mode(np.ascontiguousarray(vals, np.int64), np.ascontiguousarray(w, np.float64), out)
    return out.astype(vals.dtype)
