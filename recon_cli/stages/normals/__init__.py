"""Normal estimation (batched PCA) and consistent orientation (MST, camera, direction).

Estimation: each point's neighbourhood (``knn`` nearest, all within ``radius``, or at most
``knn`` within ``radius``) gives a covariance; the normal is the eigenvector of its smallest
eigenvalue and the surface variation l0 / (l0 + l1 + l2) is the curvature. Neighbourhoods
with fewer than 3 points, or collinear/coincident ones, are *degenerate*: they take the
normal of their nearest non-degenerate neighbour, or, with none, a unit vector orthogonal
to their line (``(0, 0, 1)`` for coincident points). Never NaN.

Orientation ``mst`` (Hoppe et al. 1992, changed for thin parts): a minimum spanning forest of
the kNN graph, then a traversal from one seed per connected component, flipping a neighbour
when ``n_i . n_j < 0``. Edge weights are ``1 - |n_i . n_j|`` plus a penalty ``|n . e|`` on edges
``e`` that leave the tangent planes: an edge jumping across a thin part (a mug handle) joins
two nearly anti-parallel normals, costs almost nothing under Hoppe's weight alone and flips
the far side; with the penalty the tree stays on one sheet. Each component's seed is the
point farthest from its centroid, turned to face away from it. After the traversal a
neighbour vote fixes isolated points that disagree with nearly all of their neighbours, a
consensus pass gives points with a poorly defined normal (noise) the side their whole
neighbourhood agrees on, a flux check (sum of ``(p - c) . n`` weighted by local area, the
divergence-theorem volume estimate) flips a component that came out inside-out, and small
open components (a scan in patches) follow the normals of the nearest points of the large
or closed ones.

References
----------
Hoppe, H., DeRose, T., Duchamp, T., McDonald, J. & Stuetzle, W. (1992). Surface reconstruction
from unorganized points. SIGGRAPH (PCA normals, orientation over a minimum spanning tree).
Pauly, M., Gross, M. & Kobbelt, L. (2002). Efficient simplification of point-sampled surfaces.
IEEE Visualization (surface variation, the ``curvature``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.execution import current
from recon_cli.geometry import SCAN_ATTRIBUTE, PointCloud, as_point_cloud, local_origin
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult
from recon_cli.stages.normals._neighbours import neighbourhoods as _neighbourhoods
from recon_cli.stages.normals._neighbours import pixel_neighbourhoods as _pixel_neighbourhoods
from recon_cli.stages.normals._neighbours import pixel_radius as _pixel_radius
from recon_cli.tolerances import tol

ORIENT_METHODS = ("mst", "camera", "direction", "keep", "none")
NEIGHBOUR_METHODS = ("auto", "kdtree", "pixels")

SPEC = StageSpec(
    name="normals",
    summary="Estimate and orient point normals.",
    description="""Estimate normals by PCA of each point's neighbourhood and orient them.

    Degenerate neighbourhoods (fewer than 3 points, collinear, duplicates) are counted in
    the report and take their nearest regular neighbour's normal. A mesh's vertices are
    used (the output is a point cloud).""",
    takes=("cloud", "mesh"),
    gives=("cloud", "oriented"),
    backends=("native", "open3d"),
    params=(
        Param(
            "knn",
            "int",
            30,
            "Neighbours per point (with --radius: at most this many).",
            unit="points",
            min=3,
            also=(0,),
            special={0: "radius only (needs --radius)"},
        ),
        Param(
            "radius",
            "float",
            None,
            "Neighbourhood radius.",
            unit="input units",
            min=0,
            min_open=True,
        ),
        Param(
            "orient",
            "choice",
            "mst",
            "mst: consistent propagation, outward; camera/direction: towards --camera/"
            "--direction; keep: signs of the input normals; none: unoriented.",
            choices=ORIENT_METHODS,
        ),
        Param(
            "camera",
            "vector",
            None,
            "Viewpoint for --orient camera (not set: the scanner position(s) the file gives).",
            unit="input units",
            metavar="X,Y,Z",
        ),
        Param("direction", "vector", None, "Direction for --orient direction.", metavar="X,Y,Z"),
        Param(
            "curvature",
            "bool",
            False,
            "Also write the vertex property 'curvature' (surface variation).",
        ),
        Param(
            "neighbours",
            "choice",
            "auto",
            "How neighbourhoods are found: kdtree (the 3-D nearest); pixels (an organized "
            "cloud's nearest among the pixels around each point); auto: pixels for an "
            "organized cloud with --knn, else kdtree.",
            choices=NEIGHBOUR_METHODS,
        ),
    ),
    from_files="recon_cli.stages.normals.distributed:run_from_files",
    execution=("workers", "scheduler", "partitions", "memory", "temp_dir"),
)

# the MST graph uses at most this many nearest neighbours of each point (more adds time, not
# accuracy)
_GRAPH_K = 12
# weight of the out-of-tangent-plane penalty on MST edges
_BETA = 2.0
# tiny weight floor: scipy treats zero-weight edges as absent
_EPS = 1e-9
# a component is flipped by the flux check only when clearly inside-out
_FLUX_MIN = 0.02
# normalised flux above which a component counts as closed (a sphere gives 1, a flat patch 0)
_CLOSED_FLUX = 0.3
# a following component votes with at most this many of its points, evenly through its sorted
# order: a nearest-anchor query from far away is slow (bench/calibration.md, _ALIGN_SAMPLES)
_ALIGN_SAMPLES = 4096
# neighbour-vote passes after propagation
_VOTE_PASSES = 2
# passes taking the side of the (tangent-weighted) mean oriented normal of the full neighbourhood
_CONSENSUS_PASSES = 2


# ----------------------------------------------------------------------------- validation


def _check_points(points: Any) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise InputError(
            f"points have {int(bad.sum())} rows with NaN or infinite coordinates (first: row "
            f"{int(np.argmax(bad))}); "
            "remove them first"
        )
    return np.ascontiguousarray(pts)


def _check_knn(knn: Any, radius: Any) -> tuple[int | None, float | None]:
    """The neighbourhood checked by the declaration: ``(knn or None, radius)``."""
    v = SPEC.check({"knn": knn, "radius": radius}, complete=False)
    if v["knn"] == 0 and v["radius"] is None:
        raise ParameterError("--knn 0 (radius only) needs --radius")
    return v["knn"] or None, v["radius"]


def _vector(v: Any, name: str) -> np.ndarray | None:
    """``camera`` / ``direction`` checked by the declaration, as a float64 array (or None)."""
    checked = SPEC.param(name).coerce(v)
    return None if checked is None else np.array(checked, dtype=np.float64)


# ----------------------------------------------------------------------------- neighbourhoods


def _check_pixels(pixels: Any, n: int, knn: int | None) -> None:
    from recon_cli.geometry import PixelGrid

    if not isinstance(pixels, PixelGrid):
        raise ParameterError(f"pixels must be a PixelGrid, got {type(pixels).__name__}")
    if knn is None:
        raise ParameterError("neighbours from pixels need knn (the k nearest pixels)")
    pix = pixels.pixel
    if len(pix) != n:
        raise InputError(f"{len(pix)} pixels for {n} points")
    if n and (pix.min() < 0 or pix.max() >= pixels.offsets()[-1]):
        raise InputError("a point's pixel is outside its image")


def _estimate_sorted(ps, indptr, indices):
    from recon_cli.stages.normals import _kernel as K

    nrm, curv, deg = K.pca_normals(ps, indptr, indices, tol.collinear)
    if deg.any():
        nrm, _ = K.borrow_from_neighbours(ps, nrm, deg, indptr, indices)
    return nrm, curv, deg


def estimate_normals(
    points: Any,
    knn: int = SPEC.param("knn").default,
    radius: float | None = SPEC.param("radius").default,
    pixels: Any = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unoriented normals by PCA of each point's neighbourhood.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Coordinates (any unit). Rows with NaN or inf are rejected.
    knn : int
        Neighbourhood size (the point itself included), at least 3. With ``radius`` too: at
        most ``knn`` neighbours within ``radius`` (hybrid); 0: all within ``radius``.
    radius : float or None
        Neighbourhood radius, in the units of ``points``.
    pixels : PixelGrid or None
        An organized cloud's pixels (:attr:`PointCloud.pixels`): the ``knn`` nearest are then
        looked for among the pixels around each point (needs ``knn``), not in a kd-tree.

    Returns
    -------
    normals : (n, 3) float64
        Unit normals, sign arbitrary (see :func:`orient_normals`). Never NaN.
    curvature : (n,) float64
        Surface variation l0 / (l0 + l1 + l2) in [0, 1/3]; 0 for coincident neighbourhoods.
    degenerate : (n,) bool
        Neighbourhoods with fewer than 3 points, or collinear/coincident ones; their normal
        is the nearest non-degenerate neighbour's, else orthogonal to their line, else (0, 0, 1).

    Raises
    ------
    InputError
        ``points`` not of shape (n, 3), or holding NaN/inf; ``pixels`` not one per point.
    ParameterError
        ``knn`` not 0 or at least 3, ``radius`` <= 0, or ``knn`` 0 without a radius;
        ``pixels`` without ``knn``.

    References
    ----------
    Holz, Holzer, Rusu & Behnke, "Real-time plane segmentation using RGB-D cameras", RoboCup
    2011 (neighbourhoods of an organized cloud from its image, as PCL's organized search).
    """
    knn, radius = _check_knn(knn, radius)  # type: ignore[assignment]  # knn 0 becomes None
    pts = _check_points(points)
    n = len(pts)
    if pixels is not None:
        _check_pixels(pixels, n, knn)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=bool)
    pts, _ = _local(pts, None, points)  # normals do not depend on the origin, precision does
    if pixels is not None:
        order, ps, indptr, indices = _pixel_neighbourhoods(pts, pixels, knn, radius)
    else:
        order, ps, indptr, indices = _neighbourhoods(pts, knn, radius)
    nrm, curv, deg = _estimate_sorted(ps, indptr, indices)
    return _unsort(order, nrm), _unsort(order, curv), _unsort(order, deg)


