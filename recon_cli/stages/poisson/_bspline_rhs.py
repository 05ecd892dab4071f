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
    cells in reach (images folded, :func:`_splat_factors`), then the flagged parents in the box,
    walking their sorted keys, and their children in it (:func:`_splat_parents`).
    """
    n_keys = len(q_keys)
    b = np.zeros(8 * n_keys)
    if n_keys == 0:
        return b
    n = 1 << level
    smin = level
    for p in range(pos.shape[0]):
        smin = min(smin, splat_level[p])
    wmax = min(2 * int(np.ceil(1.5 + 1.5 * width * 2.0 ** max(level - smin, 0))) + 4, n)
    fv = np.zeros((3, wmax))
    fd = np.zeros((3, wmax))
    box = np.empty((2, 3), np.int64)
    for p in range(pos.shape[0]):
        rho = width * 2.0 ** (level - splat_level[p])
        if _splat_factors(pos, p, rho, n, s, fv, fd, box):
            continue
        _splat_parents(q_keys, inp, box, fv, fd, normal_w, p, b)
    return b


@njit(cache=True, inline="always")  # inlined: no stage calls splat_rhs, no warm-up compiles it
def _splat_factors(pos, p, rho, n, s, fv, fd, box):
    """Item ``p``'s 1D value and derivative factors per axis, at the cells in its reach.

    ``fv``, ``fd`` (3, w): row ``a`` holds the cells ``box[0, a]`` to ``box[1, a]`` (the reach,
    clipped to the cube and to ``w`` cells), images beyond the faces folded on (sign ``s``).
    ``rho`` is the B-spline's width in cells of the level (``n`` per axis). Returns True when the
    box is empty.
    """
    wmax = fv.shape[1]
    scale = float(n)
    reach = 1.5 + 1.5 * rho
    empty = False
    for a in range(3):
        u = pos[p, a] * scale
        e0 = int(np.floor(u - 0.5 - reach))
        e1 = int(np.ceil(u - 0.5 + reach))
        box[0, a] = max(e0, 0)
        box[1, a] = min(e1, n - 1, box[0, a] + wmax - 1)
        if box[1, a] < box[0, a]:
            empty = True
            continue
        for t in range(box[1, a] - box[0, a] + 1):
            fv[a, t] = 0.0
            fd[a, t] = 0.0
        for c in range(e0, e1 + 1):
            v = u - (c + 0.5)
            if abs(v) >= reach:
                continue
            cf, sg = fold(c, n, s)
            if cf < box[0, a] or cf > box[1, a]:
                continue
            val, der = b2_factors(v, rho)
            fv[a, cf - box[0, a]] += sg * val
            fd[a, cf - box[0, a]] += sg * der * scale
    return empty


@njit(cache=True, inline="always")  # inlined: no stage calls splat_rhs, no warm-up compiles it
def _splat_parents(q_keys, inp, box, fv, fd, normal_w, p, b):
    """Add item ``p``'s share to ``b`` at the children in ``box`` of the flagged parents.

    Walks the parents' sorted keys whose cell is in the box halved, x by x; ``fv``, ``fd`` and
    ``box`` from :func:`_splat_factors`.
    """
    n_keys = len(q_keys)
    l1 = box[0, 1] >> 1
    l2 = box[0, 2] >> 1
    h1 = box[1, 1] >> 1
    h2 = box[1, 2] >> 1
    for x in range(box[0, 0] >> 1, (box[1, 0] >> 1) + 1):
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
                _splat_children(box, fv, fd, normal_w, p, x, y, z, b, 8 * j)
            j += 1


@njit(cache=True, inline="always")
def _splat_children(box, fv, fd, normal_w, p, x, y, z, b, base):
    """b[base + o] += item ``p``'s share at child ``o`` of parent (x, y, z), those in ``box``."""
    nx = normal_w[p, 0]
    ny = normal_w[p, 1]
    nz = normal_w[p, 2]
    for o in range(8):
        cx = 2 * x + (o & 1) - box[0, 0]
        cy = 2 * y + ((o >> 1) & 1) - box[0, 1]
        cz = 2 * z + ((o >> 2) & 1) - box[0, 2]
        if min(cx, cy, cz) < 0:
            continue
        if cx > box[1, 0] - box[0, 0] or cy > box[1, 1] - box[0, 1] or cz > box[1, 2] - box[0, 2]:
            continue
        b[base + o] += (
            nx * fd[0, cx] * fv[1, cy] * fv[2, cz]
            + ny * fv[0, cx] * fd[1, cy] * fv[2, cz]
            + nz * fv[0, cx] * fv[1, cy] * fd[2, cz]
        )


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


