"""The grid file format (``.npz``): :class:`recon_cli.grid.Grid` on disk.

Format (``numpy.savez``, uncompressed):

``sdf``
    float32, shape (nx, ny, nz); negative inside, NaN where unknown.
``origin``
    float64 (3,): xyz of sample [0, 0, 0].
``voxel_size``
    float64 scalar: spacing of samples along every axis.
``provenance``
    str: history lines joined by newlines (oldest first).
``point_dtype`` (optional)
    str, ``float32`` or ``float64``: the float type of the source's coordinates, which
    meshes extracted from the grid are written with (float32 when absent).
"""

from __future__ import annotations

import io
import os
import zipfile

import numpy as np

from recon_cli.errors import InputError
from recon_cli.grid import Grid
from recon_cli.io.atomic import write_bytes
from recon_cli.io.ply import read_bytes


def is_npz(data: bytes) -> bool:
    """True when ``data`` starts like a zip archive (``.npz``)."""
    return bytes(memoryview(data)[:4]) == b"PK\x03\x04"


def grid_bytes(grid: Grid) -> bytes:
    buf = io.BytesIO()
    np.savez(
        buf,
        sdf=grid.sdf.astype(np.float32),
        origin=grid.origin,
        voxel_size=np.float64(grid.voxel_size),
        provenance=np.array("\n".join(grid.history)),
        point_dtype=np.array(np.dtype(grid.point_dtype).name),
    )
    return buf.getvalue()


def read_grid(path: str | os.PathLike, data: bytes | None = None) -> Grid:
    """Read a grid ``.npz`` (``-``: standard input).

    Raises
    ------
    InputError
        Not an npz, missing arrays, wrong shapes or types.
    """
    where = "<stdin>" if str(path) == "-" else str(path)
    buf = read_bytes(path) if data is None else data
    if not is_npz(buf):
        raise InputError("not a grid .npz file", where)
    try:
        with np.load(io.BytesIO(buf), allow_pickle=False) as z:
            missing = [k for k in ("sdf", "origin", "voxel_size") if k not in z.files]
            if missing:
                raise InputError(f"grid file lacks {missing[0]!r}", where)
            sdf = z["sdf"]
            origin = z["origin"]
            voxel = z["voxel_size"]
            prov = str(z["provenance"]) if "provenance" in z.files else ""
            pdt = str(z["point_dtype"]) if "point_dtype" in z.files else "float32"
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise InputError(f"corrupt grid file ({exc})", where) from None
    if sdf.ndim != 3 or sdf.dtype.kind != "f":
        raise InputError(f"'sdf' must be a 3-d float array, got {sdf.dtype} {sdf.shape}", where)
    if origin.shape != (3,) or voxel.shape != () or not float(voxel) > 0:
        raise InputError("'origin' must have 3 values and 'voxel_size' be one positive value", where)
    if pdt not in ("float32", "float64"):
        raise InputError(f"'point_dtype' must be float32 or float64, got {pdt[:40]!r}", where)
    return Grid(
        sdf=sdf, origin=origin, voxel_size=float(voxel), history=[s for s in prov.split("\n") if s], point_dtype=pdt
    )


def write_grid(grid: Grid, path: str | os.PathLike) -> None:
    """Write ``grid`` atomically (``-``: standard output)."""
    write_bytes(path, grid_bytes(grid))
