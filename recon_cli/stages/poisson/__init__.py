"""Screened Poisson surface reconstruction (Kazhdan & Hoppe 2013), our own, adaptive.

The oriented samples define a vector field ``W``: each sample's normal, weighted by the area
it stands for, is shared among the 27 cells around it with quadratic B-spline weights and
the field is the sum of quadratic B-splines centred on those cells, as PoissonRecon (and
Open3D's copy of it) splat the normals; the indicator ``chi`` (about 1 inside, 0 outside)
minimises

    int |grad chi - W|^2  +  alpha * sum_p w_p (chi(p) - 1/2)^2,

discretised on an adaptive multilevel grid (an octree level by level), in one of two bases
(``degree``): quadratic B-splines centred on the cells, support 3 cells per axis (degree 2, the
default, as PoissonRecon's ``--degree 2``; :mod:`.bspline`), or trilinear (Q1) hat functions on the
nodes (degree 1, as Open3D's Poisson). Each sample is splatted at the depth its local density
supports (``samples_per_node`` samples per node, as PoissonRecon defines it, at most ``depth``), and
level ``d`` holds the cells of the ``2**d`` lattice within two cells of a splat of level ``d`` or
finer (every cell up to ``full_depth``), complete in siblings: the tree stops where the samples
stop, so memory and time follow the data, and a depth beyond what the samples support costs nothing
(:mod:`.splat`, :mod:`.octree`). ``chi`` is the sum of the levels' functions; it is solved
cascadically, coarse to fine, each level by Jacobi-preconditioned conjugate gradients on the
residual left by the coarser ones (as PoissonRecon does); level ``d`` is screened with weight
``alpha * 2**(d - tree depth)``, as PoissonRecon scales a node's point weight by ``2**`` its depth;
each sample's weight is scaled by how noisy its neighbourhood is (the points' scatter about the
surface, measured before the solve: :func:`.splat.noise_fraction`), so noise is smoothed and clean
detail kept. The surface is the level set of ``chi`` at the weighted mean of its values at the
samples, extracted over the leaves of the tree at each leaf's own size (Kazhdan, Klein, Dalal &
Hoppe 2007): ``chi`` is trilinear in a leaf and continuous across leaves, so its roots on the
*minimal edges* (leaf edges no smaller leaf splits) are exact, each shared by all the leaves around
it; every face between leaves pairs the roots on its boundary once, for both sides, so neighbouring
leaves of different sizes agree and there are no cracks; each leaf's segments close into polygons,
triangulated without a diagonal any other polygon could use. The surface is closed, manifold,
welded, and its size follows the tree, not the depth asked for (:mod:`.extract`). Each vertex is
then moved along its edge: with degree 1 to the root of a quadratic fit of ``chi`` along the edge's
line, with the edge's own length as the step (PoissonRecon's non-linear fit: the piecewise-linear
``chi`` stands for a smooth indicator); with degree 2 the leaves' corners take ``chi``'s exact
values (nodes on the faces of coarser leaves take those leaves' values, so neighbours agree) and
each vertex goes to ``chi``'s root. Closed specks under two finest cells across (noise leaves chi
across the iso-value around single lattice points) are dropped and counted; the largest piece always
stays.

``trim`` removes the surface where the samples' kernel density is low (the closing sheet
Poisson puts over the open side of a scan), as PoissonRecon's SurfaceTrimmer does: the mesh
is cut along the contour where the density (linear on each face) equals the threshold, the
sparse side goes, islands of the kept side below 0.1 % of its area go and holes below it are
kept (SurfaceTrimmer's ``--aRatio``); the output stays manifold (:mod:`.trim`). The
threshold differs: SurfaceTrimmer's ``--trim`` is an absolute value of the density
PoissonRecon writes (a depth-like, logarithmic value; 5 to 7 is typical, smoothed first),
Open3D users cut a quantile of the vertex densities; ours is a fraction of the median density
at the samples, so one value (0.1 to 0.3) serves any scan, depth, unit and tessellation.
``trim="auto"`` needs no value: it cuts where the surface lies farther from the samples than
their local spacing (:func:`.trim.support_ratio`), so sparse real surface stays, and keeps
every island a sample lies nearest to (:func:`.trim.trim_auto`).

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M., Klein, A., Dalal, K. & Hoppe, H. (2007). Unconstrained isosurface extraction on
arbitrary octrees. SGP.
Kazhdan, M., Bolitho, M. & Hoppe, H. (2006). Poisson surface reconstruction. SGP.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.execution import current
from recon_cli.geometry import PointCloud, TriangleMesh, as_point_cloud, local_origin, oriented_rows
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task

if TYPE_CHECKING:
    from recon_cli.grid import Grid
    from recon_cli.stages import StageResult

log = logging.getLogger("recon")

BOUNDARIES = ("neumann", "dirichlet", "free")
BACKENDS = ("native", "open3d", "pymeshlab")
MAX_DEPTH = 14
# closed pieces of the extraction smaller than this many finest cells on every side are specks
# of noise, not surface (_drop_bubbles)
BUBBLE_CELLS = 2
# a closed piece (not the largest) with fewer input points than this within BUBBLE_CELLS finest
# cells of its box is an island around a few outliers, not a surface the data shows (_drop_bubbles)
ISLAND_POINTS = 10
# closed pieces smaller than this many times the samples' median noise on every side are specks
# too: the samples scatter over a band about 8 sigma wide, and a piece that fits in it cannot be
# told from the noise (noisy clouds at a depth finer than their noise: bench/calibration.md)
SPECK_SIGMAS = 8.0
# a closed piece (not the largest) under FOLD_SPAN_SIGMAS noise medians across whose every vertex
# lies within FOLD_SIGMAS of a piece that stays whatever (the largest, or one longer than that)
# is a fold of the noise band around it, not a part (bench/calibration.md)
FOLD_SIGMAS = 4.5
FOLD_SPAN_SIGMAS = 16.0


def speck_cells(noise: float | None) -> float:
    """The size, in finest cells, under which a closed piece is a speck (:func:`_drop_bubbles`).

    :data:`BUBBLE_CELLS`, or :data:`SPECK_SIGMAS` times the samples' median ``noise`` (finest
    cells; None: not measured) when that is larger.
    """
    if noise is None or not np.isfinite(noise):
        return float(BUBBLE_CELLS)
    return max(float(BUBBLE_CELLS), SPECK_SIGMAS * float(noise))


def fold_cells(noise: float | None) -> tuple[float, float] | None:
    """The folds' sizes in finest cells: (largest span, farthest reach), None without ``noise``.

    :data:`FOLD_SPAN_SIGMAS` and :data:`FOLD_SIGMAS` times the samples' median noise (finest
    cells), as :func:`_drop_bubbles` and the slabs' merge use them.
    """
    if noise is None or not np.isfinite(noise) or noise <= 0:
        return None
    return FOLD_SPAN_SIGMAS * float(noise), FOLD_SIGMAS * float(noise)


@dataclass
class PoissonResult:
    """What :func:`screened_poisson` returns.

    Attributes
    ----------
    mesh : TriangleMesh
        The surface; ``attributes["density"]`` when asked for, ``colors`` when the input
        had colours.
    grid : Grid or None
        With ``with_grid``: the solved field on the finest lattice around the surface
        (:mod:`.field`).
    report : dict
        ``vertices``, ``faces``, ``depth``, ``iso_value``, ``solver_iterations``, ``residual``
        (relative residual of the finest level), ``bubbles_removed`` (closed specks under two finest
        cells or eight times the noise across, dropped: :func:`_drop_bubbles`),
        ``islands_removed`` (closed pieces around fewer than ten input points, dropped),
        ``folds_removed`` (closed pieces inside the noise band around the largest, dropped),
        ``trimmed_faces`` (faces cut or removed by ``trim``),
        ``trimmed_area`` (fraction of the area removed), ``noise`` (the samples' median noise in
        finest cells of the tree, :func:`.splat.noise_fraction`; None without screening) and details
        (``tree_depth``: the deepest level the samples support, ``samples``, ``nodes`` per level,
        ``timings``).
    """

    mesh: TriangleMesh
    report: dict = field(default_factory=dict)
    grid: Grid | None = None


# ---------------------------------------------------------------------------------------------
# the declaration (every option's type, default and range) and validation
SPEC = StageSpec(
    name="poisson",
    summary="Screened Poisson reconstruction of an oriented cloud.",
    description="""Screened Poisson reconstruction (Kazhdan & Hoppe 2013) on a sparse octree.

    IN must carry normals (run 'recon normals' first, or pass --estimate-normals). Colours
    on IN are interpolated onto the output vertices. With -v the solver's iterations and
    residual per level are logged.""",
    takes=("oriented",),
    takes_when=lambda p: ("cloud", "mesh") if p["estimate_normals"] else ("oriented",),
    gives=("mesh",),
    backends=BACKENDS,
    from_files="recon_cli.stages.poisson:run_from_files",
    execution=("workers", "scheduler", "partitions", "memory", "temp_dir"),
    params=(
        Param(
            "depth",
            "int",
            8,
            "Deepest octree level allowed (finest cell = reconstruction cube / 2^depth); the "
            "tree stops where the samples do.",
            min=1,
            max=MAX_DEPTH,
        ),
        Param(
            "scale",
            "float",
            1.1,
            "Reconstruction cube / largest side of the bounding box.",
            unit="ratio",
            min=1.0,
        ),
        Param(
            "point_weight",
            "float",
            4.0,
            "Screening weight (0 = classic unscreened Poisson).",
            min=0.0,
        ),
        Param(
            "samples_per_node",
            "float",
            1.5,
            "Samples per node at a sample's depth (as PoissonRecon): sparser samples are "
            "splatted coarser.",
            unit="samples",
            min=0.0,
            min_open=True,
        ),
        Param(
            "degree",
            "int",
            2,
            "B-spline degree of the basis: 2 quadratic (as PoissonRecon's --degree 2; more "
            "accurate on smooth surfaces), 1 trilinear (as Open3D's Poisson; about 0.6x the "
            "time).",
            min=1,
            max=2,
        ),
        Param(
            "boundary",
            "choice",
            "neumann",
            "Condition on the faces of the cube: neumann (the surface meets them at right angles), "
            "dirichlet (outside), free (none, as PoissonRecon's --bType 1: an open surface runs "
            "on to the faces and is cut there; degree 2).",
            choices=BOUNDARIES,
        ),
        Param(
            "confidence",
            "bool",
            False,
            "Weight each point by its normal's length (as PoissonRecon's --confidence).",
        ),
        Param(
            "density",
            "bool",
            False,
            "Write the per-vertex sampling density as vertex property 'density'.",
        ),
        Param(
            "trim",
            "float",
            0.0,
            "Cut away an open scan's closing sheet: 'auto' keeps the surface within one local "
            "sample spacing of the samples (sparse real surface stays); a number T cuts where the "
            "samples' density is below T times its median at the samples.",
            unit="of the median sample density",
            min=0.0,
            max=1.0,
            max_open=True,
            words={"auto": "auto"},
            metavar="auto|T",
        ),
        Param(
            "attributes",
            "any",
            "all",
            "Input point properties carried onto the vertices (intensity, classification, colours, "
            "any PLY property): all, none, or names separated by commas; from the points near each "
            "vertex on its side (no bleeding through thin parts), codes by majority.",
            metavar="all|none|NAME,...",
        ),
        Param(
            "envelope",
            "any",
            None,
            "A closed mesh the surface must lie in (as PoissonRecon's --envelope): nothing "
            "outside it, and the space inside it that no point sees is solid, so an open scan's "
            "closing sheet follows it (degree 2).",
            metavar="MESH",
        ),
        Param(
            "grid",
            "any",
            None,
            "Also write the solved field on the finest lattice to this grid file (.npz): zero on "
            "the surface, negative inside ('recon mcubes' extracts it).",
            metavar="OUT.npz",
        ),
        Param(
            "estimate_normals",
            "bool",
            False,
            "Estimate and orient normals first (as 'recon normals' does).",
        ),
    ),
)
# options of the library function only
_FULL_DEPTH = Param(
    "full_depth", "int", 5, "Levels up to this one are complete grids.", min=0, max=7
)
_CG_TOLERANCE = Param(
    "cg_tolerance",
    "float",
    1e-3,
    "Relative residual at which each level's CG stops.",
    min=0.0,
    max=1.0,
    min_open=True,
)


def _check_options(
    depth, scale, point_weight, samples_per_node, degree, boundary, density, trim
) -> tuple:
    """Validate and convert the options shared by :func:`screened_poisson` and :func:`run_stage`."""
    v = SPEC.check(
        dict(
            depth=depth,
            scale=scale,
            point_weight=point_weight,
            samples_per_node=samples_per_node,
            degree=degree,
            boundary=boundary,
            density=density,
            trim=trim,
        ),
        complete=False,
    )
    if v["boundary"] == "free" and v["degree"] != 2:
        raise ParameterError("--boundary free needs --degree 2")
    return (
        v["depth"],
        v["scale"],
        v["point_weight"],
        v["samples_per_node"],
        v["degree"],
        v["boundary"],
        v["density"],
        v["trim"],
    )


def _check_inputs(
    points: Any, normals: Any, lengths: list | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Finite (n, 3) points and unit normals.

    Returns (points, normals, kept mask) (and appends the kept normals' lengths to ``lengths`` when
    given).
    """
    pts, nrm, length = oriented_rows(
        points,
        normals,
        "the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)",
    )
    if not np.all(np.isfinite(pts)):
        raise InputError("points contain NaN or infinite coordinates")
    if not np.all(np.isfinite(length)):
        raise InputError("normals contain NaN or infinite values")
    keep = length > 0
    if not keep.any():
        raise InputError("every normal has zero length: run 'recon normals' to estimate them")
    if keep.sum() < 4:
        raise InputError(
            f"poisson needs at least 4 points with non-zero normals, got {int(keep.sum())}"
        )
    pts = pts[keep]
    nrm = nrm[keep] / length[keep, None]
    if lengths is not None:
        lengths.append(length[keep])
    extent = pts.max(axis=0) - pts.min(axis=0)
    if not extent.max() > 0:
        raise InputError("all points coincide: there is no surface to reconstruct")
    return pts, nrm, keep


