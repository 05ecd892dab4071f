"""The solved indicator on a regular grid (``--grid``, as PoissonRecon's ``--grid``).

Recon's own grid file (:class:`recon_cli.grid.Grid`), a field whose zero level is the surface the
stage extracts and which is negative inside, so ``recon mcubes`` gives the same surface and ``recon
info`` describes it.

The grid's samples are the points of the tree's finest lattice (the corners of its finest
cells, where the extraction reads chi) within two finest cells of the surface's bounding
box (the cube, or the free boundary's domain, bounds it; on the cube's faces chi counts as
outside, as in the extraction, so a surface running into them closes). chi is read as the
extraction reads it: in each leaf of the tree, trilinear from the leaf's corners (exact at
the finest leaves' corners), so where the surface crosses coarse leaves (an open scan's
closing sheet) the grid has the level set of that interpolant where the extraction has one
flat polygon per leaf. Its value is
``(iso - chi) / g``: zero on the surface, negative where chi is above the iso-value
(inside), and ``g``, the median of ``|grad chi|`` at the surface's vertices, makes it a
length in the input's units near the surface (about the signed distance there; chi is
flat far from the samples, so the values level off away from it).

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from recon_cli.errors import ParameterError, StageFailed
from recon_cli.grid import Grid, allocation_problem

# lattice points of margin around the surface's bounding box
MARGIN = 2
# vertices at which chi's gradient is measured for the scale g (a random subset beyond it)
GRADIENT_VERTICES = 20_000
# lattice points evaluated per call of chi (the positions' temporaries: 24 bytes a point)
CHUNK = 1 << 20


def grid_shape(
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
    domain: tuple[float, float] = (0.0, 1.0),
) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The first lattice index (3,) and the shape of the grid around ``verts`` (world units).

    The lattice of ``res`` cells over the cube ``origin + [0, size]^3``, clamped to ``domain``
    (unit-cube bounds).
    """
    u = (verts - origin) / size * res
    lo_d, hi_d = round(domain[0] * res), round(domain[1] * res)
    i0 = np.clip(np.floor(u.min(axis=0)).astype(np.int64) - MARGIN, lo_d, hi_d)
    i1 = np.clip(np.ceil(u.max(axis=0)).astype(np.int64) + MARGIN, lo_d, hi_d)
    nx, ny, nz = (int(x) for x in (i1 - i0 + 1))
    return i0, (nx, ny, nz)


