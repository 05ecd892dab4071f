"""Numba kernels of the ``sdf`` stage: the side classes of a closed mesh's grid samples.

Kernels only compute; :mod:`recon_cli.stages.sdf` validates and states the guarantee.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (threading layer, see that module)
from recon_cli._kernels.unionfind import union_min


@njit(cache=True)
def side_classes(dist, link, parent):
    """Join 6-neighbour samples whose distances add up to more than ``link``.

    Two samples one voxel apart with ``d1 + d2 > link >= voxel`` see no surface point on
    the segment between them (a point at ``s`` from the first is at least ``d1 - s`` and
    ``d2 - (voxel - s)`` from the surface, one of which is positive), so they are on the
    same side of a closed surface.

    Parameters
    ----------
    dist : (nx, ny, nz) float64, C order
        Unsigned distances (or lower bounds of them).
    link : float
        The voxel size plus a rounding margin.
    parent : (nx*ny*nz,) int32 or int64
        Work array, overwritten by the class label of each sample (0 .. classes-1).

    Returns
    -------
    classes : int
    representative : (classes,) int64
        Per class, the flat index of its sample farthest from the surface.
    """
    nx, ny, nz = dist.shape
    d = dist.reshape(-1)
    n = d.shape[0]
    for s in range(n):
        parent[s] = s
    sy = nz
    sx = ny * nz
    for i in range(nx):
        for j in range(ny):
            base = i * sx + j * sy
            for k in range(nz):
                s = base + k
                ds = d[s]
                if k + 1 < nz and ds + d[s + 1] > link:
                    union_min(parent, s, s + 1)
                if j + 1 < ny and ds + d[s + sy] > link:
                    union_min(parent, s, s + sy)
                if i + 1 < nx and ds + d[s + sx] > link:
                    union_min(parent, s, s + sx)
    # union_min keeps parent[s] <= s, so a forward pass meets every root before the
    # rest of its class and each other sample after its parent: the parent's label is
    # final by then (stored as -1 - label), and one lookup labels the sample
    classes = 0
    for s in range(n):
        p = parent[s]
        if p == s:
            parent[s] = -1 - classes
            classes += 1
        else:
            parent[s] = parent[p]
    rep = np.full(classes, -1, np.int64)
    for s in range(n):
        c = -1 - parent[s]
        parent[s] = c
        if rep[c] < 0 or d[s] > d[rep[c]]:
            rep[c] = s
    return classes, rep


@njit(cache=True)
def negate_inside(dist, classes_of, inside):
    """``dist[s] = -dist[s]`` where ``inside[classes_of[s]]`` (in place, flat)."""
    d = dist.reshape(-1)
    for s in range(d.shape[0]):
        if inside[classes_of[s]]:
            d[s] = -d[s]
