"""``recon filter``: clean and thin a point cloud before reconstruction.

The operations run in a fixed order, each on what the one before kept, and the report
counts the points each removed:

0. **levels** ``--level N`` or ``--resolution R`` (a COPC file only, as it is read): the
   octree levels 0 to N, or down to the first whose point spacing is at most R (a coarser
   cloud over the whole area). With them or ``--crop``, a COPC file (``.copc.laz``) decodes
   only the octree nodes the box and levels need (:mod:`recon_cli.io.copc`): the same points
   as reading it whole and cropping;
1. **invalid**: points with a NaN or infinite coordinate (always; normals may be NaN). The
   readers drop them already (``recon filter``'s report shows that count under ``read``):
   this step is for arrays given from Python;
2. **crop** ``x0,y0,z0,x1,y1,z1``: points outside the axis-aligned box (its faces included
   in it, as Open3D's ``crop``);
3. **classes** ``2,6`` or ``ground,building``: points of other LAS classes (attribute
   ``classification``, ASPRS codes);
4. **returns** ``first | last | single | intermediate``: LAS returns by ``return_number``
   and ``number_of_returns`` (first: return 1; last: return number = number of returns;
   single: one return; intermediate: neither first nor last);
5. **radius outliers** ``R,N``: points with at most ``N`` points (themselves included) at a
   distance below ``R``, i.e. fewer than ``N`` others: Open3D's
   ``remove_radius_outlier(N, R)``;
6. **statistical outliers** ``K,STD``: each point's mean distance to its ``K`` nearest
   points (itself, at distance 0, among them when ``K`` counts it, as Open3D's kNN search
   returns it), then the mean ``m`` and the Bessel-corrected standard deviation ``s`` of
   those means; a point is kept when its mean is positive and below ``m + STD * s``:
   Open3D's ``remove_statistical_outlier(K, STD)`` exactly (its sums in point order; a
   point whose ``K`` nearest all coincide with it has mean 0 and is dropped, as there);
7. **voxel** ``S``: one point per cell of a grid of edge ``S`` anchored, as Open3D's
   ``voxel_down_sample``, at the minimum corner of the points minus ``S/2`` (cell
   ``floor((p - (min - S/2)) / S)``): the centroid of the cell's points, normals averaged
   and made unit length (NaN normals left out), colours averaged (rounded in their integer
   type), float attributes averaged, integer measurements (:data:`MEASURES`: intensity,
   amplitude...) averaged and rounded, every other integer or boolean attribute (classes,
   return numbers, point source ids: codes) by majority, ties to the smallest value. Cells
   are output in the order of their first point.

Selection comes before the neighbourhood rules (outliers are judged among the points that
will be kept: the ground alone, inside the box), outliers before thinning (a centroid
would carry them in). Another order is another ``filter`` step in a pipeline.

Every kept point keeps all its attributes and the coordinates' precision (a subset is
exact); a filter that keeps no point is an error, not an empty file.

References
----------
Rusu, Marton, Blodow, Dolha & Beetz, "Towards 3D point cloud based object maps for
household environments", Robotics and Autonomous Systems 56(11), 2008 (statistical outlier
removal); Zhou, Park & Koltun, "Open3D: a modern library for 3D data processing",
arXiv:1801.09847, 2018 (the rules followed); ASPRS, "LAS specification 1.4 R15", 2019
(classes and returns).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.io.hint import ReadHint, levels_mark, levels_read
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult

RETURNS = ("all", "first", "last", "single", "intermediate")

#: ASPRS standard point classes (LAS 1.4 R15, table 17): name -> code
CLASS_NAMES: dict[str, int] = {
    "never-classified": 0,
    "unclassified": 1,
    "ground": 2,
    "low-vegetation": 3,
    "medium-vegetation": 4,
    "high-vegetation": 5,
    "building": 6,
    "low-point": 7,
    "noise": 7,
    "water": 9,
    "rail": 10,
    "road-surface": 11,
    "wire-guard": 13,
    "wire-conductor": 14,
    "transmission-tower": 15,
    "wire-connector": 16,
    "bridge-deck": 17,
    "high-noise": 18,
}

#: integer attributes that measure something (averaged and rounded by ``voxel``); every
#: other integer attribute is a code (taken by majority)
MEASURES = frozenset(
    {"intensity", "amplitude", "reflectance", "deviation", "scan_angle", "scan_angle_rank"}
    | {"red", "green", "blue", "nir", "alpha", "range"}
)

# attribute names as LAS readers (laspy) and CloudCompare's PLY export spell them
_CLASS_ATTRS = ("classification", "scalar_classification")
_RETURN_ATTRS = ("return_number", "scalar_return_number")
_NRETURNS_ATTRS = ("number_of_returns", "scalar_number_of_returns")

# rows per chunk of the row-wise tests (a float64 buffer that stays in cache)
_ROWS = 1 << 14
# the kernel box_codes' codes of a row: kept, a NaN or infinite coordinate, outside the box
_KEPT, _INVALID, _OUTSIDE = 0, 1, 2
# the box of no crop: every finite point is inside
_NO_BOX = (-math.inf, -math.inf, -math.inf, math.inf, math.inf, math.inf)
# kNN rows per query (bounds the distance matrix held at once)
_CHUNK = 200_000
# at most this many cells along an axis (Open3D's limit: its cell indices are C ints)
_MAX_CELLS = 2**31 - 1
# the radius grid's cells are this much wider than R: no neighbour is lost to rounding
_CELL_MARGIN = 1.0 + 1e-9


# ---- parameter rules -----------------------------------------------------------------------------
def _one_level_rule(level: Any, resolution: Any) -> None:
    if level is not None and resolution is not None:
        raise ParameterError("--level and --resolution exclude each other: give one")


def _crop_box(v: tuple) -> tuple:
    if len(v) != 6 or any(v[i] > v[i + 3] for i in range(3)):
        raise ValueError("six numbers x0,y0,z0,x1,y1,z1 with x0 <= x1, y0 <= y1, z0 <= z1")
    return tuple(v)


def _radius_rule(v: tuple) -> tuple:
    if len(v) != 2 or not v[0] > 0 or not (float(v[1]).is_integer() and v[1] >= 1):
        raise ValueError("R,N: a radius R > 0 and an integer N >= 1")
    return (v[0], int(v[1]))


def _outlier_rule(v: tuple) -> tuple:
    if len(v) != 2 or not (float(v[0]).is_integer() and v[0] >= 1) or not v[1] > 0:
        raise ValueError("K,STD: an integer K >= 1 and a ratio STD > 0")
    return (int(v[0]), v[1])


def _class_codes(v: Any) -> tuple:
    """Class codes (0-255) or ASPRS names, one or a list or comma-separated text -> sorted codes."""
    items = v.split(",") if isinstance(v, str) else list(v) if isinstance(v, (list, tuple)) else [v]
    codes = set()
    for x in items:
        if isinstance(x, str):
            word = x.strip().lower().replace("_", "-").replace(" ", "-")
            if word.isdigit():
                x = int(word)
            elif word in CLASS_NAMES:
                x = CLASS_NAMES[word]
            else:
                raise ValueError(
                    f"class codes 0-255 or names ({', '.join(CLASS_NAMES)}); "
                    f"{x.strip()!r} is neither"
                )
        if isinstance(x, bool) or not (
            isinstance(x, (int, np.integer)) or (isinstance(x, float) and x.is_integer())
        ):
            raise ValueError("class codes 0-255 or names (ground, building, ...)")
        if not 0 <= int(x) <= 255:
            raise ValueError(f"class codes 0-255 or names; {int(x)} is not a LAS class")
        codes.add(int(x))
    if not codes:
        raise ValueError("at least one class code or name")
    return tuple(sorted(codes))


# the command's work is smaller than numba's start-up: its kernels are built ahead of time
AOT = True

SPEC = StageSpec(
    name="filter",
    summary="Drop invalid points, crop, select LAS classes, remove outliers, thin.",
    description="""Drop invalid points, crop, select LAS classes and returns, remove outliers, thin.

    Operations in this order, each counted in the report: invalid points (NaN/inf, always),
    --crop, --classes, --returns, --radius-outliers, --outliers, --voxel. Kept points keep
    every attribute; outlier rules and voxel cells are Open3D's. A COPC file (.copc.laz) is
    read in part: only the octree nodes that --crop and --level/--resolution need.""",
    takes=("cloud",),
    gives=("cloud",),
    keeps=("oriented",),
    read_hint="recon_cli.stages.filter:read_hint",
    params=(
        Param(
            "crop",
            "floats",
            None,
            "Keep the points inside this box (faces included); a COPC input decodes only the "
            "octree nodes that meet it.",
            unit="input units",
            metavar="X0,Y0,Z0,X1,Y1,Z1",
            allowed="x0 <= x1, y0 <= y1, z0 <= z1",
            validate=_crop_box,
        ),
        Param(
            "level",
            "int",
            None,
            "COPC input only: read the octree levels 0 to N (level 0: the root's points; a "
            "coarser cloud over the whole area).",
            min=0,
            max=30,
            metavar="N",
        ),
        Param(
            "resolution",
            "float",
            None,
            "COPC input only: read the octree levels down to the first whose point spacing is "
            "at most this.",
            unit="input units",
            min=0,
            min_open=True,
        ),
        Param(
            "classes",
            "any",
            None,
            "Keep the points of these LAS classes: codes 0-255 or ASPRS names (ground, "
            "building, low-vegetation, ...), comma-separated.",
            metavar="C,...",
            allowed="codes 0-255 or ASPRS class names",
            validate=_class_codes,
        ),
        Param(
            "returns",
            "choice",
            "all",
            "Keep these LAS returns: first (return 1), last (return number = number of "
            "returns), single (the only return), intermediate, or all.",
            choices=RETURNS,
        ),
        Param(
            "radius_outliers",
            "floats",
            None,
            "R,N: drop the points with fewer than N other points closer than R (Open3D's "
            "remove_radius_outlier(N, R)).",
            unit="R input units, N points",
            metavar="R,N",
            allowed="R > 0, integer N >= 1",
            validate=_radius_rule,
        ),
        Param(
            "outliers",
            "floats",
            None,
            "K,STD: drop the points whose mean distance to their K nearest points (itself "
            "included) is not below the mean of all plus STD standard deviations (Open3D's "
            "remove_statistical_outlier(K, STD)).",
            unit="K points, STD standard deviations",
            metavar="K,STD",
            allowed="integer K >= 1, STD > 0",
            validate=_outlier_rule,
        ),
        Param(
            "voxel",
            "float",
            None,
            "One point per cell of this edge: the centroid, attributes averaged, codes by "
            "majority.",
            unit="input units",
            min=0,
            min_open=True,
        ),
    ),
)


# ---- the operations ------------------------------------------------------------------------------
def _points(points: Any) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    return pts if pts.flags.writeable else pts.copy()  # the kernels' compiled variants write


def _rowwise(points: Any, kernel: Any, *args: Any, dtype: Any = bool) -> np.ndarray:
    """``kernel(rows, *args)`` (a ``dtype`` value per row) over ``points`` (n, 3) of any float type.

    Native float32 and float64 rows, contiguous or a binary PLY's strided view of its records,
    are read in place (the layouts the warm-up compiles); any other rows go a chunk at a time
    through one float64 buffer, as a contiguous float64 copy of a million costs more than the
    test.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    n = len(pts)
    if (
        pts.dtype in (np.float32, np.float64)
        and pts.flags.writeable
        and (pts.flags.c_contiguous or (pts.strides[0] > 0 and pts.strides[1] == pts.itemsize))
    ):
        return kernel(pts, *args)
    out = np.empty(n, dtype=dtype)
    buf = np.empty((min(n, _ROWS), 3))
    for a in range(0, n, _ROWS):
        rows = buf[: min(_ROWS, n - a)]
        rows[...] = pts[a : a + _ROWS]
        out[a : a + len(rows)] = kernel(rows, *args)
    return out


