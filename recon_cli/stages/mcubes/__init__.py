"""Marching cubes (and marching tetrahedra): the iso-surface of a sampled scalar field.

Two entry points share one set of tables (derived in :mod:`recon_cli.stages.mcubes._luts`, stored
and read by :mod:`recon_cli.stages.mcubes._lut_data`) and kernels
(:mod:`recon_cli.stages.mcubes._kernel`):

* :func:`marching_cubes` on a dense volume (a :class:`~recon_cli.grid.Grid`'s ``sdf``);
* :func:`marching_cubes_sparse` on any set of cells of an unbounded lattice, each given
  with its 8 corner values (what an adaptive solver such as Poisson has near its surface).

Guarantees: one vertex per crossed lattice edge (shared by all cells around it);
ambiguous faces resolved by the asymptotic decider, the same from both sides, so the
surface is closed and edge-manifold wherever it does not reach the border of the given
cells or a NaN cell; triangles counter-clockwise seen from the positive side (outward
when negative = inside); no zero-area triangles unless ``allow_degenerate``.

References
----------
Lorensen, W. & Cline, H. (1987). Marching cubes: a high resolution 3D surface construction
algorithm. SIGGRAPH.
Nielson, G. & Hamann, B. (1991). The asymptotic decider: resolving the ambiguity in marching
cubes. IEEE Visualization.
Doi, A. & Koide, A. (1991). An efficient method of triangulating equi-valued surfaces by using
tetrahedral cells. IEICE Transactions E74-D(1) (marching tetrahedra).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.aot import kernels
from recon_cli.errors import InputError, ParameterError
from recon_cli.params import Param, StageSpec

# crossings are kept this fraction of an edge away from its corners, so a value exactly
# at the iso level never collapses a triangle to zero area (moves vertices <= 1e-3 voxel)
DEGENERATE_CLAMP = 1e-3

_METHODS = ("mc", "mt")
_NO_CENTRE = np.full((257, 12), -1, dtype=np.int8)  # marching tetrahedra never needs one


def _tables(method: str):
    from recon_cli.stages.mcubes import _lut_data as L

    if method == "mc":
        return L.MC_START, L.MC_TRIS, L.MC_EDGES, L.MC_EDGE_KEY, True, L.MC_CENTRE, L.CENTER
    return L.MT_START, L.MT_TRIS, L.MT_EDGES, L.MT_EDGE_KEY, False, _NO_CENTRE, -1


def _spacing3(spacing: Any) -> np.ndarray:
    s = np.asarray(spacing, dtype=np.float64).reshape(-1)
    if s.size == 1:
        s = np.repeat(s, 3)
    if s.size != 3 or not np.all(np.isfinite(s)) or not np.all(s > 0):
        raise ParameterError(f"spacing must be one or three positive numbers, got {spacing!r}")
    return s


def _origin3(origin: Any) -> np.ndarray:
    o = np.asarray(origin, dtype=np.float64).reshape(-1)
    if o.size != 3 or not np.all(np.isfinite(o)):
        raise ParameterError(f"origin must be three finite numbers, got {origin!r}")
    return o


# the command's work is smaller than numba's start-up: its kernels are built ahead of time
AOT = True

SPEC = StageSpec(
    name="mcubes",
    summary="Marching cubes: mesh the zero level set of a grid.",
    description="""Mesh the ISO level set of a grid (.npz from `recon sdf`).

    Vertex normals come from the field's gradient. The mesh is closed and manifold wherever the
    level set stays inside the grid and away from unknown (NaN) cells; unknown cells are left
    out.""",
    takes=("grid",),
    gives=("mesh", "oriented"),
    params=(
        Param("iso", "float", 0.0, "Level to extract.", unit="grid values"),
        Param(
            "method",
            "choice",
            "mc",
            "mc: marching cubes (asymptotic decider); mt: marching tetrahedra.",
            choices=_METHODS,
        ),
        Param(
            "allow_degenerate",
            "bool",
            False,
            "Keep crossings exactly at corners (may make zero-area triangles).",
        ),
    ),
)


def _check(iso: Any, method: Any, allow_degenerate: Any) -> tuple[float, str, bool]:
    """The parameters checked by the declaration (before any data is looked at)."""
    v = SPEC.check(
        {"iso": iso, "method": method, "allow_degenerate": allow_degenerate}, complete=False
    )
    return v["iso"], v["method"], v["allow_degenerate"]


def marching_cubes(
    volume: np.ndarray,
    iso: float = SPEC.param("iso").default,
    spacing: float | tuple[float, float, float] = 1.0,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    method: str = SPEC.param("method").default,
    allow_degenerate: bool = SPEC.param("allow_degenerate").default,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iso-surface of a dense 3-d scalar field.

    Parameters
    ----------
    volume : (nx, ny, nz) float array
        Samples; sample ``[i, j, k]`` sits at ``origin + (i, j, k) * spacing``. NaN marks
        unknown samples: every cell touching one is left out.
    iso : float
        Level to extract. Values below it are inside.
    spacing : float or (3,) floats
        Distance between samples (per axis if three values), in world units.
    origin : (3,) floats
        World position of sample ``[0, 0, 0]``.
    method : {"mc", "mt"}
        Marching cubes with the asymptotic decider, or marching tetrahedra (6 tetrahedra
        per cube; more, smaller triangles, no ambiguity at all).
    allow_degenerate : bool
        Place crossings exactly at the interpolated point even when it is a corner (values
        equal to ``iso``), which can make zero-area triangles. By default crossings stay
        ``1e-3`` of an edge away from corners.

    Returns
    -------
    vertices : (k, 3) float64
        World coordinates, one per crossed edge.
    faces : (m, 3) int64
        Counter-clockwise seen from the side of values above ``iso``.
    normals : (k, 3) float64
        Unit field gradient at each vertex (central differences interpolated along the
        edge); points towards increasing values (outward for a signed distance).
    """
    return _marching_cubes(volume, iso, spacing, origin, method, allow_degenerate)[:3]


