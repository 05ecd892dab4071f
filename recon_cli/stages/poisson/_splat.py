"""Numba kernels of the splats.

The normals shared among cell-centred quadratic B-splines and the right-hand side of that field
(refinement, stencil, restriction), and the samples' kernel density (counts splatted with quadratic
B-splines centred on cells).

They only compute; conventions in :mod:`recon_cli.stages.poisson._octree`; hash tables are
:mod:`recon_cli._kernels.hashtable`'s (lookups return ``-1`` for a missing key).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli._kernels.hashtable import lookup
from recon_cli.stages.poisson._octree import MASK21, lattice_key


@njit(cache=True, inline="always")
def _cube(x):
    t = x if x > 0.0 else 0.0
    return t * t * t


@njit(cache=True, inline="always")
def _quart(x):
    t = x if x > 0.0 else 0.0
    t *= t
    return t * t


@njit(cache=True)
def _b2_int1(x):
    """Antiderivative of the centred quadratic B-spline (support [-1.5, 1.5]): its CDF."""
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return 1.0
    return (_cube(x + 1.5) - 3.0 * _cube(x + 0.5) + 3.0 * _cube(x - 0.5)) / 6.0


@njit(cache=True)
def _b2_int2(x):
    """Second antiderivative of the centred quadratic B-spline (x for x >= 1.5)."""
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return x
    return (_quart(x + 1.5) - 3.0 * _quart(x + 0.5) + 3.0 * _quart(x - 0.5)) / 24.0


@njit(cache=True)
def hat_b2_value(v, rho):
    """Int hat(z) B2_rho(z - v) dz: a level's hat function against a kernel of width rho."""
    # rho * int2(t / rho) is the second antiderivative of B2_rho
    return rho * (_b2_int2((v + 1.0) / rho) - 2.0 * _b2_int2(v / rho) + _b2_int2((v - 1.0) / rho))


@njit(cache=True)
def hat_b2_deriv(v, rho):
    """Int hat'(z) B2_rho(z - v) dz (v = sample minus node, in level cells)."""
    return -_b2_int1((-1.0 - v) / rho) + 2.0 * _b2_int1(-v / rho) - _b2_int1((1.0 - v) / rho)


@njit(cache=True, inline="always")
def _b2w(t, k):
    # weight of the cell at offset k (-1, 0, 1) for a point at local coordinate t in [0, 1)
    if k == -1:
        return 0.5 * (1.0 - t) ** 2
    if k == 0:
        return 0.75 - (t - 0.5) ** 2
    return 0.5 * t * t


@njit(cache=True, parallel=True)
def spread_splat(pos, vec, level, ctk, ctv, cbits, n_cells, xcuts):
    """Each item's row of ``vec`` (n, k) shared among the 27 cells around it, summed per cell.

    The weights are the quadratic B-spline's at its position: (n_cells, k) summed per cell of
    the table. The normals'
    splat (PoissonRecon's, k = 3) and the samples' kernel density (counts, k = 1).

    The cells in bands of x, band ``b`` from ``xcuts[b]`` to ``xcuts[b + 1] - 1`` (increasing,
    covering every cell), over the threads: each band walks all items in order and adds their
    shares in its cells only, so every cell sums its shares in the items' order, as one walk
    over all cells does, whatever the bands and threads.
    """
    k = vec.shape[1]
    out = np.zeros((n_cells, k))
    scale = float(1 << level)
    for b in prange(len(xcuts) - 1):
        _spread_band(pos, vec, scale, ctk, ctv, cbits, xcuts[b], xcuts[b + 1], out)
    return out


@njit(cache=True, inline="always")
def _spread_band(pos, vec, scale, ctk, ctv, cbits, x0, x1, out):
    """:func:`spread_splat`'s shares in the cells with x in [``x0``, ``x1``)."""
    k = vec.shape[1]
    c = np.empty(3, np.int64)
    t = np.empty(3)
    for p in range(pos.shape[0]):
        u = pos[p, 0] * scale
        cx = int(np.floor(u))
        if cx + 1 < x0 or cx - 1 >= x1:
            continue
        for a in range(3):
            u = pos[p, a] * scale
            c[a] = int(np.floor(u))
            t[a] = u - c[a]
        for kx in range(-1, 2):
            if c[0] + kx < x0 or c[0] + kx >= x1:
                continue
            for ky in range(-1, 2):
                for kz in range(-1, 2):
                    if min(c[0] + kx, c[1] + ky, c[2] + kz) < 0:
                        continue
                    j = lookup(ctk, ctv, cbits, lattice_key(c[0] + kx, c[1] + ky, c[2] + kz))
                    if j >= 0:
                        w = _b2w(t[0], kx) * _b2w(t[1], ky) * _b2w(t[2], kz)
                        for q in range(k):
                            out[j, q] += w * vec[p, q]