@njit(cache=True, inline="always")
def _mirror_row(X, a, r, mr, s):
    """Row ``r`` of block ``X`` (m, m, m, 3) across axis ``a`` := its mirror row ``mr``'s.

    With sign ``s``, ``-s`` for the component along ``a`` (a reflection turns it over).
    """
    m = X.shape[0]
    for u in range(m):
        for v in range(m):
            for comp in range(3):
                sg = -s if comp == a else s
                if a == 0:
                    X[r, u, v, comp] = sg * X[mr, u, v, comp]
                elif a == 1:
                    X[u, r, v, comp] = sg * X[u, mr, v, comp]
                else:
                    X[u, v, r, comp] = sg * X[u, v, mr, comp]


@njit(cache=True)
def _fold_block(X, k, n, s):
    """Fold the cells beyond the faces of parent ``k``'s 6 x 6 x 6 block ``X`` of the field.

    Block rows 0, 1 at the low face mirror 3, 2; rows 4, 5 at the high face mirror 3, 2; axis by
    axis (:func:`_mirror_row`).
    """
    for a in range(3):
        p = (k >> (42 - 21 * a)) & MASK21
        if p == 0:
            _mirror_row(X, a, 0, 3, s)
            _mirror_row(X, a, 1, 2, s)
        if 2 * p + 2 >= n:
            _mirror_row(X, a, 4, 3, s)
            _mirror_row(X, a, 5, 2, s)


@njit(cache=True)
def _block_stencil(X, z3, y3, k, fv, fd, out, base):
    """The separable stencil of :func:`field_rhs` on a folded block, one axis at a time.

    out[base + o] += for the 8 children o of parent ``k``; ``z3`` (6, 6, 2, 3) and ``y3``
    (6, 2, 2, 3) the passes' scratch.
    """
    px = (k >> 42) & MASK21
    py = (k >> 21) & MASK21
    pz = k & MASK21
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


@njit(cache=True)
def _block_rhs(X, z3, y3, k, n, s, fv, fd, out, base):
    """The stencil of :func:`field_rhs` on one parent's 6 x 6 x 6 block ``X`` of the field.

    The block holds cells 2P - 2 .. 2P + 3 per axis (P the parent's cell ``k``), the cells beyond
    the faces folded first (:func:`_fold_block`): out[base + o] += for its 8 children
    (:func:`_block_stencil`). (A call per parent, thousands of operations each: not the
    per-element helper call that costs in the hot loops.)
    """
    _fold_block(X, k, n, s)
    _block_stencil(X, z3, y3, k, fv, fd, out, base)


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
def field_rhs_prolonged(q_keys, nb, flag, n, s, fv, fd, coarse, idx, rows, out):
    """:func:`field_rhs` for the coarser level's field, refined on the fly.

    ``coarse`` is ``(cq_keys, cnb, cvec)``: the coarser level's E (sorted parent keys, their 27
    neighbours) and the field's coefficients on it (8qc, 3), folded. The field is refined
    (:func:`prolong_field`'s mask, per parent: the coarser cells P - 2 .. P + 2 per axis give the
    block's cells 2P - 2 .. 2P + 3, :func:`_coarse_block`, :func:`_refine_x` and on) plus
    ``rows[idx]`` (:func:`_add_rows_block`): for the finest level, whose refined field on E (24 B a
    cell) would be the largest array of the solve. Equal to :func:`field_rhs` of
    :func:`prolong_field`'s result to rounding.
    Parents in chunks over the threads (each writes its own children only).
    """
    w = np.array([0.125, 0.375, 0.375, 0.125])
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
            _coarse_block(C, coarse, k, n >> 1, s)
            # refine, one axis at a time
            _refine_x(C, R1, w)
            _refine_y(R1, R2, w)
            _refine_z(R2, X, w)
            if sparse:
                _add_rows_block(X, nb, i, idx, rows)
            _block_rhs(X, z3, y3, k, n, s, fv, fd, out, 8 * i)


@njit(cache=True)
def _coarse_block(C, coarse, k, nc, s):
    """C (5, 5, 5, 3) := the coarser cells P - 2 .. P + 2 per axis around parent ``k``'s cell P.

    ``coarse`` as :func:`field_rhs_prolonged`'s, on a level of ``nc`` cells per axis; 0 where the
    coarser E has none; the cells beyond the faces their mirrors' (sign ``s``, ``-s`` for the
    component along the face's normal), axis by axis.
    """
    cq_keys, cnb, cvec = coarse
    px = (k >> 42) & MASK21
    py = (k >> 21) & MASK21
    pz = k & MASK21
    C[:] = 0.0
    j = find_cell(cq_keys, px, py, pz)
    if j < 0:
        return
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
    for ax in range(3):
        pc = (k >> (42 - 21 * ax)) & MASK21
        for a in range(5):
            cc = pc - 2 + a
            if cc < 0:
                _mirror_row(C, ax, a, -1 - cc - (pc - 2), s)
            elif cc >= nc:
                _mirror_row(C, ax, a, 2 * nc - 1 - cc - (pc - 2), s)


