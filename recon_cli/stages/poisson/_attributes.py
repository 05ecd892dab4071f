"""Numba kernels of :mod:`recon_cli.stages.poisson.attributes`.

The vertices' nearest points on a grid of the points, the surface's normals at the vertices and
the weighted vote per vertex.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.hashtable import lookup


@njit(cache=True, inline="always")
def _shell_cells(c, r, dims, tk, tv, bits, starts, out, n):
    """Append the occupied cells at Chebyshev distance ``r`` from cell ``c`` to ``out``.

    Rows x, y, z, first point, end, from row ``n``; returns the new row count.
    """
    xa, xb = max(c[0] - r, 0), min(c[0] + r, dims[0] - 1)
    ya, yb = max(c[1] - r, 0), min(c[1] + r, dims[1] - 1)
    za, zb = max(c[2] - r, 0), min(c[2] + r, dims[2] - 1)
    for cx in range(xa, xb + 1):
        ex = cx == c[0] - r or cx == c[0] + r
        for cy in range(ya, yb + 1):
            whole = r == 0 or ex or cy == c[1] - r or cy == c[1] + r
            # inside the shell's box only its two z faces are new
            step = 1 if whole else 2 * r
            for cz in range(c[2] - r, c[2] + r + 1, step):
                if cz < za or cz > zb:
                    continue
                u = lookup(tk, tv, bits, (cx * dims[1] + cy) * dims[2] + cz)
                if u >= 0:
                    out[n, 0], out[n, 1], out[n, 2] = cx, cy, cz
                    out[n, 3], out[n, 4] = starts[u], starts[u + 1]
                    n += 1
    return n


@njit(cache=True, inline="always")
def _scan(spts, sidx, cells, e0, e1, lo, h, slack, q, k, bd, bi):
    """Put the points of cells ``e0:e1`` into the sorted best lists.

    ``bd``: squared distances (inf: none yet), ``bi``: indices (equal distances: smaller index
    first).

    A cell surely farther than the k-th point so far is skipped.
    """
    kth, jk = bd[k - 1], bi[k - 1]
    for e in range(e0, e1):
        if kth < np.inf:
            g = 0.0
            for a in range(3):
                x0 = lo[a] + cells[e, a] * h
                d = max(x0 - q[a], q[a] - (x0 + h), 0.0)
                g += d * d
            far = math.sqrt(g) - 2.0 * slack
            if far > 0.0 and far * far > kth:
                continue
        for p in range(cells[e, 3], cells[e, 4]):
            d0 = q[0] - spts[p, 0]
            d1 = q[1] - spts[p, 1]
            d2 = q[2] - spts[p, 2]
            # summed in cKDTree's order, so the distances are its bits
            dd = (d0 * d0 + d1 * d1) + d2 * d2
            if dd > kth:
                continue
            j = sidx[p]
            if dd == kth and j > jk:
                continue
            t = k - 1
            while t > 0 and (bd[t - 1] > dd or (bd[t - 1] == dd and bi[t - 1] > j)):
                bd[t] = bd[t - 1]
                bi[t] = bi[t - 1]
                t -= 1
            bd[t] = dd
            bi[t] = j
            kth, jk = bd[k - 1], bi[k - 1]


@njit(cache=True, inline="always")
def _finished(c, r, dims, lo, h, slack, q, k, bd):
    """Whether no point beyond the cells within Chebyshev distance ``r`` of ``c`` is nearer.

    Nearer than the k-th so far.
    """
    if bd[k - 1] == np.inf:
        return False
    bound = np.inf  # the nearest an unread point can be: the read box's faces with cells beyond
    for a in range(3):
        if c[a] - r > 0:
            bound = min(bound, q[a] - (lo[a] + (c[a] - r) * h))
        if c[a] + r < dims[a] - 1:
            bound = min(bound, lo[a] + (c[a] + r + 1) * h - q[a])
    if bound == np.inf:
        return True
    bound -= slack
    return bound > 0.0 and bd[k - 1] < bound * bound


@njit(cache=True, parallel=True)
def grid_knn(grid, batch, k, max_shell, found):
    """The ``k`` nearest points of each query, nearest first (equal distances: smaller index).

    ``grid`` is ``(spts, sidx, starts, tk, tv, bits, lo, h, dims, slack)``: the points ``spts``
    (n, 3) sorted by grid cell (cubes of side ``h`` from ``lo``, ``dims`` per axis, cell key
    ``(x * dims[1] + y) * dims[2] + z``); ``sidx`` their indices in the caller's array; the cell
    of key ``tk``/``tv`` (hash table, ``bits``) holds ``spts[starts[u]:starts[u + 1]]``.
    ``batch`` is ``(queries, qcell, order, groups)``: the queries (m, 3), of which
    ``order[groups[g]:groups[g + 1]]`` share the cell ``qcell`` (clipped to -1..dims), whose two
    shells of cells each group looks up once. Shells of cells around the query's cell are read
    until the k-th distance is below the distance to the unread cells (less ``slack``, the cell
    assignment's rounding). ``found`` is ``(dist, idx, far)``: fills ``dist`` (m, k)
    (Euclidean, world units) and ``idx`` (m, k); a query still unfinished after ``max_shell``
    shells is marked in ``far`` (m,) (its rows are left to the caller). The tuples are unpacked
    here, once: the loops read the arrays.
    """
    spts, sidx, starts, tk, tv, bits, lo, h, dims, slack = grid
    queries, qcell, order, groups = batch
    dist, idx, far = found
    near = 2  # shells each group looks up once
    for g in prange(len(groups) - 1):
        c = qcell[order[groups[g]]]
        block = np.empty(((2 * near + 1) ** 3, 5), np.int64)
        shell = np.empty((max(0, (2 * max_shell + 1) ** 3 - (2 * max_shell - 1) ** 3), 5), np.int64)
        ends = np.empty(near + 1, np.int64)
        n = 0
        for r in range(near + 1):
            n = _shell_cells(c, r, dims, tk, tv, bits, starts, block, n)
            ends[r] = n
        bd = np.empty(k)
        bi = np.empty(k, np.int64)
        for t in range(groups[g], groups[g + 1]):
            i = order[t]
            q = queries[i]
            bd[:] = np.inf
            bi[:] = -1
            done = False
            e0 = 0
            for r in range(near + 1):
                _scan(spts, sidx, block, e0, ends[r], lo, h, slack, q, k, bd, bi)
                e0 = ends[r]
                if _finished(c, r, dims, lo, h, slack, q, k, bd):
                    done = True
                    break
            r = near + 1
            while not done and r <= max_shell:
                ns = _shell_cells(c, r, dims, tk, tv, bits, starts, shell, 0)
                _scan(spts, sidx, shell, 0, ns, lo, h, slack, q, k, bd, bi)
                done = _finished(c, r, dims, lo, h, slack, q, k, bd)
                r += 1
            far[i] = not done
            if done:
                for t2 in range(k):
                    dist[i, t2] = math.sqrt(bd[t2])
                    idx[i, t2] = bi[t2]


@njit(cache=True, parallel=True)
def _face_normals(verts, faces):
    """(f, 3) cross products of the faces' edges 0-1 and 0-2 (np.cross's operations)."""
    fn = np.empty((len(faces), 3))
    for f in prange(len(faces)):
        u, v, w = faces[f, 0], faces[f, 1], faces[f, 2]
        a0, a1, a2 = verts[v, 0] - verts[u, 0], verts[v, 1] - verts[u, 1], verts[v, 2] - verts[u, 2]
        b0, b1, b2 = verts[w, 0] - verts[u, 0], verts[w, 1] - verts[u, 1], verts[w, 2] - verts[u, 2]
        fn[f, 0] = a1 * b2 - a2 * b1
        fn[f, 1] = a2 * b0 - a0 * b2
        fn[f, 2] = a0 * b1 - a1 * b0
    return fn


@njit(cache=True)
def face_normal_sums(verts, faces, vn):
    """vn[v] += the cross product of face f's edges, for every corner v of every face f.

    Corners 0, then 1, then 2, each in face order: np.add.at's order, so its bits.
    """
    fn = _face_normals(verts, faces)
    for c in range(3):
        for f in range(len(faces)):
            v = faces[f, c]
            for d in range(3):
                vn[v, d] += fn[f, d]


@njit(cache=True, parallel=True)
def agreeing(normals, idx, vn, agree):
    """Whether the normal of point ``idx[r, t]`` has a positive dot product with ``vn[r]``."""
    m, k = idx.shape
    for r in prange(m):
        for t in range(k):
            j = idx[r, t]
            agree[r, t] = (
                normals[j, 0] * vn[r, 0] + normals[j, 1] * vn[r, 1] + normals[j, 2] * vn[r, 2]
            ) > 0.0


@njit(cache=True)
def weighted_mode(vals, w, out):
    """out[r] = the value of row ``r`` of ``vals`` (m, k) int64 with the largest summed weight.

    The weights are ``w`` (m, k), at least 0; ties go to the smallest value. Entries of weight 0
    add nothing and are passed over (a fallback row's neighbours mostly), unless the whole row
    weighs 0 (then every value sums 0: the smallest).
    """
    m, k = vals.shape
    for r in range(m):
        best_v = vals[r, 0]
        best_s = -1.0
        some = False
        for a in range(k):
            if w[r, a] > 0.0:
                some = True
                break
        for a in range(k):
            if some and not w[r, a] > 0.0:
                continue
            x = vals[r, a]
            seen = False
            for b in range(a):
                if vals[r, b] == x and (w[r, b] > 0.0 or not some):
                    seen = True
                    break
            if seen:
                continue
            s = 0.0
            for b in range(a, k):
                if vals[r, b] == x:
                    s += w[r, b]
            if s > best_s or (s == best_s and x < best_v):
                best_v = x
                best_s = s
        out[r] = best_v