# ---------------------------------------------------------------------------------------------
def screened_poisson(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    depth: int = SPEC.param("depth").default,
    scale: float = SPEC.param("scale").default,
    point_weight: float = SPEC.param("point_weight").default,
    samples_per_node: float = SPEC.param("samples_per_node").default,
    degree: int = SPEC.param("degree").default,
    boundary: str = SPEC.param("boundary").default,
    density: bool = SPEC.param("density").default,
    trim: float = SPEC.param("trim").default,
    confidence: bool = SPEC.param("confidence").default,
    colors: np.ndarray | None = None,
    properties: dict[str, np.ndarray] | None = None,
    with_grid: bool = False,
    envelope: Any = None,
    full_depth: int = _FULL_DEPTH.default,
    cg_tolerance: float = _CG_TOLERANCE.default,
    progress: Any = None,
) -> PoissonResult:
    """Screened Poisson reconstruction of an oriented point set.

    Parameters
    ----------
    points : (n, 3) float
        Sample positions (world units). Points with a zero-length normal are ignored.
    normals : (n, 3) float
        Outward normals (any non-zero length; normalised here).
    depth : int
        Deepest level allowed: the finest cell is at most the bounding cube (largest extent
        times ``scale``) divided by ``2**depth``; the tree goes only as deep as the
        samples' density supports (``report["tree_depth"]``). 1 to 14.
    scale : float
        Ratio of the reconstruction cube to the bounding box's largest side (>= 1).
    point_weight : float
        Screening weight alpha (>= 0; 0 = classic unscreened Poisson).
    samples_per_node : float
        Samples per node at a sample's depth (PoissonRecon's ``--samplesPerNode``): a
        sample is splatted at the level where its kernel density gives this many samples
        per node, so sparse regions get coarse, smooth nodes and the tree no finer ones;
        larger values give coarser, smoother surfaces on noisy data. > 0.
    degree : {1, 2}
        B-spline degree of the basis: 2 (the default), quadratic B-splines centred on the
        cells (support 3 cells per axis, :mod:`.bspline`): on smooth surfaces clearly more
        accurate (exact-distance Chamfer on 100k samples at depths 8 and 9: 0.44-0.98x
        Open3D's, where degree 1 is 0.75-0.98x and 1.35x on a box aligned with the lattice);
        1, trilinear hat functions on the nodes (Open3D's Poisson uses degree 1), about
        0.55-0.7x the time of degree 2.
    boundary : {"neumann", "dirichlet", "free"}
        Condition on the cube's faces: Neumann (``chi``'s normal derivative 0: the surface
        meets the faces at right angles), Dirichlet (``chi = 0``, the outside) or none
        (free, PoissonRecon's ``BOUNDARY_FREE``, degree 2 only: the functions of the cells
        just beyond the faces are added and every integral runs over the cube only, so chi
        takes whatever value and slope the data ask for at the faces; an open surface runs
        straight on to them and is cut there, the mesh is open along the faces). Made by
        solving on a cube twice as large, one level deeper, with the integrals over its
        middle half only (:data:`.bspline.FREE_DOMAIN`): the same finest cell.
    density : bool
        Add the per-vertex kernel density of the samples as ``attributes["density"]``.
    trim : float or "auto"
        ``"auto"``: cut away the surface farther than one local sample spacing from the
        samples (:func:`.trim.support_ratio`: the threshold comes from the samples, sparse
        real surface stays). A number: cut away the surface where the samples' density is
        below ``trim`` times its median at the samples (0 <= trim < 1; 0 keeps everything);
        see the module docstring for how this relates to PoissonRecon's SurfaceTrimmer.
    confidence : bool
        Weight each point by its normal's length, as PoissonRecon's ``--confidence``: its
        position and normal count that much in its finest cell's sample, whose weight (in the
        kernel density, the area per sample, the screening and the iso-value) is their sum.
        The weights are divided by their mean, so only their ratios matter (PoissonRecon
        uses the lengths as they are: their scale moves its splat depths).
    colors : (n, 3) or (n, 4) array or None
        Per-point colours, carried onto the output vertices (:mod:`.attributes`).
    properties : dict of str to (n,) array, optional
        Per-point properties carried onto the vertices as ``mesh.attributes`` in their
        dtypes (:func:`.attributes.transfer`: from the points near each vertex on its side;
        integer codes by majority). A requested ``density`` replaces an input one.
    with_grid : bool
        Also return the solved field on a regular grid (``PoissonResult.grid``,
        :func:`.field.indicator_grid`): the finest lattice's points around the surface,
        ``(iso - chi) / g`` (zero on the untrimmed surface, negative inside, about the
        distance near it).
    envelope : TriangleMesh or .envelope.Envelope or None
        A closed mesh (world units) the surface must lie in, as PoissonRecon's
        ``--envelope``: chi is clipped by it after the solve, so no part of the surface is
        outside, and the space inside it that no sample sees (along the normals) is solid, so
        an open scan's closing sheet follows it (:mod:`.envelope`; degree 2; the solve's cube
        grows to hold it, the finest cell kept). The report counts the input points outside
        it (``envelope_outside_points``, which the surface cannot reach) and the vertices
        moved inside it (``envelope_pulled_vertices``).
    full_depth : int
        Levels up to this one are complete grids.
    cg_tolerance : float
        Relative residual at which each level's conjugate gradients stop.
    progress : Progress or None

    Returns
    -------
    PoissonResult
    """
    depth, scale, point_weight, samples_per_node, degree, boundary, density, trim = _check_options(
        depth, scale, point_weight, samples_per_node, degree, boundary, density, trim
    )
    full_depth = _FULL_DEPTH.coerce(full_depth)
    cg_tolerance = _CG_TOLERANCE.coerce(cg_tolerance)
    confidence = SPEC.param("confidence").coerce(confidence)
    if envelope is not None:
        if degree != 2:
            raise ParameterError("--envelope needs --degree 2")
        envelope = _checked_envelope(envelope)
    lengths: list = []
    pts, nrm, keep = _check_inputs(points, normals, lengths)
    weight = lengths[0] / float(lengths[0].mean()) if confidence else None
    del lengths
    colors, props = _kept_attributes(keep, colors, properties)
    unit_nrm = nrm if (props or colors is not None) else None

    from recon_cli.stages.poisson.basis import basis_for
    from recon_cli.stages.poisson.splat import sample_density
    from recon_cli.stages.poisson.timing import Timings

    basis = basis_for(degree)
    clock = Timings()

    need_density = density or (trim != "auto" and trim > 0)
    setup = _prepare(
        pts, nrm, weight, envelope, basis, clock, progress,
        depth=depth, scale=scale, boundary=boundary, full_depth=full_depth,
        samples_per_node=samples_per_node, point_weight=point_weight, density=need_density,
    )  # fmt: skip
    del nrm  # memory: the normals are in the samples now
    origin, size, tree_depth, domain = setup.origin, setup.size, setup.tree_depth, setup.domain
    smp, splats, env = setup.smp, setup.splats, setup.env
    res = 1 << tree_depth  # the finest cells of the tree

    # ---- cascadic solve and the iso-value
    with clock.phase("solve"):
        sol = basis.solve(
            setup.levels,
            smp,
            splats,
            boundary,
            setup.full_depth,
            cg_tolerance,
            progress,
            setup.sample_ok,
            setup.clip,
        )
    setup.levels = []
    iso = sol.iso

    # ---- extraction, clipped to the cube, bubbles and islands dropped, pulled into the envelope
    with clock.phase("extract"):
        verts, faces, chi_fn, dropped, pulled = _extract_surface(
            basis, sol, origin, size, tree_depth, with_grid, domain, pts, env, setup.noise
        )
    # ---- the field on a regular grid (--grid)
    field_grid = None
    if with_grid and len(faces):
        with clock.phase("grid"):
            field_grid = _field_grid(chi_fn, iso, verts, origin, size, res, domain, progress)
    del chi_fn

    mesh = TriangleMesh(vertices=verts, faces=faces)
    vdens = None
    if need_density:
        vdens = sample_density(splats, (verts - origin) / size)
    mesh, vdens, trimmed, trimmed_area = _trimmed(mesh, vdens, trim, smp, splats, origin, size)
    # ---- the input's properties on the vertices, from the points on each vertex's side
    fallback = 0
    if props or colors is not None:
        with clock.phase("attributes"):
            fallback = _carry_attributes(mesh, pts, unit_nrm, props, colors, size / res)
    del unit_nrm
    if density:
        assert vdens is not None  # made above whenever density is asked for
        mesh.attributes["density"] = vdens
    report = _report(
        mesh,
        sol,
        clock.total(),
        depth=depth,
        tree_depth=tree_depth - (setup.depth - depth),
        samples=len(smp.count),
        ignored=int((~keep).sum()),
        finest_cell=size / res,
        noise=setup.noise,
        removed=(*dropped, trimmed, trimmed_area),
        fallback=fallback,
        attributes=sorted(props) + (["colors"] if colors is not None else []),
        envelope=(setup.outside_points, pulled) if env is not None else None,
    )
    if field_grid is not None:
        report["grid_shape"] = list(field_grid.shape)
    return PoissonResult(mesh, report, field_grid)