def _finite(points: Any) -> np.ndarray:
    """``points`` (n, 3) float64, checked finite (the neighbourhood rules take no NaN)."""
    pts = _points(points)
    if not _kernels().finite_rows(pts).all():
        raise InputError("points have NaN or infinite coordinates: drop them first (filter does)")
    return pts


def crop_mask(points: Any, box: Any) -> np.ndarray:
    """Which points lie inside an axis-aligned box, its faces included (Open3D's ``crop``).

    A point with a NaN or infinite coordinate is not inside.

    Parameters
    ----------
    points : (n, 3) array_like of float
    box : six numbers ``x0, y0, z0, x1, y1, z1``
        Minimum and maximum corners, in the units of ``points``.

    Returns
    -------
    (n,) bool

    Raises
    ------
    ParameterError
        Not six numbers, or a minimum above its maximum.
    """
    lo_hi = SPEC.param("crop").coerce(box)
    return box_codes(points, lo_hi) == _KEPT


def box_codes(points: Any, box: Any = None) -> np.ndarray:
    """Each point's fate under the invalid-point rule and a crop, in one pass over the points.

    Parameters
    ----------
    points : (n, 3) array_like of float
    box : six numbers ``x0, y0, z0, x1, y1, z1``, or None
        Minimum and maximum corners, in the units of ``points`` (faces inside); None: no crop.

    Returns
    -------
    (n,) uint8
        0: kept (finite, inside the box); 1: a NaN or infinite coordinate; 2: finite, outside
        the box.

    Raises
    ------
    ParameterError
        ``box`` not six numbers, or a minimum above its maximum.
    """
    lo_hi = _NO_BOX if box is None else SPEC.param("crop").coerce(box)
    return _rowwise(points, _kernels().box_codes, np.array(lo_hi, dtype=np.float64), dtype=np.uint8)


