"""A scalar field sampled on a regular grid (signed distance, negative inside).

Its file format (``.npz``) is read and written by :mod:`recon_cli.io.npz`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

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
    point_dtype : np.float32 or np.float64
        Float type of the coordinates of the source the grid was computed from; meshes
        extracted from it are written with it (see :func:`recon_cli.geometry.storage_dtype`).
    """

    sdf: np.ndarray
    origin: np.ndarray
    voxel_size: float
    history: list[str] = field(default_factory=list)
    point_dtype: Any = np.float32

    def __post_init__(self) -> None:
        self.sdf = np.asarray(self.sdf, dtype=np.float32)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(self.voxel_size)
        self.point_dtype = np.float64 if np.dtype(self.point_dtype) == np.float64 else np.float32
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