def _extract_surface(basis, sol, origin, size, tree_depth, with_grid, domain, pts, env, noise):
    """The iso-surface of a solve in the input's frame.

    Returns ``(verts, faces, chi_fn, (bubbles, islands, folds), pulled)``: clipped to the cube
    (free boundary), the closed pieces that are noise dropped, pulled into the envelope.
    """
    from recon_cli.stages.poisson.free import clip_to_cube

    verts, faces, chi_fn = basis.extract(sol, origin, size, tree_depth, with_grid)
    if domain is not None:
        verts, faces = clip_to_cube(verts, faces, *domain)
    verts, faces, *dropped = _drop_bubbles(verts, faces, size / (1 << tree_depth), pts, noise)
    pulled = 0
    if env is not None:
        verts, pulled = env.pull_inside(verts, size / (1 << tree_depth))
    return verts, faces, chi_fn, tuple(dropped), pulled


@dataclass
class _Setup:
    """What :func:`screened_poisson` solves: made by :func:`_prepare`.

    The solve's cube (``origin``, ``size``: the unit cube's frame; ``depth`` the finest level
    allowed, deeper than asked when the cube grew for an envelope), the tree's depth and its
    complete levels, the free boundary's domain, the merged samples and their splats, the
    samples' median noise, the envelope's state, and the tree's levels (emptied after the solve).
    """

    origin: np.ndarray
    size: float
    depth: int
    tree_depth: int
    full_depth: int
    domain: tuple | None
    smp: Any
    splats: Any
    levels: list
    noise: float | None
    env: Any = None
    sample_ok: Any = None
    clip: Any = None
    outside_points: int = 0


