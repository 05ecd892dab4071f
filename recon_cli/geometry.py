"""The data model: plain dataclasses holding numpy arrays.

A :class:`PointCloud` is what scanners give; a :class:`TriangleMesh` is what the
reconstruction stages return. Both carry ``history`` (provenance lines, written as PLY
``comment`` lines) and whatever the source file held that recon does not interpret
(``attributes`` per vertex, ``extra_elements``), so writing back loses nothing.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import InputError


class Geometry:
    """What :class:`PointCloud` and :class:`TriangleMesh` share: conversions to and from Open3D
    and trimesh (:mod:`recon_cli.backends.interop`) and the report of the stage that made them.

    Attributes
    ----------
    report : dict or None
        The report of the stage whose result this is, when a library function made it
        (``recon_cli.poisson(...).report``: the keys of ``recon poisson --json``), else None.
    """

    report: dict[str, Any] | None = None

    def _arrays(self) -> dict[str, Any]:
        """The arrays the conversions take (``faces`` None for a cloud)."""
        names = ("points", "faces", "normals", "colors", "attributes", "face_attributes")
        return {k: getattr(self, k, None) for k in names}

    def to_open3d(self, tensor: bool = False) -> Any:
        """This object as Open3D geometry (a copy; coordinates and normals in float64).

        Parameters
        ----------
        tensor : bool
            ``open3d.t.geometry`` (every attribute kept, each in its own dtype) instead of
            the legacy ``open3d.geometry``, which holds points, normals, RGB colours and
            triangles only (see :mod:`recon_cli.backends.interop`).

        Returns
        -------
        open3d.geometry.PointCloud or open3d.geometry.TriangleMesh (or their ``open3d.t`` kinds)

        Raises
        ------
        BackendError
            Open3D is not installed (``pip install 'recon[reference]'``).
        """
        from recon_cli.backends import interop

        return interop.to_open3d(**self._arrays(), tensor=tensor)

    def to_trimesh(self) -> Any:
        """This object as a ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (a copy, float64).

        A mesh keeps its vertex order (``process=False``), vertex normals, colours (RGBA 8-bit)
        and every vertex and face attribute; a cloud's normals and attributes go to the
        ``trimesh.PointCloud``'s ``metadata`` (``vertex_normals``, ``vertex_attributes``),
        where :func:`geometry_from` finds them again.
        """
        from recon_cli.backends import interop

        return interop.to_trimesh(**self._arrays())


@dataclass
class PointCloud(Geometry):
    """A set of points with optional normals, colours and per-point scalars.

    Parameters
    ----------
    points : (n, 3) float32 or float64
        Coordinates, in the units and the precision of the source (float32 columns of a
        file stay float32; integers become float64). Read from a binary PLY they are a view
        of the file's rows, not contiguous: code that computes takes :func:`float64` of the
        object (or ``np.ascontiguousarray(points, np.float64)``) first.
    normals : (n, 3) float32 or float64 or None
        Normals, in the precision of the source (unit length when estimated by recon;
        input normals are kept as read).
    colors : (n, 3) or (n, 4) array or None
        Colours, in the dtype of the source (usually uint8; RGB or RGBA).
    attributes : dict of str to (n,) array
        Other per-point scalar properties (``curvature``, ``density``, unknown ones).
    history : list of str
        Provenance lines, oldest first (PLY ``comment`` lines).
    point_dtype : numpy float type or None
        Float type of the coordinates in the source: ``np.float32`` or ``np.float64``
        (None: the type of ``points``, so a cloud built from float64 arrays is double). Files
        are written with :func:`storage_dtype`, which keeps this type unless float32 would
        round the coordinates by more than ``tol.precision`` of the bbox diagonal.
    extra_elements : list
        PLY elements recon does not interpret, kept for writing back.
    obj_info : list of str
        PLY ``obj_info`` lines.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    history: list[str] = field(default_factory=list)
    point_dtype: Any = None
    extra_elements: list = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.points = _float_rows(self.points)
        self.point_dtype = _source_dtype(self.point_dtype, self.points)
        _normalise_per_point(self, len(self.points))

    @property
    def vertices(self) -> np.ndarray:
        """Alias of ``points`` so code taking vertices accepts a cloud."""
        return self.points

    def __len__(self) -> int:
        return len(self.points)

    def copy(self) -> "PointCloud":
        return PointCloud(
            points=self.points.copy(),
            normals=None if self.normals is None else self.normals.copy(),
            colors=None if self.colors is None else self.colors.copy(),
            attributes={k: v.copy() for k, v in self.attributes.items()},
            history=list(self.history),
            point_dtype=self.point_dtype,
            extra_elements=list(self.extra_elements),
            obj_info=list(self.obj_info),
        )

    def subset(self, mask: np.ndarray) -> "PointCloud":
        """The cloud restricted to ``mask`` (boolean or index array)."""
        return PointCloud(
            points=self.points[mask],
            normals=None if self.normals is None else self.normals[mask],
            colors=None if self.colors is None else self.colors[mask],
            attributes={k: v[mask] for k, v in self.attributes.items()},
            history=list(self.history),
            point_dtype=self.point_dtype,
            obj_info=list(self.obj_info),
        )


