"""The data model: plain dataclasses holding numpy arrays.

A :class:`PointCloud` is what scanners give; a :class:`TriangleMesh` is what the
reconstruction stages return. Both carry ``history`` (provenance lines, written as PLY
``comment`` lines) and whatever the source file held that recon does not interpret
(``attributes`` per vertex, ``extra_elements``), so writing back loses nothing.

What a sensor file says about its points travels with a cloud: the scanner positions
(:class:`Sensor`, from a PCD ``VIEWPOINT``, E57 scan poses, a LAS file's "up"; the per-point
attribute ``scan`` says which of several took each point), the pixel of each point of an
organized cloud (:class:`PixelGrid`) and how many points the reader dropped because a
coordinate was NaN or infinite (``invalid_dropped``; :func:`drop_invalid`).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from recon_cli.errors import InputError

#: the per-point attribute naming the sensor (index into ``PointCloud.sensors``) of each point
SCAN_ATTRIBUTE = "scan"


@dataclass(frozen=True)
class Sensor:
    """Where a scan was taken from, in the coordinates of the cloud's points.

    Parameters
    ----------
    position : (3,) tuple of float or None
        The scanner's optical centre (PCD ``VIEWPOINT``, an E57 scan's pose translation).
    orientation : (4,) tuple of float or None
        Its rotation to the cloud's frame, a unit quaternion ``(w, x, y, z)``, when the file
        gives one (kept so that it is written back; orientation of normals uses the position).
    direction : (3,) tuple of float or None
        For a sensor far away (airborne LiDAR): the unit direction towards it. Exactly one
        of ``position`` and ``direction`` is set.
    source : str
        What gave it, for reports (``PCD VIEWPOINT``, ``E57 scan 2 'north'``, ``LAS``).
    """

    position: tuple[float, float, float] | None = None
    orientation: tuple[float, float, float, float] | None = None
    direction: tuple[float, float, float] | None = None
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "source", " ".join(str(self.source).split()))  # one line
        if (self.position is None) == (self.direction is None):
            raise InputError("a sensor has either a position or a direction")
        for name, k in (("position", 3), ("orientation", 4), ("direction", 3)):
            v = getattr(self, name)
            if v is None:
                continue
            v = tuple(float(x) for x in np.ravel(v))
            if len(v) != k or not all(math.isfinite(x) for x in v):
                raise InputError(f"a sensor's {name} must be {k} finite numbers, got {v}")
            if name == "direction":
                length = math.sqrt(sum(x * x for x in v))
                if length == 0:
                    raise InputError("a sensor's direction must not be the zero vector")
                v = tuple(x / length for x in v)
            object.__setattr__(self, name, v)

    def describe(self) -> str:
        """One line for reports: the source and the position (or direction)."""
        if self.position is not None:
            return f"{self.source} at ({', '.join(f'{x:.9g}' for x in self.position)})"
        assert self.direction is not None  # a sensor has a position or a direction
        return f"{self.source} towards ({', '.join(f'{x:.9g}' for x in self.direction)})"

    def to_line(self) -> str:
        """The ``sensor ...`` line that stores it (PLY ``obj_info``; :func:`parse_sensor_line`)."""
        parts = ["sensor"]
        for name in ("position", "orientation", "direction"):
            v = getattr(self, name)
            if v is not None:
                parts += [name, *(repr(x) for x in v)]
        parts += ["source", self.source]
        return " ".join(parts).rstrip()


def parse_sensor_line(line: str) -> Sensor | None:
    """The :class:`Sensor` a ``sensor ...`` or ``pcd_viewpoint ...`` line holds, else None.

    ``sensor`` lines are :meth:`Sensor.to_line`'s, ``pcd_viewpoint x y z qw qx qy qz`` the older
    form; any other line or a malformed one gives None.
    """
    words = line.split()
    if not words:
        return None
    try:
        if words[0] == "pcd_viewpoint" and len(words) == 8:
            v = [float(x) for x in words[1:]]
            return Sensor(
                position=(v[0], v[1], v[2]),
                orientation=(v[3], v[4], v[5], v[6]),
                source="PCD VIEWPOINT",
            )
        if words[0] != "sensor":
            return None
        kw: dict[str, Any] = {}
        i = 1
        while i < len(words):
            key = words[i]
            if key == "source":
                kw["source"] = " ".join(words[i + 1 :])
                break
            k = {"position": 3, "orientation": 4, "direction": 3}.get(key)
            if k is None or key in kw:
                return None
            kw[key] = [float(x) for x in words[i + 1 : i + 1 + k]]
            i += 1 + k
        return Sensor(**kw)
    except (ValueError, InputError):
        return None


def split_sensor_lines(lines: list[str]) -> tuple[list[Sensor], list[str]]:
    """``(sensors, other lines)`` of ``obj_info`` lines (the sensors in their order)."""
    sensors, rest = [], []
    for line in lines:
        s = parse_sensor_line(line)
        if s is None:
            rest.append(line)
        else:
            sensors.append(s)
    return sensors, rest


@dataclass
class PixelGrid:
    """The pixel of each point of an organized cloud (a depth image, a structured scan).

    Parameters
    ----------
    shapes : tuple of (height, width)
        The image(s) the points came from: one for a PCD with ``HEIGHT`` > 1, one per
        structured scan of an E57 file.
    pixel : (n,) int64
        Each point's pixel, ``offset[image] + row * width + col``, the images laid one after
        another in row-major order (:meth:`offsets`); unique.
    """

    shapes: tuple[tuple[int, int], ...]
    pixel: np.ndarray

    def __post_init__(self) -> None:
        self.shapes = tuple((int(h), int(w)) for h, w in self.shapes)
        self.pixel = np.ascontiguousarray(self.pixel, dtype=np.int64).reshape(-1)

    def offsets(self) -> np.ndarray:
        """(k + 1,) int64: where each image starts in the pixel numbering (the last.

        Their total).
        """
        sizes = [h * w for h, w in self.shapes]
        return np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).astype(np.int64)

    def describe(self) -> str:
        """``640x480`` (width x height), or one per image."""
        return ", ".join(f"{w}x{h}" for h, w in self.shapes)

    def subset(self, mask: np.ndarray) -> PixelGrid:
        """The grid of the points kept by ``mask`` (boolean or index array)."""
        return PixelGrid(self.shapes, self.pixel[mask])


class Geometry:
    """What :class:`PointCloud` and :class:`TriangleMesh` share.

    Conversions to and from Open3D and trimesh (:mod:`recon_cli.backends.interop`) and the report of
    the stage that made them.

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
        """The object as Open3D geometry (a copy; coordinates and normals in float64).

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
        """The object as a ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (a copy, float64).

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
        PLY ``obj_info`` lines (sensor lines are parsed into ``sensors``).
    sensors : list of Sensor
        The scanner position(s) the file gives (empty: none known). With more than one, the
        int attribute ``scan`` (:data:`SCAN_ATTRIBUTE`) gives each point's index in this list.
    pixels : PixelGrid or None
        The pixel of each point of an organized cloud (None: not organized). Carried by
        :meth:`subset`; not written as a vertex property.
    invalid_dropped : int
        Points the reader dropped because a coordinate was NaN or infinite (a depth image's
        missing pixels, an E57 scan's invalid returns).
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    history: list[str] = field(default_factory=list)
    point_dtype: Any = None
    extra_elements: list = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)
    sensors: list[Sensor] = field(default_factory=list)
    pixels: PixelGrid | None = None
    invalid_dropped: int = 0

    def __post_init__(self) -> None:
        self.points = _float_rows(self.points)
        self.point_dtype = _source_dtype(self.point_dtype, self.points)
        _normalise_per_point(self, len(self.points))
        if self.pixels is not None:
            _check_len("pixels", self.pixels.pixel, len(self.points))
        if any(line.startswith(("sensor ", "pcd_viewpoint ")) for line in self.obj_info):
            found, self.obj_info = split_sensor_lines(self.obj_info)
            self.sensors = list(self.sensors) + found

    @property
    def vertices(self) -> np.ndarray:
        """Alias of ``points`` so code taking vertices accepts a cloud."""
        return self.points

    def __len__(self) -> int:
        return len(self.points)

    def copy(self) -> PointCloud:
        """A copy with every array copied (the history and file metadata carried over)."""
        return PointCloud(
            points=self.points.copy(),
            normals=None if self.normals is None else self.normals.copy(),
            colors=None if self.colors is None else self.colors.copy(),
            attributes={k: v.copy() for k, v in self.attributes.items()},
            history=list(self.history),
            point_dtype=self.point_dtype,
            extra_elements=list(self.extra_elements),
            obj_info=list(self.obj_info),
            sensors=list(self.sensors),
            pixels=None
            if self.pixels is None
            else PixelGrid(self.pixels.shapes, self.pixels.pixel.copy()),
            invalid_dropped=self.invalid_dropped,
        )

    def subset(self, mask: np.ndarray) -> PointCloud:
        """The cloud restricted to ``mask`` (boolean or index array); sensors, pixels kept.

        The per-point arrays are gathered by :func:`take_rows` (those of one record, as a
        binary PLY's, in one copy).
        """
        names = list(self.attributes)
        points, normals, colors, *values = take_rows(
            [self.points, self.normals, self.colors, *self.attributes.values()], mask
        )
        assert points is not None  # a cloud always has points
        return PointCloud(
            points=points,
            normals=normals,
            colors=colors,
            attributes=dict(zip(names, values, strict=True)),  # type: ignore[arg-type]
            history=list(self.history),
            point_dtype=self.point_dtype,
            obj_info=list(self.obj_info),
            sensors=list(self.sensors),
            pixels=None if self.pixels is None else self.pixels.subset(mask),
            invalid_dropped=self.invalid_dropped,
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
    history, point_dtype, extra_elements, obj_info, invalid_dropped
        As for :class:`PointCloud` (a mesh keeps sensor lines in ``obj_info`` as they are).
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
    invalid_dropped: int = 0

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

    def copy(self) -> TriangleMesh:
        """A copy with every array copied (the history and file metadata carried over)."""
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
            invalid_dropped=self.invalid_dropped,
        )

    def to_point_cloud(self) -> PointCloud:
        """The vertices as a cloud (normals, colours, attributes, history and sensor lines kept)."""
        return PointCloud(
            points=self.vertices,
            normals=self.normals,
            colors=self.colors,
            attributes=dict(self.attributes),
            history=list(self.history),
            point_dtype=self.point_dtype,
            obj_info=list(self.obj_info),
            invalid_dropped=self.invalid_dropped,
        )