def _prepare(
    pts: np.ndarray,
    nrm: np.ndarray,
    weight: np.ndarray | None,
    envelope: Any,
    basis: Any,
    clock: Any,
    progress: Any,
    *,
    depth: int,
    scale: float,
    boundary: str,
    full_depth: int,
    samples_per_node: float,
    point_weight: float,
    density: bool,
) -> _Setup:
    """The unit cube, the samples, their splats and noise, the envelope and the tree.

    Points are merged per finest cell, as PoissonRecon does; the tree goes as deep as the splats,
    no deeper. ``density``: the splats keep what the vertices' density needs.
    """
    from recon_cli.stages.poisson.splat import make_splats, merge_samples

    with clock.phase("samples"):
        origin, size, depth, domain = _solve_cube(pts, scale, boundary, depth)
        if envelope is not None and domain is None:
            origin, size, depth = _envelope_cube(envelope, origin, size, depth)
        full_depth = min(full_depth, depth)
        smp = merge_samples((pts - origin) / size, nrm, depth, weight)
    with clock.phase("density"):  # kernel density -> area per point and splat level
        splats = make_splats(
            smp, depth, samples_per_node, point_weight, density, merge=basis.merge_splats
        )
        tree_depth = basis.tree_depth(splats.tree_depth, domain is not None)
        full_depth = min(full_depth, tree_depth)
    with clock.phase("noise"):  # noisy neighbourhoods are screened less (Splats.screening)
        noise = _screening_noise(pts, origin, size, smp, splats, tree_depth, point_weight)
    setup = _Setup(origin, size, depth, tree_depth, full_depth, domain, smp, splats, [], noise)
    item_pos, item_level = splats.pos, splats.level
    if envelope is not None:  # chi clipped by it after the solve; the tree refined along it
        with clock.phase("envelope"):
            env, setup.sample_ok, setup.clip, setup.outside_points, item_pos, item_level = (
                _envelope_setup(envelope, pts, smp, splats, origin, size, tree_depth, full_depth)
            )
            setup.env = env
    with clock.phase("tree"):
        assert item_pos is not None and item_level is not None  # the items, before the solve
        with task(progress, "poisson: tree"):
            setup.levels = basis.build_tree(item_pos, item_level, tree_depth, full_depth, boundary)
        # memory: the splat items made the fields and the tree, the samples' normals and keys
        # the splats
        del item_pos, item_level
        splats.pos = splats.vec = splats.level = smp.normal = smp.keys = None
    log.info(
        "poisson: %d points, %d samples, depth %d (tree %d), nodes per level %s",
        len(pts),
        len(smp.count),
        depth,
        tree_depth,
        [len(lv.node_keys) for lv in setup.levels],
    )
    return setup