@njit(cache=True, inline="always")
def _gallop(keys, key, lo, n):
    """The lower_bound of ``key`` in ``keys[lo:n]``, searching forward from ``lo``.

    Cheap when the answer is near it.
    """
    step = 1
    while lo + step < n and keys[lo + step] < key:
        lo += step
        step *= 2
    return lower_bound(keys, key, lo, min(lo + step + 1, n))


@njit(cache=True)
def refine_field(pkeys, pvec, rel, off):
    """A field of quadratic B-splines on one level's cells written exactly on the finer level's.

    The B-splines have unit integral, sorted keys ``pkeys`` and coefficients ``pvec`` (m, 3).
    Each coarse B-spline is (1, 3, 3, 1) / 8 per axis of the finer ones at cells
    2p - 1 .. 2p + 2. Keys hold each coordinate plus ``off`` (1: the cells just beyond the
    cube's faces, where B-splines reaching into it sit, have keys). Only the finer cells in
    ``rel`` (sorted keys) are kept; they are found column by column, searching forward.
    """
    out = np.zeros((len(rel), 3))
    n = len(rel)
    if n == 0:
        return out
    w = np.array([0.125, 0.375, 0.375, 0.125])
    cur = np.zeros(16, np.int64)
    last_col = np.int64(-1)
    for i in range(len(pkeys)):
        k = pkeys[i]
        # offset coordinates of the children: 2 (c - off) - 1 + a + off
        x = 2 * ((k >> 42) & MASK21) - off - 1
        y = 2 * ((k >> 21) & MASK21) - off - 1
        z = 2 * (k & MASK21) - off - 1
        col = k >> 21
        fresh = col != last_col
        last_col = col
        z0 = max(z, 0)
        z1 = z + 3
        for a in range(4):
            cx = x + a
            if cx < 0:
                continue
            for b in range(4):
                cy = y + b
                if cy < 0:
                    continue
                s = a * 4 + b
                j = _gallop(rel, lattice_key(cx, cy, z0), 0 if fresh else cur[s], n)
                cur[s] = j
                kend = lattice_key(cx, cy, z1)
                wab = w[a] * w[b]
                while j < n and rel[j] <= kend:
                    wt = wab * w[(rel[j] & MASK21) - z]
                    out[j, 0] += wt * pvec[i, 0]
                    out[j, 1] += wt * pvec[i, 1]
                    out[j, 2] += wt * pvec[i, 2]
                    j += 1
    return out


@njit(cache=True)
def compact_nonzero(keys, vec):
    """Move the non-zero rows of ``vec`` (m, 3) and their ``keys`` (m,) to the front.

    In order, in place; returns how many there are.
    """
    m = 0
    for i in range(len(keys)):
        if vec[i, 0] != 0.0 or vec[i, 1] != 0.0 or vec[i, 2] != 0.0:
            if m != i:
                keys[m] = keys[i]
                vec[m, 0] = vec[i, 0]
                vec[m, 1] = vec[i, 1]
                vec[m, 2] = vec[i, 2]
            m += 1
    return m


@njit(cache=True)
def stencil_rhs(ckeys, cvec, level, node_keys, n_nodes, off):
    """b_i = int grad(B_i) . W at a level's nodes for a field of B-splines on its cells.

    The field's unit-integral quadratic B-splines are centred on the same level's cells (keys
    ``ckeys`` sorted, coefficients ``cvec`` (m, 3), coordinates plus ``off`` in the keys): a fixed 4
    x 4 x 4 stencil per cell (nodes c - 1 .. c + 2 per axis). Nodes are found in the sorted
    ``node_keys`` column by column, searching forward from the previous cell's position in the same
    column.
    """
    b = np.zeros(n_nodes)
    stencil_rhs_into(ckeys, cvec, level, node_keys, off, b)
    return b


@njit(cache=True)
def stencil_rhs_into(ckeys, cvec, level, node_keys, off, b):
    """:func:`stencil_rhs` added to ``b`` (n_nodes,).

    The cells may come in consecutive parts, each node then sums its cells' terms in the same order.
    """
    n = len(node_keys)
    if n == 0:
        return
    scale = float(1 << level)
    top = 1 << level
    av = np.empty(4)
    dv = np.empty(4)
    for o in range(4):
        av[o] = hat_b2_value(1.5 - o, 1.0)
        dv[o] = hat_b2_deriv(1.5 - o, 1.0) * scale
    cur = np.zeros(16, np.int64)
    last_col = np.int64(-1)
    for i in range(len(ckeys)):
        k = ckeys[i]
        x = ((k >> 42) & MASK21) - off
        y = ((k >> 21) & MASK21) - off
        z = (k & MASK21) - off
        col = k >> 21
        fresh = col != last_col
        last_col = col
        vx = cvec[i, 0]
        vy = cvec[i, 1]
        vz = cvec[i, 2]
        z0 = max(z - 1, 0)
        z1 = min(z + 2, top)
        for ox in range(4):
            nx = x - 1 + ox
            if nx < 0 or nx > top:
                continue
            for oy in range(4):
                ny = y - 1 + oy
                if ny < 0 or ny > top:
                    continue
                s = ox * 4 + oy
                j = _gallop(node_keys, lattice_key(nx, ny, z0), 0 if fresh else cur[s], n)
                cur[s] = j
                kend = lattice_key(nx, ny, z1)
                fxy = av[ox] * av[oy]
                gx = dv[ox] * av[oy]
                gy = av[ox] * dv[oy]
                while j < n and node_keys[j] <= kend:
                    oz = (node_keys[j] & MASK21) - z + 1
                    b[j] += (vx * gx + vy * gy) * av[oz] + vz * fxy * dv[oz]
                    j += 1


