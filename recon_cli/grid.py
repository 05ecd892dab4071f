"""A scalar field sampled on a regular grid (signed distance, negative inside).

Its file format (``.npz``) is read and written by :mod:`recon_cli.io.npz`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import InputError


class _Reported:
    report: dict[str, Any] | None = None


@dataclass
class Grid(_Reported):
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

    Attributes
    ----------
    report : dict or None
        The report of the stage whose result this is, when a library function made it
        (``recon_cli.sdf(...).report``: the keys of ``recon sdf --json``), else None.
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
        if min(self.sdf.shape) == 0:
            raise InputError(
                f"the grid has no samples (shape {' x '.join(map(str, self.sdf.shape))})"
            )
        if not np.isfinite(self.origin).all():
            raise InputError(f"origin must be finite, got {self.origin.tolist()}")
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"voxel_size must be a finite positive number, got {self.voxel_size}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """The number of samples along x, y and z."""
        return tuple(self.sdf.shape)  # type: ignore[return-value]

    def positions(self, index: np.ndarray) -> np.ndarray:
        """World coordinates of (fractional) grid indices ``index`` ((k, 3))."""
        return self.origin + np.asarray(index, dtype=np.float64) * self.voxel_size


def allocation_problem(shape, bytes_per_sample: float) -> str | None:
    """Why a grid of ``shape`` (any sizes, even absurd ones) cannot be had, or None.

    ``bytes_per_sample`` is what the caller allocates per sample at its peak. The answer
    names the estimate and the memory available (:func:`recon_cli.memory.available_bytes`),
    so a caller can refuse before allocating anything.
    """
    from recon_cli.memory import available_bytes

    sizes = [int(s) for s in shape]
    samples = 1
    for s in sizes:
        samples *= s  # Python ints: no overflow for absurd shapes
    need = samples * float(bytes_per_sample)
    avail = available_bytes()
    if samples <= 2**40 and (avail is None or need <= avail):
        return None
    dims = " x ".join(str(s) for s in sizes)
    have = "" if avail is None else f", more than the {_size(avail)} available"
    return f"a grid of {dims} = {samples:.3g} samples needs about {_size(need)}{have}"


def _size(b: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if b >= scale:
            return f"{b / scale:.3g} {unit}"
    return f"{b / 1e3:.3g} kB"