@dataclass
class TriangleMesh(Geometry):
    """A triangle mesh with optional per-vertex normals, colours and scalars.

    Parameters
    ----------
    vertices : (n, 3) float32 or float64
        Vertex coordinates, as ``PointCloud.points`` (the source's precision, maybe a view).
    faces : (m, 3) int64
        Vertex indices of each triangle, counter-clockwise seen from outside.
    normals : (n, 3) float32 or float64 or None
        Per-vertex normals (the source's precision).
    colors : (n, 3) or (n, 4) array or None
        Per-vertex colours in the dtype of the source.
    attributes : dict of str to (n,) array
        Other per-vertex scalars (``density``, ``distance``, unknown properties).
    face_attributes : dict of str to (m,) array
        Per-face scalars (kept from the file; replicated over fan-triangulated polygons).
    history, point_dtype, extra_elements, obj_info
        As for :class:`PointCloud`.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    face_attributes: dict[str, np.ndarray] = field(default_factory=dict)
    history: list[str] = field(default_factory=list)
    point_dtype: Any = None
    extra_elements: list = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.vertices = _float_rows(self.vertices)
        self.point_dtype = _source_dtype(self.point_dtype, self.vertices)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        _normalise_per_point(self, len(self.vertices))
        for k, v in self.face_attributes.items():
            _check_len(k, v, len(self.faces))

    @property
    def points(self) -> np.ndarray:
        """Alias of ``vertices`` so code taking points accepts a mesh."""
        return self.vertices

    def copy(self) -> "TriangleMesh":
        return TriangleMesh(
            vertices=self.vertices.copy(),
            faces=self.faces.copy(),
            normals=None if self.normals is None else self.normals.copy(),
            colors=None if self.colors is None else self.colors.copy(),
            attributes={k: v.copy() for k, v in self.attributes.items()},
            face_attributes={k: v.copy() for k, v in self.face_attributes.items()},
            history=list(self.history),
            point_dtype=self.point_dtype,
            extra_elements=list(self.extra_elements),
            obj_info=list(self.obj_info),
        )

    def to_point_cloud(self) -> PointCloud:
        """The vertices as a cloud (normals, colours, attributes and history kept)."""
        return PointCloud(
            points=self.vertices,
            normals=self.normals,
            colors=self.colors,
            attributes=dict(self.attributes),
            history=list(self.history),
            point_dtype=self.point_dtype,
            obj_info=list(self.obj_info),
        )


def geometry_from(obj: Any) -> PointCloud | TriangleMesh:
    """recon's :class:`PointCloud` or :class:`TriangleMesh` for an Open3D or trimesh point cloud
    or triangle mesh (legacy or tensor Open3D geometry); a recon object is returned as it is.

    The arrays are copied; coordinates and normals are float64, colours 8-bit (see
    :mod:`recon_cli.backends.interop` for what each library holds).

    Raises
    ------
    InputError
        ``obj`` is none of these.
    """
    if isinstance(obj, (PointCloud, TriangleMesh)):
        return obj
    from recon_cli.backends import interop

    library = interop.library_of(obj)
    if library is None:
        raise InputError(
            f"expected a point cloud or a mesh (recon, Open3D or trimesh), got {type(obj).__name__}"
        )
    a = interop.from_open3d(obj) if library == "open3d" else interop.from_trimesh(obj)
    if a["faces"] is None:
        return PointCloud(
            points=a["points"], normals=a["normals"], colors=a["colors"], attributes=a["attributes"]
        )
    return TriangleMesh(
        vertices=a["points"],
        faces=a["faces"],
        normals=a["normals"],
        colors=a["colors"],
        attributes=a["attributes"],
        face_attributes=a["face_attributes"],
    )


def as_point_cloud(obj: PointCloud | TriangleMesh) -> PointCloud:
    """A point cloud view of ``obj`` (a mesh's vertices)."""
    if isinstance(obj, PointCloud):
        return obj
    if isinstance(obj, TriangleMesh):
        return obj.to_point_cloud()
    raise TypeError(f"expected a PointCloud or TriangleMesh, got {type(obj).__name__}")


def float64(obj: "PointCloud | TriangleMesh") -> "PointCloud | TriangleMesh":
    """``obj`` with C-contiguous float64 coordinates and normals, ready to compute with.

    ``obj`` itself when they already are; otherwise a shallow copy holding converted copies
    (colours, attributes and faces are shared). Library functions call this on the objects
    they are given, so a float32 cloud read from a file is computed on in float64.
    """

    def ready(a: np.ndarray | None) -> bool:
        return a is None or (a.dtype == np.float64 and a.flags.c_contiguous)

    if ready(obj.points) and ready(obj.normals):
        return obj
    out = copy.copy(obj)
    coords = np.ascontiguousarray(obj.points, dtype=np.float64)
    if isinstance(out, TriangleMesh):
        out.vertices = coords
    else:
        out.points = coords
    if obj.normals is not None:
        out.normals = np.ascontiguousarray(obj.normals, dtype=np.float64)
    return out


def local_origin(points: np.ndarray) -> np.ndarray:
    """A local origin for computing near ``points`` ((n, 3)): the centre of their bounding box, (3,) float64.

    Stages subtract it (in float64) before anything that loses precision far from the
    origin (float32 arrays, squared norms, cross products, a unit cube) and add it back to
    the coordinates they output, so data at UTM-like offsets (1e6) is computed on as
    precisely as the same data at the origin. ``points`` must be finite; zeros for an empty array.
    """
    if len(points) == 0:
        return np.zeros(3)
    lo = points.min(axis=0).astype(np.float64)
    hi = points.max(axis=0).astype(np.float64)
    return 0.5 * (lo + hi)


def storage_dtype(obj: "PointCloud | TriangleMesh") -> type:
    """The float type ``obj``'s coordinates (and normals) are written with: the rule of the data model.

    ``np.float64`` when the source is double (``obj.point_dtype``); otherwise ``np.float32``
    unless the coordinates are float64 values that float32 would round by more than
    ``tol.precision`` times the bounding-box diagonal (a float32 source far from the origin
    whose coordinates a stage computed anew): then ``np.float64``, which loses nothing.
    """
    if np.dtype(obj.point_dtype) == np.float64:
        return np.float64
    return np.float64 if float32_rounding(obj.points)[0] > 0 else np.float32


def float32_rounding(points: np.ndarray) -> tuple[float, float]:
    """How far storing ``points`` ((n, 3)) as float32 would move them, when it matters.

    Returns ``(bound, relative)``: a bound on the rounding of any coordinate and that bound
    over the bbox diagonal, both 0 when it is within ``tol.precision`` of the diagonal or the
    values are float32 already (or exactly representable as float32).
    """
    from recon_cli.tolerances import tol

    if len(points) == 0 or points.dtype == np.float32:
        return 0.0, 0.0
    lo = points.min(axis=0).astype(np.float64)
    hi = points.max(axis=0).astype(np.float64)
    big = float(np.maximum(np.abs(lo), np.abs(hi)).max())
    if big > float(np.finfo(np.float32).max):
        return math.inf, math.inf
    bound = (
        float(np.spacing(np.float32(big))) / 2
    )  # round to nearest: half a unit in the last place
    diag = float(np.linalg.norm(hi - lo))
    scale = diag if diag > 0 else big
    if bound <= tol.precision * scale:
        return 0.0, 0.0
    if np.array_equal(points.astype(np.float32), points):
        return 0.0, 0.0
    return bound, bound / scale


def precision_note(obj: Any) -> str | None:
    """A one-line note when :func:`storage_dtype` writes double for a float32 source, else None."""
    if not isinstance(obj, (PointCloud, TriangleMesh)) or np.dtype(obj.point_dtype) == np.float64:
        return None
    bound, rel = float32_rounding(obj.points)
    if bound == 0:
        return None
    if math.isinf(bound):
        return "coordinates kept as double: they exceed the float32 range"
    return (
        f"coordinates kept as double: float32 would round them by up to {bound:.3g} "
        f"({rel:.2g} of the bounding-box diagonal)"
    )


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of ``points`` ((n, 3)), 0 if empty."""
    if len(points) == 0:
        return 0.0
    # in float64 whatever the points' type
    return float(np.linalg.norm(points.max(axis=0).astype(np.float64) - points.min(axis=0)))


def oriented_rows(
    points: Any, normals: Any, missing: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points and normals of an oriented cloud as contiguous float64 (n, 3) arrays, with the normals' lengths.

    The shared entry check of the stages that need normals; each decides what to do with
    non-finite rows and zero normals (``length`` is NaN or inf where a normal is not finite).

    Parameters
    ----------
    points, normals : array-like (n, 3)
    missing : str
        The error when ``normals`` is None (say which command gives them).

    Returns
    -------
    points (n, 3) float64, normals (n, 3) float64, length (n,) float64
    """
    if normals is None:
        raise InputError(missing)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    if nrm.shape != pts.shape:
        raise InputError(f"normals must have the shape of points {pts.shape}, got {nrm.shape}")
    with np.errstate(invalid="ignore", over="ignore"):
        length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    return pts, nrm, length


def _float_rows(a: Any) -> np.ndarray:
    """``a`` as (n, 3) rows: float32 and float64 arrays kept as they are (views stay views), anything else as float64."""
    arr = np.asarray(a)
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    return (
        arr if arr.ndim == 2 and arr.shape[1:] == (3,) else np.ascontiguousarray(arr).reshape(-1, 3)
    )


def _source_dtype(point_dtype: Any, coords: np.ndarray) -> type:
    """``np.float64`` or ``np.float32``: ``point_dtype``, or the type of ``coords`` when None."""
    if point_dtype is None:
        point_dtype = coords.dtype
    return np.float64 if np.dtype(point_dtype) == np.float64 else np.float32


def _normalise_per_point(obj: "PointCloud | TriangleMesh", n: int) -> None:
    """Put the optional per-point arrays of ``obj`` in shape and check they have ``n`` rows."""
    if obj.normals is not None:
        obj.normals = _float_rows(obj.normals)
        _check_len("normals", obj.normals, n)
    if obj.colors is not None:
        obj.colors = np.asarray(obj.colors)
        _check_len("colors", obj.colors, n)
    for k, v in obj.attributes.items():
        _check_len(k, v, n)


def _check_len(name: str, arr: np.ndarray, n: int) -> None:
    if len(arr) != n:
        raise InputError(f"{name} has {len(arr)} rows, expected {n}")
