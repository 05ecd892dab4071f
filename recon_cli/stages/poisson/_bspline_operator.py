"""Numba kernels of the degree-2 system's operator: stiffness, screening, the level's CG.

They only compute; conventions in :mod:`._bspline`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli.stages.poisson._bspline import (
    MATVEC_CHUNK,
    w3,
)
from recon_cli.stages.poisson._octree import MASK21

# bands of parents the CG's screening product runs in over the threads (fixed: the same bits
# for any thread count, and for any bands too)
SCREEN_BANDS = 8
# below this many samples the product runs in one walk (a parallel loop costs more than it saves)
SCREEN_MIN_SAMPLES = 1 << 14


@njit(cache=True, inline="always")
def _gather_block(X, nb, i, xmap, x):
    """X (216,) := parent ``i``'s 6 x 6 x 6 block of ``x``, flat (z, y, x); 0 where there is none.

    One neighbour block (8 siblings, contiguous) at a time: 27 reads of ``nb``, not 216. ``x``
    holds parent ``p``'s block at ``8 xmap[p]`` (none where ``xmap[p]`` < 0).
    """
    for t in range(27):
        p = nb[i, t]
        if p >= 0:
            p = xmap[p]
        base = 2 * (t % 3) + 12 * ((t // 3) % 3) + 72 * (t // 9)
        if p < 0:
            for o in range(8):
                X[base + (o & 1) + 6 * ((o >> 1) & 1) + 36 * (o >> 2)] = 0.0
        else:
            for o in range(8):
                X[base + (o & 1) + 6 * ((o >> 1) & 1) + 36 * (o >> 2)] = x[8 * p + o]


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
        # flat (z, y, x) blocks: the z and y passes run along contiguous rows, which vectorise
        X = np.zeros(216)  # (z, y, x) of the 6 x 6 x 6 cells
        zm = np.empty(72)  # (oz, y, x)
        zk = np.empty(72)
        ym = np.empty(24)  # (oy, oz, x)
        yk = np.empty(24)
        for i in range(ci * MATVEC_CHUNK, min(nq, (ci + 1) * MATVEC_CHUNK)):
            if not inp[i]:
                continue
            _gather_block(X, nb, i, xmap, x)
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
                s0 = 36 * oz
                for j in range(36):
                    v0 = X[s0 + j]
                    v1 = X[s0 + 36 + j]
                    v2 = X[s0 + 72 + j]
                    v3 = X[s0 + 108 + j]
                    v4 = X[s0 + 144 + j]
                    zm[s0 + j] = 0.0 + a0 * v0 + a1 * v1 + a2 * v2 + a3 * v3 + a4 * v4
                    zk[s0 + j] = 0.0 + b0 * v0 + b1 * v1 + b2 * v2 + b3 * v3 + b4 * v4
            # y
            for oy in range(2):
                cy = py + oy
                a0, a1, a2, a3, a4 = m1[cy, 0], m1[cy, 1], m1[cy, 2], m1[cy, 3], m1[cy, 4]
                b0, b1, b2, b3, b4 = k1[cy, 0], k1[cy, 1], k1[cy, 2], k1[cy, 3], k1[cy, 4]
                for oz in range(2):
                    s0 = 36 * oz + 6 * oy
                    d0 = 12 * oy + 6 * oz
                    for bx in range(6):
                        u0 = zm[s0 + bx]
                        u1 = zm[s0 + 6 + bx]
                        u2 = zm[s0 + 12 + bx]
                        u3 = zm[s0 + 18 + bx]
                        u4 = zm[s0 + 24 + bx]
                        ym[d0 + bx] = 0.0 + a0 * u0 + a1 * u1 + a2 * u2 + a3 * u3 + a4 * u4
                        yk[d0 + bx] = (
                            0.0
                            + (b0 * u0 + a0 * zk[s0 + bx])
                            + (b1 * u1 + a1 * zk[s0 + 6 + bx])
                            + (b2 * u2 + a2 * zk[s0 + 12 + bx])
                            + (b3 * u3 + a3 * zk[s0 + 18 + bx])
                            + (b4 * u4 + a4 * zk[s0 + 24 + bx])
                        )
            # x
            for o in range(8):
                ox = o & 1
                oy = (o >> 1) & 1
                oz = (o >> 2) & 1
                cx = px + ox
                r = 12 * oy + 6 * oz + ox
                y = 0.0
                for a in range(5):
                    y += k1[cx, a] * ym[r + a] + m1[cx, a] * yk[r + a]
                out[8 * omap[i] + o] += h * y


@njit(cache=True, parallel=True)
def stiffness_blocks(q_keys, inp, cmap, m1, k1, h, out):
    """out[cmap[i], o, o2] = the stiffness between children o and o2 of each flagged parent i.

    Row ``o`` is child ``o``'s row of the operator (:func:`stiffness_matvec`): its tables' column
    at the offset of child ``o2``. Each parent writes its own block only.
    """
    for i in prange(len(q_keys)):
        if not inp[i]:
            continue
        b = cmap[i]
        k = q_keys[i]
        px = 2 * ((k >> 42) & MASK21)
        py = 2 * ((k >> 21) & MASK21)
        pz = 2 * (k & MASK21)
        for o in range(8):
            cx = px + (o & 1)
            cy = py + ((o >> 1) & 1)
            cz = pz + ((o >> 2) & 1)
            for o2 in range(8):
                tx = 2 + (o2 & 1) - (o & 1)
                ty = 2 + ((o2 >> 1) & 1) - ((o >> 1) & 1)
                tz = 2 + ((o2 >> 2) & 1) - ((o >> 2) & 1)
                out[b, o, o2] = h * (
                    k1[cx, tx] * m1[cy, ty] * m1[cz, tz]
                    + m1[cx, tx] * k1[cy, ty] * m1[cz, tz]
                    + m1[cx, tx] * m1[cy, ty] * k1[cz, tz]
                )


@njit(cache=True)
def screening_matvec(q_keys, nb, xmap, omap, n, s, samples, x, out):
    """Out += sum_p w_p B_i(p) sum_j B_j(p) x_j over the samples (cell, local coordinates).

    ``samples`` is the level's screening samples ``(scell, sloc, sw)``: each one's child cell
    ``8 i + o`` (k,), its position in that cell (k, 3) and its weight (k,). ``x`` laid out by
    ``xmap``, ``out`` by ``omap`` (:func:`stiffness_matvec`).

    The 27 cells around a sample and their weights are written out here (and in
    :func:`screening_rhs`, :func:`screening_blocks`): through a helper taking the arrays
    (``_gather27``, inlined) the matvec was 1.7x slower (``docs/design/poisson.md``).
    """
    _screening_band(
        q_keys, nb, xmap, omap, n, s, samples, x, out, (0, len(samples[0]), 0, len(q_keys))
    )


@njit(cache=True, parallel=True)
def screening_matvec_bands(q_keys, nb, xmap, omap, n, s, samples, x, out, bands):
    """:func:`screening_matvec` over the threads, a band of parents each, the same bits.

    ``bands`` (b, 4) from :func:`screening_bands`: band ``b`` writes the rows of the parents
    ``bands[b, 2]`` to ``bands[b, 3] - 1`` only, from the samples ``bands[b, 0]`` to
    ``bands[b, 1] - 1`` (all those that reach them), in order: every row sums as in one walk.
    """
    for b in prange(len(bands)):
        band = (bands[b, 0], bands[b, 1], bands[b, 2], bands[b, 3])
        _screening_band(q_keys, nb, xmap, omap, n, s, samples, x, out, band)


@njit(cache=True)
def screening_bands(q_keys, scell, nbands):
    """Bands of parents for :func:`screening_matvec_bands`: samples from, to, parents from, to.

    (b, 4); ``nbands`` bands of equal parent counts; a band's samples are those whose parent's
    x is within one of the band's parents' (the samples in order of their parent's x, as they
    come sorted by cell key). One band of everything when they are not in that order.
    """
    m = len(q_keys)
    ns = len(scell)
    px = np.empty(ns, np.int64)
    ok = nbands > 1 and m >= nbands
    for p in range(ns):
        px[p] = (q_keys[scell[p] >> 3] >> 42) & MASK21
        if p > 0 and px[p] < px[p - 1]:
            ok = False
    if not ok:
        out = np.empty((1, 4), np.int64)
        out[0, 0], out[0, 1], out[0, 2], out[0, 3] = 0, ns, 0, m
        return out
    out = np.empty((nbands, 4), np.int64)
    for b in range(nbands):
        q0 = b * m // nbands
        q1 = (b + 1) * m // nbands
        out[b, 0] = lower_bound(px, ((q_keys[q0] >> 42) & MASK21) - 1, 0, ns)
        out[b, 1] = lower_bound(px, ((q_keys[q1 - 1] >> 42) & MASK21) + 2, 0, ns)
        out[b, 2] = q0
        out[b, 3] = q1
    return out


@njit(cache=True, inline="always")
def _screening_band(q_keys, nb, xmap, omap, n, s, samples, x, out, band):
    """:func:`screening_matvec` from samples ``p0`` to ``p1 - 1`` into parents [q0, q1)'s rows.

    ``band`` is ``(p0, p1, q0, q1)`` (a row of :func:`screening_bands`).
    """
    scell, sloc, sw = samples
    p0, p1, q0, q1 = band
    wx = np.empty(3)
    wy = np.empty(3)
    wz = np.empty(3)
    idx = np.empty(27, np.int64)
    wr = np.empty(27)
    for p in range(p0, p1):
        m = scell[p]
        i = m >> 3
        o = m & 7
        k = q_keys[i]
        ox = o & 1
        oy = (o >> 1) & 1
        oz = (o >> 2) & 1
        wx[0], wx[1], wx[2] = w3(sloc[p, 0], 2 * ((k >> 42) & MASK21) + ox, n, s)
        wy[0], wy[1], wy[2] = w3(sloc[p, 1], 2 * ((k >> 21) & MASK21) + oy, n, s)
        wz[0], wz[1], wz[2] = w3(sloc[p, 2], 2 * (k & MASK21) + oz, n, s)
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
                        if qo >= 0 and q0 <= q < q1:
                            idx[r] = 8 * qo + c8
                    r += 1
        v *= sw[p]
        for r in range(27):
            j = idx[r]
            if j >= 0:
                out[j] += wr[r] * v


@njit(cache=True)
def screening_rhs(q_keys, nb, n, s, samples, target, rhs):
    """Rhs += sum_p w_p target B_i(p), in place; ``samples`` as :func:`screening_matvec`'s."""
    scell, sloc, sw = samples
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
        wx[0], wx[1], wx[2] = w3(sloc[p, 0], 2 * ((k >> 42) & MASK21) + ox, n, s)
        wy[0], wy[1], wy[2] = w3(sloc[p, 1], 2 * ((k >> 21) & MASK21) + oy, n, s)
        wz[0], wz[1], wz[2] = w3(sloc[p, 2], 2 * (k & MASK21) + oz, n, s)
        for c in range(3):
            bz = oz + c - 1
            for b in range(3):
                by = oy + b - 1
                for a in range(3):
                    bx = ox + a - 1
                    q = nb[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                    if q >= 0:
                        j = 8 * q + ((bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2))
                        rhs[j] += sw[p] * target * (wx[a] * wy[b] * wz[c])


@njit(cache=True)
def screening_blocks(q_keys, nb, cmap, n, s, samples, out):
    """out[cmap[q], r, r2] += sum_p w_p B_r(p) B_r2(p) for siblings r, r2 of each flagged parent q.

    A sample touches 3 cells per axis, of two parents: the pairs within one parent are 5 of the 9
    per axis, 125 of the 729. Samples in order, so each entry sums in the same order whatever the
    caller; in bands of parents over the threads (:func:`screening_bands`), each writing its
    parents' blocks only, from the samples in order: the same sums. ``samples`` as
    :func:`screening_matvec`'s.
    """
    screening_blocks_bands(q_keys, nb, cmap, n, s, samples, out, level_bands(q_keys, samples[0]))


@njit(cache=True, parallel=True)
def screening_blocks_bands(q_keys, nb, cmap, n, s, samples, out, bands):
    """:func:`screening_blocks` in the given ``bands`` (:func:`screening_bands`), a thread each."""
    for b in prange(len(bands)):
        band = (bands[b, 0], bands[b, 1], bands[b, 2], bands[b, 3])
        _screening_blocks_band(q_keys, nb, cmap, n, s, samples, out, band)


@njit(cache=True, inline="always")
def _screening_blocks_band(q_keys, nb, cmap, n, s, samples, out, band):
    """:func:`screening_blocks` from samples ``p0`` to ``p1 - 1`` into parents [q0, q1)'s blocks.

    ``band`` is ``(p0, p1, q0, q1)`` (a row of :func:`screening_bands`).
    """
    scell, sloc, sw = samples
    p0, p1, q0, q1 = band
    wx = np.empty(3)
    wy = np.empty(3)
    wz = np.empty(3)
    for p in range(p0, p1):
        m = scell[p]
        i = m >> 3
        o = m & 7
        k = q_keys[i]
        ox = o & 1
        oy = (o >> 1) & 1
        oz = (o >> 2) & 1
        wx[0], wx[1], wx[2] = w3(sloc[p, 0], 2 * ((k >> 42) & MASK21) + ox, n, s)
        wy[0], wy[1], wy[2] = w3(sloc[p, 1], 2 * ((k >> 21) & MASK21) + oy, n, s)
        wz[0], wz[1], wz[2] = w3(sloc[p, 2], 2 * (k & MASK21) + oz, n, s)
        swp = sw[p]
        for c in range(3):
            bz = oz + c - 1
            for c2 in range(3):
                bz2 = oz + c2 - 1
                if bz2 >> 1 != bz >> 1:
                    continue
                for b in range(3):
                    by = oy + b - 1
                    for b2 in range(3):
                        by2 = oy + b2 - 1
                        if by2 >> 1 != by >> 1:
                            continue
                        for a in range(3):
                            bx = ox + a - 1
                            q = nb[i, ((bx >> 1) + 1) + 3 * ((by >> 1) + 1) + 9 * ((bz >> 1) + 1)]
                            if q < q0 or q >= q1 or cmap[q] < 0:
                                continue
                            w = wx[a] * wy[b] * wz[c]
                            r = (bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2)
                            for a2 in range(3):
                                bx2 = ox + a2 - 1
                                if bx2 >> 1 != bx >> 1:
                                    continue
                                r2 = (bx2 & 1) | ((by2 & 1) << 1) | ((bz2 & 1) << 2)
                                out[cmap[q], r, r2] += swp * w * (wx[a2] * wy[b2] * wz[c2])


# a Cholesky pivot at most this fraction of its diagonal entry: the block is singular to rounding
PIVOT_FLOOR = 1e-10


@njit(cache=True, inline="always")
def _cholesky(A, idx, L):
    """Cholesky factor L (na, na) of A (8, 8)'s rows and columns with a positive diagonal.

    Their indices go to ``idx`` (na,); reads the lower triangle. Returns ``na``, or -1 when a
    pivot is not above ``PIVOT_FLOOR`` of its diagonal.
    """
    na = 0
    for o in range(8):
        if A[o, o] > 0.0:
            idx[na] = o
            na += 1
    for j in range(na):
        d = A[idx[j], idx[j]]
        for t in range(j):
            d -= L[j, t] * L[j, t]
        if not d > PIVOT_FLOOR * A[idx[j], idx[j]]:
            return -1
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, na):
            v = A[idx[i], idx[j]]
            for t in range(j):
                v -= L[i, t] * L[j, t]
            L[i, j] = v / L[j, j]
    return na