def geometry_from(obj: Any) -> PointCloud | TriangleMesh:
    """Recon's :class:`PointCloud` or :class:`TriangleMesh` for an Open3D or trimesh object.

    Open3D geometry may be legacy or tensor; a recon object is returned as it is.

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


def drop_invalid(obj: PointCloud | TriangleMesh, where: str | None = None):
    """``obj`` without the points (vertices) that have a NaN or infinite coordinate.

    What readers do with invalid points (a depth image's missing pixels, flagged returns):
    the kept points keep every per-point array, their precision and their pixel; the count
    is added to ``invalid_dropped`` (reports and ``recon info`` show it). ``obj`` itself
    when every point is finite.

    Raises
    ------
    InputError
        A mesh face uses an invalid vertex (a mesh is never read with faces cut out of it),
        or a kept PLY element refers to vertices by index (its indices would go stale).
    """
    pts = obj.points
    ok = np.isfinite(pts).all(axis=1)
    if ok.all():
        return obj
    nbad = int(len(ok) - np.count_nonzero(ok))
    for el in obj.extra_elements:
        if any("vertex" in p.name for p in getattr(el, "properties", ())):
            raise InputError(
                f"{nbad} vertices have a NaN or infinite coordinate and element {el.name!r} "
                "refers to vertices by index: they cannot be dropped",
                where,
            )
    if isinstance(obj, TriangleMesh):
        if len(obj.faces):
            uses = ~ok[obj.faces]
            if uses.any():
                f = int(np.flatnonzero(uses.any(axis=1))[0])
                v = int(obj.faces[f][uses[f]][0])
                nf = int(np.count_nonzero(uses.any(axis=1)))
                raise InputError(
                    f"face {f} uses vertex {v}, which has a NaN or infinite coordinate "
                    f"({nf} faces use one of the {nbad} invalid vertices): "
                    "a mesh is not read with faces dropped",
                    where,
                )
        remap = np.cumsum(ok) - 1
        names = list(obj.attributes)
        vertices, normals, colors, *values = take_rows(
            [pts, obj.normals, obj.colors, *obj.attributes.values()], ok
        )
        assert vertices is not None  # a mesh always has vertices
        out: PointCloud | TriangleMesh = TriangleMesh(
            vertices=vertices,
            faces=remap[obj.faces],
            normals=normals,
            colors=colors,
            attributes=dict(zip(names, values, strict=True)),  # type: ignore[arg-type]
            face_attributes=dict(obj.face_attributes),
            history=list(obj.history),
            point_dtype=obj.point_dtype,
            extra_elements=list(obj.extra_elements),
            obj_info=list(obj.obj_info),
        )
    else:
        out = obj.subset(ok)
        out.extra_elements = list(obj.extra_elements)
    out.invalid_dropped = obj.invalid_dropped + nbad
    return out


def take_rows(columns: list[np.ndarray | None], rows: Any) -> list[np.ndarray | None]:
    """The rows ``rows`` of each per-point array of ``columns``, columns of one record copied once.

    ``[c[rows] for c in columns]`` (None stays None), values and dtypes exactly, but faster
    for the columns of a binary file's records (a PLY's ``x y z nx ny nz red green blue``
    are strided views into one record array): columns whose rows lie in one record of a
    shared buffer are gathered as whole records in one copy (a fancy index of each strided
    column costs several times that), and come back as views into the new records, laid out
    as in the source. Other columns are indexed one by one.

    Parameters
    ----------
    columns : list of (n, ...) arrays or None
        Per-point arrays of ``n`` rows each.
    rows : (n,) bool or (k,) int array_like
        A mask of the rows to keep, or their indices (any order, repeats allowed, negative
        from the end).

    Returns
    -------
    list of (k, ...) arrays or None
        In the order of ``columns``; new arrays (the views of gathered records share only
        those records, which nothing else holds).

    Raises
    ------
    InputError
        Columns of different lengths, a mask of another length, an index out of range.
    """
    arrays = {i: c for i, c in enumerate(columns) if c is not None}
    out: list[np.ndarray | None] = [None] * len(columns)
    if not arrays:
        return out
    n = len(next(iter(arrays.values())))
    if any(c.ndim == 0 or len(c) != n for c in arrays.values()):
        lengths = [len(c) if c.ndim else None for c in arrays.values()]
        raise InputError(f"per-point arrays of different lengths ({lengths})")
    idx = np.asarray(rows)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise InputError(f"a row mask of shape {idx.shape} for {n} rows")
        idx = np.flatnonzero(idx)
    elif idx.dtype.kind not in "iu" and idx.size:
        raise InputError(f"row indices must be integers or a boolean mask, got {idx.dtype}")
    idx = idx.astype(np.intp, copy=False).reshape(-1)
    if idx.size and (int(idx.min()) < -n or int(idx.max()) >= n):
        raise InputError(f"row index out of range for {n} rows")
    for group, as_records in _record_groups(arrays, n):
        if not as_records or idx.size == 0:
            for i in group:
                out[i] = arrays[i][idx]
            continue
        starts = {i: arrays[i].__array_interface__["data"][0] for i in group}
        first = min(starts.values())
        span = max(starts[i] - first + _row_bytes(arrays[i]) for i in group)
        # the group's bytes as one record per row, read-only; ``arrays`` keeps the memory alive
        interface = {
            "data": (first, True),
            "shape": (n,),
            "strides": (arrays[group[0]].strides[0],),
            "typestr": f"|V{span}",
            "version": 3,
        }
        kept = np.asarray(_Buffer(interface)).take(idx)
        for i in group:
            c = arrays[i]
            out[i] = np.ndarray(
                (len(idx), *c.shape[1:]),
                dtype=c.dtype,
                buffer=kept,
                offset=starts[i] - first,
                strides=(span, *c.strides[1:]),
            )
    return out


class _Buffer:
    """An object numpy reads as an array through ``__array_interface__`` (no copy)."""

    def __init__(self, interface: dict[str, Any]):
        self.__array_interface__ = interface


def _row_bytes(a: np.ndarray) -> int:
    """The bytes one row of ``a`` spans (its inner strides positive)."""
    return a.itemsize + sum((k - 1) * s for k, s in zip(a.shape[1:], a.strides[1:], strict=True))


def _record_groups(arrays: dict[int, np.ndarray], n: int) -> list[tuple[list[int], bool]]:
    """The keys of ``arrays`` grouped by record, and whether to gather each group as records.

    Arrays group when they have the same row stride, their rows lie within one stride of
    the group's first byte and their memory overlaps (so one allocation holds them and the
    bytes between them). An array gathered as records holds plain values (no Python
    objects) with positive strides; any other is indexed alone, as is a lone 1-D array.
    """
    groups: list[list[int]] = []
    spans: list[tuple[int, int, int]] = []  # row stride (0: index alone), first byte, row end
    for i, c in arrays.items():
        stride = c.strides[0]
        plain = (
            n > 1
            and c.size > 0
            and not c.dtype.hasobject
            and stride > 0
            and all(s > 0 for s in c.strides[1:])
            and _row_bytes(c) <= stride
        )
        if not plain:
            groups.append([i])
            spans.append((0, 0, 0))
            continue
        start = c.__array_interface__["data"][0]
        end = start + _row_bytes(c)
        for g, (gs, lo, hi) in enumerate(spans):
            if (
                gs == stride
                and max(hi, end) - min(lo, start) <= stride
                and np.may_share_memory(arrays[groups[g][0]], c)
            ):
                groups[g].append(i)
                spans[g] = (gs, min(lo, start), max(hi, end))
                break
        else:
            groups.append([i])
            spans.append((stride, start, end))
    return [
        (g, sp[0] > 0 and (len(g) > 1 or arrays[g[0]].ndim > 1))
        for g, sp in zip(groups, spans, strict=True)
    ]


_Geometry = TypeVar("_Geometry", bound="PointCloud | TriangleMesh")


def float64(obj: _Geometry) -> _Geometry:
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
    """A local origin for computing near ``points`` ((n, 3)): their bounding box's centre, (3,).

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


def storage_dtype(obj: PointCloud | TriangleMesh) -> type:
    """The float type ``obj``'s coordinates (and normals) are written with, by the data model.

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
    """Points and normals of an oriented cloud as contiguous float64 (n, 3), and normal lengths.

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
    """``a`` as (n, 3) rows: float32 and float64 kept as they are (views stay), others float64."""
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


def _normalise_per_point(obj: PointCloud | TriangleMesh, n: int) -> None:
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
