"""From a fitted field (:class:`recon_cli.stages.learned.model.SdfModel`) to a grid and a mesh."""

from __future__ import annotations

import numpy as np

from recon_cli.stages.learned.model import SdfModel

COARSE = 4  # fine samples per coarse cell when sampling the grid


def _evaluate(model: SdfModel, ix, iy, iz) -> np.ndarray:
    """The field at the lattice ``ix x iy x iz`` (world coordinates along each axis)."""
    g = np.stack(np.meshgrid(ix, iy, iz, indexing="ij"), axis=-1).reshape(-1, 3)
    return model.values(g).reshape(len(ix), len(iy), len(iz))


def _corner_views(a: np.ndarray) -> list[np.ndarray]:
    """The 8 corner values of every cell of the lattice ``a``, as 8 arrays of the cells' shape."""
    n = a.shape
    return [
        a[dx : dx + n[0] - 1, dy : dy + n[1] - 1, dz : dz + n[2] - 1]
        for dx in (0, 1)
        for dy in (0, 1)
        for dz in (0, 1)
    ]


def _cells_in_reach(coarse: np.ndarray, reach: float) -> np.ndarray:
    """Coarse cells with a corner within ``reach`` of the surface or a sign change, (k, 3)."""
    near = np.minimum.reduce(_corner_views(np.abs(coarse))) < reach
    neg = _corner_views(coarse < 0)
    near |= np.logical_or.reduce(neg) & ~np.logical_and.reduce(neg)
    return np.argwhere(near)


def _fine_mask(cells: np.ndarray, c: int, shape: tuple[int, int, int]) -> np.ndarray:
    """The fine samples of the coarse ``cells`` (``c`` fine cells a side), corners included."""
    fine = np.zeros(shape, dtype=bool)
    for dx in range(c + 1):
        for dy in range(c + 1):
            for dz in range(c + 1):
                i = np.minimum(cells * c + (dx, dy, dz), np.array(shape) - 1)
                fine[i[:, 0], i[:, 1], i[:, 2]] = True
    return fine


def sample_grid(
    model: SdfModel, origin: np.ndarray, voxel_size: float, shape: tuple[int, int, int]
) -> np.ndarray:
    """The field on a regular grid, (nx, ny, nz) float32 (world units, negative inside).

    ``sdf``: the network is evaluated at every sample of the coarse cells (``4`` samples a
    side) whose corners can be within reach of the surface (|s| below 1.5 coarse-cell
    diagonals or 6 % of the grid's diagonal, or a sign change), elsewhere the coarse grid
    is interpolated trilinearly.
    ``occupancy`` (not a distance: no such bound) is evaluated everywhere.
    """
    from scipy.ndimage import map_coordinates

    nx, ny, nz = (int(s) for s in shape)
    shape = (nx, ny, nz)
    origin = np.asarray(origin, dtype=np.float64)
    h = float(voxel_size)
    c = COARSE
    if model.field != "sdf" or min(shape) < 4 * c:
        axes = [origin[a] + h * np.arange(shape[a]) for a in range(3)]
        return _evaluate(model, *axes).astype(np.float32)
    cshape = [(s - 1 + c - 1) // c + 1 for s in shape]  # coarse nodes cover the grid
    coarse = _evaluate(model, *[origin[a] + h * c * np.arange(cshape[a]) for a in range(3)])
    # trilinear everywhere (fine sample (i, j, k) sits at coarse index (i/c, j/c, k/c))
    idx = np.indices(shape, dtype=np.float32).reshape(3, -1) / c
    out = map_coordinates(coarse, idx, order=1, mode="nearest").reshape(shape).astype(np.float32)
    # exact values wherever the surface may be within reach, and in a band of 6 % of the
    # grid's diagonal (trilinear interpolation of a curved distance field understates its
    # gradient there)
    reach = max(1.5 * np.sqrt(3.0) * c * h, 0.06 * h * float(np.linalg.norm(np.array(shape) - 1)))
    cells = _cells_in_reach(coarse, reach)
    if len(cells):
        fine = _fine_mask(cells, c, shape)
        where = np.argwhere(fine)
        out[fine] = model.values(origin + where * h).astype(np.float32)
    return out


def extract_mesh(model: SdfModel, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes on ``grid`` (sampled from ``model``) with autodiff vertex normals.

    Returns
    -------
    vertices : (k, 3) float64
    faces : (m, 3) int64
        Counter-clockwise seen from outside.
    normals : (k, 3) float64
        Unit gradients of the network at the vertices (outward).
    """
    from recon_cli.stages.mcubes import marching_cubes

    v, f, _ = marching_cubes(grid.sdf, iso=0.0, spacing=grid.voxel_size, origin=grid.origin)
    if len(v) == 0:
        return v, f, np.zeros((0, 3))
    _, g = model.gradients(v)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return v, f, np.divide(g, n, out=np.zeros_like(g), where=n > 0)
