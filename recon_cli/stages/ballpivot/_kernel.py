"""Numba kernels of ball pivoting: compute only, the stage validates.

Validation lives in :mod:`recon_cli.stages.ballpivot`.

State is held in flat arrays:

- a uniform grid per radius (cell = 2 rho): points sorted by cell key, the unique keys and
  CSR starts, and the sorted coordinates (so a neighbourhood scan reads contiguous memory);
- edges: ``ea, eb`` (direction as in the edge's first face), ``eo`` (that face's third
  vertex, so the face is ``(ea, eb, eo)``), ``ec`` (the centre of the ball resting on that
  face), ``es`` (FRONT, BOUNDARY or INNER = two faces), found through an open-addressing
  hash of ``min * n + max``;
- per vertex: ``used`` and ``bcount`` (number of incident one-face edges; a used vertex with
  ``bcount == 0`` is interior and can no longer be touched);
- the front: a stack of edge ids (last in, first out: the newest edges are pivoted first,
  so the work stays local in memory; on 1M points this halves the time of a FIFO).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import grow1, grow2, lower_bound
from recon_cli._kernels.hashtable import probe
from recon_cli._kernels.unionfind import find

FRONT = np.int8(0)
BOUNDARY = np.int8(1)
INNER = np.int8(2)

_TWO_PI = 2.0 * np.pi
# an angle this close below 0 (rad) means the point is on the current ball (co-spherical)
_ANGLE_EPS = 1e-7
# a point is inside a ball if closer to its centre than rho * (1 - _EMPTY_EPS)
_EMPTY_EPS = 1e-7
# a seed triangle is searched among this many nearest unused neighbours of the seed point
SEED_CANDIDATES = 24


# ---------------------------------------------------------------- uniform grid
@njit(cache=True)
def build_grid(pts, lo, cell, dims):
    """Sort points by grid cell. Returns (ukeys, ustart, sidx, spts)."""
    n = pts.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        ix = min(max(int((pts[i, 0] - lo[0]) / cell), 0), dims[0] - 1)
        iy = min(max(int((pts[i, 1] - lo[1]) / cell), 0), dims[1] - 1)
        iz = min(max(int((pts[i, 2] - lo[2]) / cell), 0), dims[2] - 1)
        keys[i] = (ix * dims[1] + iy) * dims[2] + iz
    sidx = np.argsort(keys, kind="mergesort")
    nu = 0
    for t in range(n):
        if t == 0 or keys[sidx[t]] != keys[sidx[t - 1]]:
            nu += 1
    ukeys = np.empty(nu, np.int64)
    ustart = np.empty(nu + 1, np.int64)
    u = 0
    for t in range(n):
        if t == 0 or keys[sidx[t]] != keys[sidx[t - 1]]:
            ukeys[u] = keys[sidx[t]]
            ustart[u] = t
            u += 1
    ustart[nu] = n
    spts = np.empty((n, 3), np.float64)
    for t in range(n):
        spts[t, 0] = pts[sidx[t], 0]
        spts[t, 1] = pts[sidx[t], 1]
        spts[t, 2] = pts[sidx[t], 2]
    return ukeys, ustart, sidx, spts


@njit(cache=True)
def gather(ukeys, ustart, sidx, spts, lo, cell, dims, qx, qy, qz, r, out):
    """Write into ``out`` the ids of points within ``r`` of (qx, qy, qz); return their count."""
    r2 = r * r
    ix0 = max(int(np.floor((qx - r - lo[0]) / cell)), 0)
    ix1 = min(int(np.floor((qx + r - lo[0]) / cell)), dims[0] - 1)
    iy0 = max(int(np.floor((qy - r - lo[1]) / cell)), 0)
    iy1 = min(int(np.floor((qy + r - lo[1]) / cell)), dims[1] - 1)
    iz0 = max(int(np.floor((qz - r - lo[2]) / cell)), 0)
    iz1 = min(int(np.floor((qz + r - lo[2]) / cell)), dims[2] - 1)
    cnt = 0
    nu = ukeys.shape[0]
    for ix in range(ix0, ix1 + 1):
        for iy in range(iy0, iy1 + 1):
            base = (ix * dims[1] + iy) * dims[2]
            k1 = base + iz1
            pos = lower_bound(ukeys, base + iz0, 0, len(ukeys))
            while pos < nu and ukeys[pos] <= k1:
                for t in range(ustart[pos], ustart[pos + 1]):
                    dx = spts[t, 0] - qx
                    dy = spts[t, 1] - qy
                    dz = spts[t, 2] - qz
                    if dx * dx + dy * dy + dz * dz <= r2:
                        out[cnt] = sidx[t]
                        cnt += 1
                pos += 1
    return cnt


@njit(cache=True)
def _cell_of(x, lo, cell, dim):
    return min(max(int((x - lo) / cell), 0), dim - 1)


@njit(cache=True)
def nearest_positive(ukeys, ustart, spts, lo, cell, dims, queries, max_rings):
    """Distance from each query to the nearest grid point at a positive distance.

    Inf where there is none within ``max_rings`` rings of cells.

    Shells of cells at growing Chebyshev distance r around the query's cell are scanned
    until the best distance found is at most ``r * cell``: the cells within r of the query's
    cell hold every point closer than that, so the answer is exact. For each (x, y) column
    of a shell the occupied cells of the z range are one run of the sorted keys (one binary
    search per column).
    """
    m = queries.shape[0]
    out = np.empty(m, np.float64)
    nu = ukeys.shape[0]
    for q in range(m):
        qx = queries[q, 0]
        qy = queries[q, 1]
        qz = queries[q, 2]
        cx = _cell_of(qx, lo[0], cell, dims[0])
        cy = _cell_of(qy, lo[1], cell, dims[1])
        cz = _cell_of(qz, lo[2], cell, dims[2])
        best = np.inf
        r = 0
        while True:
            for ix in range(max(cx - r, 0), min(cx + r, dims[0] - 1) + 1):
                for iy in range(max(cy - r, 0), min(cy + r, dims[1] - 1) + 1):
                    side = abs(ix - cx) == r or abs(iy - cy) == r
                    z0 = max(cz - r, 0)
                    z1 = min(cz + r, dims[2] - 1)
                    base = (ix * dims[1] + iy) * dims[2]
                    u = lower_bound(ukeys, base + z0, 0, len(ukeys))
                    while u < nu and ukeys[u] <= base + z1:
                        iz = ukeys[u] - base
                        if (
                            side or iz == cz - r or iz == cz + r
                        ):  # inner columns: the two end cells only
                            for t in range(ustart[u], ustart[u + 1]):
                                dx = spts[t, 0] - qx
                                dy = spts[t, 1] - qy
                                dz = spts[t, 2] - qz
                                d2 = dx * dx + dy * dy + dz * dz
                                if d2 > 0.0 and d2 < best:
                                    best = d2
                        u += 1
            reach = r * cell
            if best <= reach * reach or r >= max_rings:
                break
            if (
                cx - r <= 0
                and cy - r <= 0
                and cz - r <= 0
                and cx + r >= dims[0] - 1
                and cy + r >= dims[1] - 1
                and cz + r >= dims[2] - 1
            ):
                break  # the whole grid was scanned
            r += 1
        out[q] = np.sqrt(best)
    return out


@njit(cache=True)
def mark_duplicates(ustart, sidx, spts, tol2):
    """Flag every point within sqrt(tol2) of an earlier kept point of its grid cell."""
    n = sidx.shape[0]
    dup = np.zeros(n, np.bool_)
    for c in range(ustart.shape[0] - 1):
        for t in range(ustart[c], ustart[c + 1]):
            for u in range(ustart[c], t):
                dx = spts[t, 0] - spts[u, 0]
                dy = spts[t, 1] - spts[u, 1]
                dz = spts[t, 2] - spts[u, 2]
                if dx * dx + dy * dy + dz * dz <= tol2 and not dup[sidx[u]]:
                    dup[sidx[t]] = True
                    break
    return dup


# ---------------------------------------------------------------- geometry
@njit(cache=True)
def ball_center(pts, nrm, i, j, k, rho, check_normals):
    """Centre of the rho-ball on the side of the normal of triangle (i, j, k).

    Returns (ok, cx, cy, cz). ``ok`` is False for a degenerate triangle, a circumradius
    above rho, or (``check_normals``) a triangle normal disagreeing with a vertex normal.
    """
    ax = pts[i, 0] - pts[k, 0]
    ay = pts[i, 1] - pts[k, 1]
    az = pts[i, 2] - pts[k, 2]
    bx = pts[j, 0] - pts[k, 0]
    by = pts[j, 1] - pts[k, 1]
    bz = pts[j, 2] - pts[k, 2]
    # triangle normal (j - i) x (k - i) == a x b
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    nn2 = nx * nx + ny * ny + nz * nz
    a2 = ax * ax + ay * ay + az * az
    b2 = bx * bx + by * by + bz * bz
    if not nn2 > 1e-24 * (a2 * b2):  # collinear or coincident
        return False, 0.0, 0.0, 0.0
    if check_normals:
        if nx * nrm[i, 0] + ny * nrm[i, 1] + nz * nrm[i, 2] < 0.0:
            return False, 0.0, 0.0, 0.0
        if nx * nrm[j, 0] + ny * nrm[j, 1] + nz * nrm[j, 2] < 0.0:
            return False, 0.0, 0.0, 0.0
        if nx * nrm[k, 0] + ny * nrm[k, 1] + nz * nrm[k, 2] < 0.0:
            return False, 0.0, 0.0, 0.0
    # circumcentre: k + ((|a|^2 b - |b|^2 a) x (a x b)) / (2 |a x b|^2)
    wx = a2 * bx - b2 * ax
    wy = a2 * by - b2 * ay
    wz = a2 * bz - b2 * az
    inv = 0.5 / nn2
    ox = (wy * nz - wz * ny) * inv
    oy = (wz * nx - wx * nz) * inv
    oz = (wx * ny - wy * nx) * inv
    rc2 = ox * ox + oy * oy + oz * oz
    h2 = rho * rho - rc2
    if h2 < 0.0:
        return False, 0.0, 0.0, 0.0
    s = np.sqrt(h2 / nn2)
    return True, pts[k, 0] + ox + s * nx, pts[k, 1] + oy + s * ny, pts[k, 2] + oz + s * nz


@njit(cache=True)
def _ball_empty(pts, ids, cnt, cx, cy, cz, rho, i, j, k):
    lim = (rho * (1.0 - _EMPTY_EPS)) ** 2
    for t in range(cnt):
        p = ids[t]
        if p == i or p == j or p == k:
            continue
        dx = pts[p, 0] - cx
        dy = pts[p, 1] - cy
        dz = pts[p, 2] - cz
        if dx * dx + dy * dy + dz * dz < lim:
            return False
    return True


# ---------------------------------------------------------------- growing state
@njit(cache=True)
def _rehash(ea, eb, ne, n, bits):
    """The edge hash of edges ``0 .. ne-1`` in a table of ``1 << bits`` slots: (hkeys, hvals)."""
    hkeys = np.full(1 << bits, -1, np.int64)
    hvals = np.empty(1 << bits, np.int64)
    for e in range(ne):
        a = ea[e]
        b = eb[e]
        key = min(a, b) * n + max(a, b)
        s = probe(hkeys, bits, key)
        hkeys[s] = key
        hvals[s] = e
    return hkeys, hvals


@njit(cache=True)
def _grow_edges(ea, eb, eo, es, ec, ne, n, bits):
    """The edge arrays at twice their capacity, the hash one bit larger.

    (ea, eb, eo, es, ec, hkeys, hvals, bits).
    """
    cap = 2 * ea.shape[0]
    ea = grow1(ea, cap)
    eb = grow1(eb, cap)
    hkeys, hvals = _rehash(ea, eb, ne, n, bits + 1)
    return ea, eb, grow1(eo, cap), grow1(es, cap), grow2(ec, cap), hkeys, hvals, bits + 1


@njit(cache=True)
def _grow_stack(queue, qh, qt):
    """The ring ``queue`` (items ``qh .. qt-1`` mod its size) at twice its size, unwrapped.

    (queue, 0, qt - qh).
    """
    qcap = queue.shape[0]
    nq = np.empty(2 * qcap, np.int64)
    for t in range(qt - qh):
        nq[t] = queue[(qh + t) & (qcap - 1)]
    return nq, 0, qt - qh


@njit(cache=True)
def _put_face(faces, nf, used, u0, u1, u2):
    """Write face (u0, u1, u2) at row ``nf`` (room reserved) and mark its corners used.

    Returns ``nf + 1``.
    """
    faces[nf, 0] = u0
    faces[nf, 1] = u1
    faces[nf, 2] = u2
    used[u0] = True
    used[u1] = True
    used[u2] = True
    return nf + 1


@njit(cache=True, inline="always")
def _edge_id(hkeys, hvals, bits, n, u, v):
    """Id of the edge {u, v}, or -1."""
    key = min(u, v) * n + max(u, v)
    s = probe(hkeys, bits, key)
    return hvals[s] if hkeys[s] == key else -1


@njit(cache=True, inline="always")
def _push_front_edge(edges, ne, queue, qt, u0, u1, u2, cx, cy, cz):
    """Make edge ``ne`` = u0 -> u1 of face (u0, u1, u2), ball centre c, and push it on the front.

    ``edges`` is the edge state ``(ea, eb, eo, es, ec, hkeys, hvals, bits, bcount, n)``; room
    for the edge and the stack item is reserved. Returns ``(ne + 1, qt + 1)``.
    """
    ea, eb, eo, es, ec, hkeys, hvals, bits, bcount, n = edges
    key = min(u0, u1) * n + max(u0, u1)
    s = probe(hkeys, bits, key)
    hkeys[s] = key
    hvals[s] = ne
    ea[ne] = u0
    eb[ne] = u1
    eo[ne] = u2
    ec[ne, 0] = cx
    ec[ne, 1] = cy
    ec[ne, 2] = cz
    es[ne] = FRONT
    bcount[u0] += 1
    bcount[u1] += 1
    queue[qt & (queue.shape[0] - 1)] = ne
    return ne + 1, qt + 1


# ---------------------------------------------------------------- phases
@njit(cache=True)
def _edges_from_faces(faces0, n, ecap):
    """Edge state of the triangles ``faces0``; one-face edges are BOUNDARY.

    Returns (ea, eb, eo, es, ec, hkeys, hvals, bits, ne, used, bcount) with edge capacity ``ecap``.
    """
    used = np.zeros(n, np.bool_)
    bcount = np.zeros(n, np.int32)
    ea = np.empty(ecap, np.int64)
    eb = np.empty(ecap, np.int64)
    eo = np.empty(ecap, np.int64)
    ec = np.empty((ecap, 3), np.float64)
    es = np.empty(ecap, np.int8)
    ne = 0
    bits = 4
    while (1 << bits) < 2 * ecap:
        bits += 1
    hkeys = np.full(1 << bits, -1, np.int64)
    hvals = np.empty(1 << bits, np.int64)
    for f in range(faces0.shape[0]):
        for c in range(3):
            u0 = faces0[f, c]
            u1 = faces0[f, (c + 1) % 3]
            used[u0] = True
            key = min(u0, u1) * n + max(u0, u1)
            sl = probe(hkeys, bits, key)
            if hkeys[sl] == key:
                e = hvals[sl]
                es[e] = INNER
                bcount[u0] -= 1
                bcount[u1] -= 1
            else:
                hkeys[sl] = key
                hvals[sl] = ne
                ea[ne] = u0
                eb[ne] = u1
                eo[ne] = faces0[f, (c + 2) % 3]
                es[ne] = BOUNDARY
                bcount[u0] += 1
                bcount[u1] += 1
                ne += 1
    return ea, eb, eo, es, ec, hkeys, hvals, bits, ne, used, bcount


@njit(cache=True)
def _requeue_boundary(pts, nrm, rho, grid, ea, eb, eo, es, ec, ne, buf, queue):
    """Put back on the front the boundary edges whose face carries an empty ball of radius rho.

    Their ids are written to ``queue`` (of capacity >= ne) from 0; returns their count.
    """
    ukeys, ustart, sidx, spts, lo, cell, dims = grid
    qt = 0
    for e in range(ne):
        if es[e] != BOUNDARY:
            continue
        ok, cx, cy, cz = ball_center(pts, nrm, ea[e], eb[e], eo[e], rho, False)
        if not ok:
            continue
        cnt = gather(ukeys, ustart, sidx, spts, lo, cell, dims, cx, cy, cz, rho, buf)
        if not _ball_empty(pts, buf, cnt, cx, cy, cz, rho, ea[e], eb[e], eo[e]):
            continue
        es[e] = FRONT
        ec[e, 0] = cx
        ec[e, 1] = cy
        ec[e, 2] = cz
        queue[qt] = e
        qt += 1
    return qt


@njit(cache=True)
def _pivot(pts, nrm, rho, grid, buf, a, b, o, c0x, c0y, c0z):
    """Pivot the ball resting on face (a, b, o) with centre c0 around edge a -> b.

    Returns (k, cx, cy, cz): the first point the ball touches (-1 if none) and the ball's
    centre there, resting on (b, a, k).
    """
    ukeys, ustart, sidx, spts, lo, cell, dims = grid
    mx = 0.5 * (pts[a, 0] + pts[b, 0])
    my = 0.5 * (pts[a, 1] + pts[b, 1])
    mz = 0.5 * (pts[a, 2] + pts[b, 2])
    ux = pts[b, 0] - pts[a, 0]
    uy = pts[b, 1] - pts[a, 1]
    uz = pts[b, 2] - pts[a, 2]
    ul = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux /= ul
    uy /= ul
    uz /= ul
    acx = c0x - mx
    acy = c0y - my
    acz = c0z - mz
    rp = np.sqrt(acx * acx + acy * acy + acz * acz)
    cnt = gather(ukeys, ustart, sidx, spts, lo, cell, dims, mx, my, mz, rp + rho, buf)
    best = -1
    bth = np.inf
    bcx = 0.0
    bcy = 0.0
    bcz = 0.0
    for t in range(cnt):
        k = buf[t]
        if k == a or k == b or k == o:
            continue
        ok, cx, cy, cz = ball_center(pts, nrm, b, a, k, rho, True)
        if not ok:
            continue
        vx = cx - mx
        vy = cy - my
        vz = cz - mz
        # signed angle from ac to v about u
        sn = ux * (acy * vz - acz * vy) + uy * (acz * vx - acx * vz) + uz * (acx * vy - acy * vx)
        cs = acx * vx + acy * vy + acz * vz
        th = np.arctan2(sn, cs)
        if th < -_ANGLE_EPS:
            th += _TWO_PI
        if th < bth:
            bth = th
            best = k
            bcx = cx
            bcy = cy
            bcz = cz
    return best, bcx, bcy, bcz


@njit(cache=True)
def _seed_triangle(pts, nrm, rho, grid, used, s, nbr):
    """An empty-ball triangle (s, a, b) on unused points near unused point ``s``.

    Returns (found, a, b, cx, cy, cz) with c the ball's centre.
    """
    ukeys, ustart, sidx, spts, lo, cell, dims = grid
    cnt = gather(
        ukeys, ustart, sidx, spts, lo, cell, dims, pts[s, 0], pts[s, 1], pts[s, 2], 2.0 * rho, nbr
    )
    # candidates: unused neighbours, nearest first
    m = 0
    d2 = np.empty(cnt, np.float64)
    cand = np.empty(cnt, np.int64)
    for t in range(cnt):
        p = nbr[t]
        if p == s or used[p]:
            continue
        dx = pts[p, 0] - pts[s, 0]
        dy = pts[p, 1] - pts[s, 1]
        dz = pts[p, 2] - pts[s, 2]
        d2[m] = dx * dx + dy * dy + dz * dz
        cand[m] = p
        m += 1
    if m < 2:
        return False, -1, -1, 0.0, 0.0, 0.0
    order = np.argsort(d2[:m])
    m = min(m, SEED_CANDIDATES)
    for i1 in range(m):
        for i2 in range(i1 + 1, m):
            a = cand[order[i1]]
            b = cand[order[i2]]
            dx = pts[a, 0] - pts[b, 0]
            dy = pts[a, 1] - pts[b, 1]
            dz = pts[a, 2] - pts[b, 2]
            if dx * dx + dy * dy + dz * dz > 4.0 * rho * rho:
                continue
            ok, cx, cy, cz = ball_center(pts, nrm, s, a, b, rho, True)
            if not ok:
                a, b = b, a
                ok, cx, cy, cz = ball_center(pts, nrm, s, a, b, rho, True)
                if not ok:
                    continue
            if not _ball_empty(pts, nbr, cnt, cx, cy, cz, rho, s, a, b):
                continue
            return True, a, b, cx, cy, cz
    return False, -1, -1, 0.0, 0.0, 0.0


# ---------------------------------------------------------------- main loop
@njit(cache=True)
def ball_pivot(pts, nrm, rho, lo, dims, faces0):
    """One radius of Bernardini et al. 1999, continuing from the triangles ``faces0``.

    The front state is rebuilt from ``faces0``: edges with one face are boundary edges; those
    whose face carries an empty ball of radius ``rho`` are put back on the front and pivoted
    first. Each step then pivots the newest front edge; when the front is empty, the next
    seed triangle is searched among the unused points (in grid order, :func:`_next_seed`). A
    pivot (:func:`_pivot_front_edge`) makes a face, joins a used vertex or glues onto an edge.

    Parameters
    ----------
    pts, nrm : (n, 3) float64
        Finite points, unit normals.
    rho : float
        Ball radius.
    lo : (3,) float64
        Grid origin (bounding-box minimum).
    dims : (3,) int64
        Grid dimensions (cell = 2 * rho).
    faces0 : (m0, 3) int64
        Triangles made so far (edge-manifold, consistently wound).

    Returns
    -------
    faces : (m, 3) int64
        ``faces0`` followed by the new triangles.
    stats : (4,) int64
        seeds, joins, glues, rejected pivots (first hit interior or not manifold).
    """
    n = pts.shape[0]
    m0 = faces0.shape[0]
    faces = np.empty((max(2 * n + 64, m0 + 64), 3), np.int64)
    faces[:m0] = faces0
    nf = m0
    ea, eb, eo, es, ec, hkeys, hvals, bits, ne, used, bcount = _edges_from_faces(
        faces0, n, max(3 * n + 64, 2 * m0 + 64)
    )
    qcap = 1024
    while qcap < n or qcap < ne:
        qcap *= 2
    queue = np.empty(qcap, np.int64)
    buf = np.empty(n, np.int64)
    nbr = np.empty(n, np.int64)
    stats = np.zeros(4, np.int64)
    cell = 2.0 * rho
    ukeys, ustart, sidx, spts = build_grid(pts, lo, cell, dims)
    grid = (ukeys, ustart, sidx, spts, lo, cell, dims)

    # boundary edges left by the smaller ball go back to the front if the new ball
    # resting on their face is empty
    qh = 0
    qt = _requeue_boundary(pts, nrm, rho, grid, ea, eb, eo, es, ec, ne, buf, queue)
    # the front: a stack of edge ids, items at qh .. qt-1 (mod its size), popped from qt
    s_iter = 0
    while True:
        # room for what one step adds at most: one face, three edges, three stack items
        if nf + 1 > faces.shape[0]:
            faces = grow2(faces, 2 * faces.shape[0])
        if ne + 3 > ea.shape[0]:
            ea, eb, eo, es, ec, hkeys, hvals, bits = _grow_edges(ea, eb, eo, es, ec, ne, n, bits)
        if qt - qh + 3 > queue.shape[0]:
            queue, qh, qt = _grow_stack(queue, qh, qt)
        edges = (ea, eb, eo, es, ec, hkeys, hvals, bits, bcount, n)
        if qh == qt:  # the front is empty: the next seed triangle
            found, s, a, b, cx, cy, cz, s_iter = _next_seed(pts, nrm, rho, grid, used, s_iter, nbr)
            if not found:
                break
            nf = _put_face(faces, nf, used, s, a, b)
            stats[0] += 1
            ne, qt = _push_front_edge(edges, ne, queue, qt, s, a, b, cx, cy, cz)
            ne, qt = _push_front_edge(edges, ne, queue, qt, a, b, s, cx, cy, cz)
            ne, qt = _push_front_edge(edges, ne, queue, qt, b, s, a, cx, cy, cz)
            continue
        qt -= 1
        e = queue[qt & (queue.shape[0] - 1)]
        if es[e] == FRONT:  # the newest front edge
            ball = (pts, nrm, rho, grid, buf)
            nf, ne, qt = _pivot_front_edge(ball, edges, used, faces, nf, ne, e, queue, qt, stats)
    return faces[:nf].copy(), stats


@njit(cache=True)
def _next_seed(pts, nrm, rho, grid, used, s_iter, nbr):
    """The next seed triangle, from the unused points in grid order from ``s_iter`` on.

    Returns ``(found, s, a, b, cx, cy, cz, s_iter)``: the triangle (s, a, b), its ball's
    centre and where the search goes on.
    """
    sidx = grid[2]
    n = sidx.shape[0]
    while s_iter < n:
        s = sidx[s_iter]
        s_iter += 1
        if not used[s]:
            found, a, b, cx, cy, cz = _seed_triangle(pts, nrm, rho, grid, used, s, nbr)
            if found:
                return True, s, a, b, cx, cy, cz, s_iter
    return False, -1, -1, -1, 0.0, 0.0, 0.0, s_iter


@njit(cache=True)
def _pivot_front_edge(ball, edges, used, faces, nf, ne, e, queue, qt, stats):
    """Pivot the ball around front edge ``e`` = a -> b; the face it finds joins the mesh.

    ``ball`` is ``(pts, nrm, rho, grid, buf)``, ``edges`` the edge state. The edge becomes a
    boundary edge when the ball touches no point, or a point that is interior or whose new
    edges would not be manifold (a rejected pivot); else face (b, a, k) is made: each of its
    two new edges glues onto an existing one (which gets its second face) or goes on the front.
    Returns ``(nf, ne, qt)``.
    """
    pts, nrm, rho, grid, buf = ball
    ea, eb, eo, es, ec, hkeys, hvals, bits, bcount, n = edges
    a = ea[e]
    b = eb[e]
    k, cx, cy, cz = _pivot(pts, nrm, rho, grid, buf, a, b, eo[e], ec[e, 0], ec[e, 1], ec[e, 2])
    if k < 0:
        es[e] = BOUNDARY
        return nf, ne, qt
    # new face (b, a, k): edges b->a (e), a->k, k->b
    e1 = _edge_id(hkeys, hvals, bits, n, a, k)
    e2 = _edge_id(hkeys, hvals, bits, n, k, b)
    if (
        (used[k] and bcount[k] == 0)
        or (e1 >= 0 and (es[e1] == INNER or ea[e1] == a))
        or (e2 >= 0 and (es[e2] == INNER or ea[e2] == k))
    ):
        es[e] = BOUNDARY
        stats[3] += 1
        return nf, ne, qt
    if used[k] and e1 < 0 and e2 < 0:
        stats[1] += 1
    nf = _put_face(faces, nf, used, b, a, k)
    es[e] = INNER
    bcount[a] -= 1
    bcount[b] -= 1
    for side in range(2):
        ex, u0, u1, u2 = (e1, a, k, b) if side == 0 else (e2, k, b, a)
        if ex >= 0:  # glue: the edge gets its second face
            es[ex] = INNER
            bcount[u0] -= 1
            bcount[u1] -= 1
            stats[2] += 1
        else:
            ne, qt = _push_front_edge(edges, ne, queue, qt, u0, u1, u2, cx, cy, cz)
    return nf, ne, qt


# ---------------------------------------------------------------- pinched fans
@njit(cache=True)
def _vertex_faces(faces, n, alive):
    deg = np.zeros(n + 1, np.int64)
    for f in range(faces.shape[0]):
        if alive[f]:
            for c in range(3):
                deg[faces[f, c] + 1] += 1
    for v in range(n):
        deg[v + 1] += deg[v]
    vf = np.empty(deg[n], np.int64)
    fill = deg[:n].copy()
    for f in range(faces.shape[0]):
        if alive[f]:
            for c in range(3):
                v = faces[f, c]
                vf[fill[v]] = f
                fill[v] += 1
    return deg, vf


@njit(cache=True)
def resolve_pinches(faces, n):
    """Remove faces until every vertex has a single fan (keep the largest fan).

    A vertex whose faces form several fans (connected through edges at that vertex) is
    not vertex-manifold; the faces of all its fans but the largest are removed at that
    vertex. Removal can split a fan elsewhere, so this repeats until no vertex is pinched.
    Returns (alive mask, number of faces removed).
    """
    m = faces.shape[0]
    alive = np.ones(m, np.bool_)
    removed = 0
    todo = np.ones(n, np.bool_)
    while True:
        deg, vf = _vertex_faces(faces, n, alive)
        changed = False
        nxt = np.zeros(n, np.bool_)
        for v in range(n):
            if not todo[v] or deg[v + 1] - deg[v] < 2:
                continue
            loc = vf[deg[v] : deg[v + 1]]
            parent, big, single = _fans(faces, loc, v)
            if single:
                continue
            k = _drop_other_fans(faces, loc, parent, big, alive, nxt)
            removed += k
            changed = changed or k > 0
        if not changed:
            break
        todo = nxt
    return alive, removed


@njit(cache=True)
def _fans(faces, loc, v):
    """The fans of vertex ``v``'s faces ``loc``: faces sharing an edge at ``v`` are one fan.

    Returns ``(parent, big, single)``: union-find parents over ``loc``, the root of the largest
    fan, and whether there is only that one.
    """
    d = loc.shape[0]
    w1 = np.empty(d, np.int64)
    w2 = np.empty(d, np.int64)
    for t in range(d):
        f = loc[t]
        for c in range(3):
            if faces[f, c] == v:
                w1[t] = faces[f, (c + 1) % 3]
                w2[t] = faces[f, (c + 2) % 3]
    parent = np.arange(d)
    for t in range(d):
        for q in range(t + 1, d):
            if w1[t] == w1[q] or w1[t] == w2[q] or w2[t] == w1[q] or w2[t] == w2[q]:
                ra = find(parent, t)
                rb = find(parent, q)
                if ra != rb:
                    parent[ra] = rb
    size = np.zeros(d, np.int64)
    for t in range(d):
        size[find(parent, t)] += 1
    big = 0  # the largest fan (np.argmax would load numba.np.arraymath with the kernel)
    for t in range(1, d):
        if size[t] > size[big]:
            big = t
    return parent, big, size[big] == d


@njit(cache=True)
def _drop_other_fans(faces, loc, parent, big, alive, nxt):
    """Remove the faces of ``loc`` outside fan ``big``; their corners go to ``nxt``. The count."""
    removed = 0
    for t in range(loc.shape[0]):
        if find(parent, t) != big:
            f = loc[t]
            if alive[f]:
                alive[f] = False
                removed += 1
                for c in range(3):
                    nxt[faces[f, c]] = True
    return removed
