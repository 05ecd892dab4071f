"""Conversions between recon's arrays and Open3D or trimesh geometry.

They serve ``to_open3d()``, ``to_trimesh()`` and what the library functions accept.

Arrays in, arrays out: this module knows neither :mod:`recon_cli.geometry` nor the stages
(geometry calls it), and imports Open3D or trimesh only when converting to or from one of
their objects; recognising one (:func:`library_of`) imports nothing. Coordinates and normals
stay float64 (both libraries hold double); faces become Open3D's int32 (legacy) or int64.

What each target holds:

- Open3D legacy geometry (``open3d.geometry``): points/vertices, normals, RGB colours as
  floats in [0, 1] (8-bit colours go there and back exactly), triangles. Other attributes,
  alpha and face attributes have no place there: ask for tensor geometry to keep them.
- Open3D tensor geometry (``open3d.t.geometry``): everything, each array in its own dtype.
- trimesh: a ``Trimesh`` holds vertex normals, RGBA 8-bit vertex colours and every per-vertex
  and per-face attribute; a ``trimesh.PointCloud`` has RGBA colours and ``metadata``, where
  the normals and attributes go (``metadata["vertex_normals"]``,
  ``metadata["vertex_attributes"]``) and come back from.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError

#: the keys of the dictionaries :func:`from_open3d` and :func:`from_trimesh` return
FIELDS = ("points", "faces", "normals", "colors", "attributes", "face_attributes")


def library_of(obj: Any) -> str | None:
    """``"open3d"`` or ``"trimesh"`` when ``obj`` is one of their objects, else None.

    Imports nothing.
    """
    top = type(obj).__module__.split(".")[0]
    return top if top in ("open3d", "trimesh") else None


def _open3d():
    from recon_cli.backends import require

    return require("open3d")


def _trimesh():
    from recon_cli.errors import BackendError

    try:
        import trimesh
    except ImportError as exc:
        raise BackendError(f"trimesh is not available ({exc}); pip install trimesh") from None
    return trimesh


def _unit_colors(colors: np.ndarray) -> np.ndarray:
    """RGB colours as floats in [0, 1] (integers over their type's maximum)."""
    c = np.asarray(colors)[:, :3]
    if c.dtype.kind in "ui":
        return c.astype(np.float64) / float(np.iinfo(c.dtype).max)
    return c.astype(np.float64)


def _byte_colors(colors: np.ndarray) -> np.ndarray:
    """Colours as 8-bit integers: floats in [0, 1] scaled, wider integers shifted."""
    c = np.asarray(colors)
    if c.dtype == np.uint8:
        return c
    if c.dtype.kind in "ui":
        bits = np.iinfo(c.dtype).bits
        return (c.astype(np.uint64) >> max(bits - 8, 0)).astype(np.uint8)
    return np.clip(np.round(c.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def _drop_opaque_alpha(colors: np.ndarray) -> np.ndarray:
    """RGBA colours whose alpha is 255 everywhere as RGB (what both libraries add to RGB)."""
    if colors.ndim == 2 and colors.shape[1] == 4 and bool(np.all(colors[:, 3] == 255)):
        return np.ascontiguousarray(colors[:, :3])
    return colors


# ---- Open3D --------------------------------------------------------------------------------------
def to_open3d(
    points: np.ndarray,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    attributes: dict[str, np.ndarray] | None = None,
    face_attributes: dict[str, np.ndarray] | None = None,
    tensor: bool = False,
) -> Any:
    """An Open3D point cloud (``faces`` None) or triangle mesh of these arrays.

    Parameters
    ----------
    points : (n, 3) float
    faces : (m, 3) int, optional
    normals : (n, 3) float, optional
    colors : (n, 3) or (n, 4), optional
    attributes, face_attributes : dict of str to array, optional
        Kept by tensor geometry only.
    tensor : bool
        ``open3d.t.geometry`` (every array in its own dtype) instead of ``open3d.geometry``.

    Returns
    -------
    open3d.geometry.PointCloud, open3d.geometry.TriangleMesh or their ``open3d.t`` kinds
    """
    o3d = _open3d()
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = None if normals is None else np.ascontiguousarray(normals, dtype=np.float64)
    if tensor:
        T = o3d.core.Tensor
        if faces is None:
            out = o3d.t.geometry.PointCloud(T(pts))
            per_point = out.point
        else:
            out = o3d.t.geometry.TriangleMesh()
            out.vertex.positions = T(pts)
            out.triangle.indices = T(np.ascontiguousarray(faces, dtype=np.int64))
            per_point = out.vertex
            for k, v in (face_attributes or {}).items():
                out.triangle[k] = T(np.ascontiguousarray(v))
        if nrm is not None:
            per_point.normals = T(nrm)
        if colors is not None:
            per_point.colors = T(np.ascontiguousarray(colors))
        for k, v in (attributes or {}).items():
            per_point[k] = T(np.ascontiguousarray(v))
        return out
    V = o3d.utility.Vector3dVector
    if faces is None:
        pc = o3d.geometry.PointCloud()
        pc.points = V(pts)
        if nrm is not None:
            pc.normals = V(nrm)
        if colors is not None:
            pc.colors = V(_unit_colors(colors))
        return pc
    m = o3d.geometry.TriangleMesh()
    m.vertices = V(pts)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) and (f.max() > np.iinfo(np.int32).max):
        raise InputError("the mesh has too many vertices for Open3D's legacy 32-bit triangles")
    m.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(f, dtype=np.int32))
    if nrm is not None:
        m.vertex_normals = V(nrm)
    if colors is not None:
        m.vertex_colors = V(_unit_colors(colors))
    return m


def from_open3d(obj: Any) -> dict[str, Any]:
    """The arrays of an Open3D point cloud or triangle mesh (legacy or tensor), by :data:`FIELDS`.

    ``faces`` is None for a cloud. Legacy colours (floats in [0, 1]) come back as 8-bit.

    Raises
    ------
    InputError
        ``obj`` is another Open3D type (a voxel grid, a line set, ...).
    """
    name = type(obj).__name__
    tensor = ".t." in type(obj).__module__ + "."
    out: dict[str, Any] = dict.fromkeys(FIELDS)
    out["attributes"], out["face_attributes"] = {}, {}
    if tensor and name in ("PointCloud", "TriangleMesh"):
        per_point = obj.point if name == "PointCloud" else obj.vertex
        arrays = {k: per_point[k].numpy() for k in per_point}
        out["points"] = arrays.pop("positions", np.zeros((0, 3)))
        out["normals"] = arrays.pop("normals", None)
        if "colors" in arrays:
            out["colors"] = _drop_opaque_alpha(arrays.pop("colors"))
        out["attributes"] = arrays
        if name == "TriangleMesh":
            tri = {k: obj.triangle[k].numpy() for k in obj.triangle}
            out["faces"] = tri.pop("indices", np.zeros((0, 3), np.int64)).astype(np.int64)
            out["face_attributes"] = tri
        return out
    if name == "PointCloud":
        out["points"] = np.asarray(obj.points, dtype=np.float64)
        if obj.has_normals():
            out["normals"] = np.asarray(obj.normals, dtype=np.float64)
        if obj.has_colors():
            out["colors"] = _byte_colors(np.asarray(obj.colors))
        return out
    if name == "TriangleMesh":
        out["points"] = np.asarray(obj.vertices, dtype=np.float64)
        out["faces"] = np.asarray(obj.triangles, dtype=np.int64).reshape(-1, 3)
        if obj.has_vertex_normals():
            out["normals"] = np.asarray(obj.vertex_normals, dtype=np.float64)
        if obj.has_vertex_colors():
            out["colors"] = _byte_colors(np.asarray(obj.vertex_colors))
        return out
    raise InputError(f"an Open3D {name} is not a point cloud or a triangle mesh")


# ---- trimesh -------------------------------------------------------------------------------------
def to_trimesh(
    points: np.ndarray,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    attributes: dict[str, np.ndarray] | None = None,
    face_attributes: dict[str, np.ndarray] | None = None,
) -> Any:
    """A ``trimesh.PointCloud`` (``faces`` None) or ``trimesh.Trimesh`` of these arrays.

    The mesh is made with ``process=False``: trimesh neither merges nor reorders anything,
    so vertex ``i`` stays vertex ``i``.
    """
    trimesh = _trimesh()
    pts = np.ascontiguousarray(points, dtype=np.float64)
    rgba = None if colors is None else _byte_colors(colors)
    if faces is None:
        meta: dict[str, Any] = {}
        if normals is not None:
            meta["vertex_normals"] = np.array(normals, dtype=np.float64)
        if attributes:
            meta["vertex_attributes"] = {k: np.array(v) for k, v in attributes.items()}
        return trimesh.PointCloud(pts, colors=rgba, metadata=meta)
    return trimesh.Trimesh(
        vertices=pts,
        faces=np.asarray(faces, dtype=np.int64),
        vertex_normals=None if normals is None else np.array(normals, dtype=np.float64),
        vertex_colors=rgba,
        vertex_attributes={k: np.array(v) for k, v in (attributes or {}).items()},
        face_attributes={k: np.array(v) for k, v in (face_attributes or {}).items()},
        process=False,
        validate=False,
    )


def from_trimesh(obj: Any) -> dict[str, Any]:
    """The arrays of a ``trimesh.Trimesh`` or ``trimesh.PointCloud``, by :data:`FIELDS`.

    Only normals the mesh was given (or computed and kept) are taken, as trimesh's own PLY
    export does; colours come as 8-bit RGB, or RGBA when some alpha is not 255.

    Raises
    ------
    InputError
        ``obj`` is another trimesh type (a scene, a path, ...).
    """
    name = type(obj).__name__
    out: dict[str, Any] = dict.fromkeys(FIELDS)
    out["attributes"], out["face_attributes"] = {}, {}
    if name == "PointCloud":
        out["points"] = np.asarray(obj.vertices, dtype=np.float64)
        meta = getattr(obj, "metadata", None) or {}
        if meta.get("vertex_normals") is not None:
            out["normals"] = np.asarray(meta["vertex_normals"], dtype=np.float64)
        out["attributes"] = {k: np.asarray(v) for k, v in meta.get("vertex_attributes", {}).items()}
        colors = np.asarray(obj.colors) if len(obj.colors) else None
        if colors is not None and colors.shape[:1] == (len(out["points"]),):
            out["colors"] = _drop_opaque_alpha(colors)
        return out
    if name == "Trimesh":
        out["points"] = np.asarray(obj.vertices, dtype=np.float64)
        out["faces"] = np.asarray(obj.faces, dtype=np.int64).reshape(-1, 3)
        # trimesh computes normals on access: take only those it holds, as its PLY export does
        if "vertex_normals" in obj._cache:
            out["normals"] = np.asarray(obj.vertex_normals, dtype=np.float64)
        if obj.visual.kind == "vertex":
            out["colors"] = _drop_opaque_alpha(np.asarray(obj.visual.vertex_colors))
        n, m = len(out["points"]), len(out["faces"])
        out["attributes"] = {
            k: np.asarray(v)
            for k, v in obj.vertex_attributes.items()
            if k != "color" and len(v) == n
        }
        out["face_attributes"] = {
            k: np.asarray(v) for k, v in obj.face_attributes.items() if len(v) == m
        }
        return out
    raise InputError(f"a trimesh {name} is not a point cloud or a triangle mesh")
