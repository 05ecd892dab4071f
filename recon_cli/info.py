"""``recon info``: what a file holds, as a dict with stable keys.

Keys (PLY): ``file``, ``kind`` ("point_cloud" or "mesh"), ``format``, ``vertices``,
``faces``, ``elements`` (name -> count), ``properties`` (element -> list of
"type name"), ``bbox`` ({"min", "max", "diagonal"}), ``has_normals``, ``has_colors``,
``invalid_dropped`` (points with a NaN or infinite coordinate the reader dropped),
``organized`` (``"640x480"``: the image(s) an organized cloud came from, else None),
``sensors`` (the scanner positions the file gives, one line each), ``history``
(provenance lines), and for meshes ``topology`` (see :func:`recon_cli.mesh.topology.report`).
Other formats (OBJ, OFF, STL, XYZ, PCD, LAS, E57): the same keys, ``format`` being the
format's name, plus ``details`` (what the reader reports: STL weld, LAS header, PCD fields...).
A COPC file (``.copc.laz``, or a LAS/LAZ name holding one) is described from its header and
hierarchy without decoding a point: ``bbox`` is the header's, ``details`` has the octree's
levels (:func:`describe_copc`).
Keys (grid): ``file``, ``kind`` ("grid"), ``shape``, ``origin``, ``voxel_size``,
``unknown_cells``, ``range``, ``eikonal`` (with ``near``: the figures near the zero level,
``recon_cli.stages.sdf.eikonal_check``), ``history``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from recon_cli.geometry import TriangleMesh, bbox_diagonal
from recon_cli.io.npz import is_npz, read_grid
from recon_cli.io.ply import parse_ply, ply_to_geometry, read_bytes


def describe(path: str | os.PathLike, format: str | None = None) -> dict[str, Any]:
    """Describe the file at ``path`` (``-``: stdin).

    It is read in the format its suffix (or ``format``) names.
    """
    from recon_cli.io.load import decode, format_of, load_detailed

    name = "<stdin>" if str(path) == "-" else str(path)
    fmt = format_of(path, format)
    if fmt is not None and fmt.name in ("las", "copc") and str(path) != "-" and format is None:
        from recon_cli.io.copc import is_copc_file

        if fmt.name == "copc" or is_copc_file(path):
            return describe_copc(path, name)
    if fmt is not None and fmt.name in ("las", "e57") and str(path) != "-":
        geom, details, fmt = load_detailed(path, format)
        return describe_geometry(geom, name, fmt.name, details)
    data = read_bytes(path)
    if fmt is None or fmt.name not in ("ply", "npz"):
        obj, details, fmt = decode(data, path, fmt)
        if fmt.name not in ("ply", "npz"):
            return describe_geometry(obj, name, fmt.name, details)
    if is_npz(data):
        return describe_grid(read_grid(path, data), name)
    ply = parse_ply(data, str(path))
    geom = ply_to_geometry(ply, str(path))
    pts = geom.points
    out: dict[str, Any] = {
        "file": name,
        "kind": "mesh" if isinstance(geom, TriangleMesh) else "point_cloud",
        "format": ply.format,
        "vertices": int(len(pts)),
        "faces": int(len(geom.faces)) if isinstance(geom, TriangleMesh) else 0,
        "elements": {e.name: e.count for e in ply.elements},
        "properties": {
            e.name: [p.header_line().replace("property ", "") for p in e.properties]
            for e in ply.elements
        },
        **_geometry_keys(geom),
        "history": list(ply.comments),
    }
    if isinstance(geom, TriangleMesh):
        from recon_cli.mesh.topology import report as topology_report

        # only what the report reads (float64 rows: no copy when the file's are doubles): the
        # file's bytes, the parsed face lists and the attributes go before the topology needs
        # its memory
        mesh = TriangleMesh(
            vertices=np.ascontiguousarray(geom.vertices, dtype=np.float64), faces=geom.faces
        )
        del geom, pts, ply, data
        out["topology"] = topology_report(mesh)
    return out


def describe_geometry(geom, name: str, fmt: str, details: dict) -> dict[str, Any]:
    """Describe a cloud or mesh read from a non-PLY file: the keys of PLY's, and ``details``."""
    pts = geom.points
    mesh = isinstance(geom, TriangleMesh)
    vprops = [f"{np.dtype(pts.dtype).name} x y z"]
    if geom.normals is not None:
        vprops.append(f"{geom.normals.dtype.name} normals")
    if geom.colors is not None:
        vprops.append(f"{geom.colors.dtype.name} colours x{geom.colors.shape[1]}")
    vprops += [f"{v.dtype.name} {k}" for k, v in geom.attributes.items()]
    elements = {"vertex": int(len(pts))}
    properties = {"vertex": vprops}
    if mesh:
        elements["face"] = int(len(geom.faces))
        properties["face"] = ["int64 vertex_indices x3"] + [
            f"{v.dtype.name} {k}" for k, v in geom.face_attributes.items()
        ]
    out: dict[str, Any] = {
        "file": name,
        "kind": "mesh" if mesh else "point_cloud",
        "format": fmt,
        "vertices": int(len(pts)),
        "faces": int(len(geom.faces)) if mesh else 0,
        "elements": elements,
        "properties": properties,
        **_geometry_keys(geom),
        "history": list(geom.history),
        "details": {k: v for k, v in details.items() if k != "format"},
    }
    if mesh:
        try:
            from recon_cli.mesh.topology import report as topology_report
        except ModuleNotFoundError:
            topology_report = None  # type: ignore[assignment]  # a build without the mesh package
        if topology_report is not None:
            out["topology"] = topology_report(geom)
    return out