@njit(cache=True, inline="always")
def _diagonal_inverse(A):
    """A (8, 8) := the inverse of its diagonal, where positive (0 elsewhere)."""
    for o in range(8):
        d = A[o, o]
        for o2 in range(8):
            A[o, o2] = 0.0
        if d > 0.0:
            A[o, o] = 1.0 / d


@njit(cache=True, inline="always")
def _inverse_from_cholesky(A, idx, L, Li, na):
    """A (8, 8) := L^-T L^-1 on the rows and columns ``idx[:na]`` (:func:`_cholesky`), 0 elsewhere.

    L^-1 column by column into ``Li``, then the product.
    """
    for j in range(na):
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, na):
            v = 0.0
            for t in range(j, i):
                v -= L[i, t] * Li[t, j]
            Li[i, j] = v / L[i, i]
    A[:, :] = 0.0
    for i in range(na):
        for j in range(i + 1):
            v = 0.0
            for t in range(i, na):
                v += Li[t, i] * Li[t, j]
            A[idx[i], idx[j]] = v
            A[idx[j], idx[i]] = v


@njit(cache=True, inline="always")
def _invert_block(A, idx, L, Li):
    """A (8, 8) := the inverse of its rows and columns with a positive diagonal, 0 elsewhere.

    By Cholesky on the lower triangle; returns 1 and leaves the diagonal's inverse alone when a
    pivot is not above ``PIVOT_FLOOR`` of its diagonal (the block is not numerically positive
    definite: the pure Neumann level 1 without screening, one block holding the constant).
    """
    na = _cholesky(A, idx, L)
    if na < 0:
        _diagonal_inverse(A)
        return 1
    _inverse_from_cholesky(A, idx, L, Li, na)
    return 0


