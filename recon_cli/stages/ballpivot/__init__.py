"""Ball-pivoting reconstruction (Bernardini, Mittleman, Rushmeier, Silva, Taubin 1999).

A ball of radius rho that rests on three points and contains no other point makes a
triangle. Starting from such a seed triangle, the ball pivots around each edge of the
active front (keeping contact with the edge's two end points) until it touches another
point; that point makes the next triangle. Front edges that share their end points with
the new triangle in the opposite direction are glued (they become interior). When the
front is empty a new seed is searched among the unused points. Several radii are used in
increasing order: each larger ball first pivots on the boundary edges left by the smaller
ones (those whose face still carries an empty ball), then seeds among the unused points.

The points' normals decide the side of the ball (outside = the side the normals point to)
and the winding: every triangle's normal agrees with the normals of its three points, so
the faces agree with the input normals.

Topology is controlled by construction: an edge never gets a third face, a new triangle
may only reuse an edge in the opposite direction (so faces are consistently wound and never
duplicated), and a pivot whose first hit is an interior vertex stops at a boundary. The
"join" step of the algorithm (a triangle touching a front vertex without sharing an edge
with it) can pinch a vertex between two fans; glues usually close these, and the ones left
at the end are resolved by removing, at each pinched vertex, the faces of every fan but the
largest (repeated until every vertex has one fan). The output is therefore edge-manifold,
vertex-manifold and consistently oriented.

Automatic radii (``radii="auto"``)
----------------------------------
Let ``s`` be the median distance from a point to its nearest other point, over the points
with a positive such distance (exact duplicates ignored), measured on up to 200 000 points
evenly strided through the input (queried against a k-d tree of all points). The median is
robust to outliers and to clustered duplicates. The radii are ``2 s`` and ``4 s`` (why these
multiples: the ballpivot page of the user guide).

References
----------
Bernardini, F., Mittleman, J., Rushmeier, H., Silva, C. & Taubin, G. (1999). The ball-pivoting
algorithm for surface reconstruction. IEEE TVCG 5(4).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from recon_cli.aot import kernels
from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.geometry import (
    PointCloud,
    TriangleMesh,
    as_point_cloud,
    bbox_diagonal,
    local_origin,
    oriented_rows,
)
from recon_cli.params import Param, StageSpec
from recon_cli.stages import StageResult
from recon_cli.tolerances import tol

AUTO_MULTIPLES = (2.0, 4.0)
AUTO_SAMPLE = 200_000
# nn_spacing: a point with no other point within this many grid cells is an outlier, left
# out of the median (the cell is ~2x the spacing of a sample as dense as the cloud's extent)
SPACING_RINGS = 16
BACKENDS = ("native", "open3d", "pymeshlab")
# radii above this multiple of the bounding-box diagonal are rejected (a ball that large
# only ever sees the convex hull)
MAX_RADIUS_DIAGONALS = 1.0
_MAX_GRID_CELLS = 2**62
# extra passes of the largest ball over the holes left by cutting pinched fans
REFILL_PASSES = 1

# the command's work is smaller than numba's start-up: its kernels are built ahead of time
AOT = True

SPEC = StageSpec(
    name="ballpivot",
    summary="Ball-pivoting reconstruction of an oriented cloud.",
    description="""Ball-pivoting reconstruction (Bernardini et al. 1999) of an oriented cloud.

    Needs point normals (run `recon normals` first); faces are wound to agree with them.
    The mesh interpolates the points, is edge- and vertex-manifold, and keeps every input
    point as a vertex (points no ball reached stay unreferenced). The radii used are
    printed and recorded in the output's history.""",
    takes=("oriented",),
    gives=("mesh",),
    backends=BACKENDS,
    params=(
        Param(
            "radii",
            "floats",
            "auto",
            "Ball radii, comma-separated (e.g. 0.002,0.004), or 'auto': "
            "2x and 4x the median nearest-neighbour spacing.",
            unit="input units",
            min=0.0,
            min_open=True,
            words={"auto": "auto"},
            metavar="auto|R1,R2,...",
        ),
    ),
)


