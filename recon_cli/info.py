"""``recon info``: what a file holds, as a dict with stable keys.

Keys (PLY): ``file``, ``kind`` ("point_cloud" or "mesh"), ``format``, ``vertices``,
``faces``, ``elements`` (name -> count), ``properties`` (element -> list of
"type name"), ``bbox`` ({"min", "max", "diagonal"}), ``has_normals``, ``has_colors``,
``history`` (provenance lines), and for meshes ``topology`` (see
:func:`recon_cli.mesh.topology.report`).
Keys (grid): ``file``, ``kind`` ("grid"), ``shape``, ``origin``, ``voxel_size``,
``unknown_cells``, ``range``, ``eikonal``, ``history``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from recon_cli.geometry import TriangleMesh, bbox_diagonal
from recon_cli.io.npz import is_npz, read_grid
from recon_cli.io.ply import parse_ply, ply_to_geometry, read_bytes


def describe(path: str | os.PathLike) -> dict[str, Any]:
    """Describe the file at ``path`` (``-``: stdin)."""
    data = read_bytes(path)
    name = "<stdin>" if str(path) == "-" else str(path)
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
        "properties": {e.name: [p.header_line().replace("property ", "") for p in e.properties] for e in ply.elements},
        "bbox": {
            "min": pts.min(axis=0).tolist() if len(pts) else None,
            "max": pts.max(axis=0).tolist() if len(pts) else None,
            "diagonal": bbox_diagonal(pts),
        },
        "has_normals": geom.normals is not None,
        "has_colors": geom.colors is not None,
        "attributes": sorted(geom.attributes),
        "history": list(ply.comments),
    }
    if isinstance(geom, TriangleMesh):
        from recon_cli.mesh.topology import report as topology_report

        out["topology"] = topology_report(geom)
    return out


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
        from recon_cli.sdf import eikonal_check
    except ModuleNotFoundError:
        eikonal_check = None
    if eikonal_check is not None:
        out["eikonal"] = eikonal_check(grid)
    return out
