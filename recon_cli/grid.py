"""A signed-distance grid and its ``.npz`` file format.

Format (``numpy.savez``, uncompressed):

``sdf``
    float32, shape (nx, ny, nz); negative inside, NaN where unknown.
``origin``
    float64 (3,): xyz of sample [0, 0, 0].
``voxel_size``
    float64 scalar: spacing of samples along every axis.
``provenance``
    str: history lines joined by newlines (oldest first).
"""

from __future__ import annotations

import io
import os
import zipfile
from dataclasses import dataclass, field

import numpy as np

from recon_cli.errors import InputError


@dataclass
class Grid:
    """Samples of a scalar field on a regular grid.

    Parameters
    ----------
    sdf : (nx, ny, nz) float32
        Field values (signed distance, negative inside; NaN = unknown).
    origin : (3,) float64
        Position of sample [0, 0, 0].
    voxel_size : float
        Spacing between samples, in the units of the source.
    history : list of str
        Provenance lines.
    """

    sdf: np.ndarray
    origin: np.ndarray
    voxel_size: float
    history: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.sdf = np.asarray(self.sdf, dtype=np.float32)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(self.voxel_size)
        if self.sdf.ndim != 3:
            raise InputError(f"sdf must be 3-d, got shape {self.sdf.shape}")
        if not self.voxel_size > 0:
            raise InputError(f"voxel_size must be positive, got {self.voxel_size}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.sdf.shape)  # type: ignore[return-value]

    def positions(self, index: np.ndarray) -> np.ndarray:
        """World coordinates of (fractional) grid indices ``index`` ((k, 3))."""
        return self.origin + np.asarray(index, dtype=np.float64) * self.voxel_size


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
    )
    return buf.getvalue()


def read_grid(path: str | os.PathLike, data: bytes | None = None) -> Grid:
    """Read a grid ``.npz`` (``-``: standard input).

    Raises
    ------
    InputError
        Not an npz, missing arrays, wrong shapes or types.
    """
    from recon_cli.io.ply import read_bytes

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
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise InputError(f"corrupt grid file ({exc})", where) from None
    if sdf.ndim != 3 or sdf.dtype.kind != "f":
        raise InputError(f"'sdf' must be a 3-d float array, got {sdf.dtype} {sdf.shape}", where)
    if origin.shape != (3,) or voxel.shape != () or not float(voxel) > 0:
        raise InputError("'origin' must have 3 values and 'voxel_size' be one positive value", where)
    return Grid(sdf=sdf, origin=origin, voxel_size=float(voxel), history=[s for s in prov.split("\n") if s])


def write_grid(grid: Grid, path: str | os.PathLike) -> None:
    """Write ``grid`` atomically (``-``: standard output)."""
    from recon_cli.io.atomic import write_bytes

    write_bytes(path, grid_bytes(grid))
