"""Numba kernels of the degree-2 B-spline system.

The basis and its lookups: functions centred on cells, their 1D integrals, neighbour tables,
cells of points, prolongation from the coarser level. The operator (stiffness, screening, the
level's conjugate gradients) is in :mod:`._bspline_operator`, the right-hand side in
:mod:`._bspline_rhs`, the evaluation of the solved field in :mod:`._bspline_eval`.

They only compute; conventions in :mod:`recon_cli.stages.poisson._octree`, and these:

- at level ``d`` (``n = 2**d`` cells per axis) the function of cell ``c`` is the tensor
  product of the centred quadratic B-spline ``B2(u - c - 1/2)`` per axis (``u`` in cells),
  reflected at the cube's faces: evenly (Neumann, ``s = 1``) or oddly (Dirichlet,
  ``s = -1``); cell ``-1 - c`` and ``2n - 1 - c`` are images of ``c`` with sign ``s``
  (:func:`fold`), so every operator is the unbounded one with out-of-range indices folded;
- a level's coefficients live on ``E``: the children of a parent set ``Q`` (sorted keys of
  the coarser level) in block order, cell ``8 i + o`` the child of octant
  ``o = ox | oy << 1 | oz << 2`` of ``Q[i]`` (siblings side by side: a gather reads whole
  blocks); ``nb`` (q, 27) is the index in ``Q`` of each parent's neighbour at offset
  ``(dx, dy, dz)`` in ``{-1, 0, 1}^3``, slot ``(dx + 1) + 3 (dy + 1) + 9 (dz + 1)`` (-1 absent);
  the neighbour of a cell at any offset in ``[-2, 2]^3`` is a child of one of its parent's
  neighbours;
- the 1D tables ``m1``, ``k1`` (n, 5) hold the folded mass and stiffness between cell ``i``
  and cell ``i + t`` at column ``t + 2`` (cell units).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli.stages.poisson._octree import MASK21, bsearch, lattice_key

# B2''' = sum_k A_k delta(u - T_k)
_A = (1.0, -3.0, 3.0, -1.0)
_T = (-1.5, -0.5, 0.5, 1.5)
# parents (matvec) and points (chi_at) per chunk of a parallel loop
MATVEC_CHUNK = 512
POINT_CHUNK = 1024
# rows a thread takes at a time in the gathers over a level's cells (neighbour tables, prolongation)
ROW_CHUNK = 1 << 13


@njit(cache=True, inline="always")
def fold(c, n, s):
    """The in-range cell of which ``c`` is an image, and the image's sign."""
    sg = 1.0
    while c < 0 or c >= n:
        if c < 0:
            c = -1 - c
        else:
            c = 2 * n - 1 - c
        sg *= s
    return c, sg


@njit(cache=True, inline="always")
def _p4(x):
    t = x if x > 0.0 else 0.0
    t *= t
    return t * t


@njit(cache=True, inline="always")
def _p5(x):
    t = x if x > 0.0 else 0.0
    u = t * t
    return u * u * t


@njit(cache=True)
def b2_int2(x):
    """Second antiderivative of the centred quadratic B-spline (0 below -1.5, x above 1.5)."""
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return x
    return (_p4(x + 1.5) - 3.0 * _p4(x + 0.5) + 3.0 * _p4(x - 0.5)) / 24.0


@njit(cache=True)
def b2_int3(x):
    """Third antiderivative of the centred quadratic B-spline.

    0 below -1.5, x^2/2 + 1/8 above 1.5.
    """
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return 0.5 * x * x + 0.125
    return (_p5(x + 1.5) - 3.0 * _p5(x + 0.5) + 3.0 * _p5(x - 0.5)) / 120.0


@njit(cache=True)
def b2_factors(v, rho):
    """Int B2(w) K(w - v) dw and int B2'(w) K(w - v) dw for the kernel K = B2(./rho)/rho.

    The derivatives go onto the narrower of the two (three integrations by parts against
    its third derivative, a sum of deltas), so no term is much larger than the result.
    """
    val = 0.0
    der = 0.0
    if rho < 1.0:
        for k in range(4):
            x = (_T[k] - v) / rho
            val -= _A[k] * rho * rho * b2_int3(x)
            der += _A[k] * rho * b2_int2(x)
    else:
        r3 = rho * rho * rho
        for k in range(4):
            x = rho * _T[k] + v
            val -= _A[k] * b2_int3(x) / r3
            der -= _A[k] * b2_int2(x) / r3
    return val, der