def _local(
    pts: np.ndarray, cam: np.ndarray | None, source: Any
) -> tuple[np.ndarray, np.ndarray | None]:
    """``pts`` and the viewpoint ``cam`` about the points' local origin.

    Far from the world origin the kd-tree, centroids and flux sums keep their digits. In place
    when ``pts``
    is a converted copy of ``source``.
    """
    centre = local_origin(pts)
    if np.may_share_memory(pts, source):
        pts = pts - centre
    else:
        pts -= centre
    return pts, None if cam is None else cam - centre


def _unsort(order: np.ndarray, a: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    out[order] = a
    return out


# ----------------------------------------------------------------------------- orientation


def _orient_mst_sorted(ps, nrm, indptr, indices, seed_mask=None, seed_sign=None):
    """Signs (+1/-1 int8) orienting ``nrm`` consistently, and the number of components.

    ``seed_mask``/``seed_sign``: points whose sign is known (``keep``); components with no
    known point are seeded outward and checked by flux. The steps: the spanning forest and its
    traversal (:func:`_propagate`), the neighbour vote and consensus (:func:`_smooth_signs`),
    the flux check (:func:`_flux_check`).
    """
    from recon_cli.stages.normals import _kernel as K

    eptr, dst = K.graph_edges(indptr, indices, _GRAPH_K)
    sign, comps = _propagate(ps, nrm, eptr, dst, seed_mask, seed_sign)
    sign = _smooth_signs(ps, nrm, sign, (eptr, dst, indptr, indices), seed_mask)
    if comps.free.any():
        _flux_check(ps, nrm, sign, indptr, indices, comps)
    return sign, comps.count


class _Components:
    """The connected components of the orientation graph and their outward seeds."""

    def __init__(self, ps: np.ndarray, nrm: np.ndarray, count: int, labels: np.ndarray) -> None:
        self.count = count
        self.labels = labels
        n = len(ps)
        # outward seed per component: farthest point from the component's centroid
        self.size = np.bincount(labels, minlength=count).astype(np.float64)
        cen = (
            np.stack([np.bincount(labels, ps[:, d], minlength=count) for d in range(3)], axis=1)
            / self.size[:, None]
        )
        self.rel = ps - cen[labels]
        self.d2 = np.einsum("ij,ij->i", self.rel, self.rel)
        by = np.lexsort((-self.d2, labels))  # per label, farthest first
        first = np.ones(n, dtype=bool)
        first[1:] = labels[by[1:]] != labels[by[:-1]]
        self.seeds = by[first]
        self.seed_signs = _seed_signs(nrm[self.seeds], self.rel[self.seeds])
        self.free = np.ones(count, dtype=bool)  # no point of known sign


def _propagate(ps, nrm, eptr, dst, seed_mask, seed_sign) -> tuple[np.ndarray, _Components]:
    """Signs from a traversal of the minimum spanning forest, from the seeds; the components."""
    from scipy import sparse
    from scipy.sparse.csgraph import (
        breadth_first_order,
        connected_components,
        minimum_spanning_tree,
    )

    from recon_cli.stages.normals import _kernel as K

    n = len(ps)
    w = K.edge_weights(ps, nrm, eptr, dst, _BETA, _EPS)
    g = sparse.csr_matrix((w, dst, eptr), shape=(n, n))
    ncomp, labels = connected_components(g, directed=True, connection="weak")
    tree = minimum_spanning_tree(g).tocoo()
    comps = _Components(ps, nrm, ncomp, labels)
    seeds = comps.seeds
    seed_sign_all = np.zeros(n, dtype=np.int8)
    if seed_mask is not None and seed_mask.any():
        comps.free[np.unique(labels[seed_mask])] = False
        seed_sign_all[seed_mask] = seed_sign[seed_mask]
        root_nodes = np.concatenate([np.flatnonzero(seed_mask), seeds[comps.free[labels[seeds]]]])
    else:
        root_nodes = seeds
    keep = comps.free[labels[seeds]]
    seed_sign_all[seeds[keep]] = comps.seed_signs[keep]

    # forest + a virtual root joined to every seed: one traversal covers all components
    rows = np.concatenate([tree.row, tree.col, np.full(len(root_nodes), n)])
    cols = np.concatenate([tree.col, tree.row, root_nodes])
    adj = sparse.csr_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n + 1, n + 1))
    order, pred = breadth_first_order(adj, n, directed=True, return_predecessors=True)
    return K.propagate_signs(ps, nrm, order, pred, n, seed_sign_all), comps