def nn_spacing(points: np.ndarray) -> float:
    """Robust nearest-neighbour spacing: the median distance to the nearest other point.

    Parameters
    ----------
    points : (n, 3) float64
        Finite coordinates, n >= 2.

    Returns
    -------
    float
        Median over (at most :data:`AUTO_SAMPLE` evenly strided) points of the distance to the
        nearest point at a positive distance, in the units of ``points``; 0.0 if all points
        coincide. Points with no other point within :data:`SPACING_RINGS` grid cells (far
        outliers) are left out of the median.

    Notes
    -----
    Exact nearest distances from a uniform grid (our ball-pivoting grid kernels; no k-d tree
    to import): the cell is twice the spacing a sample covering the bounding box's largest
    face would have, ``2 * extent / sqrt(n)``, and each query scans shells of cells until its
    nearest point is known.
    """
    K = kernels("recon_cli.stages.ballpivot._kernel")

    pts = np.ascontiguousarray(points, dtype=np.float64)
    lo = pts.min(axis=0)
    extent = pts.max(axis=0) - lo
    if not extent.max() > 0:
        return 0.0
    cell = 2.0 * float(extent.max()) / np.sqrt(len(pts))
    dims = (np.floor(extent / cell) + 1).astype(np.int64)
    ukeys, ustart, _, spts = K.build_grid(pts, lo, cell, dims)
    step = max(1, len(pts) // AUTO_SAMPLE)
    d = K.nearest_positive(
        ukeys, ustart, spts, lo, cell, dims, np.ascontiguousarray(pts[::step]), SPACING_RINGS
    )
    d = d[np.isfinite(d)]
    if not len(d):
        return 0.0
    # np.median's value, without the numpy.ma import its NaN check makes (~10 ms of a process)
    k = len(d) // 2
    if len(d) % 2:
        return float(np.partition(d, k)[k])
    part = np.partition(d, [k - 1, k])
    return float(0.5 * (part[k - 1] + part[k]))


def auto_radii(points: np.ndarray) -> list[float]:
    """The radii used by ``radii="auto"`` (see the module docstring).

    Parameters
    ----------
    points : (n, 3) float64
        Finite coordinates.

    Returns
    -------
    list of float
        Increasing radii, in the units of ``points``.
    """
    s = nn_spacing(points)
    if not s > 0:
        raise InputError("all points coincide: no spacing to derive ball radii from")
    return [float(m * s) for m in AUTO_MULTIPLES]


def parse_radii(radii: Any) -> list[float] | None:
    """``radii`` checked by the declaration: ``"auto"`` -> None, ``"r1,r2"`` or numbers -> a list.

    Raises
    ------
    ParameterError
        Not ``"auto"`` nor one or more positive finite numbers.
    """
    checked = SPEC.param("radii").coerce(radii)
    return None if checked == "auto" else [float(r) for r in checked]


def _check_radii(radii: list[float], diagonal: float) -> list[float]:
    """Positive radii checked against the cloud's size, sorted and without repeats.

    The radii were checked by :func:`parse_radii` or derived.
    """
    for r in radii:
        if r > MAX_RADIUS_DIAGONALS * diagonal:
            raise ParameterError(
                f"radius {r:g} is larger than the cloud (bounding-box diagonal {diagonal:g}); "
                "ball radii should be a few point spacings (try --radii auto)"
            )
    return sorted(set(float(r) for r in radii))


def _prepare(points: Any, normals: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate; return (points, unit normals, indices of the usable rows)."""
    pts, nrm, length = oriented_rows(
        points,
        normals,
        "ball pivoting needs point normals; the input has none (run `recon normals` first)",
    )
    usable = np.isfinite(pts).all(axis=1) & np.isfinite(length) & (length > 0)
    keep = np.flatnonzero(usable)
    if len(keep) < 3:
        raise InputError(
            "ball pivoting needs at least 3 points with finite coordinates and non-zero normals, "
            f"got {len(keep)}"
        )
    return (
        np.ascontiguousarray(pts[keep]),
        np.ascontiguousarray(nrm[keep] / length[keep, None]),
        keep,
    )


def _grid_dims(rr: list[float], extent: np.ndarray, diagonal: float) -> np.ndarray:
    """(len(rr), 3) int64 dimensions of each radius' search grid (cell = 2 r) over ``extent``."""
    dims = np.empty((len(rr), 3), dtype=np.int64)
    for i, r in enumerate(rr):
        d = np.floor(extent / (2.0 * r)).astype(np.float64) + 1.0
        if float(np.prod(d)) >= _MAX_GRID_CELLS:
            raise ParameterError(f"radius {r:g} is too small for a cloud of extent {diagonal:g}")
        dims[i] = d.astype(np.int64)
    return dims


def _spatial_order(pts: np.ndarray, lo: np.ndarray, r0: float, dims0: np.ndarray, diagonal: float):
    """Indices of the distinct points in the first grid's cell order, and the repeats left out.

    Neighbours then sit close in memory; a point within ``tol.merge`` of the diagonal of an
    earlier one is a repeat.
    """
    K = kernels("recon_cli.stages.ballpivot._kernel")

    _, ustart, order, sorted_pts = K.build_grid(pts, lo, 2.0 * r0, dims0)
    dup = K.mark_duplicates(ustart, order, sorted_pts, (tol.merge * diagonal) ** 2)
    n_dup = int(dup.sum())
    if n_dup:
        order = order[~dup[order]]
    if len(order) < 3:
        raise InputError("ball pivoting needs at least 3 distinct points")
    return order, n_dup


def _pivot_passes(
    spts: np.ndarray,
    snrm: np.ndarray,
    rr: list[float],
    lo: np.ndarray,
    dims: np.ndarray,
    progress_cb: Any,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Run the kernel once per radius, then cut pinched fans and refill.

    Returns (faces, stats, pinch faces removed).

    Each radius continues from the previous triangles (its front may still glue the pinches
    of the earlier passes); after the last radius, pinched fans are cut and the largest ball
    gets up to :data:`REFILL_PASSES` more passes over the holes this leaves.
    """
    K = kernels("recon_cli.stages.ballpivot._kernel")

    faces = np.empty((0, 3), dtype=np.int64)
    stats = np.zeros(4, dtype=np.int64)
    removed = 0
    passes = list(range(len(rr))) + [len(rr) - 1] * REFILL_PASSES
    for p, i in enumerate(passes):
        faces, st = K.ball_pivot(spts, snrm, rr[i], lo, dims[i], faces)
        stats += st
        cut = -1
        if p >= len(rr) - 1:
            alive, cut = K.resolve_pinches(faces, len(spts))
            faces = faces[alive]
            removed += int(cut)
        if progress_cb is not None:
            progress_cb(1)
        if cut == 0:
            break
    return faces, stats, removed


def ball_pivoting(
    points: np.ndarray,
    normals: np.ndarray,
    radii: Sequence[float] | str = SPEC.param("radii").default,
    *,
    return_info: bool = False,
    progress_cb: Any = None,
) -> np.ndarray | tuple[np.ndarray, dict]:
    """Ball-pivoting triangulation of an oriented point cloud.

    Parameters
    ----------
    points : (n, 3) float64
        Coordinates. Rows with a non-finite coordinate are ignored (no face uses them), and
        so are repeats of an earlier point (closer than ``tol.merge`` times the bounding-box
        diagonal): only the first copy is meshed.
    normals : (n, 3) float64
        Outward normals (any non-zero length; normalised here). Rows with a non-finite or
        zero normal are ignored. Must not be None.
    radii : sequence of float or "auto"
        Ball radii in the units of ``points`` (sorted increasing, duplicates dropped), or
        ``"auto"`` for ``(2, 4) x`` the median nearest-neighbour spacing.
    return_info : bool
        Also return a dict with ``radii`` (used), ``skipped_points``, ``duplicate_points``,
        ``seeds``, ``joins``,
        ``glues``, ``rejected_pivots`` and ``pinch_faces_removed``.
    progress_cb : callable or None
        Called with 1 after each pass (one per radius, plus refill passes).

    Returns
    -------
    faces : (m, 3) int64
        Triangles as indices into ``points``, wound counter-clockwise seen from the side
        the normals point to. Edge-manifold, vertex-manifold, consistently oriented, no
        duplicate faces. May be empty (radii far below the point spacing).
    info : dict
        Only with ``return_info``.

    Raises
    ------
    InputError
        No normals, wrong shapes, fewer than 3 usable points, all points coincident.
    ParameterError
        A radius that is not positive, larger than the bounding-box diagonal, or so small
        that the search grid would overflow.
    """
    parsed = parse_radii(radii)
    pts, nrm, keep = _prepare(points, normals)
    # about a local origin: ball centres and cross products far from the world origin lose digits
    pts -= local_origin(pts)  # pts is _prepare's copy
    diagonal = bbox_diagonal(pts)
    if parsed is None:
        parsed = auto_radii(pts)
    rr = _check_radii(parsed, diagonal)
    lo = pts.min(axis=0)
    dims = _grid_dims(rr, pts.max(axis=0) - lo, diagonal)
    order, n_dup = _spatial_order(pts, lo, rr[0], dims[0], diagonal)
    faces_local, stats, removed = _pivot_passes(
        np.ascontiguousarray(pts[order]),
        np.ascontiguousarray(nrm[order]),
        rr,
        lo,
        dims,
        progress_cb,
    )
    faces = keep[order[faces_local]].astype(np.int64)
    if not return_info:
        return faces
    info = {
        "radii": rr,
        "skipped_points": int(len(np.asarray(points).reshape(-1, 3)) - len(keep)),
        "duplicate_points": n_dup,
        "seeds": int(stats[0]),
        "joins": int(stats[1]),
        "glues": int(stats[2]),
        "rejected_pivots": int(stats[3]),
        "pinch_faces_removed": int(removed),
    }
    return faces, info


@SPEC.runner
def run_stage(
    data: PointCloud | TriangleMesh,
    *,
    radii: Sequence[float] | str,
    backend: str,
    progress: Any = None,
) -> StageResult:
    """``recon ballpivot``: mesh an oriented cloud by ball pivoting.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Points with normals (a mesh's vertices and vertex normals are used).
    radii : "auto", "r1,r2,..." or sequence of float
        Ball radii in the units of the input (see :func:`ball_pivoting`).
    backend : {"native", "open3d", "pymeshlab"}
        Ours, Open3D's ``create_from_point_cloud_ball_pivoting`` or PyMeshLab's
        ``generate_surface_reconstruction_ball_pivoting`` (applied once per radius).
    progress : Progress or None

    Returns
    -------
    StageResult
        ``output``: TriangleMesh over all input points (unused ones unreferenced), with the
        input's normals, colours and attributes. ``report``: ``faces``, ``boundary_edges``,
        ``boundary_loops``, ``radii``, ``non_manifold_edges``, ``non_manifold_vertices``,
        ``unused_points``, ``skipped_points``, ``pinch_faces_removed``, ``backend`` and
        ``provenance`` = ``{"radii": [...]}``.
    """
    from recon_cli.progress import task

    cloud = as_point_cloud(data)  # parameters and the input's kind: checked by SPEC
    parsed = parse_radii(radii)
    if cloud.normals is None:
        raise InputError(
            "ball pivoting needs point normals; the input has none (run `recon normals` first)"
        )
    info: dict[str, Any] = {}
    n_radii = len(AUTO_MULTIPLES) if parsed is None else len(set(parsed))
    with task(
        progress, "ball pivoting", n_radii + REFILL_PASSES if backend == "native" else 1
    ) as t:
        if backend == "native":
            faces, info = ball_pivoting(
                cloud.points,
                cloud.normals,
                "auto" if parsed is None else parsed,
                return_info=True,
                progress_cb=t.advance,
            )
            rr = info["radii"]
        else:
            pts, nrm, keep = _prepare(cloud.points, cloud.normals)
            rr = _check_radii(auto_radii(pts) if parsed is None else parsed, bbox_diagonal(pts))
            sub = PointCloud(points=pts - local_origin(pts), normals=nrm)
            if backend == "open3d":
                from recon_cli.backends import open3d_backend

                ref = open3d_backend.ball_pivoting(sub, rr)
            else:
                from recon_cli.backends import pymeshlab_backend

                ref = pymeshlab_backend.ball_pivoting_radii(sub, rr)
            if len(ref.vertices) != len(pts):
                raise StageFailed(
                    f"{backend} ball pivoting changed the vertex count "
                    f"({len(pts)} -> {len(ref.vertices)})"
                )
            faces = keep[np.asarray(ref.faces, dtype=np.int64)]
            info = {"skipped_points": int(len(cloud.points) - len(keep))}
            t.advance(1)
    if len(faces) == 0:
        raise StageFailed(
            "ball pivoting made no triangle: the radii "
            + ", ".join(f"{r:g}" for r in rr)
            + " are too small for the point spacing (try --radii auto)"
        )
    out = TriangleMesh(
        vertices=cloud.points.copy(),
        faces=faces,
        normals=cloud.normals.copy(),
        colors=None if cloud.colors is None else cloud.colors.copy(),
        attributes={k: v.copy() for k, v in cloud.attributes.items()},
        history=list(cloud.history),
        point_dtype=cloud.point_dtype,
        obj_info=list(cloud.obj_info),
    )
    from recon_cli.mesh.topology import Connectivity

    # only the figures reported (the full topology.report costs ~12 % of the stage on a raw scan)
    conn = Connectivity(faces, len(out.vertices))
    report = {
        "backend": backend,
        "radii": [float(r) for r in rr],
        "faces": int(len(faces)),
        "boundary_edges": int(len(conn.boundary_edges)),
        "boundary_loops": int(len(conn.boundary_loops)),
        "non_manifold_edges": int(len(conn.non_manifold_edges)),
        "non_manifold_vertices": int(len(conn.non_manifold_vertices)),
        "unused_points": int(len(out.vertices) - int(conn.referenced.sum())),
        "skipped_points": int(info.get("skipped_points", 0)),
    }
    if backend == "native":
        report["pinch_faces_removed"] = info["pinch_faces_removed"]
    report["provenance"] = {"radii": [float(r) for r in rr]}
    return StageResult(output=out, report=report)
