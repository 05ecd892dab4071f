"""The free boundary (PoissonRecon's ``--bType 1``, ``BOUNDARY_FREE``).

No condition on the reconstruction cube's faces.

The Neumann and Dirichlet bases reflect each level's B-splines at the cube's faces (chi's
normal derivative, or chi, is 0 there), so an open surface bends to meet the faces at right
angles, or closes before them, and sheets hug the faces (Open3D#6095, #6481). The free basis
also has the functions of the cells just beyond the faces, unreflected, and every integral of
the system (stiffness, mass, the normals' right-hand side) runs over the cube only: chi takes
whatever value and slope the samples ask for at the faces, an open surface runs straight on
to them and the mesh is cut there (open along the faces).

Made with the solver's own machinery: :func:`recon_cli.stages.poisson.screened_poisson` solves
on a cube twice as large, one level deeper (the same finest cell), whose middle half
(:data:`FREE_DOMAIN` along every axis) is the reconstruction cube; the levels' 1D tables are
the integrals over that half only (:func:`domain_tables`), so the cells whose support misses
it have no equation (their rows are 0: the conjugate gradients leave them at 0), and the
mesh is clipped to it (:func:`clip_to_cube`). Level 1 of the doubled cube (2 cells a side),
whose cells the half does not follow, carries no function: every finer level up to the full
depth is solved exactly and holds what it would.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M. PoissonRecon 18 (BSplineData: BOUNDARY_FREE, functions padded beyond the faces).
"""

from __future__ import annotations

import numpy as np

# the reconstruction cube: the middle half of the solve's cube along every axis
FREE_DOMAIN = (0.25, 0.75)
# Gauss-Legendre points and weights on [0, 1]: exact for the quartic products of two pieces
_GAUSS_T = 0.5 + 0.5 * np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GAUSS_W = np.array([5.0, 8.0, 5.0]) / 18.0


def domain_tables(n: int, lo: float, hi: float) -> tuple[np.ndarray, ...]:
    """(n, 5) tables ``m1``, ``k1``, ``fv``, ``fd`` integrated over ``[lo, hi]`` only.

    The (unreflected) functions of cells ``0..n-1``, in cell units: between cell ``i`` and cell
    ``i + t`` (column ``t + 2``) the mass, the stiffness, the value factor (the mass) and
    the derivative factor ``int B_i' B_{i+t}`` (per cell, not per unit length). Rows of the
    cells whose support misses the interval are 0 (no equation: fixed in the solve).
    """
    m1 = np.zeros((n, 5))
    k1 = np.zeros((n, 5))
    fd = np.zeros((n, 5))
    lo, hi = max(lo, -2.0), min(hi, n + 2.0)
    cells = np.arange(int(np.floor(lo)), int(np.ceil(hi)))
    a = np.maximum(cells, lo)
    b = np.minimum(cells + 1, hi)
    keep = b > a
    cells, a, b = cells[keep], a[keep], b[keep]
    if not len(cells):
        return m1, k1, m1.copy(), fd
    # quadrature points (p,) in the cells, their local coordinate and weight
    u = (a[:, None] + (b - a)[:, None] * _GAUSS_T[None, :]).reshape(-1)
    w = ((b - a)[:, None] * _GAUSS_W[None, :]).reshape(-1)
    c = np.repeat(cells, 3)
    t = u - c
    # the functions of cells c - 1, c, c + 1 at u: values and derivatives
    val = np.stack([0.5 * (1 - t) ** 2, 0.75 - (t - 0.5) ** 2, 0.5 * t * t], axis=1)
    der = np.stack([-(1 - t), -2.0 * (t - 0.5), t], axis=1)
    for ia in range(3):
        i = c - 1 + ia
        ok = (i >= 0) & (i < n)
        for ib in range(3):
            col = ib - ia + 2
            np.add.at(m1[:, col], i[ok], (w * val[:, ia] * val[:, ib])[ok])
            np.add.at(k1[:, col], i[ok], (w * der[:, ia] * der[:, ib])[ok])
            np.add.at(fd[:, col], i[ok], (w * der[:, ia] * val[:, ib])[ok])
    return m1, k1, m1.copy(), fd


def clip_to_cube(
    verts: np.ndarray, faces: np.ndarray, origin: np.ndarray, size: float
) -> tuple[np.ndarray, np.ndarray]:
    """The faces inside the cube ``origin + [0, size]^3`` and their vertices.

    The cube is the free boundary's domain. The extraction's leaves are cells of levels whose
    lattice the cube's faces follow, so every triangle lies in a leaf on one side; its centroid says
    which.
    """
    if not len(faces):
        return verts, faces
    cen = verts[faces].mean(axis=1)
    eps = 1e-9 * size
    inside = np.all((cen > origin - eps) & (cen < origin + size + eps), axis=1)
    faces = faces[inside]
    used = np.zeros(len(verts), bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return verts[used], remap[faces].astype(faces.dtype)