@njit(cache=True, parallel=True)
def neighbour_table_into(keys, top, out):
    """Index in sorted ``keys`` of each key's 27 neighbours, into ``out`` (k, 27) int32.

    ``out`` is a slice of the levels' table; -1 where a neighbour is absent or outside
    [0, ``top``].

    A neighbour's key is the key plus a constant (its offset, packed), so the 27 queries of
    all keys, taken in the keys' order, are 27 sorted sequences: one cursor per offset walks
    ``keys`` once (linear merges; a binary search per query cost ~3x more at depth 9). Rows in
    chunks over the threads, each chunk's cursors found by one binary search.
    """
    n = len(keys)
    offs = np.empty(27, np.int64)
    for t in range(27):
        offs[t] = ((t % 3 - 1) << 42) + (((t // 3) % 3 - 1) << 21) + (t // 9 - 1)
    for ch in prange((n + ROW_CHUNK - 1) // ROW_CHUNK):
        i0 = ch * ROW_CHUNK
        cur = np.empty(27, np.int64)
        for t in range(27):
            cur[t] = lower_bound(keys, keys[i0] + offs[t], 0, n)
        for i in range(i0, min(n, i0 + ROW_CHUNK)):
            _neighbour_row(keys, top, out, offs, cur, i, n)
    return out


@njit(cache=True, inline="always")
def _neighbour_row(keys, top, out, offs, cur, i, n):
    """Row ``i`` of :func:`neighbour_table_into`, its 27 cursors ``cur`` moved on."""
    k = keys[i]
    x = (k >> 42) & MASK21
    y = (k >> 21) & MASK21
    z = k & MASK21
    for t in range(27):
        X = x + t % 3 - 1
        Y = y + (t // 3) % 3 - 1
        Z = z + t // 9 - 1
        if X < 0 or Y < 0 or Z < 0 or X > top or Y > top or Z > top:
            out[i, t] = -1
            continue
        q = k + offs[t]
        j = cur[t]
        while j < n and keys[j] < q:
            j += 1
        cur[t] = j
        out[i, t] = j if j < n and keys[j] == q else -1


@njit(cache=True, inline="always")
def nbr_cell(nb, i, o, tx, ty, tz):
    """Index in E of the neighbour at offset (tx, ty, tz) in [-2, 2]^3 of a parent's child.

    The child is ``o`` of parent ``i``; -1 outside the cube.
    """
    bx = (o & 1) + tx
    by = ((o >> 1) & 1) + ty
    bz = ((o >> 2) & 1) + tz
    p = nb[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
    if p < 0:
        return -1
    return 8 * p + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))


@njit(cache=True, inline="always")
def w3(t, c, n, s):
    """Values of the functions of cells c - 1, c, c + 1 (folded) at ``t`` in cell ``c``.

    ``t`` is the local coordinate; three scalars are returned (a helper taking no arrays: one that
    takes arrays, called per sample in the hot loops, cost several times the arithmetic).
    """
    w0 = 0.5 * (1.0 - t) * (1.0 - t)
    w1 = 0.75 - (t - 0.5) * (t - 0.5)
    w2 = 0.5 * t * t
    if c == 0:
        w1 += s * w0
        w0 = 0.0
    if c == n - 1:
        w1 += s * w2
        w2 = 0.0
    return w0, w1, w2


@njit(cache=True, inline="always")
def find_cell(q_keys, x, y, z):
    """Index in E of cell (x, y, z) (-1 if its parent is not in ``q_keys``)."""
    i = bsearch(q_keys, lattice_key(x >> 1, y >> 1, z >> 1))
    if i < 0:
        return -1
    return 8 * i + ((x & 1) | ((y & 1) << 1) | ((z & 1) << 2))


@njit(cache=True)
def locate(pos, level, q_keys, inp):
    """Index in E of the cell holding each position, -1 if none, and local coordinates.

    Only cells of flagged parents count; local coordinates are in [0, 1].
    """
    n = pos.shape[0]
    scale = float(1 << level)
    top = (1 << level) - 1
    cell = np.empty(n, np.int64)
    loc = np.empty((n, 3))
    for i in range(n):
        c0 = min(max(int(np.floor(pos[i, 0] * scale)), 0), top)
        c1 = min(max(int(np.floor(pos[i, 1] * scale)), 0), top)
        c2 = min(max(int(np.floor(pos[i, 2] * scale)), 0), top)
        m = find_cell(q_keys, c0, c1, c2)
        if m >= 0 and not inp[m >> 3]:
            m = -1
        cell[i] = m
        loc[i, 0] = min(max(pos[i, 0] * scale - c0, 0.0), 1.0)
        loc[i, 1] = min(max(pos[i, 1] * scale - c1, 0.0), 1.0)
        loc[i, 2] = min(max(pos[i, 2] * scale - c2, 0.0), 1.0)
    return cell, loc


@njit(cache=True)
def prolong(q_keys, coarse_q_keys, coarse_nb, coarse, n_coarse, s):
    """Coefficients on E (the children of ``q_keys``) of the coarser level's function.

    The coarser function has coefficients ``coarse`` on the coarser E (the children of
    ``coarse_q_keys``):
    refinement mask (1, 3, 3, 1)/4 per axis, the coarse index folded at the cube's faces.
    """
    out = np.empty(8 * len(q_keys))
    prolong_into(q_keys, coarse_q_keys, coarse_nb, coarse, n_coarse, s, out)
    return out


@njit(cache=True, parallel=True)
def prolong_into(q_keys, coarse_q_keys, coarse_nb, coarse, n_coarse, s, out):
    """:func:`prolong` into ``out`` (8q,), every entry written; parents in chunks over threads."""
    m = len(q_keys)
    for ch in prange((m + ROW_CHUNK - 1) // ROW_CHUNK):
        loc = np.zeros(27)
        ox_ = np.empty(2, np.int64)
        oy_ = np.empty(2, np.int64)
        oz_ = np.empty(2, np.int64)
        wx_ = np.empty(2)
        wy_ = np.empty(2)
        wz_ = np.empty(2)
        for i in range(ch * ROW_CHUNK, min(m, (ch + 1) * ROW_CHUNK)):
            k = q_keys[i]
            px = (k >> 42) & MASK21
            py = (k >> 21) & MASK21
            pz = k & MASK21
            # the parent cell in the coarser E and its neighbours there
            j = find_cell(coarse_q_keys, px, py, pz)
            for t in range(27):
                loc[t] = 0.0
                if j >= 0:
                    jj = nbr_cell(coarse_nb, j >> 3, j & 7, t % 3 - 1, (t // 3) % 3 - 1, t // 9 - 1)
                    if jj >= 0:
                        loc[t] = coarse[jj]
            for o in range(8):
                _mask(o & 1, px, n_coarse, s, ox_, wx_)
                _mask((o >> 1) & 1, py, n_coarse, s, oy_, wy_)
                _mask((o >> 2) & 1, pz, n_coarse, s, oz_, wz_)
                v = 0.0
                for a in range(2):
                    for b in range(2):
                        for c in range(2):
                            v += (
                                wx_[a]
                                * wy_[b]
                                * wz_[c]
                                * loc[(ox_[a] + 1) + 3 * (oy_[b] + 1) + 9 * (oz_[c] + 1)]
                            )
                out[8 * i + o] = v
    return out


@njit(cache=True, inline="always")
def _mask(bit, p, n_coarse, s, off, w):
    """The two coarse cells a fine cell of parity ``bit`` takes from, and their weights.

    Cells are offsets from the parent, weights 3/4 and 1/4 (the far one folded onto the parent
    at a face).
    """
    off[0] = 0
    w[0] = 0.75
    d = 1 if bit else -1
    if 0 <= p + d < n_coarse:
        off[1] = d
        w[1] = 0.25
    else:
        off[1] = 0
        w[1] = 0.25 * s


@njit(cache=True, inline="always")
def gallop(keys, key, lo, hi):
    """First index in [lo, hi) of sorted ``keys`` whose key is >= ``key``.

    Searches from ``lo`` with doubling steps (the next row is usually near).
    """
    step = 1
    end = lo
    while end < hi and keys[end] < key:
        lo = end + 1
        end = lo + step
        step *= 2
    return lower_bound(keys, key, lo, min(end, hi))