@njit(cache=True, parallel=True)
def factor_blocks(blocks):
    """Each (8, 8) block of ``blocks`` (b, 8, 8) replaced by its inverse, in place.

    Rows and columns whose diagonal is not positive get 0 (:func:`_invert_block`). Returns the
    number of blocks left with their diagonal's inverse (not positive definite).
    """
    nb = len(blocks)
    nchunks = (nb + MATVEC_CHUNK - 1) // MATVEC_CHUNK
    nd = 0
    for ci in prange(nchunks):
        idx = np.empty(8, np.int64)
        L = np.zeros((8, 8))
        Li = np.zeros((8, 8))
        for b in range(ci * MATVEC_CHUNK, min(nb, (ci + 1) * MATVEC_CHUNK)):
            nd += _invert_block(blocks[b], idx, L, Li)
    return nd


# a symmetric (8, 8) block packed: its lower triangle, row by row (entry (o, o2), o2 <= o, at
# o (o + 1) / 2 + o2)
PACKED = 36


@njit(cache=True)
def pack_blocks(flat, nb):
    """The first ``nb`` (8, 8) blocks of ``flat`` (64 nb,) packed into its first 36 nb entries.

    In place, block by block (a block's packed entries end before the next block's start); the
    blocks must be symmetric (:func:`factor_blocks`' inverses are, to the bit).
    """
    tmp = np.empty(PACKED)
    for b in range(nb):
        k = 0
        for o in range(8):
            for o2 in range(o + 1):
                tmp[k] = flat[64 * b + 8 * o + o2]
                k += 1
        for k in range(PACKED):
            flat[PACKED * b + k] = tmp[k]