# Refinement of a coarser block, one axis at a time (:func:`field_rhs_prolonged`): block cell
# 2P - 2 + b takes coarser cell P - 2 + a with weight w[b + 3 - 2a].


@njit(cache=True)
def _refine_x(C, R1, w):
    """R1 (6, 5, 5, 3) := C (5, 5, 5, 3) refined along its first axis."""
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


@njit(cache=True)
def _refine_y(R1, R2, w):
    """R2 (6, 6, 5, 3) := R1 (6, 5, 5, 3) refined along its second axis."""
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


@njit(cache=True)
def _refine_z(R2, X, w):
    """X (6, 6, 6, 3) := R2 (6, 6, 5, 3) refined along its third axis."""
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


@njit(cache=True)
def _add_rows_block(X, nb, i, idx, rows):
    """X += the sparse field ``rows[idx[m]]`` at parent ``i``'s block's cells.

    ``idx``, ``rows`` as :func:`field_rows` gives them.
    """
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
    ``blocks`` is :func:`finer_blocks`; finer cells not in the finer E count as 0. Per parent: its
    block of finer cells (:func:`_fine_block`), folded (:func:`_fold_fine_block`), restricted
    (:func:`_restrict_block`).
    """
    out = np.zeros(8 * len(q_keys))
    X = np.zeros((6, 6, 6))
    zr = np.empty((6, 6, 2))
    yr = np.empty((6, 2, 2))
    r4 = np.array([0.25, 0.75, 0.75, 0.25])
    for i in range(len(q_keys)):
        if not flag[i]:
            continue
        _fine_block(X, nb, i, blocks, fine)
        _fold_fine_block(X, q_keys[i], n, s)
        _restrict_block(X, zr, yr, r4, out, 8 * i)
    return out


@njit(cache=True)
def _fine_block(X, nb, i, blocks, fine):
    """X (6, 6, 6) := the finer cells 4P - 1 .. 4P + 4 per axis around parent ``i``'s cell P.

    The cells 2P - 1 .. 2P + 2 per axis (cell 2P - 1 + a is child (a + 1) & 1 of the parent at
    offset ((a + 1) >> 1) - 1) and their children: block rows 0..5 (row 2a - 1 + child); 0 where
    the finer E has none (``blocks``, ``fine`` as :func:`restrict_rhs`'s).
    """
    X[:] = 0.0
    for c in range(4):
        for b in range(4):
            for a in range(4):
                p = nb[i, ((a + 1) >> 1) + 3 * ((b + 1) >> 1) + 9 * ((c + 1) >> 1)]
                if p < 0:
                    continue
                jf = blocks[8 * p + (((a + 1) & 1) | (((b + 1) & 1) << 1) | (((c + 1) & 1) << 2))]
                if jf < 0:
                    continue
                for of in range(8):
                    rx = 2 * a - 1 + (of & 1)
                    ry = 2 * b - 1 + ((of >> 1) & 1)
                    rz = 2 * c - 1 + ((of >> 2) & 1)
                    if rx < 0 or ry < 0 or rz < 0 or rx > 5 or ry > 5 or rz > 5:
                        continue
                    X[rx, ry, rz] = fine[8 * jf + of]


@njit(cache=True)
def _fold_fine_block(X, k, n, s):
    """The finer cells beyond the faces: row 0 (cell -1) mirrors row 1, row 5 (cell 2n) row 4.

    Sign ``s``; ``X`` (6, 6, 6) is parent ``k``'s block (:func:`_fine_block`), ``n`` the cells
    per axis of the parent's level.
    """
    px = (k >> 42) & MASK21
    py = (k >> 21) & MASK21
    pz = k & MASK21
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


@njit(cache=True)
def _restrict_block(X, zr, yr, r4, out, base):
    """out[base + o] := the restriction of block ``X`` (6, 6, 6) to child ``o`` of its parent.

    Child ``o``: finer rows 2 o .. 2 o + 3 per axis, weights ``r4``, one axis at a time (``zr``
    (6, 6, 2), ``yr`` (6, 2, 2) the passes' scratch).
    """
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
        out[base + o] = v