def _report(
    mesh: TriangleMesh,
    sol: Any,
    timings: dict,
    *,
    depth: int,
    tree_depth: int,
    samples: int,
    ignored: int,
    finest_cell: float,
    noise: Any,
    removed: tuple,
    fallback: int,
    attributes: list[str],
    envelope: tuple[int, int] | None,
) -> dict[str, Any]:
    """The report of :func:`screened_poisson` (its keys are listed in its Returns section).

    ``removed`` is (bubbles, islands, folds, trimmed faces, trimmed area); ``envelope`` is
    (points outside, vertices pulled), or None without one.
    """
    bubbles, islands, folds, trimmed, trimmed_area = removed
    return {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "depth": depth,
        "tree_depth": tree_depth,
        "iso_value": sol.iso,
        "solver_iterations": int(sol.iterations),
        "residual": float(sol.residual),
        "bubbles_removed": bubbles,
        "islands_removed": islands,
        "folds_removed": folds,
        "trimmed_faces": int(trimmed),
        "trimmed_area": trimmed_area,
        "noise": noise,
        "attributes": attributes,
        "attribute_fallback_vertices": fallback,
        "envelope_outside_points": None if envelope is None else envelope[0],
        "envelope_pulled_vertices": None if envelope is None else envelope[1],
        "samples": int(samples),
        "ignored_points": ignored,
        "finest_cell": finest_cell,
        "levels": sol.per_level,
        "timings": timings,
    }


def _screening_noise(
    pts: np.ndarray,
    origin: np.ndarray,
    size: float,
    smp: Any,
    splats: Any,
    tree_depth: int,
    point_weight: float,
) -> float | None:
    """The samples' median noise, their clean fractions set on ``splats`` (None unscreened).

    Noisy neighbourhoods are screened less (:meth:`.splat.Splats.screening`).
    """
    from recon_cli.stages.poisson.splat import noise_fraction

    if point_weight <= 0:
        return None
    splats.clean, sample_noise = noise_fraction((pts - origin) / size, smp, tree_depth)
    return float(np.median(sample_noise))


def _solve_cube(
    pts: np.ndarray, scale: float, boundary: str, depth: int
) -> tuple[np.ndarray, float, int, tuple[np.ndarray, float] | None]:
    """The solve's cube around ``pts`` (n, 3): (origin, side, depth, the free boundary's domain).

    With the free boundary the points' cube is the middle half of the solve's, one level
    deeper; the domain is then the points' cube (origin, side), else None.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    size = float((hi - lo).max()) * scale
    origin = 0.5 * (lo + hi) - 0.5 * size
    if boundary != "free":
        return origin, size, depth, None
    return origin - 0.5 * size, 2.0 * size, depth + 1, (origin.copy(), size)


def _field_grid(
    chi_fn: Any,
    iso: float,
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
    domain: tuple[np.ndarray, float] | None,
    progress: Any,
) -> Any:
    """The solved field on the finest lattice around the surface (``--grid``, :mod:`.field`)."""
    from recon_cli.stages.poisson.field import indicator_grid
    from recon_cli.stages.poisson.free import FREE_DOMAIN

    assert chi_fn is not None  # made with_grid
    with task(progress, "poisson: grid"):
        return indicator_grid(
            chi_fn, iso, verts, origin, size, res, FREE_DOMAIN if domain else (0.0, 1.0)
        )


def _carry_attributes(
    mesh: TriangleMesh,
    pts: np.ndarray,
    unit_nrm: np.ndarray | None,
    props: dict[str, np.ndarray],
    colors: np.ndarray | None,
    cell: float,
) -> int:
    """Put the points' properties and colours on ``mesh``'s vertices (:mod:`.attributes`).

    Returns the count of vertices that fell back to the nearest point (no point on their side).
    """
    from recon_cli.stages.poisson.attributes import transfer

    assert unit_nrm is not None  # kept when there are properties to carry
    moved = transfer(pts, unit_nrm, props, colors, mesh.vertices, mesh.faces, cell)
    mesh.attributes.update(moved.values)
    mesh.colors = moved.colors
    return int(moved.fallback)


def _kept_attributes(
    keep: np.ndarray, colors: Any, properties: dict[str, np.ndarray] | None
) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """The colours (n, k) and properties (n,) of the points ``keep`` (N,) bool keeps, checked."""
    if colors is not None:
        colors = np.asarray(colors)
        if len(colors) != len(keep):
            raise InputError(f"colors has {len(colors)} rows, expected {len(keep)}")
        colors = colors[keep]
    props: dict[str, np.ndarray] = {}
    for name, values in (properties or {}).items():
        values = np.asarray(values)
        if values.ndim != 1 or len(values) != len(keep):
            raise InputError(
                f"attribute {name!r} has shape {values.shape}, expected ({len(keep)},)"
            )
        props[name] = values[keep]
    return colors, props


def _checked_envelope(envelope: Any) -> Any:
    """``envelope`` as an :class:`.envelope.Envelope` (a closed mesh, checked)."""
    from recon_cli.stages.poisson.envelope import Envelope

    return envelope if isinstance(envelope, Envelope) else Envelope(envelope)


def _envelope_cube(
    envelope: Any, origin: np.ndarray, size: float, depth: int
) -> tuple[np.ndarray, float, int]:
    """The solve's cube grown to hold the checked envelope, the finest lattice kept."""
    from recon_cli.stages.poisson.envelope import covering_cube

    v = envelope.vertices[np.unique(envelope.faces)]
    return covering_cube(v, origin, size, depth, MAX_DEPTH + 2)


def _envelope_setup(
    envelope: Any,
    pts: np.ndarray,
    smp: Any,
    splats: Any,
    origin: np.ndarray,
    size: float,
    tree_depth: int,
    full_depth: int,
) -> tuple[Any, np.ndarray, Any, int, np.ndarray, np.ndarray]:
    """The envelope's part of the set-up, the tree refined along its surface.

    Returns the envelope, the samples inside it, the field's clip (``clip(iso)``), the count of
    points outside it, and the tree's items (positions, levels).
    """
    import functools

    from recon_cli.stages.poisson.envelope import (
        CARVE_MAX_LEVEL,
        CARVE_OFFSET,
        REFINE_OFFSET,
        Carving,
        FieldClip,
    )

    env = envelope  # checked by _checked_envelope
    outside_points = int(np.count_nonzero(~env.inside(pts)))
    sample_ok = env.inside(origin + size * smp.pos)
    if not sample_ok.any():
        raise InputError("every point lies outside the envelope")
    carve_level = max(1, min(CARVE_MAX_LEVEL, tree_depth - CARVE_OFFSET))
    carving = Carving(smp.pos[sample_ok], smp.normal[sample_ok], carve_level)
    clip = functools.partial(FieldClip, env, carving, origin, size, size / (1 << tree_depth))
    lv = min(tree_depth, max(full_depth, tree_depth - REFINE_OFFSET))
    # the tree refined along the envelope and along the carving's sheet
    extra = np.concatenate([env.surface_items(origin, size, lv), carving.boundary_items()])
    item_pos = np.concatenate([splats.pos, extra])
    item_level = np.concatenate([splats.level, np.full(len(extra), lv, np.int64)])
    return env, sample_ok, clip, outside_points, item_pos, item_level