@njit(cache=True, inline="always")
def _packed(o, o2):
    """Index of entry (o, o2) of a packed symmetric block."""
    hi = max(o, o2)
    return hi * (hi + 1) // 2 + min(o, o2)


@njit(cache=True, inline="always")
def _apply_block(inv, b, r, z):
    """Block ``b``'s 8 rows of z = inv r (``inv`` packed: :func:`pack_blocks`); returns their r.z.

    The products summed in the order of the whole block's rows: the same bits as unpacked.
    """
    rz = 0.0
    for o in range(8):
        v = 0.0
        for o2 in range(8):
            v += inv[b, _packed(o, o2)] * r[8 * b + o2]
        z[8 * b + o] = v
    for o in range(8):
        rz += r[8 * b + o] * z[8 * b + o]
    return rz


@njit(cache=True)
def apply_blocks(inv, r, z):
    """Set z to the block-diagonal ``inv`` (b, 36: packed) times r (8b,); returns r.z."""
    rz = 0.0
    for b in range(len(inv)):
        rz += _apply_block(inv, b, r, z)
    return rz


@njit(cache=True)
def level_matvec(q_keys, nb, inp, xmap, omap, stiffness, n, s, samples, x, out):
    """Out = A x (stiffness and screening) at the unknowns.

    Elsewhere whatever A gives; ``x`` laid out by ``xmap``, ``out`` by ``omap``
    (:func:`stiffness_matvec`). ``stiffness`` is ``(m1, k1, h)``, the level's 1D tables (n, 5)
    and its cell size (:func:`stiffness_matvec`); ``samples`` the screening's
    (:func:`screening_matvec`).
    """
    bands = level_bands(q_keys, samples[0])
    _level_product(q_keys, nb, inp, (xmap, omap), stiffness, n, s, samples, bands, x, out)


