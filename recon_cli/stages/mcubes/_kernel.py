"""Numba kernels of marching cubes / tetrahedra: they only compute, the caller validates.

Tables and conventions: :mod:`recon_cli.stages.mcubes._luts`. Positions are returned in lattice
(index) units; the caller applies spacing and origin.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)

N_TYPES = 8  # as in _mcubes_luts: 7 edge types and the cell-centre vertex


@njit(cache=True, inline="always")
def _face_code(v0, v1, v2, v3, iso):
    """Bits of the four corners of a cell face below ``iso`` (corners 0-3 order)."""
    return (
        (1 if v0 < iso else 0)
        | (2 if v1 < iso else 0)
        | (4 if v2 < iso else 0)
        | (8 if v3 < iso else 0)
    )


@njit(cache=True, inline="always")
def _case(v0, v1, v2, v3, v4, v5, v6, v7, iso):
    """Case index (bit c set when corner c is below ``iso``), -1 when a corner is NaN."""
    case = 0
    if v0 < iso:
        case |= 1
    if v1 < iso:
        case |= 2
    if v2 < iso:
        case |= 4
    if v3 < iso:
        case |= 8
    if v4 < iso:
        case |= 16
    if v5 < iso:
        case |= 32
    if v6 < iso:
        case |= 64
    if v7 < iso:
        case |= 128
    # NaN compares false: checked only when the cell is not trivially empty (the hot path)
    if case != 0 and case != 255 and np.isnan(v0 + v1 + v2 + v3 + v4 + v5 + v6 + v7):
        return -1
    return case


@njit(cache=True)
def _face_bits(v, case, iso, ambiguous, face_corners):
    """Asymptotic decider on the ambiguous faces of ``case``: bit f = inside corners joined."""
    bits = 0
    amb = ambiguous[case]
    if amb:
        for f in range(6):
            if (amb >> f) & 1:
                a = v[face_corners[f, 0]] - iso
                b = v[face_corners[f, 1]] - iso
                c_ = v[face_corners[f, 2]] - iso
                d = v[face_corners[f, 3]] - iso
                # the inside pair is joined when the bilinear saddle is inside; both cells
                # sharing the face evaluate the same products, so they agree
                if a < 0.0:
                    joined = a * c_ > b * d
                else:
                    joined = b * d > a * c_
                if joined:
                    bits |= 1 << f
    return bits


@njit(cache=True)
def _table_index(v, iso, ambiguous, use_faces, face_corners):
    """Row of the case table for the 8 corner values ``v`` (-1: a NaN corner)."""
    case = _case(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], iso)
    if case < 0 or not use_faces:
        return case
    return case * 64 + _face_bits(v, case, iso, ambiguous, face_corners)


@njit(cache=True)
def _lerp_t(fa, fb, iso, clamp):
    t = (iso - fa) / (fb - fa)
    if t < clamp:
        t = clamp
    elif t > 1.0 - clamp:
        t = 1.0 - clamp
    return t


@njit(cache=True)
def _edge_point(v, e, edges, iso, clamp, p):
    """Local position (in [0, 1]^3) of the crossing on local edge ``e``."""
    ca = edges[e, 0]
    cb = edges[e, 1]
    tt = _lerp_t(v[ca], v[cb], iso, clamp)
    for ax in range(3):
        oa = (ca >> ax) & 1
        ob = (cb >> ax) & 1
        p[ax] = oa + tt * (ob - oa)


@njit(cache=True)
def _centre_point(v, loop, edges, iso, clamp, p):
    q = np.empty(3, np.float64)
    p[:] = 0.0
    n = 0
    for s in range(loop.shape[0]):
        if loop[s] < 0:
            break
        _edge_point(v, loop[s], edges, iso, clamp, q)
        for ax in range(3):
            p[ax] += q[ax]
        n += 1
    for ax in range(3):
        p[ax] /= n


@njit(cache=True)
def _trilinear_grad(v, p, g):
    """Gradient (per unit cell) of the trilinear interpolant of ``v`` at local ``p``."""
    g[:] = 0.0
    for c in range(8):
        w0 = p[0] if c & 1 else 1.0 - p[0]
        w1 = p[1] if (c >> 1) & 1 else 1.0 - p[1]
        w2 = p[2] if (c >> 2) & 1 else 1.0 - p[2]
        f = v[c]
        g[0] += f * (1.0 if c & 1 else -1.0) * w1 * w2
        g[1] += f * (1.0 if (c >> 1) & 1 else -1.0) * w0 * w2
        g[2] += f * (1.0 if (c >> 2) & 1 else -1.0) * w0 * w1


@njit(cache=True)
def _grow2(a, n):
    out = np.empty((n, a.shape[1]), a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _point_grad(vol, i, j, k, g):
    """Central-difference gradient at sample (i, j, k) (one-sided at borders and NaN)."""
    n0, n1, n2 = vol.shape
    f = vol[i, j, k]
    idx = (i, j, k)
    dims = (n0, n1, n2)
    for ax in range(3):
        lo_ok = idx[ax] > 0
        hi_ok = idx[ax] < dims[ax] - 1
        flo = 0.0
        fhi = 0.0
        if lo_ok:
            if ax == 0:
                flo = vol[i - 1, j, k]
            elif ax == 1:
                flo = vol[i, j - 1, k]
            else:
                flo = vol[i, j, k - 1]
            lo_ok = flo == flo
        if hi_ok:
            if ax == 0:
                fhi = vol[i + 1, j, k]
            elif ax == 1:
                fhi = vol[i, j + 1, k]
            else:
                fhi = vol[i, j, k + 1]
            hi_ok = fhi == fhi
        if lo_ok and hi_ok:
            g[ax] = 0.5 * (fhi - flo)
        elif hi_ok:
            g[ax] = fhi - f
        elif lo_ok:
            g[ax] = f - flo
        else:
            g[ax] = 0.0


@njit(cache=True, inline="always")
def _sum4(a, b, c, d):
    """Sum in float64 of four corner values: NaN when one is NaN or +inf and -inf meet."""
    return np.float64(a) + np.float64(b) + np.float64(c) + np.float64(d)


ROW_ABOVE = 0  # every sample of the row >= iso
ROW_BELOW = 1  # every sample < iso
ROW_MIXED = 2  # both, no NaN
ROW_NAN = 3  # a NaN or infinite sample


@njit(cache=True)
def _row_classes(vol, iso):
    """(nx, ny) int8: the class of each row ``vol[i, j, :]`` (ROW_ABOVE .. ROW_NAN).

    One read of every sample, in loops LLVM vectorises; a row of cells whose four rows are
    all ROW_ABOVE (or all ROW_BELOW) has no crossing and no cell to leave out, and is
    skipped whole.
    """
    nx, ny, nz = vol.shape
    cls = np.empty((nx, ny), np.int8)
    for i in range(nx):
        for j in range(ny):
            r = vol[i, j]
            below = 0
            nonfinite = 0
            for k in range(nz):
                x = r[k]
                below += 1 if x < iso else 0
                nonfinite += 0 if (x > -np.inf and x < np.inf) else 1
            if nonfinite:
                cls[i, j] = ROW_NAN
            elif below == 0:
                cls[i, j] = ROW_ABOVE
            elif below == nz:
                cls[i, j] = ROW_BELOW
            else:
                cls[i, j] = ROW_MIXED
    return cls


@njit(cache=True, inline="always")
def _nan_cells(r00, r10, r01, r11, nz):
    """Count the cells of a row left out: the sum of their 8 corners is NaN.

    That is a NaN corner, or +inf and -inf together: no crossing can be placed.
    """
    count = 0
    low = _sum4(r00[0], r10[0], r01[0], r11[0])
    for k in range(nz - 1):
        up = _sum4(r00[k + 1], r10[k + 1], r01[k + 1], r11[k + 1])
        if np.isnan(low + up):
            count += 1
        low = up
    return count


@njit(cache=True, inline="always")
def _centre_vertex(v, loop, edges, iso, clamp, cell, verts, grads, cid, p, g):
    """Write vertex ``cid``: the mean of the loop's crossings in cell ``cell`` = (i, j, k).

    Its gradient is the cell's trilinear interpolant's there.
    """
    i, j, k = cell
    _centre_point(v, loop, edges, iso, clamp, p)
    verts[cid, 0] = i + p[0]
    verts[cid, 1] = j + p[1]
    verts[cid, 2] = k + p[2]
    _trilinear_grad(v, p, g)
    for ax in range(3):
        grads[cid, ax] = g[ax]


@njit(cache=True, inline="always")
def _edge_vertex(vol, v, ends, iso, clamp, cell, verts, grads, nv, ga, gb):
    """Write vertex ``nv``: the crossing on the edge between corners ``ends`` of a cell.

    The cell is ``cell`` = (i, j, k); the gradient is interpolated between the corners'
    central differences.
    """
    i, j, k = cell
    ca = ends[0]
    cb = ends[1]
    tt = _lerp_t(v[ca], v[cb], iso, clamp)
    ai = i + (ca & 1)
    aj = j + ((ca >> 1) & 1)
    ak = k + ((ca >> 2) & 1)
    bi = i + (cb & 1)
    bj = j + ((cb >> 1) & 1)
    bk = k + ((cb >> 2) & 1)
    verts[nv, 0] = ai + tt * (bi - ai)
    verts[nv, 1] = aj + tt * (bj - aj)
    verts[nv, 2] = ak + tt * (bk - ak)
    _point_grad(vol, ai, aj, ak, ga)
    _point_grad(vol, bi, bj, bk, gb)
    for ax in range(3):
        grads[nv, ax] = ga[ax] + tt * (gb[ax] - ga[ax])


@njit(cache=True)
def dense_extract(
    vol,
    iso,
    start,
    tris,
    edges,
    edge_key,
    ambiguous,
    use_faces,
    face_corners,
    centre,
    centre_id,
    clamp,
):
    """Extract the iso-surface of a dense volume, slab by slab along axis 0.

    Returns vertices (k, 3) in index units, unnormalised gradients (k, 3), faces (m, 3)
    and the number of cells left out: those whose corner sum is NaN (a NaN corner, or
    +inf and -inf corners together). Vertices are made once per crossed
    edge: a map of the two lattice planes of the current slab (by parity of the plane)
    holds the vertex id of every edge keyed by its lower corner. An entry of plane P is
    only valid when made since slab P - 1 started, which saves clearing the map for every
    slab. Rows of cells with no crossing are skipped whole (see :func:`_row_classes`); the
    others are walked by :func:`_extract_row`.
    """
    nx, ny, nz = vol.shape
    rows = _row_classes(vol, iso)
    tables = (start, tris, edges, edge_key, ambiguous, use_faces, face_corners, centre, centre_id)
    skipped = 0
    vmap = np.full((2, ny, nz, N_TYPES), -1, np.int64)
    lo_valid = 0  # first vertex id valid in plane i
    hi_valid = 0  # first vertex id valid in plane i + 1
    mesh = (
        np.empty((1024, 3), np.float64),  # vertices
        np.empty((1024, 3), np.float64),  # their gradients
        np.empty((2048, 3), np.int64),  # faces
        0,  # vertices made
        0,  # faces made
    )
    scratch = (
        np.empty(8, np.float64),
        np.empty(3, np.float64),
        np.empty(3, np.float64),
        np.empty(3, np.float64),
        np.empty(3, np.float64),
    )
    for i in range(nx - 1):
        lo_valid = hi_valid
        hi_valid = mesh[3]
        for j in range(ny - 1):
            c00 = rows[i, j]
            c10 = rows[i + 1, j]
            c01 = rows[i, j + 1]
            c11 = rows[i + 1, j + 1]
            if c00 == c10 and c00 == c01 and c00 == c11 and c00 <= ROW_BELOW:
                continue  # all four rows on one side, no NaN: no cell of this row crosses
            if c00 == ROW_NAN or c10 == ROW_NAN or c01 == ROW_NAN or c11 == ROW_NAN:
                # count the cells left out below: the sum of the 8 corners is NaN (a NaN
                # corner, or +inf and -inf together: no crossing can be placed)
                skipped += _nan_cells(
                    vol[i, j], vol[i + 1, j], vol[i, j + 1], vol[i + 1, j + 1], nz
                )
            mesh = _extract_row(
                vol, iso, clamp, i, j, tables, vmap, (lo_valid, hi_valid), mesh, scratch
            )
    verts, grads, faces, nv, nf = mesh
    return verts[:nv].copy(), grads[:nv].copy(), faces[:nf].copy(), skipped


@njit(cache=True, inline="always")
def _extract_row(vol, iso, clamp, i, j, tables, vmap, valid, mesh, scratch):
    """The triangles of the row of cells (i, j, 0..nz-2), added to ``mesh``.

    ``mesh`` is ``(verts, grads, faces, nv, nf)``, returned with the arrays grown as needed;
    ``valid`` the first vertex ids valid in ``vmap``'s planes i and i + 1.
    """
    nz = vol.shape[2]
    start = tables[0]
    use_faces, ambiguous, face_corners = tables[5], tables[4], tables[6]
    v = scratch[0]
    # slide along k: the upper face's four corner bits become the next cell's lower
    # face, so each cell reads four new values (three times faster on empty space)
    r00 = vol[i, j]
    r10 = vol[i + 1, j]
    r01 = vol[i, j + 1]
    r11 = vol[i + 1, j + 1]
    lower = _face_code(r00[0], r10[0], r01[0], r11[0], iso)
    for k in range(nz - 1):
        upper = _face_code(r00[k + 1], r10[k + 1], r01[k + 1], r11[k + 1], iso)
        case = lower | (upper << 4)
        lower = upper
        if case == 0 or case == 255:  # all outside or all inside
            continue
        for c in range(8):
            v[c] = vol[i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)]
        if np.isnan((v[0] + v[1] + v[2] + v[3]) + (v[4] + v[5] + v[6] + v[7])):
            # NaN compares false: a cell with a NaN corner is left out (counted by the caller)
            continue
        row = case
        if use_faces:
            row = case * 64 + _face_bits(v, case, iso, ambiguous, face_corners)
        if start[row] != start[row + 1]:
            mesh = _cell_triangles(
                vol, iso, clamp, (i, j, k), row, tables, vmap, valid, mesh, scratch
            )
    return mesh


@njit(cache=True, inline="always")
def _cell_triangles(vol, iso, clamp, cell, row, tables, vmap, valid, mesh, scratch):
    """Add the triangles of table row ``row`` in cell ``cell`` = (i, j, k) to ``mesh``.

    A crossing's vertex is taken from ``vmap`` when an earlier cell made it, else made
    (:func:`_edge_vertex`); a cell's centre vertex (:func:`_centre_vertex`) is its own.
    """
    start, tris, edges, edge_key, _amb, _uf, _fc, centre, centre_id = tables
    verts, grads, faces, nv, nf = mesh
    v, ga, gb, p, g = scratch
    i, j, k = cell
    lo_valid, hi_valid = valid
    s0 = start[row]
    s1 = start[row + 1]
    if nf + (s1 - s0) > faces.shape[0]:
        faces = _grow2(faces, 2 * faces.shape[0] + (s1 - s0))
    if nv + 13 > verts.shape[0]:
        verts = _grow2(verts, 2 * verts.shape[0])
        grads = _grow2(grads, verts.shape[0])
    cid = -1
    if centre[row, 0] >= 0:
        # a vertex of this cell alone: mean of its loop's crossings
        cid = nv
        nv += 1
        _centre_vertex(v, centre[row], edges, iso, clamp, cell, verts, grads, cid, p, g)
    for t in range(s0, s1):
        for q in range(3):
            e = tris[t, q]
            if e == centre_id:
                faces[nf, q] = cid
                continue
            dx = edge_key[e, 0]
            jj = j + edge_key[e, 1]
            kk = k + edge_key[e, 2]
            ty = edge_key[e, 3]
            pl = (i + dx) & 1
            vid = vmap[pl, jj, kk, ty]
            if vid < (hi_valid if dx else lo_valid):
                if nv == verts.shape[0]:
                    verts = _grow2(verts, 2 * verts.shape[0])
                    grads = _grow2(grads, verts.shape[0])
                _edge_vertex(vol, v, edges[e], iso, clamp, cell, verts, grads, nv, ga, gb)
                vid = nv
                vmap[pl, jj, kk, ty] = vid
                nv += 1
            faces[nf, q] = vid
        nf += 1
    return verts, grads, faces, nv, nf


@njit(cache=True)
def sparse_rows(values, iso, start, ambiguous, use_faces, face_corners):
    """Table row of every cell (-1 for NaN) and its triangle count."""
    n = values.shape[0]
    rows = np.empty(n, np.int64)
    counts = np.zeros(n, np.int64)
    for i in range(n):
        r = _table_index(values[i], iso, ambiguous, use_faces, face_corners)
        rows[i] = r
        if r >= 0:
            counts[i] = start[r + 1] - start[r]
    return rows, counts


@njit(cache=True)
def sparse_corners(cells, rows, offsets, start, tris, edge_key, lo, dims):
    """Global edge key, cell and local edge of every triangle corner."""
    m = offsets[-1]
    keys = np.empty(3 * m, np.int64)
    cell_of = np.empty(3 * m, np.int32)  # cell counts stay far below 2**31 (checked by the caller)
    edge_of = np.empty(3 * m, np.int8)  # local edge id, < 14
    for i in range(cells.shape[0]):
        r = rows[i]
        if r < 0:
            continue
        f = offsets[i]
        for t in range(start[r], start[r + 1]):
            for q in range(3):
                e = tris[t, q]
                x = cells[i, 0] - lo[0] + edge_key[e, 0]
                y = cells[i, 1] - lo[1] + edge_key[e, 1]
                z = cells[i, 2] - lo[2] + edge_key[e, 2]
                p = 3 * f + q
                keys[p] = ((x * dims[1] + y) * dims[2] + z) * N_TYPES + edge_key[e, 3]
                cell_of[p] = i
                edge_of[p] = e
            f += 1
    return keys, cell_of, edge_of


@njit(cache=True)
def sparse_points(cells, values, rows, cell_of, edge_of, edges, centre, centre_id, iso, clamp):
    """Lattice position and trilinear field gradient of each (cell, local vertex)."""
    n = cell_of.shape[0]
    pos = np.empty((n, 3), np.float64)
    grad = np.empty((n, 3), np.float64)
    p = np.empty(3, np.float64)
    g = np.empty(3, np.float64)
    for s in range(n):
        i = cell_of[s]
        e = edge_of[s]
        if e == centre_id:
            _centre_point(values[i], centre[rows[i]], edges, iso, clamp, p)
        else:
            _edge_point(values[i], e, edges, iso, clamp, p)
        _trilinear_grad(values[i], p, g)
        for ax in range(3):
            pos[s, ax] = cells[i, ax] + p[ax]
            grad[s, ax] = g[ax]
    return pos, grad


# ---------------------------------------------------------------- report
@njit(cache=True)
def boundary_edge_count(faces, n_vertices):
    """Number of edges used by exactly one face of ``faces`` ((m, 3) int, indices < ``n_vertices``).

    Each edge is filed under its smaller end point (a counting sort by vertex, two passes
    over the faces); an end point's few larger neighbours are then sorted in place and the
    ones listed once are counted. Linear in the faces, ~10x cheaper than ``np.unique`` on
    the sorted edge pairs.
    """
    m = faces.shape[0]
    ptr = np.zeros(n_vertices + 1, np.int64)
    for f in range(m):
        for c in range(3):
            u = faces[f, c]
            v = faces[f, (c + 1) % 3]
            ptr[min(u, v) + 1] += 1
    for v in range(n_vertices):
        ptr[v + 1] += ptr[v]
    fill = ptr[:n_vertices].copy()
    other = np.empty(3 * m, np.int64)
    for f in range(m):
        for c in range(3):
            u = faces[f, c]
            v = faces[f, (c + 1) % 3]
            lo = min(u, v)
            other[fill[lo]] = max(u, v)
            fill[lo] += 1
    count = 0
    for v in range(n_vertices):
        a = ptr[v]
        b = ptr[v + 1]
        for i in range(a + 1, b):  # insertion sort: a vertex has a handful of larger neighbours
            x = other[i]
            j = i - 1
            while j >= a and other[j] > x:
                other[j + 1] = other[j]
                j -= 1
            other[j + 1] = x
        i = a
        while i < b:
            j = i + 1
            while j < b and other[j] == other[i]:
                j += 1
            if j - i == 1:
                count += 1
            i = j
    return count