def find_attribute(cloud: PointCloud, names: tuple[str, ...]) -> str | None:
    """The name of the first attribute of ``cloud`` called one of ``names`` (any case)."""
    lower = {k.lower(): k for k in cloud.attributes}
    return next((lower[n] for n in names if n in lower), None)


def class_mask(classification: Any, classes: Any) -> np.ndarray:
    """Which points belong to one of ``classes``.

    Parameters
    ----------
    classification : (n,) array_like of int
        LAS class codes (ASPRS, LAS 1.4 R15 table 17).
    classes : int, str or sequence
        Codes 0-255 or names of :data:`CLASS_NAMES` (``"2,6"``, ``["ground", 6]``).

    Returns
    -------
    (n,) bool
    """
    codes = SPEC.param("classes").coerce(classes)
    return np.isin(np.asarray(classification), np.asarray(codes))


def return_mask(return_number: Any, number_of_returns: Any, returns: str) -> np.ndarray:
    """Which points are the ``returns`` asked for.

    Parameters
    ----------
    return_number, number_of_returns : (n,) array_like of int
        The LAS fields (1-based return number; returns of the pulse).
    returns : {"all", "first", "last", "single", "intermediate"}
        first: return 1; last: return number equal to the number of returns; single: one
        return; intermediate: after the first and before the last.

    Returns
    -------
    (n,) bool
    """
    which = SPEC.param("returns").coerce(returns)
    r = np.asarray(return_number)
    nr = np.asarray(number_of_returns)
    if which == "first":
        return r == 1
    if which == "last":
        return r == nr
    if which == "single":
        return nr == 1
    if which == "intermediate":
        return (r > 1) & (r < nr)
    return np.ones(len(r), dtype=bool)