def gradient_norms(
    chi_at: Callable[[np.ndarray], np.ndarray],
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
) -> np.ndarray:
    """Norms (v,) of chi's gradient (per world unit) at ``verts`` (v, 3), by central differences.

    The differences are a quarter of a finest cell wide.
    """
    u = (verts - origin) / size
    step = 0.25 / res
    g = np.empty((len(u), 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = step
        g[:, a] = (chi_at(u + e) - chi_at(u - e)) / (2.0 * step)
    return np.linalg.norm(g, axis=1) / size


def scale_of(norms: np.ndarray) -> float:
    """The grid's scale ``g``: the median of the gradient's norms at the surface."""
    scale = float(np.median(norms)) if len(norms) else float("nan")
    if not (np.isfinite(scale) and scale > 0):
        raise ParameterError("--grid: chi is flat at the surface; no field to write")
    return scale


def gradient_scale(
    chi_at: Callable[[np.ndarray], np.ndarray],
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
) -> float:
    """Median norm of chi's gradient (per world unit) at up to :data:`GRADIENT_VERTICES` vertices.

    A random subset of that many when there are more.
    """
    if len(verts) > GRADIENT_VERTICES:
        pick = np.random.default_rng(0).choice(len(verts), GRADIENT_VERTICES, replace=False)
        verts = verts[np.sort(pick)]
    return scale_of(gradient_norms(chi_at, verts, origin, size, res))


def field_block(
    chi_at: Callable[[np.ndarray], np.ndarray],
    iso: float,
    g: float,
    i0: np.ndarray,
    shape: tuple[int, int, int],
    res: int,
    xs: range,
) -> np.ndarray:
    """The grid's planes ``xs`` (indices into its first axis): ``(iso - chi) / g``, float32.

    Returns (len(xs), ny, nz); ``i0`` and ``shape`` as :func:`grid_shape` gives them.
    """
    ny, nz = shape[1], shape[2]
    out = np.empty((len(xs), ny, nz), np.float32)
    jy, jz = np.meshgrid(np.arange(ny), np.arange(nz), indexing="ij")
    plane = np.stack([jy.reshape(-1), jz.reshape(-1)], axis=1).astype(np.float64)
    step = max(1, CHUNK // max(ny * nz, 1))
    for x0 in range(0, len(xs), step):
        cols = np.arange(xs.start + x0, min(xs.stop, xs.start + x0 + step))
        pos = np.empty((len(cols), ny * nz, 3))
        pos[:, :, 0] = (cols + i0[0])[:, None]
        pos[:, :, 1] = plane[None, :, 0] + i0[1]
        pos[:, :, 2] = plane[None, :, 1] + i0[2]
        vals = chi_at(pos.reshape(-1, 3) / res)
        out[x0 : x0 + len(cols)] = ((iso - vals) / g).reshape(len(cols), ny, nz)
    return out


def close_cube_faces(sdf: np.ndarray, i0: np.ndarray, res: int, g: float) -> None:
    """Lift the grid's planes on the cube's faces to outside, as the extraction clamps them.

    A surface running into the cube's faces then closes there. ``sdf`` is changed in place.
    """
    from recon_cli.stages.poisson.extract import FACE_MARGIN

    floor = np.float32(FACE_MARGIN / g)
    shape = sdf.shape
    for a in range(3):
        for idx, on in ((0, i0[a] == 0), (shape[a] - 1, i0[a] + shape[a] - 1 == res)):
            if on:
                sl: list[slice | int] = [slice(None)] * 3
                sl[a] = idx
                np.maximum(sdf[tuple(sl)], floor, out=sdf[tuple(sl)])


def indicator_grid(
    chi_at: Callable[[np.ndarray], np.ndarray],
    iso: float,
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
    domain: tuple[float, float] = (0.0, 1.0),
    history: list[str] | None = None,
    point_dtype=np.float64,
) -> Grid:
    """The grid of ``(iso - chi) / g`` (module docstring) around the surface ``verts``.

    Parameters
    ----------
    chi_at : callable
        chi at (m, 3) positions in the solve's unit cube (``origin + size * u``).
    iso : float
        The surface's iso-value.
    verts : (v, 3) float
        The extracted surface's vertices (world units): its bounding box and the scale.
    origin, size, res
        The solve's cube and its finest lattice (``res`` cells a side).
    domain : (lo, hi)
        Unit-cube bounds of the grid (the free boundary's middle half).
    history, point_dtype
        Of the written grid.

    Raises
    ------
    ParameterError
        The grid would not fit in memory (:func:`recon_cli.grid.allocation_problem`), or
        chi is flat at the surface.
    """
    i0, shape = grid_shape(verts, origin, size, res, domain)
    check_allocation(shape)
    g = gradient_scale(chi_at, verts, origin, size, res)
    sdf = field_block(chi_at, iso, g, i0, shape, res, range(shape[0]))
    if domain == (0.0, 1.0):
        close_cube_faces(sdf, i0, res, g)
    return grid_of(sdf, i0, origin, size, res, history, point_dtype)


def check_allocation(shape: tuple[int, int, int]) -> None:
    """Refuse a grid that would not fit in memory (with the evaluation's temporaries)."""
    why = allocation_problem(shape, 4 + 8)
    if why:
        raise ParameterError(f"--grid: {why}; use a smaller --depth")


def grid_of(
    sdf: np.ndarray,
    i0: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
    history: list[str] | None = None,
    point_dtype=np.float64,
) -> Grid:
    """The :class:`~recon_cli.grid.Grid` of ``sdf`` whose first point is lattice point ``i0``."""
    h = size / res
    return Grid(
        sdf=sdf,
        origin=origin + i0 * h,
        voxel_size=h,
        history=list(history or []),
        point_dtype=point_dtype,
    )


def checked_grid_path(grid: Any) -> str | None:
    """``--grid``'s path, checked before the run (None: no grid asked for).

    Raises
    ------
    ParameterError
        ``-`` (standard output is the mesh's), or a path that cannot be written
        (:func:`recon_cli.io.atomic.check_output`).
    """
    from recon_cli.io.atomic import check_output

    if grid in (None, ""):
        return None
    path = os.fspath(grid)
    if path == "-":
        raise ParameterError("--grid needs a file name ('-' is the mesh's standard output)")
    check_output(path)
    return path


def write_solved_grid(grid: Grid | None, path: str, depth: int, boundary: str, iso: float) -> dict:
    """Write ``grid`` to ``path``, its history ending with how it was made; the report's entries.

    Raises
    ------
    StageFailed
        No grid: the surface is empty.
    """
    from recon_cli.io.npz import write_grid

    if grid is None:
        raise StageFailed("--grid: the surface is empty; no field to write")
    line = (
        f"poisson: (iso - chi) / |grad chi| on the finest lattice, depth {depth}, "
        f"boundary {boundary}, iso {iso:.9g}"
    )
    grid.history = [*grid.history, line]
    write_grid(grid, path)
    return {"grid": path, "grid_shape": list(grid.sdf.shape)}
