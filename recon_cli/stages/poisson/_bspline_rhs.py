"""Numba kernels of the degree-2 right-hand side: the normals' field, splatted or refined.

They only compute; conventions in :mod:`._bspline`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli.stages.poisson._bspline import (
    MATVEC_CHUNK,
    b2_factors,
    find_cell,
    fold,
    gallop,
)
from recon_cli.stages.poisson._octree import MASK21, lattice_key


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
        # the coarse cells around the parent (written out rather than through nbr_cell: a
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