def radius_outlier_mask(points: Any, radius: float, min_neighbours: int) -> np.ndarray:
    """Open3D's ``remove_radius_outlier(min_neighbours, radius)``: the points to keep.

    A point is kept when more than ``min_neighbours`` points, itself included, lie at a
    distance strictly below ``radius`` (so at least ``min_neighbours`` others). Candidates
    come from a grid of cells of edge ``radius`` (the 27 around a point's cell); a point's
    count stops once it is decided.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Finite coordinates.
    radius : float
        R > 0, in the units of ``points``.
    min_neighbours : int
        N >= 1.

    Returns
    -------
    (n,) bool

    References
    ----------
    Zhou, Park & Koltun, "Open3D", arXiv:1801.09847, 2018 (``RemoveRadiusOutliers``).
    """
    radius, n_min = SPEC.param("radius_outliers").coerce((radius, min_neighbours))
    pts = _finite(points)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    size = radius * _CELL_MARGIN
    lo, hi = _kernels().bounds(pts)
    if float((hi - lo).max()) / size > _MAX_CELLS:
        raise ParameterError(
            f"--radius-outliers radius {radius:g} is too small for the extent of the points "
            f"(more than {_MAX_CELLS} cells along an axis)"
        )
    return _kernels().radius_keep(pts, size, float(radius), np.int64(n_min))


def mean_neighbour_distances(points: Any, k: int, progress: Any = None) -> np.ndarray:
    """Each point's mean distance to its ``k`` nearest points (itself included, at 0).

    The kNN search runs in the kd-tree's leaf order (cache friendly) in chunks; distances
    are differences of float64 coordinates, as precise far from the origin as near it.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Finite coordinates.
    k : int
        Neighbours, the point itself included (fewer when ``n < k``).
    progress : Progress, optional
        A bar over the points.

    Returns
    -------
    (n,) float64
    """
    from scipy.spatial import cKDTree

    pts = _finite(points)
    n = len(pts)
    k = min(int(k), n)
    out = np.empty(n)
    with task(progress, "statistical outliers", total=n) as bar:
        tree = cKDTree(pts)
        order = np.asarray(tree.indices, dtype=np.int64)
        ps = pts[order]
        for a in range(0, n, _CHUNK):
            d, _ = tree.query(ps[a : a + _CHUNK], k, workers=-1)
            out[order[a : a + _CHUNK]] = _kernels().row_means(np.asarray(d).reshape(-1, k))
            bar.advance(min(_CHUNK, n - a))
    return out


