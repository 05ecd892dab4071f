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

import inspect
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import TriangleMesh, oriented_rows
from recon_cli.params import Param, StageSpec

if TYPE_CHECKING:
    from recon_cli.grid import Grid

BOUNDARIES = ("neumann", "dirichlet", "free")
BACKENDS = ("native", "open3d", "pymeshlab")
MAX_DEPTH = 14
# closed pieces of the extraction smaller than this many finest cells on every side are specks
# of noise, not surface (steps.drop_bubbles)
BUBBLE_CELLS = 2
# a closed piece (not the largest) with fewer input points than this within BUBBLE_CELLS
# finest cells of its box is an island around outliers, not a surface (steps.drop_bubbles)
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
    """The size, in finest cells, under which a closed piece is a speck (steps.drop_bubbles).

    :data:`BUBBLE_CELLS`, or :data:`SPECK_SIGMAS` times the samples' median ``noise`` (finest
    cells; None: not measured) when that is larger.
    """
    if noise is None or not np.isfinite(noise):
        return float(BUBBLE_CELLS)
    return max(float(BUBBLE_CELLS), SPECK_SIGMAS * float(noise))


def fold_cells(noise: float | None) -> tuple[float, float] | None:
    """The folds' sizes in finest cells: (largest span, farthest reach), None without ``noise``.

    :data:`FOLD_SPAN_SIGMAS` and :data:`FOLD_SIGMAS` times the samples' median noise (finest
    cells), as :func:`steps.drop_bubbles` and the slabs' merge use them.
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
        cells or eight times the noise across, dropped: :func:`steps.drop_bubbles`),
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
SPEC: StageSpec = StageSpec(
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
    from_files="recon_cli.stages.poisson.stage:run_from_files",
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


@dataclass(frozen=True)
class PoissonOptions:
    """The algorithm's parameters of one reconstruction, checked and converted when made.

    The fields are :func:`screened_poisson`'s keywords (see there); a run in slabs takes the
    same (:func:`.distributed.distributed_poisson`, degree 2 only). A wrong value raises
    :class:`~recon_cli.errors.ParameterError` naming the option.
    """

    depth: int = SPEC.param("depth").default
    scale: float = SPEC.param("scale").default
    point_weight: float = SPEC.param("point_weight").default
    samples_per_node: float = SPEC.param("samples_per_node").default
    degree: int = SPEC.param("degree").default
    boundary: str = SPEC.param("boundary").default
    density: bool = SPEC.param("density").default
    trim: float | str = SPEC.param("trim").default
    confidence: bool = SPEC.param("confidence").default
    with_grid: bool = False
    full_depth: int = _FULL_DEPTH.default
    cg_tolerance: float = _CG_TOLERANCE.default

    def __post_init__(self) -> None:
        own = {f.name for f in fields(self)}
        names = [p.name for p in SPEC.params if p.name in own]  # those the stage declares
        checked = SPEC.check({k: getattr(self, k) for k in names}, complete=False)
        checked["full_depth"] = _FULL_DEPTH.coerce(self.full_depth)
        checked["cg_tolerance"] = _CG_TOLERANCE.coerce(self.cg_tolerance)
        checked["with_grid"] = bool(self.with_grid)
        for k, v in checked.items():
            object.__setattr__(self, k, v)  # frozen: set once, here
        if self.boundary == "free" and self.degree != 2:
            raise ParameterError("--boundary free needs --degree 2")

    @classmethod
    def of(cls, caller: str, values: dict[str, Any]) -> PoissonOptions:
        """The options named in ``values``, the rest their defaults; ``caller`` for errors.

        An unknown name raises TypeError, as Python does for an unexpected keyword.
        """
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"{caller}() got an unexpected keyword argument {unknown[0]!r}")
        return cls(**values)


def takes_options(fn: Any) -> Any:
    """Show ``fn``'s ``**options`` as :class:`PoissonOptions`' keywords in its signature.

    ``help()``, the API reference and editors then list them with their defaults.
    """
    sig = inspect.signature(fn)
    own = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    extra = [
        inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default)
        for f in fields(PoissonOptions)
    ]
    fn.__signature__ = sig.replace(parameters=own + extra)
    return fn


def check_inputs(
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
@takes_options
def screened_poisson(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    properties: dict[str, np.ndarray] | None = None,
    envelope: Any = None,
    progress: Any = None,
    **options: Any,
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
        cells (support 3 cells per axis, :mod:`.bspline`), the more accurate on smooth
        surfaces; 1, trilinear hat functions on the nodes (as Open3D's Poisson), faster
        (``make bench`` compares them).
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
    opts = PoissonOptions.of("screened_poisson", options)
    if envelope is not None:
        if opts.degree != 2:
            raise ParameterError("--envelope needs --degree 2")
        envelope = checked_envelope(envelope)
    lengths: list = []
    pts, nrm, keep = check_inputs(points, normals, lengths)
    weight = lengths[0] / float(lengths[0].mean()) if opts.confidence else None
    del lengths
    colors, props = kept_attributes(keep, colors, properties)
    from recon_cli.stages.poisson.steps import reconstruct

    return reconstruct(pts, nrm, weight, keep, colors, props, envelope, opts, progress)


def kept_attributes(
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


def checked_envelope(envelope: Any) -> Any:
    """``envelope`` as an :class:`.envelope.Envelope` (a closed mesh, checked)."""
    from recon_cli.stages.poisson.envelope import Envelope

    return envelope if isinstance(envelope, Envelope) else Envelope(envelope)


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
# and with --envelope
ENVELOPE_KEYS = ("envelope_outside_points", "envelope_pulled_vertices")


def command_report(rep: dict, envelope: bool) -> dict:
    """The entries of a run's report ``rep`` the command reports (with ``envelope``: its too)."""
    return {k: rep[k] for k in REPORT_KEYS + (ENVELOPE_KEYS if envelope else ())}


# the stage's runner (CLI, pipelines) registers itself on SPEC; it needs SPEC defined first
from recon_cli.stages.poisson.stage import run_stage  # noqa: E402, F401