@njit(cache=True)
def level_bands(q_keys, scell):
    """The screening's bands of parents for a level (:func:`screening_bands`).

    One band below :data:`SCREEN_MIN_SAMPLES` samples, where a thread each costs more than it saves.
    """
    return screening_bands(q_keys, scell, SCREEN_BANDS if len(scell) >= SCREEN_MIN_SAMPLES else 1)


@njit(cache=True, inline="always")
def _level_product(q_keys, nb, inp, maps, stiffness, n, s, samples, bands, x, out):
    """Out = A x (:func:`level_matvec`), the screening in ``bands`` (:func:`level_bands`).

    ``maps`` is ``(xmap, omap)``, the layouts of ``x`` and ``out`` (:func:`stiffness_matvec`).
    """
    xmap, omap = maps
    m1, k1, h = stiffness
    out[:] = 0.0
    stiffness_matvec(q_keys, nb, inp, xmap, omap, m1, k1, h, x, out)
    if len(bands) > 1:
        screening_matvec_bands(q_keys, nb, xmap, omap, n, s, samples, x, out, bands)
    elif len(samples[2]):
        screening_matvec(q_keys, nb, xmap, omap, n, s, samples, x, out)


# blocks of 8 rows a chunk of the conjugate gradients' vector updates: the chunks' partial sums
# add in chunk order, so the dot products have the same bits whatever the threads
CG_CHUNK = 4096