def _smooth_signs(ps, nrm, sign, graph, seed_mask) -> np.ndarray:
    """The neighbour vote, then the neighbourhood consensus; known seeds keep their signs.

    ``graph`` is ``(eptr, dst, indptr, indices)``: the orientation graph and the neighbourhoods.
    """
    from recon_cli.stages.normals import _kernel as K

    eptr, dst, indptr, indices = graph
    # isolated disagreements (noise at sharp or thin places): follow a clear neighbour majority
    deg = K.degree(eptr, dst)
    for _ in range(_VOTE_PASSES):
        vote = K.vote_flips(ps, nrm, sign, eptr, dst)
        # only points that disagree with a clear majority, and never known seeds
        bad = vote < -0.25 * np.maximum(deg, 1)
        if seed_mask is not None:
            bad &= ~seed_mask
        if not bad.any():
            break
        sign[bad] = -sign[bad]

    # points with a poorly defined normal (noise): take the side their whole neighbourhood agrees on
    for _ in range(_CONSENSUS_PASSES):
        cons = K.consensus(ps, nrm, sign, indptr, indices, 1.0)
        new = np.where(cons < 0, -1, np.where(cons > 0, 1, sign)).astype(np.int8)
        if seed_mask is not None:
            new[seed_mask] = sign[seed_mask]
        if (new == sign).all():
            break
        sign = new
    return sign


