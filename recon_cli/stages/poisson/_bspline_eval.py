"""Numba kernels evaluating the solved degree-2 field: chi at points, roots, leaf corners.

They only compute; conventions in :mod:`._bspline`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli.stages.poisson._bspline import (
    POINT_CHUNK,
    ROW_CHUNK,
    w3,
)
from recon_cli.stages.poisson._octree import MASK21, bsearch, lattice_key


@njit(cache=True, parallel=True)
def chi_at(pos, top, q_all, q_off, inp_all, nb_all, coef_all, s):
    """Chi at unit-cube positions (m, 3) from every level's coefficients.

    The levels' arrays are concatenated: level ``L``'s parents at ``q_off[L]:q_off[L + 1]``, its
    ``nb`` rows there with indices local to the level, its coefficients at ``8 q_off[L]``).

    A level's functions are the coarser levels' plus its corrections, which live on its
    cells and reach the cells next to them: a point takes its value from the finest level
    with a cell of its own within one cell of the point's (every finer level adds nothing
    there), evaluated from the 27 coefficients around it (all in that level's E). Points in
    chunks over the threads.
    """
    m = pos.shape[0]
    out = np.zeros(m)
    nchunks = (m + POINT_CHUNK - 1) // POINT_CHUNK
    for ci in prange(nchunks):
        w = np.empty((3, 3))
        idx = np.empty(27, np.int64)
        for p in range(ci * POINT_CHUNK, min(m, (ci + 1) * POINT_CHUNK)):
            for lv in range(top, 0, -1):
                lo = q_off[lv]
                hi = q_off[lv + 1]
                if hi == lo:
                    continue
                n = 1 << lv
                scale = float(n)
                c0 = min(max(int(np.floor(pos[p, 0] * scale)), 0), n - 1)
                c1 = min(max(int(np.floor(pos[p, 1] * scale)), 0), n - 1)
                c2 = min(max(int(np.floor(pos[p, 2] * scale)), 0), n - 1)
                key = lattice_key(c0 >> 1, c1 >> 1, c2 >> 1)
                i = lower_bound(q_all, key, lo, hi)
                if i >= hi or q_all[i] != key:
                    continue
                ox = c0 & 1
                oy = c1 & 1
                oz = c2 & 1
                # the 27 cells around, looked up once for both loops below (as fast as through
                # nbr_cell on a slice of nb_all: docs/design/poisson.md)
                near = False
                for r in range(27):
                    bx = ox + r % 3 - 1
                    by = oy + (r // 3) % 3 - 1
                    bz = oz + r // 9 - 1
                    q = nb_all[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                    if q < 0:
                        idx[r] = -1
                    else:
                        idx[r] = 8 * (lo + q) + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                        if inp_all[lo + q]:
                            near = True
                if not near:
                    continue
                w[0, 0], w[0, 1], w[0, 2] = w3(min(max(pos[p, 0] * scale - c0, 0.0), 1.0), c0, n, s)
                w[1, 0], w[1, 1], w[1, 2] = w3(min(max(pos[p, 1] * scale - c1, 0.0), 1.0), c1, n, s)
                w[2, 0], w[2, 1], w[2, 2] = w3(min(max(pos[p, 2] * scale - c2, 0.0), 1.0), c2, n, s)
                v = 0.0
                for r in range(27):
                    j = idx[r]
                    if j >= 0:
                        v += w[0, r % 3] * w[1, (r // 3) % 3] * w[2, r // 9] * coef_all[j]
                out[p] = v
                break
    return out


@njit(cache=True)
def edge_roots(lat, iso, v0, vm, v1, clamp):
    """Position along each lattice edge where the quadratic through its samples crosses ``iso``.

    The quadratic goes through (0, ``v0``), (1/2, ``vm``), (1, ``v1``) (the edge's root nearest the
    linear estimate ``lat``, a fraction in [0, 1]), kept ``clamp`` away from the ends as marching
    cubes keeps its own (a vertex at a lattice point would leave degenerate faces); ``lat`` itself
    where the end values do not straddle ``iso``.
    """
    n = len(lat)
    out = lat.copy()
    for i in range(n):
        a = v0[i] - iso
        b = v1[i] - iso
        if a * b > 0.0 or a == b:
            continue
        # q(t) = a + (4 (vm - iso) - 3 a - b) t + (2 a + 2 b - 4 (vm - iso)) t^2
        c1 = 4.0 * (vm[i] - iso) - 3.0 * a - b
        c2 = 2.0 * a + 2.0 * b - 4.0 * (vm[i] - iso)
        t = lat[i]
        if abs(c2) < 1e-12 * (abs(c1) + abs(a) + 1e-300):
            if c1 != 0.0:
                t = min(max(-a / c1, min(lat[i], clamp)), max(lat[i], 1.0 - clamp))
        else:
            disc = c1 * c1 - 4.0 * c2 * a
            if disc >= 0.0:
                sq = np.sqrt(disc)
                # the numerically stable pair of roots
                qq = -0.5 * (c1 + (sq if c1 >= 0.0 else -sq))
                r1 = qq / c2
                r2 = a / qq if qq != 0.0 else r1
                best = -1.0
                bd = 1e300
                for r in (r1, r2):
                    if -1e-9 <= r <= 1.0 + 1e-9 and abs(r - lat[i]) < bd:
                        bd = abs(r - lat[i])
                        best = r
                if bd < 1e300:
                    t = min(max(best, min(lat[i], clamp)), max(lat[i], 1.0 - clamp))
        out[i] = t
    return out


@njit(cache=True, parallel=True)
def constrain_to_coarse_leaves(node_keys, g, coarse_keys, coarse_nodes, coarse_leaf, g_coarse):
    """Give a level's nodes on the coarser level's leaves' faces or edges the leaves' values.

    The values are the leaves' trilinear interpolation, in place (as hanging nodes do): the
    extraction interpolates a
    leaf trilinearly from its corners, so the finer side of a face must see the same values
    there or the surface cracks along it. Cells of a level touch leaves of the next coarser
    level only, so one level up suffices (coarse to fine, the coarse values already
    constrained). Nodes in chunks over the threads.
    """
    m = len(node_keys)
    for ch in prange((m + ROW_CHUNK - 1) // ROW_CHUNK):
        cand = np.empty((3, 2), np.int64)
        nc = np.empty(3, np.int64)
        for j in range(ch * ROW_CHUNK, min(m, (ch + 1) * ROW_CHUNK)):
            k = node_keys[j]
            x = (k >> 42) & MASK21
            y = (k >> 21) & MASK21
            z = k & MASK21
            if (x & 1) == 0 and (y & 1) == 0 and (z & 1) == 0:
                continue  # a corner of the coarser lattice: chi's own value on both sides
            for a in range(3):
                v = x if a == 0 else (y if a == 1 else z)
                if v & 1:
                    cand[a, 0] = (v - 1) >> 1
                    nc[a] = 1
                else:
                    cand[a, 0] = (v >> 1) - 1
                    cand[a, 1] = v >> 1
                    nc[a] = 2
            done = False
            for ia in range(nc[0]):
                for ib in range(nc[1]):
                    for ic in range(nc[2]):
                        cx = cand[0, ia]
                        cy = cand[1, ib]
                        cz = cand[2, ic]
                        if cx < 0 or cy < 0 or cz < 0 or done:
                            continue
                        c = bsearch(coarse_keys, lattice_key(cx, cy, cz))
                        if c < 0 or not coarse_leaf[c]:
                            continue
                        fx = 0.5 * (x - 2 * cx)
                        fy = 0.5 * (y - 2 * cy)
                        fz = 0.5 * (z - 2 * cz)
                        v = 0.0
                        for r in range(8):
                            w = (
                                (fx if r & 1 else 1.0 - fx)
                                * (fy if (r >> 1) & 1 else 1.0 - fy)
                                * (fz if (r >> 2) & 1 else 1.0 - fz)
                            )
                            if w != 0.0:
                                v += w * g_coarse[coarse_nodes[c, r & 3] + (r >> 2)]
                        g[j] = v
                        done = True