@njit(cache=True)
def restrict_nodes(fine_keys, fine_vals, coarse_keys):
    """Integrals against a level's hat functions from those against the next finer level's.

    A coarse hat is the fine hats at nodes 2i - 1, 2i, 2i + 1 per axis with weights 1/2, 1, 1/2, so
    ``out_i = sum_j r_ij fine_vals_j`` (fine nodes absent from ``fine_keys`` count as 0). Both key
    arrays sorted; fine nodes found column by column, searching forward.
    """
    out = np.zeros(len(coarse_keys))
    n = len(fine_keys)
    if n == 0:
        return out
    w = np.array([0.5, 1.0, 0.5])
    cur = np.zeros(9, np.int64)
    last_col = np.int64(-1)
    for i in range(len(coarse_keys)):
        k = coarse_keys[i]
        x = (k >> 42) & MASK21
        y = (k >> 21) & MASK21
        z = k & MASK21
        col = k >> 21
        fresh = col != last_col
        last_col = col
        z0 = max(2 * z - 1, 0)
        z1 = 2 * z + 1
        v = 0.0
        for a in range(3):
            fx = 2 * x - 1 + a
            if fx < 0:
                continue
            for b in range(3):
                fy = 2 * y - 1 + b
                if fy < 0:
                    continue
                s = a * 3 + b
                j = _gallop(fine_keys, lattice_key(fx, fy, z0), 0 if fresh else cur[s], n)
                cur[s] = j
                kend = lattice_key(fx, fy, z1)
                wab = w[a] * w[b]
                while j < n and fine_keys[j] <= kend:
                    v += wab * w[(fine_keys[j] & MASK21) - 2 * z + 1] * fine_vals[j]
                    j += 1
        out[i] = v
    return out


@njit(cache=True)
def density_eval(pos, level, ctk, ctv, cbits, dens):
    n = pos.shape[0]
    out = np.zeros(n)
    scale = float(1 << level)
    for p in range(n):
        c = np.empty(3, np.int64)
        t = np.empty(3)
        for a in range(3):
            u = pos[p, a] * scale
            c[a] = int(np.floor(u))
            t[a] = u - c[a]
        v = 0.0
        for kx in range(-1, 2):
            for ky in range(-1, 2):
                for kz in range(-1, 2):
                    if min(c[0] + kx, c[1] + ky, c[2] + kz) < 0:
                        continue
                    j = lookup(ctk, ctv, cbits, lattice_key(c[0] + kx, c[1] + ky, c[2] + kz))
                    if j >= 0:
                        v += dens[j] * _b2w(t[0], kx) * _b2w(t[1], ky) * _b2w(t[2], kz)
        out[p] = v
    return out


@njit(cache=True)
def height_fit_moments(unit, inv, cen, frame, res, m):
    """The normal equations of a quadratic height field per cell.

    Each point ``unit[i]`` (unit cube) of cell ``inv[i]`` in that cell's frame (rows: two tangents
    and the normal, origin ``cen``, lengths in cells of ``res``), ``w = a + b u + c v + d u^2 + e u
    v + f v^2``. Returns (m, 6, 6) sums of the monomials' products, (m, 6) their products with ``w``
    and (m,) the sums of ``w^2``.
    """
    A = np.zeros((m, 6, 6))
    b = np.zeros((m, 6))
    ww = np.zeros(m)
    x = np.empty(6)
    for i in range(unit.shape[0]):
        c = inv[i]
        dx = (unit[i, 0] - cen[c, 0]) * res
        dy = (unit[i, 1] - cen[c, 1]) * res
        dz = (unit[i, 2] - cen[c, 2]) * res
        u = dx * frame[c, 0, 0] + dy * frame[c, 0, 1] + dz * frame[c, 0, 2]
        v = dx * frame[c, 1, 0] + dy * frame[c, 1, 1] + dz * frame[c, 1, 2]
        w = dx * frame[c, 2, 0] + dy * frame[c, 2, 1] + dz * frame[c, 2, 2]
        x[0] = 1.0
        x[1] = u
        x[2] = v
        x[3] = u * u
        x[4] = u * v
        x[5] = v * v
        for j in range(6):
            b[c, j] += x[j] * w
            for k in range(j, 6):
                A[c, j, k] += x[j] * x[k]
        ww[c] += w * w
    for c in range(m):
        for j in range(6):
            for k in range(j):
                A[c, j, k] = A[c, k, j]
    return A, b, ww