def _trimmed(
    mesh: TriangleMesh,
    vdens: np.ndarray | None,
    trim: float | str,
    smp: Any,
    splats: Any,
    origin: np.ndarray,
    size: float,
) -> tuple[TriangleMesh, np.ndarray | None, int, float]:
    """``mesh`` trimmed as ``trim`` asks: (mesh, vertex densities, faces cut, area removed).

    ``"auto"`` cuts by :func:`.trim.support_ratio` from the samples, a value ``T > 0`` at ``T``
    times the median density at the samples (``vdens`` (n,) the vertices' densities then).
    """
    from recon_cli.stages.poisson.splat import sample_density
    from recon_cli.stages.poisson.trim import trim_auto, trim_by_density

    if not len(mesh.faces) or trim == 0:
        return mesh, vdens, 0, 0.0
    if trim == "auto":
        cut = trim_auto(mesh, smp.pos * size + origin, carry=vdens)
        if len(cut.mesh.faces) == 0:
            raise InputError("trim auto removes the whole surface: no part lies near the samples")
        return cut.mesh, cut.carried, len(mesh.faces) - cut.untouched_faces, cut.removed_area
    assert vdens is not None  # made whenever trim > 0
    at_samples = sample_density(splats, smp.pos)
    cut = trim_by_density(mesh, vdens, float(trim) * float(np.median(at_samples)))
    if len(cut.mesh.faces) == 0:
        raise ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value")
    return cut.mesh, cut.density, len(mesh.faces) - cut.untouched_faces, cut.removed_area