def statistical_outlier_mask(
    points: Any, k: int, std_ratio: float, progress: Any = None
) -> tuple[np.ndarray, dict[str, float]]:
    """Open3D's ``remove_statistical_outlier(k, std_ratio)``: the points to keep.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Finite coordinates.
    k : int
        Neighbours (the point itself included, as Open3D's kNN search counts it), >= 1.
    std_ratio : float
        Standard deviations above the mean of the mean distances, > 0.
    progress : Progress, optional
        A bar over the points' kNN searches.

    Returns
    -------
    keep : (n,) bool
        Mean distance positive and below ``mean + std_ratio * std``.
    figures : dict
        ``mean``, ``std`` and ``threshold`` of the mean distances (input units).

    References
    ----------
    Rusu et al., "Towards 3D point cloud based object maps for household environments",
    2008; Zhou, Park & Koltun, "Open3D", 2018 (``RemoveStatisticalOutliers``).
    """
    k, std_ratio = SPEC.param("outliers").coerce((k, std_ratio))
    pts = _finite(points)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool), {"mean": 0.0, "std": 0.0, "threshold": 0.0}
    mean_dist = mean_neighbour_distances(pts, k, progress)
    keep, mean, std = _kernels().statistical_keep(mean_dist, std_ratio)
    return keep, {"mean": mean, "std": std, "threshold": mean + std_ratio * std}