def _flux_check(ps, nrm, sign, indptr, indices, comps: _Components) -> None:
    """Turn inside-out free components outward; small open ones follow the anchors (in place).

    The outward flux is the divergence theorem's volume estimate.
    """
    labels, ncomp, free = comps.labels, comps.count, comps.free
    # local area ~ squared distance to the farthest neighbour
    far_pt = ps[indices[np.maximum(indptr[1:] - 1, 0)]]
    far = np.einsum("ij,ij->i", ps - far_pt, ps - far_pt)
    flux_i = np.einsum("ij,ij->i", comps.rel, nrm) * sign * far
    flux = np.bincount(labels, flux_i, minlength=ncomp)
    scale = np.bincount(labels, np.sqrt(comps.d2) * far, minlength=ncomp)
    inside_out = free & (flux < -_FLUX_MIN * scale)
    if inside_out.any():
        sign[inside_out[labels]] = -sign[inside_out[labels]]
        flux[inside_out] = -flux[inside_out]
    # small open pieces (a scan broken into patches) have no inside: follow the normals
    # of the nearest points of the anchors (the largest component and every closed one)
    with np.errstate(invalid="ignore", divide="ignore"):
        closedness = np.where(scale > 0, flux / scale, 0.0)
    anchor = (np.abs(closedness) >= _CLOSED_FLUX) | ~free
    anchor[np.argmax(comps.size)] = True
    follow = ~anchor
    if follow.any():
        _align_to_anchors(ps, nrm, sign, labels, anchor, follow)