def _marching_cubes(volume, iso, spacing, origin, method, allow_degenerate):
    """:func:`marching_cubes` and the number of cells left out, counted in the same pass.

    A cell is left out for a NaN corner, or +inf and -inf corners together.
    """
    iso, method, allow_degenerate = _check(iso, method, allow_degenerate)
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise InputError(f"volume must be 3-d, got shape {vol.shape}")
    if vol.dtype.kind not in "fiu":
        raise InputError(f"volume must be numeric, got {vol.dtype}")
    sp = _spacing3(spacing)
    org = _origin3(origin)
    if min(vol.shape) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3)), 0
    K = kernels("recon_cli.stages.mcubes._kernel")
    from recon_cli.stages.mcubes._lut_data import FACE_CORNERS, MC_AMBIGUOUS

    start, tris, edges, keys, use_faces, centre, centre_id = _tables(method)
    vol = np.ascontiguousarray(vol, dtype=np.float64 if vol.dtype == np.float64 else np.float32)
    verts, grads, faces, skipped = K.dense_extract(
        vol,
        iso,
        start,
        tris,
        edges,
        keys,
        MC_AMBIGUOUS,
        use_faces,
        FACE_CORNERS,
        centre,
        centre_id,
        0.0 if allow_degenerate else DEGENERATE_CLAMP,
    )
    verts *= sp
    verts += org
    grads /= sp
    return verts, faces, _unit(grads), int(skipped)


