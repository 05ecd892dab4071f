"""Load any recon input (PLY cloud or mesh, grid npz) and save any stage output."""

from __future__ import annotations

import os
from typing import Any

from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.grid import Grid
from recon_cli.io.npz import is_npz, read_grid, write_grid
from recon_cli.io.ply import read_bytes, read_ply, write_ply


def load(path: str | os.PathLike) -> PointCloud | TriangleMesh | Grid:
    """Read ``path`` (``-``: stdin), telling PLY from grid ``.npz`` by content."""
    if str(path) != "-" and os.path.isfile(path):
        with open(path, "rb") as f:
            magic = f.read(4)
        # PLY files go straight to read_ply, which decodes the vertices while it reads
        return read_grid(path) if is_npz(magic) else read_ply(path)
    data = read_bytes(path)
    if is_npz(data):
        return read_grid(path, data)
    return read_ply(path, data)


def save(obj: Any, path: str | os.PathLike, ascii: bool = False) -> None:
    """Write a stage output atomically: grids as ``.npz``, clouds and meshes as PLY."""
    if isinstance(obj, Grid):
        write_grid(obj, path)
    else:
        write_ply(obj, path, ascii=ascii)