def _seed_signs(nrm: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """Signs turning seed normals ``nrm`` away from their component centroid (``rel`` = p - c)."""
    out_dot = np.einsum("ij,ij->i", nrm, rel)
    sign0 = np.where(out_dot < 0, -1, 1).astype(np.int8)
    flat = np.abs(out_dot) <= 1e-9 * np.sqrt(np.einsum("ij,ij->i", rel, rel))
    if flat.any():  # a flat component: any consistent choice; make it deterministic
        big = np.argmax(np.abs(nrm[flat]), axis=1)
        sign0[flat] = np.where(nrm[flat, big] < 0, -1, 1)
    return sign0


def _align_to_anchors(ps, nrm, sign, labels, anchor, follow) -> None:
    """Flip each ``follow`` component whose normals mostly disagree with the nearest anchors'.

    A component votes with up to ``_ALIGN_SAMPLES`` of its points. In place on ``sign``.
    """
    from scipy.spatial import cKDTree

    amask = anchor[labels]
    fmask = follow[labels]
    if not amask.any():
        return
    a_idx = np.flatnonzero(amask)
    f_idx = np.flatnonzero(fmask)
    # every stride-th point of each component (its points in their sorted order)
    lab = labels[f_idx]
    by = np.argsort(lab, kind="stable")
    size = np.bincount(lab, minlength=len(anchor))
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    rank = np.empty(len(by), np.int64)
    rank[by] = np.arange(len(by)) - start[lab[by]]
    stride = np.maximum(-(-size // _ALIGN_SAMPLES), 1)
    f_idx = f_idx[rank % stride[lab] == 0]
    dist, j = cKDTree(ps[a_idx]).query(ps[f_idx], 1, workers=-1)
    j = a_idx[j]
    agree = np.einsum("ij,ij->i", nrm[f_idx] * sign[f_idx, None], nrm[j] * sign[j, None])
    # nearer pairs count more
    scale = np.median(dist) + 1e-300
    vote = np.bincount(labels[f_idx], agree / (1.0 + dist / scale), minlength=len(anchor))
    flip = follow & (vote < 0)
    if flip.any():
        sign[flip[labels]] = -sign[flip[labels]]


def orient_normals(
    points: Any,
    normals: Any,
    method: str = SPEC.param("orient").default,
    *,
    knn: int = SPEC.param("knn").default,
    camera: Any = None,
    direction: Any = None,
    reference: Any = None,
    sensors: list | None = None,
    scan: Any = None,
) -> tuple[np.ndarray, dict]:
    """Orient (flip) unit normals consistently.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Coordinates.
    normals : (n, 3) array_like of float
        Normals to orient (sign arbitrary), e.g. from :func:`estimate_normals`.
    method : {"mst", "camera", "direction", "keep", "none"}
        ``mst``: consistent propagation over the kNN graph, outward per component;
        ``camera``: towards the viewpoint ``camera``; ``direction``: along ``direction``;
        ``keep``: the sign of ``reference`` where it is a non-zero finite vector, propagated
        by ``mst`` to the other points; ``none``: unchanged.
    knn : int
        Neighbourhood size for ``mst``/``keep``: the spanning-tree graph uses the 12 nearest
        at most, the final neighbourhood consensus all ``knn``.
    camera : (3,) array_like or "X,Y,Z"
        Viewpoint for ``camera``, in the units of ``points``.
    direction : (3,) array_like or "X,Y,Z"
        Direction for ``direction`` (any length but zero).
    reference : (n, 3) array_like
        Normals whose signs ``keep`` follows.
    sensors : list of Sensor, optional
        For ``camera`` without ``camera``: the scanner positions (or directions, for a
        sensor far away) to face, as :attr:`PointCloud.sensors`.
    scan : (n,) array_like of int, optional
        With several ``sensors``: each point's sensor (the attribute ``scan``).

    Returns
    -------
    normals : (n, 3) float64
        The oriented normals (same lines as the input).
    info : dict
        ``components`` (connected components of the graph, ``mst``/``keep`` only, else None)
        and ``flipped`` (number of normals whose sign changed).

    Raises
    ------
    InputError
        Bad shapes, NaN/inf coordinates or normals; several ``sensors`` without a valid
        ``scan``.
    ParameterError
        Unknown method, missing or bad ``camera``/``direction``/``reference``.
    """
    k = SPEC.param("knn").coerce(knn)
    if k == 0:
        raise ParameterError("orienting needs --knn of at least 3, got 0")
    method, cam, dirn = _check_orient(method, camera, direction)
    pts = _check_points(points)
    nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float64))
    if nrm.shape != pts.shape:
        raise InputError(f"normals have shape {nrm.shape}, expected {pts.shape}")
    if not np.isfinite(nrm).all():
        raise InputError("normals hold NaN or infinite values")
    ref = _check_reference(method, reference, len(pts))
    views = None
    if method == "camera" and cam is None:  # no camera: the sensors given
        if not sensors:
            raise ParameterError("--orient camera needs --camera X,Y,Z (or the sensors)")
        views = _sensor_views(sensors, scan, len(pts), local_origin(pts))
    pts, cam = _local(pts, cam, points)
    if views is not None:
        method, cam = "sensors", views
    if method in ("mst", "keep") and len(pts):
        order, ps, indptr, indices = _neighbourhoods(pts, k, None)
        ref_s = None if ref is None else ref[order]
        sign_s, ncomp = _orient_sorted(method, ps, nrm[order], indptr, indices, None, None, ref_s)
        sign = _unsort(order, sign_s)
        info: dict[str, Any] = {"components": int(ncomp)}
    else:
        sign = _orient_direct(method, pts, nrm, cam, dirn)
        info = {"components": None}
    info["flipped"] = int((sign < 0).sum())
    return nrm * sign[:, None], info


def _check_orient(method, camera, direction):
    """``(method, camera, unit direction)`` checked by the declaration and the options' rules.

    ``--orient camera`` without ``--camera`` faces the data's sensors (:func:`_sensor_views`).
    """
    method = SPEC.param("orient").coerce(method)
    cam = _vector(camera, "camera")
    dirn = _vector(direction, "direction")
    if dirn is not None:
        length = np.linalg.norm(dirn)
        if length == 0:
            raise ParameterError("--direction must not be the zero vector")
        dirn = dirn / length
    if method == "direction" and dirn is None:
        raise ParameterError("--orient direction needs --direction X,Y,Z")
    if cam is not None and method != "camera":
        raise ParameterError("--camera is only used with --orient camera")
    if dirn is not None and method != "direction":
        raise ParameterError("--direction is only used with --orient direction")
    return method, cam, dirn


def _check_reference(method, reference, n):
    """The normals whose signs ``keep`` follows, (n, 3) float64 (None for other methods)."""
    if method != "keep":
        return None
    if reference is None:
        raise InputError("--orient keep needs input normals (the input has none)")
    ref = np.asarray(reference, dtype=np.float64)
    if ref.shape != (n, 3):
        raise InputError(f"reference normals have shape {ref.shape}, expected ({n}, 3)")
    return ref


def _sensor_views(sensors: list, scan: Any, n: int, centre: np.ndarray) -> tuple:
    """``(positions, directions, is_direction, which)``.

    The sensors about ``centre`` ((k, 3) each; a position for a scanner, a direction for one far
    away) and each point's sensor.
    """
    k = len(sensors)
    if k == 0:
        raise InputError(
            "--orient camera needs --camera X,Y,Z: the input gives no scanner position "
            "(a PCD VIEWPOINT, E57 scan poses, a LAS file's up)"
        )
    pos = np.zeros((k, 3))
    dirs = np.zeros((k, 3))
    is_dir = np.zeros(k, dtype=bool)
    for i, sensor in enumerate(sensors):
        if sensor.direction is not None:
            dirs[i] = sensor.direction
            is_dir[i] = True
        else:
            pos[i] = np.asarray(sensor.position, np.float64) - centre
    if k == 1:
        return pos, dirs, is_dir, np.zeros(n, dtype=np.int64)
    if scan is None:
        raise InputError(
            f"the input gives {k} scanner positions but no per-point attribute "
            f"{SCAN_ATTRIBUTE!r} saying which took each point"
        )
    w = np.asarray(scan)
    whole = w.dtype.kind in "iub" or (
        w.dtype.kind == "f" and bool(np.all(np.isfinite(w) & (w == np.round(w))))
    )
    if w.shape != (n,) or not whole or (n and (w.min() < 0 or w.max() >= k)):
        raise InputError(
            f"attribute {SCAN_ATTRIBUTE!r} must give each point's scanner, "
            f"an integer 0..{k - 1} (the input gives {k} scanner positions)"
        )
    return pos, dirs, is_dir, w.astype(np.int64)


def _orient_direct(method, pts, nrm, cam, dirn) -> np.ndarray:
    if method == "sensors":  # cam: _sensor_views() with ``which`` in the order of pts
        pos, dirs, is_dir, which = cam
        towards = np.where(is_dir[which][:, None], dirs[which], pos[which] - pts)
        d = np.einsum("ij,ij->i", nrm, towards)
    elif method == "camera":
        d = np.einsum("ij,ij->i", nrm, cam[None, :] - pts)
    elif method == "direction":
        d = nrm @ dirn
    else:
        d = np.ones(len(pts))
    return np.where(d < 0, -1, 1).astype(np.int8)


def _orient_sorted(method, ps, nrm_s, indptr, indices, cam, dirn, ref_s):
    """Signs in sorted order and the component count (None for direct methods)."""
    if method in ("camera", "direction", "none", "sensors"):
        return _orient_direct(method, ps, nrm_s, cam, dirn), None
    seed_mask = seed_sign = None
    if method == "keep":
        ok = np.isfinite(ref_s).all(axis=1) & (
            np.einsum("ij,ij->i", np.nan_to_num(ref_s), np.nan_to_num(ref_s)) > 0
        )
        dots = np.einsum("ij,ij->i", nrm_s, np.nan_to_num(ref_s))
        seed_mask = ok & (dots != 0)
        seed_sign = np.where(dots < 0, -1, 1).astype(np.int8)
    return _orient_mst_sorted(ps, nrm_s, indptr, indices, seed_mask, seed_sign)


# ----------------------------------------------------------------------------- stage


def _use_pixels(neighbours: str, pixels: Any, knn: int | None, radius: float | None, n: int):
    """Whether neighbourhoods come from the pixel grid (``neighbours`` checked by SPEC)."""
    if neighbours == "kdtree":
        return False
    if neighbours == "pixels":
        if pixels is None:
            raise InputError("--neighbours pixels needs an organized cloud; this one is not")
        _check_pixels(pixels, n, knn)
        return True
    # auto: measured as accurate as the kd-tree and faster on organized depth images (bench)
    if pixels is None or knn is None or radius is not None:
        return False
    _check_pixels(pixels, n, knn)
    return True


def _viewpoints_report(method, views, sensors, camera) -> list[str] | None:
    """What ``--orient camera`` oriented towards.

    The ``--camera`` given, or each sensor used (with its point count when there are several).
    """
    if method != "camera":
        return None
    if views is None:
        cam = _vector(camera, "camera")
        assert cam is not None  # --orient camera without sensors needs --camera (checked)
        return ["--camera (" + ", ".join(f"{float(x):.9g}" for x in cam) + ")"]
    counts = np.bincount(views[3], minlength=len(sensors))
    if len(sensors) == 1:
        return [sensors[0].describe()]
    return [f"{s.describe()}: {int(c)} points" for s, c in zip(sensors, counts, strict=True)]


@SPEC.runner
def run_stage(
    data: Any,
    *,
    knn: int,
    radius: float | None,
    orient: str,
    camera: tuple[float, float, float] | None,
    direction: tuple[float, float, float] | None,
    curvature: bool,
    neighbours: str,
    backend: str,
    progress: Any = None,
) -> StageResult:
    """Stage ``normals``: estimate and orient normals of a cloud (or of a mesh's vertices).

    Where it runs is the :func:`recon_cli.execution.current` execution's: in slabs on its Dask
    cluster, in slabs in this process when the cloud needs more than its memory in one piece,
    else in one piece.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Input; a mesh's vertices are used and the output is a point cloud.
    knn, radius
        Neighbourhood, see :func:`estimate_normals` (``knn=0`` with a radius: radius only).
    orient : {"mst", "camera", "direction", "keep", "none"}
        See :func:`orient_normals`. ``camera`` without ``camera``: towards the scanner
        position(s) of ``data.sensors`` (PCD VIEWPOINT, E57 poses, each point towards its own
        scan's; a LAS file's up).
    camera, direction : "X,Y,Z" or (3,) sequence
        For ``orient="camera"`` / ``"direction"``.
    curvature : bool
        Also write the vertex attribute ``curvature`` (surface variation).
    neighbours : {"auto", "kdtree", "pixels"}
        ``pixels``: an organized cloud's k nearest among the pixels around each point
        (:func:`estimate_normals`); ``auto``: that for an organized cloud with ``knn`` and
        no ``radius``, else the kd-tree.
    backend : {"native", "open3d"}
        ``open3d``: Open3D's estimate_normals (+ orient_normals_consistent_tangent_plane(knn) for
        ``mst``).

    Returns
    -------
    StageResult
        ``output``: a PointCloud with unit ``normals``; ``report`` keys: points, knn, radius,
        neighbours, neighbourhood_size, degenerate, components, flipped, orient, viewpoints,
        input_normals, backend.
    """
    from recon_cli.stages.normals import _kernel as _normals_kernel  # noqa: F401  (numba compiles before timing starts)

    # each value checked by SPEC, the pair here; knn 0 becomes None (radius only)
    knn, radius = _check_knn(knn, radius)  # type: ignore[assignment]
    method, cam, dirn = _check_orient(orient, camera, direction)
    cloud = as_point_cloud(data)
    pts = _check_points(cloud.points)
    n = len(pts)
    ref = _check_reference(method, cloud.normals, n)
    from_sensors = method == "camera" and cam is None
    if backend == "open3d" and curvature:
        raise ParameterError("--curvature is not available with --backend open3d")
    if n == 0:
        raise InputError("the input has no points")
    ex = current()
    slabs = None
    if not ex.distributed and backend == "native":
        from recon_cli.stages.normals.distributed import slab_count

        slabs = ex.partitions or slab_count(None, n, None, knn, ex.budget())[0]
    if ex.distributed or (slabs or 1) > 1:
        check_distributed_neighbours(neighbours)
        return _run_distributed(cloud, knn, radius, method, cam, dirn, curvature, backend, progress)
    use_pixels = _use_pixels(neighbours, cloud.pixels, knn, radius, n)
    views: tuple | None = None
    if from_sensors:
        views = _sensor_views(
            cloud.sensors, cloud.attributes.get(SCAN_ATTRIBUTE), n, local_origin(pts)
        )
    pts, cam = _local(pts, cam, cloud.points)
    out = _output_cloud(data, cloud)
    report = _first_report(cloud, n, knn, radius, method, backend, use_pixels, views, camera)
    if backend == "open3d":
        out.normals = _open3d_normals(
            pts, knn, radius, method, views, cam, dirn, ref, report, progress
        )
        return StageResult(out, report)

    with task(progress, "neighbourhoods"):
        if use_pixels:
            order, ps, indptr, indices = _pixel_neighbourhoods(pts, cloud.pixels, knn, radius)
        else:
            order, ps, indptr, indices = _neighbourhoods(pts, knn, radius)
    with task(progress, "estimating normals"):
        nrm_s, curv_s, deg_s = _estimate_sorted(ps, indptr, indices)
    report["neighbourhood_size"] = float(indptr[-1] / n)
    report["degenerate"] = int(deg_s.sum())
    with task(progress, f"orienting ({method})"):
        ref_s = None if ref is None else ref[order]
        omethod = method
        cview: Any = cam
        if views is not None:  # each point towards its own sensor, in the sorted order
            omethod, cview = "sensors", (*views[:3], views[3][order])
        sign_s, ncomp = _orient_sorted(omethod, ps, nrm_s, indptr, indices, cview, dirn, ref_s)
    report["components"] = None if ncomp is None else int(ncomp)
    report["flipped"] = int((sign_s < 0).sum())
    report["provenance"] = {"neighbours": "pixels" if use_pixels else "kdtree"}
    out.normals = _unsort(order, nrm_s * sign_s[:, None])
    if curvature:
        out.attributes["curvature"] = _unsort(order, curv_s)
    if report["degenerate"]:
        report["warning"] = (
            f"{report['degenerate']} degenerate neighbourhoods (< 3 points, collinear or "
            "duplicates)"
        )
    return StageResult(out, report)


def _output_cloud(data: Any, cloud: PointCloud) -> PointCloud:
    """The output: a copy of the input cloud, or a cloud of a mesh's vertices."""
    if isinstance(data, PointCloud):
        return cloud.copy()
    return PointCloud(
        points=cloud.points,
        colors=cloud.colors,
        attributes=dict(cloud.attributes),
        history=list(cloud.history),
        point_dtype=cloud.point_dtype,
        obj_info=list(cloud.obj_info),
        sensors=list(cloud.sensors),
    )


def _first_report(
    cloud: PointCloud,
    n: int,
    knn: int,
    radius: float | None,
    method: str,
    backend: str,
    use_pixels: bool,
    views: Any,
    camera: Any,
) -> dict[str, Any]:
    """The report's keys, the figures the estimate fills in still None."""
    return {
        "points": n,
        "knn": knn,
        "radius": radius,
        "neighbours": "open3d"
        if backend == "open3d"
        else (
            f"pixels ({2 * _pixel_radius(knn) + 1}x{2 * _pixel_radius(knn) + 1} window "
            f"in {cloud.pixels.describe() if cloud.pixels is not None else ''})"
            if use_pixels
            else "kdtree"
        ),
        "neighbourhood_size": None,
        "degenerate": None,
        "components": None,
        "flipped": 0,
        "orient": method,
        "viewpoints": _viewpoints_report(method, views, cloud.sensors, camera),
        "input_normals": "none"
        if cloud.normals is None
        else ("sign kept" if method == "keep" else "replaced"),
        "backend": backend,
    }


def _open3d_normals(
    pts: np.ndarray,
    knn: int,
    radius: float | None,
    method: str,
    views: Any,
    cam: Any,
    dirn: Any,
    ref: np.ndarray | None,
    report: dict[str, Any],
    progress: Any,
) -> np.ndarray:
    """Open3D's normals of ``pts``, oriented as ``method`` asks; ``report["flipped"]`` set."""
    from recon_cli.backends import open3d_backend

    with task(progress, "open3d normals"):
        nrm = open3d_backend.estimate_normals(
            PointCloud(points=pts),
            knn=knn,
            radius=radius,
            orient_tangent_plane=(knn or 30) if method == "mst" else None,
        )
    if method != "mst":
        if method == "keep":
            assert ref is not None  # _check_reference gives the input's normals for keep
            d = np.einsum("ij,ij->i", nrm, np.nan_to_num(ref))
            sign = np.where(d < 0, -1, 1).astype(np.int8)
        elif views is not None:  # each point towards its own scanner
            sign = _orient_direct("sensors", pts, nrm, views, dirn)
        else:
            sign = _orient_direct(method, pts, nrm, cam, dirn)
        report["flipped"] = int((sign < 0).sum())
        nrm = nrm * sign[:, None]
    return nrm


def _run_distributed(
    cloud, knn, radius, method, cam, dirn, curvature, backend, progress
) -> StageResult:
    """:func:`run_stage` in slabs (:mod:`.distributed`), the cloud in memory.

    On the execution's Dask cluster, or in this process in as many slabs as its memory needs.
    """
    from recon_cli.stages.normals.distributed import distributed_normals

    if backend != "native":
        raise ParameterError("--workers/--scheduler run the native normals: leave out --backend")
    views = None
    if method == "camera" and cam is None:  # each point towards its own scanner
        views = _sensor_views(
            cloud.sensors, cloud.attributes.get(SCAN_ATTRIBUTE), len(cloud), np.zeros(3)
        )
    nrm, curv, report = distributed_normals(
        cloud.points,
        cloud.normals,
        sensors=views,
        knn=knn or 0,
        radius=radius,
        orient=method,
        camera=cam,
        direction=dirn,
        curvature=curvature,
        progress=progress,
    )
    out = cloud.copy()
    out.normals = nrm
    if curvature:
        out.attributes["curvature"] = curv
    report["input_normals"] = (
        "none" if cloud.normals is None else ("sign kept" if method == "keep" else "replaced")
    )
    report["backend"] = backend
    report["viewpoints"] = _viewpoints_report(method, views, cloud.sensors, cam)
    return StageResult(out, report)


def check_distributed_neighbours(neighbours: str) -> None:
    """Refuse ``--neighbours pixels`` in a run in slabs.

    Such a run finds neighbours with the kd-tree (a slab's pixels are not an image).
    """
    if neighbours == "pixels":
        raise ParameterError("--neighbours pixels is not available in slabs (kd-tree only)")


# public names of the pieces the distributed normals (.distributed) run per slab
neighbourhoods = _neighbourhoods
estimate_sorted = _estimate_sorted
orient_sorted = _orient_sorted
check_knn = _check_knn
check_orient = _check_orient
check_points = _check_points
sensor_views = _sensor_views
GRAPH_K = _GRAPH_K
FLUX_MIN = _FLUX_MIN