def _drop_bubbles(
    verts: np.ndarray, faces: np.ndarray, cell: float, points: np.ndarray, noise: float | None
) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """Drop the closed pieces that are noise, never the largest.

    Returns the vertices and faces left and how many specks, islands and folds went.

    - **Specks:** pieces smaller than :func:`speck_cells` finest cells on every side.
      Noisy, sparse samples leave chi slightly across the iso-value around single lattice
      points off the surface: closed specks of 8-16 triangles, one or two cells across (on
      the shared stereo fragment at depth 9: 53 of them, 0.8-1.2 cells, beside one surface
      of 128 cells). A piece that small cannot stand for a real feature at this depth (the
      lattice samples chi once per cell). Where the samples' median ``noise`` (finest cells)
      is larger, a depth finer than the noise leaves blobs inside the band the samples
      scatter over, up to several times the noise across; a piece under
      :data:`SPECK_SIGMAS` times the noise fits in that band and is taken for one.
    - **Islands:** larger pieces with fewer than :data:`ISLAND_POINTS` of the input
      ``points`` within :data:`BUBBLE_CELLS` cells of their bounding box. A few outliers
      away from the surface splat a dipole that Poisson closes into a blob (on the stereo
      fragment: 82 triangles, 3.6 cells across, around 5 stray points); a real part,
      however small, carries the samples it was made from.
    - **Folds:** pieces under :data:`FOLD_SPAN_SIGMAS` times the noise across whose every
      vertex lies within :data:`FOLD_SIGMAS` times the noise of the vertices of the pieces
      that stay whatever (the largest and those longer than that: :func:`fold_cells`). Such a
      piece lies wholly inside the band that piece's own samples scatter over: the data
      cannot tell it from a fold of that band. A real part farther out, or longer (the inner
      wall of a thin shell), stays.

    Every piece of the extraction is closed, so what is left is too. ``verts``, ``points``
    and ``cell`` are in the same units (the report counts ``bubbles_removed``,
    ``islands_removed`` and ``folds_removed``).
    """
    if not len(faces):
        return verts, faces, 0, 0, 0
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.stages.poisson.octree import points_in_boxes
    from recon_cli.stages.poisson.pieces import (
        noise_pieces,
        piece_boxes,
        piece_reach,
        reach_vertices,
    )

    lab = Connectivity(faces, len(verts)).face_components
    n = int(lab.max()) + 1
    if n == 1:
        return verts, faces, 0, 0, 0
    # boxes of the pieces but the largest (piece 0, which always stays): few faces
    rest = lab != 0
    _, lo, hi = piece_boxes(verts, faces[rest], lab[rest], n)

    def farthest(which, anchor, a, b):
        m = reach_vertices(verts, faces, lab, which, anchor, a, b)
        return piece_reach(m["points"], m["ids"], len(a), m["targets"])

    speck, island, fold = noise_pieces(
        lo,
        hi,
        0,
        cell,
        speck_cells(noise),
        fold_cells(noise),
        lambda a, b: points_in_boxes(points, a, b),
        farthest,
    )
    gone = speck | island | fold
    if not gone.any():
        return verts, faces, 0, 0, 0
    faces = faces[~gone[lab]]
    used = np.zeros(len(verts), bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    counts = int(speck.sum()), int(island.sum()), int(fold.sum())
    return verts[used], remap[faces].astype(faces.dtype), *counts


# the native solve's report keys, in the report's order
REPORT_KEYS = (
    "vertices",
    "faces",
    "depth",
    "iso_value",
    "solver_iterations",
    "residual",
    "bubbles_removed",
    "islands_removed",
    "folds_removed",
    "trimmed_faces",
    "trimmed_area",
    "samples",
    "ignored_points",
    "tree_depth",
    "noise",
    "attributes",
    "attribute_fallback_vertices",
)


def run_from_files(input: str, output: str, params: dict, **kw: Any) -> dict | None:
    """The stage's ``from_files``: a run in slabs from IN's chunks, never holding the cloud.

    On a cluster (``--workers``, ``--scheduler``), or in this process when IN is too large for
    the memory in one piece (:func:`local_slabs`): :func:`.distributed.run_from_files` then.
    Else None (the command loads IN and runs the stage). A single-process run never imports the
    distributed solve (nor, through it, Dask).
    """
    ex = current()
    if not ex.distributed:
        if input == "-" or kw.get("load_kw", {}).get("format"):
            return None
        from recon_cli.io.chunks import plan_chunks

        chunks = plan_chunks(input)
        if any(c.kind == "whole" for c in chunks):
            return None  # rows not known before reading: loaded whole, the solve in slabs
        if local_slabs(sum(c.stop - c.start for c in chunks), ex) == 1:
            return None
    from recon_cli.stages.poisson.distributed import run_from_files as run

    return run(input, output, params, **kw)


def local_slabs(npoints: int, ex: Any) -> int:
    """The slabs of a run in this process: 1 when the memory holds the whole solve.

    ``ex``: the :class:`recon_cli.execution.Execution` (its ``partitions`` or its memory budget).
    Refuses a memory too small for the most slabs (one line with the least that would do).
    """
    if ex.partitions is not None:
        return int(ex.partitions)
    from recon_cli.stages.poisson.distributed import slab_count

    return slab_count(None, npoints, None, ex.budget())[0]


def check_slab_options(
    backend: str,
    degree: int,
    estimate_normals: bool,
    boundary: str,
    envelope: Any,
    grid: Any,
    trim: Any,
    where: str,
) -> None:
    """What a run in slabs does not take (one line each); ``where`` says why it is in slabs."""
    if backend != "native":
        raise ParameterError(f"{where} runs the native solver: leave out --backend")
    if degree != 2:
        raise ParameterError(f"{where} uses degree 2: leave out --degree 1")
    for name, used in (
        ("--boundary free", boundary == "free"),
        ("--envelope", envelope not in (None, "")),
        ("--grid", grid not in (None, "")),
        ("--trim auto", trim == "auto"),
    ):
        if used:
            raise ParameterError(f"{name} is not available {where}")
    if estimate_normals:
        raise ParameterError(f"--estimate-normals {where}: run 'recon normals' first")


def slab_reason(ex: Any) -> str:
    """Why a run is in slabs, for messages."""
    if ex.distributed:
        return "with --workers/--scheduler"
    if ex.partitions is not None:
        return "in slabs (--partitions)"
    return "in slabs (the cloud does not fit the memory in one piece)"


@SPEC.runner
def run_stage(
    data: Any,
    *,
    depth: int,
    scale: float,
    point_weight: float,
    samples_per_node: float,
    degree: int,
    boundary: str,
    confidence: bool,
    density: bool,
    trim: float,
    attributes: Any,
    envelope: Any,
    grid: Any,
    estimate_normals: bool,
    backend: str,
    progress: Any = None,
) -> StageResult:
    """Stage ``poisson``: screened Poisson reconstruction of an oriented cloud.

    Where it runs is the :func:`recon_cli.execution.current` execution's: in slabs on its Dask
    cluster, in slabs in this process (their states spilled to files) when the cloud needs more
    than its memory in one piece, else the single-process solve.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Oriented points (a mesh's vertices and vertex normals are used).
    depth, scale, point_weight, samples_per_node, degree, boundary, confidence, density, trim
        See :func:`screened_poisson`.
    attributes : str or list of str
        ``all`` (every property of the input and its colours), ``none``, or names
        separated by commas (``colors`` for the colours): carried onto the vertices
        (:mod:`.attributes`; with a reference backend, Open3D's colours are its own).
    envelope : path or None
        A closed mesh file (any format recon reads) the surface must lie in
        (:mod:`.envelope`; native only).
    grid : path or None
        Also write the solved field here as a grid file (:mod:`.field`; native only).
    estimate_normals : bool
        Estimate and orient normals first with the ``normals`` stage (its defaults), replacing
        any the input has.
    backend : {"native", "open3d", "pymeshlab"}
        ``open3d``: ``create_from_point_cloud_poisson`` (depth, scale; its densities);
        ``pymeshlab``: ``generate_surface_reconstruction_screened_poisson`` (depth, scale,
        samples per node, point weight). ``density``/``trim`` use Open3D's densities; the
        PyMeshLab backend has none.

    Returns
    -------
    StageResult
        ``output`` a TriangleMesh; ``report`` with ``vertices``, ``faces``, ``depth``,
        ``iso_value``, ``solver_iterations``, ``residual``, ``bubbles_removed``,
        ``islands_removed``, ``folds_removed``, ``trimmed_faces``, ``trimmed_area``, ``backend``
        (the solver keys are None for the reference backends).
    """
    from recon_cli.stages import StageResult

    ex = current()
    grid_path, env = _check_run_options(
        backend, degree, boundary, confidence, density, trim, envelope, grid
    )
    cloud, history, props, keep_colors = _stage_input(data, attributes, estimate_normals, progress)
    solve = {
        "depth": depth,
        "scale": scale,
        "point_weight": point_weight,
        "samples_per_node": samples_per_node,
        "boundary": boundary,
        "density": density,
        "trim": trim,
        "confidence": confidence,
    }
    colors = cloud.colors if keep_colors else None
    slabs = None if ex.distributed or backend != "native" else local_slabs(len(cloud.points), ex)
    if ex.distributed or (slabs or 1) > 1:
        # the cloud is in memory: its normals were estimated above unless the run is on a cluster
        check_slab_options(
            backend,
            degree,
            estimate_normals and ex.distributed,
            boundary,
            envelope,
            grid,
            trim,
            slab_reason(ex),
        )
        mesh, report = _run_distributed(cloud, colors, props, solve, ex, slabs, progress)
    elif backend == "native":
        mesh, report = _run_native(
            cloud, colors, props, solve, degree, env, grid_path, history, progress
        )
    else:
        mesh, report = _run_reference(cloud, keep_colors, props, solve, backend, history)
    mesh.history = history
    mesh.obj_info = list(cloud.obj_info)  # a LAS file's header and coordinate system
    mesh.point_dtype = (
        cloud.point_dtype
    )  # double in, double out (float32 in: see geometry.storage_dtype)
    report["backend"] = backend
    return StageResult(output=mesh, report=report)


def _check_run_options(
    backend: str,
    degree: int,
    boundary: str,
    confidence: bool,
    density: bool,
    trim: float | str,
    envelope: Any,
    grid: Any,
) -> tuple[str | None, Any]:
    """The stage's checks of its options together; returns the grid's path and the envelope."""
    if backend == "pymeshlab" and (density or trim != 0):
        raise ParameterError(
            "the pymeshlab backend gives no densities: --density/--trim need native or open3d"
        )
    # ---- PoissonRecon parity options (free boundary, confidence, grid): the native solver only
    grid_path = None if grid in (None, "") else os.fspath(grid)
    if backend != "native":
        for name, used in (
            ("--boundary free", boundary == "free"),
            ("--confidence", confidence),
            ("--grid", grid_path is not None),
            ("--envelope", envelope not in (None, "")),
        ):
            if used:
                raise ParameterError(f"{name} needs the native backend")
    if grid_path is not None:
        from recon_cli.io.atomic import check_output

        if grid_path == "-":
            raise ParameterError("--grid needs a file name ('-' is the mesh's standard output)")
        check_output(grid_path)
    env = None
    if envelope not in (None, ""):
        if degree != 2:
            raise ParameterError("--envelope needs --degree 2")
        from recon_cli.stages.poisson.envelope import load_envelope

        env = load_envelope(envelope)
    return grid_path, env


def _stage_input(
    data: Any, attributes: Any, estimate_normals: bool, progress: Any
) -> tuple[PointCloud, list[str], dict[str, np.ndarray], bool]:
    """The oriented cloud, its history, the properties carried and whether colours are."""
    cloud = as_point_cloud(data)
    from recon_cli.stages.poisson.attributes import select

    prop_names, keep_colors = select(attributes, list(cloud.attributes), cloud.colors is not None)
    props = {k: cloud.attributes[k] for k in prop_names}
    history = list(cloud.history)
    if estimate_normals:
        try:
            from recon_cli.stages import normals as normals_mod
        except ModuleNotFoundError:
            raise ParameterError(
                "--estimate-normals needs the normals stage, which is not available"
            ) from None
        est = normals_mod.run_stage(PointCloud(points=cloud.points), progress=progress)
        cloud = cloud.copy()
        cloud.normals = est.output.normals
    if cloud.normals is None:
        raise InputError(
            "the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)"
        )
    return cloud, history, props, keep_colors


def _run_distributed(
    cloud: PointCloud,
    colors: np.ndarray | None,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    ex: Any,
    slabs: int | None,
    progress: Any,
) -> tuple[TriangleMesh, dict]:
    """The cloud in slabs (:mod:`.distributed`): on ``ex``'s Dask cluster, or in this process.

    ``slabs``: their number in this process (None on a cluster: its workers' memory decides,
    or ``ex.partitions``). Returns the mesh and the report.
    """
    import contextlib

    from recon_cli.stages.poisson.distributed import distributed_poisson

    assert cloud.normals is not None  # _stage_input refuses a cloud without
    if ex.distributed:
        from recon_cli.batch.cluster import open_client

        opened: Any = open_client(ex.scheduler, ex.workers, ex.worker_memory(), stealing=False)
    else:
        opened = contextlib.nullcontext((None, {"workers": 0, "memory": ex.budget()}))
    with opened as (client, info):
        res = distributed_poisson(
            cloud.points,
            cloud.normals,
            partitions=slabs if slabs is not None else ex.partitions,
            **solve,
            colors=colors,
            properties=props,
            client=client,
            temp_dir=ex.spill_parent(),
            progress=progress,
        )
    rep = res.report
    report = {k: rep[k] for k in REPORT_KEYS}
    report["distributed"] = {"cluster": info, **rep["distributed"]}
    return res.mesh, report


def _run_native(
    cloud: PointCloud,
    colors: np.ndarray | None,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    degree: int,
    env: Any,
    grid_path: str | None,
    history: list[str],
    progress: Any,
) -> tuple[TriangleMesh, dict]:
    """:func:`screened_poisson` on the cloud, the grid written; returns the mesh and report."""
    assert cloud.normals is not None  # _stage_input refuses a cloud without
    res = screened_poisson(
        cloud.points,
        cloud.normals,
        **solve,
        degree=degree,
        colors=colors,
        properties=props,
        with_grid=grid_path is not None,
        envelope=env,
        progress=progress,
    )
    rep = res.report
    report = {k: rep[k] for k in REPORT_KEYS}
    if env is not None:
        report["envelope_outside_points"] = rep["envelope_outside_points"]
        report["envelope_pulled_vertices"] = rep["envelope_pulled_vertices"]
    if grid_path is not None:
        if res.grid is None:
            raise StageFailed("--grid: the surface is empty; no field to write")
        from recon_cli.io.npz import write_grid

        line = (
            f"poisson: (iso - chi) / |grad chi| on the finest lattice, depth {solve['depth']}, "
            f"boundary {solve['boundary']}, iso {rep['iso_value']:.9g}"
        )
        res.grid.history = [*history, line]
        res.grid.point_dtype = cloud.point_dtype
        write_grid(res.grid, grid_path)
        report["grid"] = grid_path
        report["grid_shape"] = rep["grid_shape"]
    return res.mesh, report


def _run_reference(
    cloud: PointCloud,
    keep_colors: bool,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    backend: str,
    history: list[str],
) -> tuple[TriangleMesh, dict]:
    """A reference library's Poisson, then our trim and attributes; returns the mesh, report."""
    depth, scale, trim = solve["depth"], solve["scale"], solve["trim"]
    pts, nrm, keep = _check_inputs(cloud.points, cloud.normals)
    # the references about a local origin (Open3D's Poisson loses digits at UTM offsets)
    centre = local_origin(pts)
    clean = PointCloud(
        points=pts - centre,
        normals=nrm,
        colors=None if cloud.colors is None or not keep_colors else cloud.colors[keep],
        history=history,
    )
    from recon_cli.backends import backend_module

    mod = backend_module(backend)
    if backend == "open3d":
        mesh, dens = mod.poisson(clean, depth=depth, scale=scale)
    else:
        mesh, dens = (
            mod.poisson(
                clean,
                depth=depth,
                scale=scale,
                samples_per_node=solve["samples_per_node"],
                point_weight=solve["point_weight"],
            ),
            None,
        )
    mesh.vertices = mesh.vertices + centre
    trimmed, trimmed_area = 0, 0.0
    if trim == "auto" and len(mesh.faces):
        from recon_cli.stages.poisson.trim import merge_per_cell, trim_auto

        cell = float((pts.max(axis=0) - pts.min(axis=0)).max()) * scale / (1 << depth)
        cut = trim_auto(mesh, merge_per_cell(pts, cell), carry=dens)
        if len(cut.mesh.faces) == 0:
            raise InputError("trim auto removes the whole surface: no part lies near the samples")
        trimmed = len(mesh.faces) - cut.untouched_faces
        mesh, dens, trimmed_area = cut.mesh, cut.carried, cut.removed_area
    elif trim != "auto" and trim > 0 and len(mesh.faces):
        from scipy.spatial import cKDTree

        from recon_cli.stages.poisson.trim import trim_by_density

        # the density at the samples: Open3D's at the vertex nearest each sample
        at_samples = dens[cKDTree(mesh.vertices).query(pts, workers=-1)[1]]
        cut = trim_by_density(mesh, dens, trim * float(np.median(at_samples)))
        if len(cut.mesh.faces) == 0:
            raise ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value")
        trimmed = len(mesh.faces) - cut.untouched_faces
        mesh, dens, trimmed_area = cut.mesh, cut.density, cut.removed_area
    fallback = 0
    if props and len(mesh.faces):
        from recon_cli.stages.poisson.attributes import transfer

        e = mesh.vertices[mesh.faces[:, [0, 1]]]
        sigma = float(np.median(np.linalg.norm(e[:, 0] - e[:, 1], axis=1)))
        kept = {k: v[keep] for k, v in props.items()}
        moved = transfer(pts, nrm, kept, None, mesh.vertices, mesh.faces, sigma)
        mesh.attributes.update(moved.values)
        fallback = moved.fallback
    if solve["density"] and dens is not None:
        mesh.attributes["density"] = dens
    report = {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "depth": depth,
        "iso_value": None,
        "solver_iterations": None,
        "residual": None,
        "bubbles_removed": None,
        "islands_removed": None,
        "folds_removed": None,
        "trimmed_faces": int(trimmed),
        "trimmed_area": trimmed_area,
        "noise": None,
        "attributes": sorted(props) + (["colors"] if mesh.colors is not None else []),
        "attribute_fallback_vertices": fallback,
    }
    return mesh, report


# public names of the pieces the distributed solve (.distributed, .slab) shares
check_inputs = _check_inputs
kept_attributes = _kept_attributes
check_options = _check_options
