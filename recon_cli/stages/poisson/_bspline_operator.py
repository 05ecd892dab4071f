"""Numba kernels of the degree-2 system's operator: stiffness, screening, the level's CG.

They only compute; conventions in :mod:`._bspline`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli.stages.poisson._bspline import (
    MATVEC_CHUNK,
    w3,
)
from recon_cli.stages.poisson._octree import MASK21


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
                        w = wx[a] * wy[b] * wz[c]
                        diag[j] += sw[p] * w * w
                        rhs[j] += sw[p] * target * w


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
    fixed (the free boundary's cells outside): their search directions and
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