def describe_copc(path: str | os.PathLike, name: str) -> dict[str, Any]:
    """Describe a COPC file from its header and hierarchy, decoding no point.

    The keys of :func:`describe_geometry` (``bbox`` the header's bounds), and in ``details``
    the octree's: ``octree_center``, ``octree_halfsize``, ``octree_spacing``,
    ``octree_nodes``, ``nodes_per_level`` and ``points_per_level``.
    """
    from recon_cli.io.copc import summary

    s = summary(str(path), name)
    corners = np.array([s["mins"], s["maxs"]])
    return {
        "file": name,
        "kind": "point_cloud",
        "format": "copc",
        "vertices": s["points"],
        "faces": 0,
        "elements": {"vertex": s["points"]},
        "properties": {"vertex": s["dimensions"]},
        "bbox": {"min": s["mins"], "max": s["maxs"], "diagonal": bbox_diagonal(corners)},
        "has_normals": s["normals"],
        "has_colors": s["colors"],
        "attributes": s["attributes"],
        "invalid_dropped": 0,
        "organized": None,
        "sensors": s["sensors"],
        "history": [],
        "details": {k: v for k, v in s["details"].items() if k != "format"},
    }


def describe_grid(grid, name: str) -> dict[str, Any]:
    """Describe a grid, with the eikonal check when the grid module offers it."""
    sdf = grid.sdf
    finite = np.isfinite(sdf)
    out: dict[str, Any] = {
        "file": name,
        "kind": "grid",
        "shape": list(sdf.shape),
        "origin": grid.origin.tolist(),
        "voxel_size": grid.voxel_size,
        "unknown_cells": int((~finite).sum()),
        "range": [float(sdf[finite].min()), float(sdf[finite].max())] if finite.any() else None,
        "inside_cells": int((sdf[finite] < 0).sum()),
        "history": list(grid.history),
    }
    try:
        from recon_cli.stages.sdf import eikonal_check
    except ModuleNotFoundError:
        eikonal_check = None  # type: ignore[assignment]  # a build without the sdf stage
    if eikonal_check is not None:
        out["eikonal"] = eikonal_check(grid)
    return out


def _geometry_keys(geom: Any) -> dict[str, Any]:
    """The keys every cloud or mesh description shares.

    Bounding box, normals, colours, attributes.
    """
    pts = geom.points
    return {
        "bbox": {
            "min": pts.min(axis=0).tolist() if len(pts) else None,
            "max": pts.max(axis=0).tolist() if len(pts) else None,
            "diagonal": bbox_diagonal(pts),
        },
        "has_normals": geom.normals is not None,
        "has_colors": geom.colors is not None,
        "attributes": sorted(geom.attributes),
        "invalid_dropped": int(getattr(geom, "invalid_dropped", 0)),
        "organized": None if getattr(geom, "pixels", None) is None else geom.pixels.describe(),
        "sensors": [s.describe() for s in getattr(geom, "sensors", ())],
    }