@njit(cache=True, parallel=True)
def _cg_update(x, r, p, q, a, inv):
    """X += a p, r -= a q, q = the preconditioned residual, block by block; returns (r.r, r.z).

    ``r.r`` over the rows not fixed (a positive diagonal in ``inv``). With ``a`` = 0 and ``p``,
    ``q`` zero, x and r stay as they are and ``q`` receives the preconditioned residual (the
    start). Each block's ``q`` is read before its preconditioned residual overwrites it.
    Chunks of :data:`CG_CHUNK` blocks over the threads.
    """
    nb = len(inv)
    nc = (nb + CG_CHUNK - 1) // CG_CHUNK
    part = np.zeros((nc, 2))
    for c in prange(nc):
        rr = 0.0
        rz = 0.0
        for b in range(c * CG_CHUNK, min(nb, (c + 1) * CG_CHUNK)):
            for o in range(8):
                i = 8 * b + o
                x[i] += a * p[i]
                r[i] -= a * q[i]
                if inv[b, _packed(o, o)] > 0.0:  # rows without a positive diagonal are fixed
                    rr += r[i] * r[i]
            rz += _apply_block(inv, b, r, q)
        part[c, 0] = rr
        part[c, 1] = rz
    rr = 0.0
    rz = 0.0
    for c in range(nc):
        rr += part[c, 0]
        rz += part[c, 1]
    return rr, rz


@njit(cache=True, parallel=True)
def _cg_dot(p, q):
    """The dot product of p and q, in chunks of :data:`CG_CHUNK` blocks summed in order."""
    m = len(p)
    step = 8 * CG_CHUNK
    nc = (m + step - 1) // step
    part = np.zeros(nc)
    for c in prange(nc):
        v = 0.0
        for i in range(c * step, min(m, (c + 1) * step)):
            v += p[i] * q[i]
        part[c] = v
    v = 0.0
    for c in range(nc):
        v += part[c]
    return v


@njit(cache=True, parallel=True)
def _cg_direction(p, q, beta):
    """The next search direction: ``p`` := q + beta p, in place."""
    for i in prange(len(p)):
        p[i] = q[i] + beta * p[i]


@njit(cache=True)
def level_pcg(q_keys, nb, inp, cmap, stiffness, n, s, samples, rhs, inv, tol, max_iter):
    """Block-Jacobi-preconditioned conjugate gradients on the unknown cells only.

    ``rhs`` and the solution hold the children of the flagged parents, parent ``i``'s at
    ``8 cmap[i]`` (the ring of E, 40 % of its cells at the finest level, carries no unknown: vectors
    on all of E would be zero there); ``inv`` the inverse of each flagged parent's block
    of siblings (:func:`factor_blocks`), 0 on the rows and columns that are fixed (no positive
    diagonal: the free boundary's cells outside), whose search directions and solution stay 0 and
    whose residual does not count; packed (u, 36) (:func:`pack_blocks`). ``rhs`` is overwritten by
    the residual. ``stiffness`` and ``samples`` as :func:`level_matvec`'s.
    Returns (x, iterations, relative residual).
    """
    m = len(rhs)
    x = np.zeros(m)
    r = rhs
    p = np.zeros(m)
    bn, rz = _cg_update(x, r, x, p, 0.0, inv)
    bn = np.sqrt(bn)
    if bn == 0.0:
        return x, 0, 0.0
    q = np.empty(m)
    it = 0
    rel = 1.0
    bands = level_bands(q_keys, samples[0])
    maps = (cmap, cmap)
    while it < max_iter:
        _level_product(q_keys, nb, inp, maps, stiffness, n, s, samples, bands, p, q)
        pq = _cg_dot(p, q)
        if pq <= 0.0:
            break
        a = rz / pq
        rr, rz_new = _cg_update(x, r, p, q, a, inv)
        it += 1
        rel = np.sqrt(rr) / bn
        if rel < tol:
            break
        beta = rz_new / rz
        _cg_direction(p, q, beta)
        rz = rz_new
    return x, it, rel