def voxel_cells(points: Any, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The voxel cell of every point, as Open3D's ``voxel_down_sample`` numbers them.

    Cells have edge ``size`` and are anchored at ``min - size / 2`` (the points' minimum
    corner): cell ``floor((p - (min - size/2)) / size)`` computed in that order in float64,
    so a point lands in Open3D's cell.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Finite coordinates.
    size : float
        Cell edge (> 0), in the units of ``points``.

    Returns
    -------
    cell : (n,) int64
        Cell of each point, cells numbered in the order of their first point.
    first : (m,) int64
        The first point of each cell.
    count : (m,) int64
        Points per cell.
    centroid : (m, 3) float64
        The mean of each cell's points (summed about the centre of their bounding box).

    Raises
    ------
    ParameterError
        ``size`` <= 0, or more than 2**31 - 1 cells along an axis (Open3D's limit).
    """
    size = SPEC.param("voxel").coerce(size)
    pts = _finite(points)
    if len(pts) == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, np.zeros((0, 3))
    cell, first, count, centroid, along = _kernels().voxel_grid(pts, float(size))
    if along > _MAX_CELLS:
        raise ParameterError(
            f"--voxel {size:g} is too small for the extent of the points "
            f"({along:.3g} cells along an axis, at most {_MAX_CELLS})"
        )
    return cell, first, count, centroid


def voxel_downsample(cloud: PointCloud, size: float) -> PointCloud:
    """One point per voxel cell (:func:`voxel_cells`), every per-point value merged.

    Coordinates: the centroid (summed about the points' local origin, so far from the world
    origin too). Normals: the mean of the finite ones, unit length (a zero mean stays zero).
    Colours: the mean, rounded when their type is an integer. Attributes: floats averaged,
    integer :data:`MEASURES` averaged and rounded, other integers and booleans by majority
    (ties to the smallest value). Any other per-point field is the cell's first point's.

    Parameters
    ----------
    cloud : PointCloud
        Finite coordinates.
    size : float
        Cell edge (> 0), in the units of the points.

    Returns
    -------
    PointCloud
        The cells in the order of their first point; the source's precision kept.

    References
    ----------
    Zhou, Park & Koltun, "Open3D", arXiv:1801.09847, 2018 (``VoxelDownSample``).
    """
    K = _kernels()
    cell, first, count, centroid = voxel_cells(cloud.points, size)

    def mean(values: np.ndarray, skip_nan_rows: bool = False) -> np.ndarray:
        rows = np.ascontiguousarray(values, dtype=np.float64).reshape(len(cell), -1)
        return K.cell_means(cell, count, rows, skip_nan_rows)

    # the cloud's metadata; every per-point array is merged below (a centroid is no pixel)
    out = dataclasses.replace(
        cloud,
        points=centroid,
        normals=None,
        colors=None,
        attributes={},
        history=list(cloud.history),
        extra_elements=[],
        obj_info=list(cloud.obj_info),
        sensors=list(cloud.sensors),
        pixels=None,
    )
    if cloud.normals is not None:
        avg = mean(cloud.normals, skip_nan_rows=True)  # Open3D leaves NaN normals out
        length = np.sqrt(np.einsum("ij,ij->i", avg, avg))[:, None]
        np.divide(avg, length, out=avg, where=length > 0)
        out.normals = avg.astype(cloud.normals.dtype, copy=False)
    if cloud.colors is not None:
        out.colors = _averaged(mean(cloud.colors), cloud.colors.dtype)
    for name, values in cloud.attributes.items():
        v = np.asarray(values)
        if v.dtype.kind == "f" or (v.dtype.kind in "iu" and _bare(name) in MEASURES):
            out.attributes[name] = _averaged(mean(v)[:, 0], v.dtype)
        elif v.dtype.kind in "iub":
            modes = K.cell_modes(cell, count, np.ascontiguousarray(v, dtype=np.int64))
            out.attributes[name] = modes.astype(v.dtype)
        else:  # any other kind (strings, records): the first point's
            out.attributes[name] = v[first]
    return out


def _kernels() -> Any:
    """The stage's kernels: built ahead of time when ``recon warmup`` made them (no numba)."""
    from recon_cli.aot import kernels

    return kernels("recon_cli.stages.filter._kernel")


def _bare(name: str) -> str:
    low = name.lower()
    return low.removeprefix("scalar_")


def _averaged(mean: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """A mean in the type of its values: rounded to the nearest integer for integer types."""
    if np.dtype(dtype).kind in "iu":
        return np.rint(mean).astype(dtype)
    return mean.astype(dtype)


# ---- the stage -----------------------------------------------------------------------------------
def read_hint(params: dict[str, Any]) -> ReadHint | None:
    """The part of its input file ``filter`` keeps: the ``crop`` box and the octree levels.

    Parameters
    ----------
    params : dict
        The stage's checked parameters (``crop``, ``level``, ``resolution`` read).

    Returns
    -------
    ReadHint or None
        None when none of the three is given (the whole file is kept).

    Raises
    ------
    ParameterError
        Both ``level`` and ``resolution``.
    """
    crop, level, resolution = params.get("crop"), params.get("level"), params.get("resolution")
    _one_level_rule(level, resolution)
    given = (("crop", crop), ("level", level), ("resolution", resolution))
    asked = " ".join(f"--{n} {_text(v)}" for n, v in given if v is not None)
    if not asked:
        return None
    box = None if crop is None else tuple(float(v) for v in crop)
    return ReadHint(box=box, level=level, resolution=resolution, asked=asked)


def _check_levels(cloud: PointCloud, level: int | None, resolution: float | None) -> None:
    """Refuse levels the cloud was not read with (the reader chooses them; a cloud has none)."""
    _one_level_rule(level, resolution)
    want = levels_mark(level, resolution)
    if want is None:
        return
    have = levels_read(cloud.obj_info)
    if have is None:
        raise InputError(
            f"--{want} chooses the octree levels of a COPC file as it is read (recon filter "
            "IN.copc.laz, a pipeline's first stage, recon_cli.filter('IN.copc.laz')): this "
            "cloud was not read so"
        )
    if have != want:
        raise InputError(
            f"--{want}: this cloud holds the levels read for --{have}; read its COPC file "
            f"again with --{want}"
        )


def filter_cloud(
    cloud: PointCloud,
    *,
    crop: Any = None,
    level: int | None = None,
    resolution: float | None = None,
    classes: Any = None,
    returns: str = "all",
    radius_outliers: Any = None,
    outliers: Any = None,
    voxel: float | None = None,
    progress: Any = None,
) -> tuple[PointCloud, dict[str, Any]]:
    """Run the filter's operations on ``cloud`` in their fixed order (see the module).

    Parameters
    ----------
    cloud : PointCloud
        Coordinates (n, 3) float32 or float64, any attributes.
    crop : six numbers or None
        Box ``x0, y0, z0, x1, y1, z1`` (input units); points on its faces are kept.
    level, resolution : int, float or None
        The octree levels a COPC file was read with (:func:`read_hint`): the cloud must have
        been read so (its ``copc_read`` line), as a cloud holds no octree to choose from.
    classes : codes or names, or None
        LAS classes to keep (:func:`class_mask`); needs the attribute ``classification``.
    returns : {"all", "first", "last", "single", "intermediate"}
        LAS returns to keep (:func:`return_mask`); needs ``return_number`` and
        ``number_of_returns`` unless "all".
    radius_outliers, outliers : (R, N), (K, STD) or None
        :func:`radius_outlier_mask`, :func:`statistical_outlier_mask`.
    voxel : float or None
        :func:`voxel_downsample` cell edge (input units).

    Returns
    -------
    cloud : PointCloud
        The kept points (a subset, exact) or, with ``voxel``, the cells' points.
    report : dict
        ``points_in``, ``invalid_removed``, ``crop_removed``, ``classes_removed``,
        ``returns_removed``, ``radius_outliers_removed``, ``outliers_removed``,
        ``voxel_merged`` (points in minus cells; null for an operation not asked for),
        ``outlier_threshold`` (the mean-distance threshold, input units), ``points_out``.

    Raises
    ------
    InputError
        No points; an operation that leaves no point; ``classes``/``returns`` without the
        LAS attributes they read; ``level``/``resolution`` for a cloud not read with them.
    ParameterError
        A parameter out of its range (see :data:`SPEC`), or both ``level`` and ``resolution``.
    """
    values = SPEC.check(
        {
            "crop": crop,
            "level": level,
            "resolution": resolution,
            "classes": classes,
            "returns": returns,
            "radius_outliers": radius_outliers,
            "outliers": outliers,
            "voxel": voxel,
        }
    )
    crop, classes, returns = values["crop"], values["classes"], values["returns"]
    radius_outliers, outliers = values["radius_outliers"], values["outliers"]
    voxel = values["voxel"]
    raw = cloud.points
    n = len(raw)
    if n == 0:
        raise InputError("the input has no points")
    _check_levels(cloud, values["level"], values["resolution"])
    class_codes, return_codes = _las_codes(cloud, classes, returns)
    kept = _Kept(n)
    with task(progress, "invalid points" if crop is None else "invalid points, crop"):
        kept.valid_in_box(raw, crop)
    if class_codes is not None:
        with task(progress, "classes"):
            kept.classes(class_codes, classes)
    if return_codes is not None:
        with task(progress, "returns"):
            keep = return_mask(
                kept.current(return_codes[0]), kept.current(return_codes[1]), returns
            )
            kept.apply("returns_removed", keep, f"--returns {returns}")
    if radius_outliers is not None:
        with task(progress, "radius outliers"):
            keep = radius_outlier_mask(kept.current(raw), *radius_outliers)
            kept.apply(
                "radius_outliers_removed", keep, f"--radius-outliers {_text(radius_outliers)}"
            )
    if outliers is not None:
        k, std_ratio = outliers
        keep, figures = statistical_outlier_mask(kept.current(raw), k, std_ratio, progress=progress)
        kept.report["outlier_threshold"] = figures["threshold"]
        kept.apply("outliers_removed", keep, f"--outliers {_text(outliers)}")
    # nothing removed: the same arrays in a new cloud (with its own history)
    out = (
        dataclasses.replace(cloud, history=list(cloud.history))
        if kept.rows is None
        else cloud.subset(kept.rows)
    )
    if voxel is not None:
        with task(progress, "voxel thinning"):
            thinned = voxel_downsample(out, voxel)
            kept.report["voxel_merged"] = len(out) - len(thinned)
            out = thinned
    # PLY elements that are not per point travel; one indexing the points would go stale
    linked = [e.name for e in cloud.extra_elements if _indexes_points(e)]
    if linked and len(out) < n:
        raise InputError(
            f"element {linked[0]!r} refers to the points by index: filter cannot drop points "
            "from under it"
        )
    out.extra_elements = list(cloud.extra_elements)
    kept.report["points_out"] = len(out)
    return out, kept.report


def _las_codes(
    cloud: PointCloud, classes: Any, returns: str
) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """The LAS attributes ``--classes`` and ``--returns`` read (None: not asked for).

    The class codes, and the return numbers with the numbers of returns.
    """
    class_codes: np.ndarray | None = None
    if classes is not None:
        class_attr = find_attribute(cloud, _CLASS_ATTRS)
        if class_attr is None:
            raise InputError("--classes needs the LAS attribute 'classification', which it has not")
        class_codes = cloud.attributes[class_attr]
    return_codes: tuple[np.ndarray, np.ndarray] | None = None
    if returns != "all":
        ret_attr = find_attribute(cloud, _RETURN_ATTRS)
        nret_attr = find_attribute(cloud, _NRETURNS_ATTRS)
        if ret_attr is None or nret_attr is None:
            raise InputError(
                "--returns needs the LAS attributes 'return_number' and 'number_of_returns'"
            )
        return_codes = (cloud.attributes[ret_attr], cloud.attributes[nret_attr])
    return class_codes, return_codes


class _Kept:
    """The rows of the input the steps kept so far, and the report of what each removed."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.rows: np.ndarray | None = None  # None: all of them
        self.report: dict[str, Any] = {
            "points_in": n,
            "invalid_removed": 0,
            "crop_removed": None,
            "classes_removed": None,
            "returns_removed": None,
            "radius_outliers_removed": None,
            "outliers_removed": None,
            "voxel_merged": None,
            "outlier_threshold": None,
            "points_out": None,
        }

    def current(self, a: np.ndarray) -> np.ndarray:
        """The kept rows of the per-point array ``a``."""
        return a if self.rows is None else a[self.rows]

    def apply(self, key: str, keep: np.ndarray, what: str) -> None:
        """Keep the rows ``keep`` of the kept ones; ``report[key]`` counts the others."""
        before = len(keep)
        kept = int(np.count_nonzero(keep))
        self.report[key] = before - kept
        if kept == 0:
            raise InputError(f"{what} leaves no point (of {before})")
        if kept < before:
            rows = np.flatnonzero(keep)
            self.rows = rows if self.rows is None else self.rows[rows]

    def valid_in_box(self, raw: np.ndarray, crop: Any) -> None:
        """The first step: drop invalid points and, with ``crop``, those outside the box."""
        n = self.n
        fate = box_codes(raw, crop)
        count = np.bincount(fate, minlength=3)
        self.report["invalid_removed"] = int(count[_INVALID])
        if count[_INVALID] == n:
            raise InputError(f"every point (of {n}) has a NaN or infinite coordinate")
        if crop is not None:
            self.report["crop_removed"] = int(count[_OUTSIDE])
            if count[_KEPT] == 0:
                raise InputError(f"--crop {_text(crop)} leaves no point (of {n - count[_INVALID]})")
        if count[_KEPT] < n:
            self.rows = np.flatnonzero(fate == _KEPT)

    def classes(self, class_codes: np.ndarray, classes: Any) -> None:
        """Keep the points of the LAS ``classes``; the error lists the classes present."""
        codes = self.current(class_codes)
        keep = class_mask(codes, classes)
        if not keep.any():
            present = ", ".join(str(int(c)) for c in np.unique(codes)[:20])
            raise InputError(
                f"--classes {_text(classes)} leaves no point (of {len(keep)}; "
                f"classes present: {present})"
            )
        self.apply("classes_removed", keep, f"--classes {_text(classes)}")


def _indexes_points(element: Any) -> bool:
    return any("vertex" in p.name for p in getattr(element, "properties", ()))


def _text(v: Any) -> str:
    if isinstance(v, (tuple, list)):
        return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
    return str(v)


@SPEC.runner
def run_stage(
    data: Any,
    *,
    crop: tuple | None,
    level: int | None,
    resolution: float | None,
    classes: tuple | None,
    returns: str,
    radius_outliers: tuple | None,
    outliers: tuple | None,
    voxel: float | None,
    progress: Any = None,
) -> StageResult:
    """Stage ``filter``: :func:`filter_cloud` on a point cloud.

    Parameters
    ----------
    data : PointCloud
        The input (a mesh is refused: dropping vertices would cut its faces).
    crop, level, resolution, classes, returns, radius_outliers, outliers, voxel
        See :func:`filter_cloud`.

    Returns
    -------
    StageResult
        ``output``: the filtered PointCloud; ``report``: :func:`filter_cloud`'s.
    """
    out, report = filter_cloud(
        data,
        crop=crop,
        level=level,
        resolution=resolution,
        classes=classes,
        returns=returns,
        radius_outliers=radius_outliers,
        outliers=outliers,
        voxel=voxel,
        progress=progress,
    )
    return StageResult(out, report)
