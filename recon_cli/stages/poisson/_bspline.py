"""Numba kernels of the degree-2 B-spline system.

Functions centred on cells, stiffness and screening operators, prolongation from the coarser level,
Jacobi-preconditioned conjugate gradients, evaluation.

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


@njit(cache=True)
def neighbour_table_into(keys, top, out):
    """Index in sorted ``keys`` of each key's 27 neighbours, into ``out`` (k, 27) int32.

    ``out`` is a slice of the levels' table; -1 where a neighbour is absent or outside
    [0, ``top``].

    A neighbour's key is the key plus a constant (its offset, packed), so the 27 queries of
    all keys, taken in the keys' order, are 27 sorted sequences: one cursor per offset walks
    ``keys`` once (linear merges; a binary search per query cost ~3x more at depth 9).
    """
    n = len(keys)
    cur = np.zeros(27, np.int64)
    offs = np.empty(27, np.int64)
    for t in range(27):
        offs[t] = ((t % 3 - 1) << 42) + (((t // 3) % 3 - 1) << 21) + (t // 9 - 1)
    for i in range(n):
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
    return out


@njit(cache=True, inline="always")
def _nbr(nb, i, o, tx, ty, tz):
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


@njit(cache=True, parallel=True)
def stiffness_matvec(q_keys, nb, inp, xmap, omap, m1, k1, h, x, out):
    """out[m] += h * the stiffness times x over the 125 cells within 2 of m, by parent blocks.

    For the children m of the parents flagged ``inp``: each parent's 6x6x6 block of cells is
    gathered once and the separable stencil (K M M + M K M + M M K) applied one axis at a time to
    all 8 children together. ``x`` holds parent ``i``'s block at ``8 xmap[i]`` (none where
    ``xmap[i]`` < 0, read as 0), ``out`` at ``8 omap[i]``: the identity for vectors on all of E, the
    rank among the flagged parents for the solve's vectors on the unknowns only (the prolonged
    coarse field is on all of E, its product only needed at the unknowns).
    Parents in chunks over the threads: each writes its own children only, so the sums are the
    same whatever the threads.
    """
    nq = len(q_keys)
    nchunks = (nq + MATVEC_CHUNK - 1) // MATVEC_CHUNK
    for ci in prange(nchunks):
        X = np.zeros((6, 6, 6))
        zm = np.empty((6, 6, 2))
        zk = np.empty((6, 6, 2))
        ym = np.empty((6, 2, 2))
        yk = np.empty((6, 2, 2))
        for i in range(ci * MATVEC_CHUNK, min(nq, (ci + 1) * MATVEC_CHUNK)):
            if not inp[i]:
                continue
            # one neighbour block (8 siblings, contiguous) at a time: 27 reads of nb, not 216
            for t in range(27):
                p = nb[i, t]
                if p >= 0:
                    p = xmap[p]
                ax = 2 * (t % 3)
                ay = 2 * ((t // 3) % 3)
                az = 2 * (t // 9)
                if p < 0:
                    for o in range(8):
                        X[ax + (o & 1), ay + ((o >> 1) & 1), az + (o >> 2)] = 0.0
                else:
                    for o in range(8):
                        X[ax + (o & 1), ay + ((o >> 1) & 1), az + (o >> 2)] = x[8 * p + o]
            k = q_keys[i]
            px = 2 * ((k >> 42) & MASK21)
            py = 2 * ((k >> 21) & MASK21)
            pz = 2 * (k & MASK21)
            # z: the two children's rows, for every (x, y) of the block (the table rows read
            # once per child and the 5 taps written out, with the gather by blocks above: 44 ->
            # 32 ms of CPU on 1.7M cells, the same sums in the same order)
            for oz in range(2):
                cz = pz + oz
                a0, a1, a2, a3, a4 = m1[cz, 0], m1[cz, 1], m1[cz, 2], m1[cz, 3], m1[cz, 4]
                b0, b1, b2, b3, b4 = k1[cz, 0], k1[cz, 1], k1[cz, 2], k1[cz, 3], k1[cz, 4]
                for bx in range(6):
                    for by in range(6):
                        v0 = X[bx, by, oz]
                        v1 = X[bx, by, oz + 1]
                        v2 = X[bx, by, oz + 2]
                        v3 = X[bx, by, oz + 3]
                        v4 = X[bx, by, oz + 4]
                        zm[bx, by, oz] = 0.0 + a0 * v0 + a1 * v1 + a2 * v2 + a3 * v3 + a4 * v4
                        zk[bx, by, oz] = 0.0 + b0 * v0 + b1 * v1 + b2 * v2 + b3 * v3 + b4 * v4
            # y
            for oy in range(2):
                cy = py + oy
                a0, a1, a2, a3, a4 = m1[cy, 0], m1[cy, 1], m1[cy, 2], m1[cy, 3], m1[cy, 4]
                b0, b1, b2, b3, b4 = k1[cy, 0], k1[cy, 1], k1[cy, 2], k1[cy, 3], k1[cy, 4]
                for bx in range(6):
                    for oz in range(2):
                        u0 = zm[bx, oy, oz]
                        u1 = zm[bx, oy + 1, oz]
                        u2 = zm[bx, oy + 2, oz]
                        u3 = zm[bx, oy + 3, oz]
                        u4 = zm[bx, oy + 4, oz]
                        ym[bx, oy, oz] = 0.0 + a0 * u0 + a1 * u1 + a2 * u2 + a3 * u3 + a4 * u4
                        yk[bx, oy, oz] = (
                            0.0
                            + (b0 * u0 + a0 * zk[bx, oy, oz])
                            + (b1 * u1 + a1 * zk[bx, oy + 1, oz])
                            + (b2 * u2 + a2 * zk[bx, oy + 2, oz])
                            + (b3 * u3 + a3 * zk[bx, oy + 3, oz])
                            + (b4 * u4 + a4 * zk[bx, oy + 4, oz])
                        )
            # x
            for o in range(8):
                ox = o & 1
                oy = (o >> 1) & 1
                oz = (o >> 2) & 1
                cx = px + ox
                y = 0.0
                for a in range(5):
                    y += k1[cx, a] * ym[ox + a, oy, oz] + m1[cx, a] * yk[ox + a, oy, oz]
                out[8 * omap[i] + o] += h * y


@njit(cache=True)
def stiffness_diag(q_keys, inp, m1, k1, h):
    out = np.zeros(8 * len(q_keys))
    for i in range(len(q_keys)):
        if not inp[i]:
            continue
        k = q_keys[i]
        px = (k >> 42) & MASK21
        py = (k >> 21) & MASK21
        pz = k & MASK21
        for o in range(8):
            cx = 2 * px + (o & 1)
            cy = 2 * py + ((o >> 1) & 1)
            cz = 2 * pz + ((o >> 2) & 1)
            out[8 * i + o] = h * (
                k1[cx, 2] * m1[cy, 2] * m1[cz, 2]
                + m1[cx, 2] * k1[cy, 2] * m1[cz, 2]
                + m1[cx, 2] * m1[cy, 2] * k1[cz, 2]
            )
    return out


@njit(cache=True, inline="always")
def _w3(t, c, n, s):
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


@njit(cache=True)
def screening_matvec(q_keys, nb, xmap, omap, n, s, scell, sloc, sw, x, out):
    """Out += sum_p w_p B_i(p) sum_j B_j(p) x_j over the samples (cell, local coordinates).

    ``x`` laid out by ``xmap``, ``out`` by ``omap`` (:func:`stiffness_matvec`).

    The 27 cells around a sample and their weights are written out here (and in
    :func:`screening_diag_rhs`): through a helper taking the arrays (``_gather27``, inlined)
    the matvec was 1.7x slower (``bench/calibration.md``).
    """
    wx = np.empty(3)
    wy = np.empty(3)
    wz = np.empty(3)
    idx = np.empty(27, np.int64)
    wr = np.empty(27)
    for p in range(len(scell)):
        m = scell[p]
        i = m >> 3
        o = m & 7
        k = q_keys[i]
        ox = o & 1
        oy = (o >> 1) & 1
        oz = (o >> 2) & 1
        wx[0], wx[1], wx[2] = _w3(sloc[p, 0], 2 * ((k >> 42) & MASK21) + ox, n, s)
        wy[0], wy[1], wy[2] = _w3(sloc[p, 1], 2 * ((k >> 21) & MASK21) + oy, n, s)
        wz[0], wz[1], wz[2] = _w3(sloc[p, 2], 2 * (k & MASK21) + oz, n, s)
        v = 0.0
        r = 0
        for c in range(3):
            bz = oz + c - 1
            for b in range(3):
                by = oy + b - 1
                wyz = wy[b] * wz[c]
                for a in range(3):
                    bx = ox + a - 1
                    q = nb[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                    idx[r] = -1
                    if q >= 0:
                        c8 = (bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2)
                        w = wx[a] * wyz
                        wr[r] = w
                        qx = xmap[q]
                        if qx >= 0:
                            v += w * x[8 * qx + c8]
                        qo = omap[q]
                        if qo >= 0:
                            idx[r] = 8 * qo + c8
                    r += 1
        v *= sw[p]
        for r in range(27):
            j = idx[r]
            if j >= 0:
                out[j] += wr[r] * v


@njit(cache=True)
def screening_diag_rhs(q_keys, nb, n, s, scell, sloc, sw, target, diag, rhs):
    """Diag += sum_p w_p B_i(p)^2 and rhs += sum_p w_p target B_i(p), in place."""
    wx = np.empty(3)
    wy = np.empty(3)
    wz = np.empty(3)
    for p in range(len(scell)):
        m = scell[p]
        i = m >> 3
        o = m & 7
        k = q_keys[i]
        ox = o & 1
        oy = (o >> 1) & 1
        oz = (o >> 2) & 1
        wx[0], wx[1], wx[2] = _w3(sloc[p, 0], 2 * ((k >> 42) & MASK21) + ox, n, s)
        wy[0], wy[1], wy[2] = _w3(sloc[p, 1], 2 * ((k >> 21) & MASK21) + oy, n, s)
        wz[0], wz[1], wz[2] = _w3(sloc[p, 2], 2 * (k & MASK21) + oz, n, s)
        for c in range(3):
            bz = oz + c - 1
            for b in range(3):
                by = oy + b - 1
                for a in range(3):
                    bx = ox + a - 1
                    q = nb[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                    if q >= 0:
                        j = 8 * q + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                        w = wx[a] * wy[b] * wz[c]
                        diag[j] += sw[p] * w * w
                        rhs[j] += sw[p] * target * w


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


@njit(cache=True)
def prolong_into(q_keys, coarse_q_keys, coarse_nb, coarse, n_coarse, s, out):
    """:func:`prolong` into ``out`` (8q,) (every entry written)."""
    loc = np.zeros(27)
    ox_ = np.empty(2, np.int64)
    oy_ = np.empty(2, np.int64)
    oz_ = np.empty(2, np.int64)
    wx_ = np.empty(2)
    wy_ = np.empty(2)
    wz_ = np.empty(2)
    for i in range(len(q_keys)):
        k = q_keys[i]
        px = (k >> 42) & MASK21
        py = (k >> 21) & MASK21
        pz = k & MASK21
        # the parent cell in the coarser E and its neighbours there
        j = find_cell(coarse_q_keys, px, py, pz)
        for t in range(27):
            loc[t] = 0.0
            if j >= 0:
                jj = _nbr(coarse_nb, j >> 3, j & 7, t % 3 - 1, (t // 3) % 3 - 1, t // 9 - 1)
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


@njit(cache=True)
def splat_rhs(pos, normal_w, splat_level, level, q_keys, inp, s, width):
    """b_i = int grad(B_i) . W at the unknown cells, W the normals splatted with B-splines.

    The quadratic B-splines have their splat level's width (as the degree-1 solver did before
    :class:`recon_cli.stages.poisson.splat.NormalField`): per item and axis, the 1D factors of the
    cells in reach (images folded), then the flagged parents in the box, walking their sorted keys,
    and their children in it.
    """
    n_keys = len(q_keys)
    b = np.zeros(8 * n_keys)
    if n_keys == 0:
        return b
    n = 1 << level
    scale = float(n)
    smin = level
    for p in range(pos.shape[0]):
        smin = min(smin, splat_level[p])
    wmax = min(2 * int(np.ceil(1.5 + 1.5 * width * 2.0 ** max(level - smin, 0))) + 4, n)
    fv = np.zeros((3, wmax))
    fd = np.zeros((3, wmax))
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for p in range(pos.shape[0]):
        rho = width * 2.0 ** (level - splat_level[p])
        reach = 1.5 + 1.5 * rho
        empty = False
        for a in range(3):
            u = pos[p, a] * scale
            e0 = int(np.floor(u - 0.5 - reach))
            e1 = int(np.ceil(u - 0.5 + reach))
            lo[a] = max(e0, 0)
            hi[a] = min(e1, n - 1, lo[a] + wmax - 1)
            if hi[a] < lo[a]:
                empty = True
                continue
            for t in range(hi[a] - lo[a] + 1):
                fv[a, t] = 0.0
                fd[a, t] = 0.0
            for c in range(e0, e1 + 1):
                v = u - (c + 0.5)
                if abs(v) >= reach:
                    continue
                cf, sg = fold(c, n, s)
                if cf < lo[a] or cf > hi[a]:
                    continue
                val, der = b2_factors(v, rho)
                fv[a, cf - lo[a]] += sg * val
                fd[a, cf - lo[a]] += sg * der * scale
        if empty:
            continue
        nx = normal_w[p, 0]
        ny = normal_w[p, 1]
        nz = normal_w[p, 2]
        l0 = lo[0] >> 1
        l1 = lo[1] >> 1
        l2 = lo[2] >> 1
        h1 = hi[1] >> 1
        h2 = hi[2] >> 1
        for x in range(l0, (hi[0] >> 1) + 1):
            kend = lattice_key(x, h1, h2)
            j = lower_bound(q_keys, lattice_key(x, l1, l2), 0, n_keys)
            while j < n_keys and q_keys[j] <= kend:
                k = q_keys[j]
                y = (k >> 21) & MASK21
                z = k & MASK21
                if z < l2:
                    j = gallop(q_keys, lattice_key(x, y, l2), j, n_keys)
                    continue
                if z > h2:
                    j = gallop(q_keys, lattice_key(x, y + 1, l2), j, n_keys)
                    continue
                if inp[j]:
                    for o in range(8):
                        cx = 2 * x + (o & 1) - lo[0]
                        cy = 2 * y + ((o >> 1) & 1) - lo[1]
                        cz = 2 * z + ((o >> 2) & 1) - lo[2]
                        if (
                            cx < 0
                            or cy < 0
                            or cz < 0
                            or cx > hi[0] - lo[0]
                            or cy > hi[1] - lo[1]
                            or cz > hi[2] - lo[2]
                        ):
                            continue
                        b[8 * j + o] += (
                            nx * fd[0, cx] * fv[1, cy] * fv[2, cz]
                            + ny * fv[0, cx] * fd[1, cy] * fv[2, cz]
                            + nz * fv[0, cx] * fv[1, cy] * fd[2, cz]
                        )
                j += 1
    return b


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


@njit(cache=True)
def level_matvec(q_keys, nb, inp, xmap, omap, m1, k1, h, n, s, scell, sloc, sw, x, out):
    """Out = A x (stiffness and screening) at the unknowns.

    Elsewhere whatever A gives; ``x`` laid out by ``xmap``, ``out`` by ``omap``
    (:func:`stiffness_matvec`).
    """
    out[:] = 0.0
    stiffness_matvec(q_keys, nb, inp, xmap, omap, m1, k1, h, x, out)
    if len(sw):
        screening_matvec(q_keys, nb, xmap, omap, n, s, scell, sloc, sw, x, out)


@njit(cache=True)
def level_pcg(q_keys, nb, inp, cmap, m1, k1, h, n, s, scell, sloc, sw, rhs, diag, tol, max_iter):
    """Jacobi-preconditioned conjugate gradients on the unknown cells only.

    ``rhs``, ``diag`` and the solution hold the children of the flagged parents, parent ``i``'s at
    ``8 cmap[i]`` (the ring of E, 40 % of its cells at the finest level, carries no unknown: vectors
    on all of E would be zero there). ``rhs`` is overwritten by the residual and ``diag`` by the
    preconditioner (its inverse, 0 where not positive). Rows whose diagonal is not positive are
    fixed (the envelope's and the free boundary's cells outside): their search directions and
    solution stay 0 and their residual does not count. Returns (x, iterations, relative residual).
    """
    m = len(rhs)
    inv = diag
    for i in range(m):
        if diag[i] > 0.0:
            inv[i] = 1.0 / diag[i]
        else:
            inv[i] = 0.0
    x = np.zeros(m)
    r = rhs
    p = np.empty(m)
    bn = 0.0
    rz = 0.0
    for i in range(m):
        p[i] = r[i] * inv[i]
        if inv[i] > 0.0:  # rows without a positive diagonal are fixed: x stays 0 there
            bn += r[i] * r[i]
        rz += r[i] * p[i]
    bn = np.sqrt(bn)
    if bn == 0.0:
        return x, 0, 0.0
    q = np.empty(m)
    it = 0
    rel = 1.0
    while it < max_iter:
        level_matvec(q_keys, nb, inp, cmap, cmap, m1, k1, h, n, s, scell, sloc, sw, p, q)
        pq = 0.0
        for i in range(m):
            pq += p[i] * q[i]
        if pq <= 0.0:
            break
        a = rz / pq
        rr = 0.0
        rz_new = 0.0
        for i in range(m):
            x[i] += a * p[i]
            r[i] -= a * q[i]
            if inv[i] > 0.0:
                rr += r[i] * r[i]
            q[i] = r[i] * inv[i]
            rz_new += r[i] * q[i]
        it += 1
        rel = np.sqrt(rr) / bn
        if rel < tol:
            break
        beta = rz_new / rz
        for i in range(m):
            p[i] = q[i] + beta * p[i]
        rz = rz_new
    return x, it, rel


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
                # _nbr on a slice of nb_all: bench/calibration.md)
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
                w[0, 0], w[0, 1], w[0, 2] = _w3(
                    min(max(pos[p, 0] * scale - c0, 0.0), 1.0), c0, n, s
                )
                w[1, 0], w[1, 1], w[1, 2] = _w3(
                    min(max(pos[p, 1] * scale - c1, 0.0), 1.0), c1, n, s
                )
                w[2, 0], w[2, 1], w[2, 2] = _w3(
                    min(max(pos[p, 2] * scale - c2, 0.0), 1.0), c2, n, s
                )
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


@njit(cache=True)
def constrain_to_coarse_leaves(node_keys, g, coarse_keys, coarse_nodes, coarse_leaf, g_coarse):
    """Give a level's nodes on the coarser level's leaves' faces or edges the leaves' values.

    The values are the leaves' trilinear interpolation, in place (as hanging nodes do): the
    extraction interpolates a
    leaf trilinearly from its corners, so the finer side of a face must see the same values
    there or the surface cracks along it. Cells of a level touch leaves of the next coarser
    level only, so one level up suffices (coarse to fine, the coarse values already
    constrained).
    """
    cand = np.empty((3, 2), np.int64)
    nc = np.empty(3, np.int64)
    for j in range(len(node_keys)):
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


@njit(cache=True)
def field_rows(q_keys, keys):
    """(8q,) int32: each cell of E's row of ``keys``, -1 if none; and how many are not in E.

    ``keys`` are the sorted cells of a field of the level.
    """
    out = np.full(8 * len(q_keys), -1, np.int32)
    missing = 0
    for r in range(len(keys)):
        k = keys[r]
        m = find_cell(q_keys, (k >> 42) & MASK21, (k >> 21) & MASK21, k & MASK21)
        if m < 0:
            missing += 1
        else:
            out[m] = r
    return out, missing


@njit(cache=True)
def add_rows(out, idx, rows):
    """out[m] += rows[idx[m]] (out (8q, 3) on E) where ``idx[m]`` >= 0."""
    for m in range(len(idx)):
        r = idx[m]
        if r >= 0:
            out[m, 0] += rows[r, 0]
            out[m, 1] += rows[r, 1]
            out[m, 2] += rows[r, 2]


@njit(cache=True)
def prolong_field(q_keys, coarse_q_keys, coarse_nb, coarse, n_coarse, s):
    """A field of unit-integral cell-centred quadratic B-splines written exactly on a finer E.

    The field has coefficients ``coarse`` (8qc, 3) on the coarser E; E is the children of
    ``q_keys``; mask
    (1, 3, 3, 1) / 8 per axis. The field is kept folded (its images beyond the cube's faces
    added onto the cells they mirror): a coarse cell beyond a face is its mirror cell with
    sign ``s``, and ``-s`` for the component along the face's normal (a reflection turns
    that component over), as the test functions' gradients are reflected (:func:`fold`).
    """
    out = np.zeros((8 * len(q_keys), 3))
    loc = np.zeros((27, 3))
    for i in range(len(q_keys)):
        k = q_keys[i]
        px = (k >> 42) & MASK21
        py = (k >> 21) & MASK21
        pz = k & MASK21
        j = find_cell(coarse_q_keys, px, py, pz)
        if j < 0:
            continue
        jb = j >> 3
        jo = j & 7
        # the coarse cells around the parent (written out rather than through _nbr: a
        # helper taking arrays, called in the loop, costs far more than its arithmetic)
        for t in range(27):
            bx = (jo & 1) + t % 3 - 1
            by = ((jo >> 1) & 1) + (t // 3) % 3 - 1
            bz = ((jo >> 2) & 1) + t // 9 - 1
            p = coarse_nb[jb, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
            if p < 0:
                loc[t, 0] = 0.0
                loc[t, 1] = 0.0
                loc[t, 2] = 0.0
            else:
                jj = 8 * p + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                loc[t, 0] = coarse[jj, 0]
                loc[t, 1] = coarse[jj, 1]
                loc[t, 2] = coarse[jj, 2]
        for o in range(8):
            # per axis: the far coarse cell's offset (0 when it lies beyond a face: the
            # parent's mirror), its weight for the components across and along the axis
            ex = 1 if o & 1 else -1
            ey = 1 if (o >> 1) & 1 else -1
            ez = 1 if (o >> 2) & 1 else -1
            fx = 0 <= px + ex < n_coarse
            fy = 0 <= py + ey < n_coarse
            fz = 0 <= pz + ez < n_coarse
            dx = ex if fx else 0
            dy = ey if fy else 0
            dz = ez if fz else 0
            wx = 0.125 if fx else 0.125 * s  # far weight, components across x
            wy = 0.125 if fy else 0.125 * s
            wz = 0.125 if fz else 0.125 * s
            for a in range(2):
                for b in range(2):
                    for c in range(2):
                        t = (1 + a * dx) + 3 * (1 + b * dy) + 9 * (1 + c * dz)
                        ax = wx if a else 0.375
                        ay = wy if b else 0.375
                        az = wz if c else 0.375
                        # along an axis the far mirror's sign is -s: -wx where wx = s / 8
                        gx = ax if fx or not a else -ax
                        gy = ay if fy or not b else -ay
                        gz = az if fz or not c else -az
                        out[8 * i + o, 0] += gx * ay * az * loc[t, 0]
                        out[8 * i + o, 1] += ax * gy * az * loc[t, 1]
                        out[8 * i + o, 2] += ax * ay * gz * loc[t, 2]
    return out


@njit(cache=True)
def _block_rhs(X, z3, y3, k, n, s, fv, fd, out, base):
    """The stencil of :func:`field_rhs` on one parent's 6 x 6 x 6 block ``X`` of the field.

    The block holds cells 2P - 2 .. 2P + 3 per axis (P the parent's cell ``k``), the cells beyond
    the faces folded first: out[base + o] += for its 8 children. (A call per parent, thousands of
    operations each: not the per-element helper call that costs in the hot loops.)
    """
    px = (k >> 42) & MASK21
    py = (k >> 21) & MASK21
    pz = k & MASK21
    # fold the cells beyond the faces (block rows 0, 1 at the low face mirror 3, 2; rows
    # 4, 5 at the high face mirror 3, 2), axis by axis
    lo_x = px == 0
    hi_x = 2 * px + 2 >= n
    lo_y = py == 0
    hi_y = 2 * py + 2 >= n
    lo_z = pz == 0
    hi_z = 2 * pz + 2 >= n
    for r in range(6):
        if not ((r < 2 and lo_x) or (r > 3 and hi_x)):
            continue
        mr = 3 - r if r < 2 else 7 - r
        for u in range(6):
            for v in range(6):
                X[r, u, v, 0] = -s * X[mr, u, v, 0]
                X[r, u, v, 1] = s * X[mr, u, v, 1]
                X[r, u, v, 2] = s * X[mr, u, v, 2]
    for r in range(6):
        if not ((r < 2 and lo_y) or (r > 3 and hi_y)):
            continue
        mr = 3 - r if r < 2 else 7 - r
        for u in range(6):
            for v in range(6):
                X[u, r, v, 0] = s * X[u, mr, v, 0]
                X[u, r, v, 1] = -s * X[u, mr, v, 1]
                X[u, r, v, 2] = s * X[u, mr, v, 2]
    for r in range(6):
        if not ((r < 2 and lo_z) or (r > 3 and hi_z)):
            continue
        mr = 3 - r if r < 2 else 7 - r
        for u in range(6):
            for v in range(6):
                X[u, v, r, 0] = s * X[u, v, mr, 0]
                X[u, v, r, 1] = s * X[u, v, mr, 1]
                X[u, v, r, 2] = -s * X[u, v, mr, 2]
    # z: value factor for the x and y components, derivative for z
    for oz in range(2):
        cz = 2 * pz + oz
        for bx in range(6):
            for by in range(6):
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for c in range(5):
                    a0 += fv[cz, c] * X[bx, by, oz + c, 0]
                    a1 += fv[cz, c] * X[bx, by, oz + c, 1]
                    a2 += fd[cz, c] * X[bx, by, oz + c, 2]
                z3[bx, by, oz, 0] = a0
                z3[bx, by, oz, 1] = a1
                z3[bx, by, oz, 2] = a2
    # y: derivative for the y component
    for oy in range(2):
        cy = 2 * py + oy
        for bx in range(6):
            for oz in range(2):
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for c in range(5):
                    a0 += fv[cy, c] * z3[bx, oy + c, oz, 0]
                    a1 += fd[cy, c] * z3[bx, oy + c, oz, 1]
                    a2 += fv[cy, c] * z3[bx, oy + c, oz, 2]
                y3[bx, oy, oz, 0] = a0
                y3[bx, oy, oz, 1] = a1
                y3[bx, oy, oz, 2] = a2
    # x: derivative for the x component
    for o in range(8):
        ox = o & 1
        oy = (o >> 1) & 1
        oz = (o >> 2) & 1
        cx = 2 * px + ox
        v = 0.0
        for c in range(5):
            v += fd[cx, c] * y3[ox + c, oy, oz, 0] + fv[cx, c] * (
                y3[ox + c, oy, oz, 1] + y3[ox + c, oy, oz, 2]
            )
        out[base + o] += v


@njit(cache=True, parallel=True)
def field_rhs(q_keys, nb, flag, n, s, fv, fd, vec, idx, rows, out):
    """out[m] += int grad(B_m) . W for the children m of the parents flagged ``flag``.

    W is the field of unit-integral cell-centred quadratic B-splines with coefficients ``vec`` (8q,
    3) on E (folded, :func:`prolong_field`; or none, shape (0, 3)) plus ``rows[idx[m]]`` (a sparse
    field, :func:`field_rows`; or none, ``idx`` of length 0; a dense copy on E of the finest level's
    would be the largest array of the solve): a 5 x 5 x 5 stencil, ``fv[c, t + 2]`` and ``fd[c, t +
    2]`` (n, 5) the value and derivative factors, along an axis, of the field's cell at offset ``t``
    from the test function's cell ``c`` (:func:`b2_factors`, width 1, on every row; integrals over
    the free boundary's domain only; ``fd`` per unit length). Each parent's 6 x 6 x 6 block of the
    field is gathered once (cells beyond the faces: their mirror's, with sign ``s``, ``-s`` for the
    component along the face's normal) and the separable stencil applied one axis at a time to all 8
    children together.
    Parents in chunks over the threads (each writes its own children only).
    """
    dense = len(vec) > 0
    sparse = len(idx) > 0
    nq = len(q_keys)
    nchunks = (nq + MATVEC_CHUNK - 1) // MATVEC_CHUNK
    for ci in prange(nchunks):
        X = np.zeros((6, 6, 6, 3))
        z3 = np.empty((6, 6, 2, 3))
        y3 = np.empty((6, 2, 2, 3))
        for i in range(ci * MATVEC_CHUNK, min(nq, (ci + 1) * MATVEC_CHUNK)):
            if not flag[i]:
                continue
            for bz in range(6):
                for by in range(6):
                    for bx in range(6):
                        p = nb[i, (bx >> 1) + 3 * (by >> 1) + 9 * (bz >> 1)]
                        if p >= 0:
                            m = 8 * p + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                            v0 = 0.0
                            v1 = 0.0
                            v2 = 0.0
                            if dense:
                                v0 = vec[m, 0]
                                v1 = vec[m, 1]
                                v2 = vec[m, 2]
                            if sparse:
                                r = idx[m]
                                if r >= 0:
                                    if dense:
                                        v0 += rows[r, 0]
                                        v1 += rows[r, 1]
                                        v2 += rows[r, 2]
                                    else:
                                        v0 = rows[r, 0]
                                        v1 = rows[r, 1]
                                        v2 = rows[r, 2]
                            X[bx, by, bz, 0] = v0
                            X[bx, by, bz, 1] = v1
                            X[bx, by, bz, 2] = v2
                        else:
                            X[bx, by, bz, 0] = 0.0
                            X[bx, by, bz, 1] = 0.0
                            X[bx, by, bz, 2] = 0.0
            _block_rhs(X, z3, y3, q_keys[i], n, s, fv, fd, out, 8 * i)


@njit(cache=True, parallel=True)
def field_rhs_prolonged(q_keys, nb, flag, n, s, fv, fd, cq_keys, cnb, cvec, idx, rows, out):
    """:func:`field_rhs` for the coarser level's field ``cvec``, refined on the fly.

    ``cvec`` lives on the coarser E, folded; it is refined (:func:`prolong_field`'s mask, per
    parent: the coarser cells P - 2 .. P + 2 per axis give the block's cells 2P - 2 .. 2P + 3) plus
    ``rows[idx]``: for the finest level, whose refined field on E (24 B a cell) would be the largest
    array of the solve. Equal to :func:`field_rhs` of :func:`prolong_field`'s result to rounding.
    Parents in chunks over the threads (each writes its own children only).
    """
    w = np.array([0.125, 0.375, 0.375, 0.125])
    nc = n >> 1
    sparse = len(idx) > 0
    nq = len(q_keys)
    nchunks = (nq + MATVEC_CHUNK - 1) // MATVEC_CHUNK
    for ci in prange(nchunks):
        C = np.zeros((5, 5, 5, 3))
        R1 = np.zeros((6, 5, 5, 3))
        R2 = np.zeros((6, 6, 5, 3))
        X = np.zeros((6, 6, 6, 3))
        z3 = np.empty((6, 6, 2, 3))
        y3 = np.empty((6, 2, 2, 3))
        for i in range(ci * MATVEC_CHUNK, min(nq, (ci + 1) * MATVEC_CHUNK)):
            if not flag[i]:
                continue
            k = q_keys[i]
            px = (k >> 42) & MASK21
            py = (k >> 21) & MASK21
            pz = k & MASK21
            C[:] = 0.0
            j = find_cell(cq_keys, px, py, pz)
            if j >= 0:
                jb = j >> 3
                jo = j & 7
                for c in range(5):
                    bz = ((jo >> 2) & 1) + c - 2
                    for b in range(5):
                        by = ((jo >> 1) & 1) + b - 2
                        for a in range(5):
                            bx = (jo & 1) + a - 2
                            q = cnb[jb, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                            if q >= 0:
                                m = 8 * q + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                                C[a, b, c, 0] = cvec[m, 0]
                                C[a, b, c, 1] = cvec[m, 1]
                                C[a, b, c, 2] = cvec[m, 2]
                # coarser cells beyond the faces: their mirrors' (sign s, -s for the component
                # along the face's normal), axis by axis
                for ax in range(3):
                    pc = px if ax == 0 else (py if ax == 1 else pz)
                    for a in range(5):
                        cc = pc - 2 + a
                        if cc < 0:
                            ma = -1 - cc - (pc - 2)
                        elif cc >= nc:
                            ma = 2 * nc - 1 - cc - (pc - 2)
                        else:
                            continue
                        for u in range(5):
                            for v in range(5):
                                for comp in range(3):
                                    sg = -s if comp == ax else s
                                    if ax == 0:
                                        C[a, u, v, comp] = sg * C[ma, u, v, comp]
                                    elif ax == 1:
                                        C[u, a, v, comp] = sg * C[u, ma, v, comp]
                                    else:
                                        C[u, v, a, comp] = sg * C[u, v, ma, comp]
            # refine, one axis at a time: block cell 2P - 2 + b takes coarser cell P - 2 + a with
            # weight w[b + 3 - 2a]
            for b in range(6):
                for u in range(5):
                    for v in range(5):
                        for comp in range(3):
                            t = 0.0
                            for a in range(5):
                                e = b + 3 - 2 * a
                                if 0 <= e <= 3:
                                    t += w[e] * C[a, u, v, comp]
                            R1[b, u, v, comp] = t
            for b in range(6):
                for u in range(6):
                    for v in range(5):
                        for comp in range(3):
                            t = 0.0
                            for a in range(5):
                                e = b + 3 - 2 * a
                                if 0 <= e <= 3:
                                    t += w[e] * R1[u, a, v, comp]
                            R2[u, b, v, comp] = t
            for b in range(6):
                for u in range(6):
                    for v in range(6):
                        for comp in range(3):
                            t = 0.0
                            for a in range(5):
                                e = b + 3 - 2 * a
                                if 0 <= e <= 3:
                                    t += w[e] * R2[u, v, a, comp]
                            X[u, v, b, comp] = t
            if sparse:
                for t27 in range(27):
                    p = nb[i, t27]
                    if p < 0:
                        continue
                    ax = 2 * (t27 % 3)
                    ay = 2 * ((t27 // 3) % 3)
                    az = 2 * (t27 // 9)
                    for o in range(8):
                        r = idx[8 * p + o]
                        if r >= 0:
                            X[ax + (o & 1), ay + ((o >> 1) & 1), az + (o >> 2), 0] += rows[r, 0]
                            X[ax + (o & 1), ay + ((o >> 1) & 1), az + (o >> 2), 1] += rows[r, 1]
                            X[ax + (o & 1), ay + ((o >> 1) & 1), az + (o >> 2), 2] += rows[r, 2]
            _block_rhs(X, z3, y3, k, n, s, fv, fd, out, 8 * i)


@njit(cache=True)
def finer_blocks(q_keys, fine_q_keys):
    """(8q,) int64: for each cell of E, the index of its children's block in the finer level.

    The index is into ``fine_q_keys``, -1 when the children are not in the finer E.
    """
    out = np.full(8 * len(q_keys), -1, np.int64)
    for j in range(len(fine_q_keys)):
        k = fine_q_keys[j]
        m = find_cell(q_keys, (k >> 42) & MASK21, (k >> 21) & MASK21, k & MASK21)
        if m >= 0:
            out[m] = j
    return out


@njit(cache=True)
def restrict_rhs(q_keys, nb, flag, blocks, fine, n, s):
    """Integrals against this level's (folded) functions from those against the finer level's.

    The finer level's are ``fine`` (8qf,) on the finer E: a function of cell ``c`` is the finer ones
    of cells 2c - 1 .. 2c + 2 per axis with weights (1, 3, 3, 1) / 4 (a finer cell beyond a face is
    its mirror with sign ``s``); at the children of the parents flagged ``flag``, 0 elsewhere.
    ``blocks`` is :func:`finer_blocks`; finer cells not in the finer E count as 0.
    """
    out = np.zeros(8 * len(q_keys))
    X = np.zeros((6, 6, 6))
    zr = np.empty((6, 6, 2))
    yr = np.empty((6, 2, 2))
    r4 = np.array([0.25, 0.75, 0.75, 0.25])
    for i in range(len(q_keys)):
        if not flag[i]:
            continue
        X[:] = 0.0
        # the cells 2P - 1 .. 2P + 2 per axis around the parent P (cell 2P - 1 + a is child
        # (a + 1) & 1 of the parent at offset ((a + 1) >> 1) - 1) and their children: finer
        # cells 4P - 1 .. 4P + 4, block rows 0..5 (row 2a - 1 + child)
        for c in range(4):
            for b in range(4):
                for a in range(4):
                    p = nb[i, ((a + 1) >> 1) + 3 * ((b + 1) >> 1) + 9 * ((c + 1) >> 1)]
                    if p < 0:
                        continue
                    jf = blocks[
                        8 * p + (((a + 1) & 1) | (((b + 1) & 1) << 1) | (((c + 1) & 1) << 2))
                    ]
                    if jf < 0:
                        continue
                    for of in range(8):
                        rx = 2 * a - 1 + (of & 1)
                        ry = 2 * b - 1 + ((of >> 1) & 1)
                        rz = 2 * c - 1 + ((of >> 2) & 1)
                        if rx < 0 or ry < 0 or rz < 0 or rx > 5 or ry > 5 or rz > 5:
                            continue
                        X[rx, ry, rz] = fine[8 * jf + of]
        k = q_keys[i]
        px = (k >> 42) & MASK21
        py = (k >> 21) & MASK21
        pz = k & MASK21
        # finer cells beyond the faces: row 0 (cell -1) mirrors row 1, row 5 (cell 2n) row 4
        if px == 0:
            X[0, :, :] = s * X[1, :, :]
        if 2 * px + 2 >= n:
            X[5, :, :] = s * X[4, :, :]
        if py == 0:
            X[:, 0, :] = s * X[:, 1, :]
        if 2 * py + 2 >= n:
            X[:, 5, :] = s * X[:, 4, :]
        if pz == 0:
            X[:, :, 0] = s * X[:, :, 1]
        if 2 * pz + 2 >= n:
            X[:, :, 5] = s * X[:, :, 4]
        # child o of the parent: finer rows 2 o .. 2 o + 3 per axis
        for oz in range(2):
            for bx in range(6):
                for by in range(6):
                    v = 0.0
                    for c in range(4):
                        v += r4[c] * X[bx, by, 2 * oz + c]
                    zr[bx, by, oz] = v
        for oy in range(2):
            for bx in range(6):
                for oz in range(2):
                    v = 0.0
                    for c in range(4):
                        v += r4[c] * zr[bx, 2 * oy + c, oz]
                    yr[bx, oy, oz] = v
        for o in range(8):
            ox = o & 1
            v = 0.0
            for c in range(4):
                v += r4[c] * yr[2 * ox + c, (o >> 1) & 1, (o >> 2) & 1]
            out[8 * i + o] = v
    return out