def marching_cubes_sparse(
    cells: np.ndarray,
    corner_values: np.ndarray,
    iso: float = SPEC.param("iso").default,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    spacing: float | tuple[float, float, float] = 1.0,
    method: str = SPEC.param("method").default,
    allow_degenerate: bool = SPEC.param("allow_degenerate").default,
    return_normals: bool = False,
):
    """Iso-surface over a set of cells of an unbounded regular lattice.

    Parameters
    ----------
    cells : (c, 3) int array
        Integer lattice coordinates of the lower corner of each cell; no duplicates.
        Cell ``(x, y, z)`` spans ``origin + [x, x+1] * spacing`` (etc. per axis).
    corner_values : (c, 8) float array
        Field value at each cell's corners. Corner ``q`` (0..7) sits at offset
        ``(q & 1, (q >> 1) & 1, (q >> 2) & 1)``: bit ``i`` of ``q`` is the offset along axis
        ``i``. Neighbouring cells must give the same value for a shared corner, or the
        surface may crack. A row with a NaN is left out.
    iso : float
        Level to extract; values below it are inside.
    origin : (3,) floats
        World position of lattice point (0, 0, 0).
    spacing : float or (3,) floats
        Cell size (per axis if three values), world units.
    method : {"mc", "mt"}
        As in :func:`marching_cubes`.
    allow_degenerate : bool
        As in :func:`marching_cubes`.
    return_normals : bool
        Also return unit normals (the trilinear gradient, averaged over the cells that
        share the vertex).

    Returns
    -------
    vertices : (k, 3) float64
        World coordinates; one vertex per crossed lattice edge, shared by neighbouring
        cells (keyed by global edge id), so the mesh needs no welding.
    faces : (m, 3) int64
        Counter-clockwise seen from the side above ``iso``.
    normals : (k, 3) float64
        Only when ``return_normals``.
    """
    iso, method, allow_degenerate = _check(iso, method, allow_degenerate)
    cells = np.asarray(cells)
    vals = np.asarray(corner_values, dtype=np.float64)
    if cells.ndim != 2 or cells.shape[1] != 3 or (cells.size and cells.dtype.kind not in "iu"):
        raise InputError(f"cells must be an integer (c, 3) array, got {cells.dtype} {cells.shape}")
    if vals.shape != (len(cells), 8):
        raise InputError(f"corner_values must have shape ({len(cells)}, 8), got {vals.shape}")
    sp = _spacing3(spacing)
    org = _origin3(origin)
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if len(cells) == 0:
        return (*empty, np.zeros((0, 3))) if return_normals else empty
    lo = cells.min(axis=0)
    dims = cells.max(axis=0) - lo + 2
    if float(np.prod(dims.astype(np.float64))) * 8 >= 2.0**62:
        raise InputError("cells span too large a lattice for 64-bit edge ids")
    flat = ((cells[:, 0] - lo[0]) * dims[1] + (cells[:, 1] - lo[1])) * dims[2] + (
        cells[:, 2] - lo[2]
    )
    flat.sort()
    if np.any(flat[1:] == flat[:-1]):  # one int64 key per cell: far cheaper than np.unique(axis=0)
        raise InputError("cells has duplicate rows")
    del flat
    K = kernels("recon_cli.stages.mcubes._kernel")
    from recon_cli.stages.mcubes._lut_data import FACE_CORNERS, MC_AMBIGUOUS

    start, tris, edges, keys, use_faces, centre, centre_id = _tables(method)
    vals = np.ascontiguousarray(vals)
    rows, counts = K.sparse_rows(vals, iso, start, MC_AMBIGUOUS, use_faces, FACE_CORNERS)
    offsets = np.zeros(len(cells) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    if len(cells) >= 2**31:
        raise InputError("more than 2**31 cells")
    ekeys, cell_of, edge_of = K.sparse_corners(cells, rows, offsets, start, tris, keys, lo, dims)
    n_unique, first, inverse = _unique_first_inverse(ekeys)
    del ekeys
    faces = inverse.reshape(-1, 3)
    clamp = 0.0 if allow_degenerate else DEGENERATE_CLAMP
    if return_normals:
        pos, grad = K.sparse_points(
            cells, vals, rows, cell_of, edge_of, edges, centre, centre_id, iso, clamp
        )
        verts = pos[first] * sp + org
        acc = np.zeros((n_unique, 3))
        for ax in range(3):
            acc[:, ax] = np.bincount(inverse, weights=grad[:, ax], minlength=n_unique)
        return verts, faces, _unit(acc / sp)
    pos, _ = K.sparse_points(
        cells, vals, rows, cell_of[first], edge_of[first], edges, centre, centre_id, iso, clamp
    )
    return pos * sp + org, faces


def _unique_first_inverse(keys: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """``np.unique(keys, return_index=True, return_inverse=True)`` without the unique values.

    Same results (``first`` is the lowest index of each key), from an unstable sort: the
    stable merge sort that ``np.unique`` needs for ``return_index`` is the slow part.
    """
    order = np.argsort(keys)
    sk = keys[order]
    new = np.empty(len(keys), dtype=bool)
    new[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    del sk  # the big temporaries go as soon as they are used (Poisson's extraction peak)
    starts = np.flatnonzero(new)
    group = np.cumsum(new, dtype=np.int64)
    del new
    group -= 1
    inverse = np.empty(len(keys), dtype=np.int64)
    inverse[order] = group
    del group
    first = np.minimum.reduceat(order, starts) if len(keys) else order
    return len(starts), first, inverse


def _unit(g: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(g, axis=1, keepdims=True)
    out = np.zeros_like(g)
    np.divide(g, n, out=out, where=n > 0)
    return out


@SPEC.runner
def run_stage(
    data,
    *,
    iso: float,
    method: str,
    allow_degenerate: bool,
    progress=None,
):
    """Stage ``mcubes``: mesh the ``iso`` level set of a grid.

    Parameters
    ----------
    data : Grid
    iso : float
        Level (same units as the grid values; default 0 = the surface of an SDF).
    method : {"mc", "mt"}
    allow_degenerate : bool

    Returns
    -------
    StageResult
        A :class:`~recon_cli.geometry.TriangleMesh` with vertex normals; report keys
        ``vertices``, ``faces``, ``method``, ``iso``, ``grid_shape``, ``skipped_nan_cells``
        (cells left out for a NaN corner), ``boundary_edges`` (0 = closed).

    Raises
    ------
    InputError
        When the level set is empty (no sample on one side of ``iso``, a grid without a
        cell, or only cells with unknown corners): an empty mesh is refused, not written.
    """
    from recon_cli.geometry import TriangleMesh
    from recon_cli.progress import task
    from recon_cli.stages import StageResult

    # parameters and the input's kind: checked by SPEC
    with task(progress, "marching cubes", 1) as t:
        v, f, n, skipped = _marching_cubes(
            data.sdf, iso, data.voxel_size, data.origin, method, allow_degenerate
        )
        t.advance(1)
    if len(f) == 0:
        # an empty mesh is never a result: say why there is nothing to mesh
        finite = data.sdf[np.isfinite(data.sdf)]
        if min(data.shape) < 2:
            why = f"the grid ({' x '.join(map(str, data.shape))}) has no cell"
        elif finite.size == 0:
            why = "every sample is unknown (NaN)"
        elif finite.min() >= iso or finite.max() <= iso:
            why = (
                f"no sample is on the other side of iso {iso:g} "
                f"(values {finite.min():.6g} .. {finite.max():.6g})"
            )
        else:
            why = "every cell the level set crosses has an unknown (NaN) corner"
        raise InputError(f"nothing to mesh: {why}")
    mesh = TriangleMesh(
        vertices=v, faces=f, normals=n, history=list(data.history), point_dtype=data.point_dtype
    )
    report = {
        "vertices": int(len(v)),
        "faces": int(len(f)),
        "method": method,
        "iso": iso,
        "grid_shape": list(data.shape),
        "skipped_nan_cells": skipped,
        "boundary_edges": boundary_edge_count(f, len(v)),
    }
    return StageResult(output=mesh, report=report)


def boundary_edge_count(faces: np.ndarray, n_vertices: int | None = None) -> int:
    """Number of edges used by exactly one face of ``faces`` ((m, 3) int).

    The vertex count is ``n_vertices``, default ``faces.max() + 1``; counted by a linear numba
    pass.
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return 0
    K = kernels("recon_cli.stages.mcubes._kernel")

    return int(
        K.boundary_edge_count(
            faces, int(faces.max()) + 1 if n_vertices is None else int(n_vertices)
        )
    )
