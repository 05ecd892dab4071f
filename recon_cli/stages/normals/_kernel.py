"""Numba kernels of :mod:`recon_cli.stages.normals`: they only compute, the public module validates.

Neighbourhoods are CSR arrays (``indptr``, ``indices``) over points stored in a spatially
coherent order, so the loops below read memory mostly sequentially.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@njit(cache=True, parallel=True)
def pca_normals(pts, indptr, indices, collinear):
    """Per-point PCA of the neighbourhood covariance.

    Returns normals (n, 3), curvature (n,) = l0 / (l0 + l1 + l2), degenerate (n,) bool
    (fewer than 3 points, collinear or coincident neighbourhood).
    """
    n = pts.shape[0]
    normals = np.zeros((n, 3))
    curvature = np.zeros(n)
    degenerate = np.zeros(n, dtype=np.bool_)
    for i in prange(n):
        a, b = indptr[i], indptr[i + 1]
        cnt = b - a
        px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
        # offsets from the query point keep the sums small (points far from the origin)
        mx = 0.0
        my = 0.0
        mz = 0.0
        for t in range(a, b):
            j = indices[t]
            mx += pts[j, 0] - px
            my += pts[j, 1] - py
            mz += pts[j, 2] - pz
        if cnt > 0:
            mx /= cnt
            my /= cnt
            mz /= cnt
        cxx = 0.0
        cxy = 0.0
        cxz = 0.0
        cyy = 0.0
        cyz = 0.0
        czz = 0.0
        for t in range(a, b):
            j = indices[t]
            dx = pts[j, 0] - px - mx
            dy = pts[j, 1] - py - my
            dz = pts[j, 2] - pz - mz
            cxx += dx * dx
            cxy += dx * dy
            cxz += dx * dz
            cyy += dy * dy
            cyz += dy * dz
            czz += dz * dz
        nx, ny, nz, l0, l1, l2 = _smallest_eigvec(cxx, cxy, cxz, cyy, cyz, czz)
        normals[i, 0] = nx
        normals[i, 1] = ny
        normals[i, 2] = nz
        s = l0 + l1 + l2
        curvature[i] = l0 / s if s > 0.0 else 0.0
        degenerate[i] = cnt < 3 or l1 <= collinear * l2
    return normals, curvature, degenerate


@njit(cache=True)
def _smallest_eigvec(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of a symmetric PSD 3x3 matrix's smallest eigenvalue, and the eigenvalues.

    The eigenvalues come ascending. Closed form (trigonometric eigenvalues,
    :func:`_eigenvalues`; cross products of the rows of A - l0 I, :func:`_null_vector`); a
    zero matrix gives (0, 0, 1).
    """
    m = max(abs(a00), abs(a01), abs(a02), abs(a11), abs(a12), abs(a22))
    if m == 0.0:
        return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
    # scale to O(1) so squares neither overflow nor underflow
    a00 /= m
    a01 /= m
    a02 /= m
    a11 /= m
    a12 /= m
    a22 /= m
    q, l0, l1, l2, distinct = _eigenvalues(a00, a01, a02, a11, a12, a22)
    if not distinct:
        # a multiple of the identity: every direction is an eigenvector
        return 0.0, 0.0, 1.0, q * m, q * m, q * m
    # rows of A - l0 I; the eigenvector is orthogonal to all of them
    nx, ny, nz = _null_vector(a00 - l0, a01, a02, a11 - l0, a12, a22 - l0)
    return nx, ny, nz, max(l0, 0.0) * m, max(l1, 0.0) * m, l2 * m


@njit(cache=True, inline="always")
def _eigenvalues(a00, a01, a02, a11, a12, a22):
    """``(q, l0, l1, l2, distinct)``: the mean and ascending eigenvalues of a symmetric 3x3 matrix.

    Trigonometric closed form; not ``distinct`` for a multiple of the identity (q times it).
    """
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-30:
        return q, q, q, q, False
    p = math.sqrt(p2 / 6.0)
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = det / (2.0 * p * p * p)
    r = min(1.0, max(-1.0, r))
    phi = math.acos(r) / 3.0
    l2 = q + 2.0 * p * math.cos(phi)
    l0 = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    l1 = 3.0 * q - l2 - l0
    return q, l0, l1, l2, True


@njit(cache=True, inline="always")
def _null_vector(r0x, r0y, r0z, r1y, r1z, r2z):
    """A unit vector orthogonal to the rows of the symmetric matrix with these entries.

    The largest cross product of two rows; for a matrix of rank one (a double smallest
    eigenvalue: a line), any unit vector orthogonal to its largest row.
    """
    r1x, r2x, r2y = r0y, r0z, r1z
    c0x = r0y * r1z - r0z * r1y
    c0y = r0z * r1x - r0x * r1z
    c0z = r0x * r1y - r0y * r1x
    c1x = r0y * r2z - r0z * r2y
    c1y = r0z * r2x - r0x * r2z
    c1z = r0x * r2y - r0y * r2x
    c2x = r1y * r2z - r1z * r2y
    c2y = r1z * r2x - r1x * r2z
    c2z = r1x * r2y - r1y * r2x
    d0 = c0x * c0x + c0y * c0y + c0z * c0z
    d1 = c1x * c1x + c1y * c1y + c1z * c1z
    d2 = c2x * c2x + c2y * c2y + c2z * c2z
    dmax = max(d0, d1, d2)
    if dmax > 1e-24:
        if d0 == dmax:
            s = 1.0 / math.sqrt(d0)
            return c0x * s, c0y * s, c0z * s
        if d1 == dmax:
            s = 1.0 / math.sqrt(d1)
            return c1x * s, c1y * s, c1z * s
        s = 1.0 / math.sqrt(d2)
        return c2x * s, c2y * s, c2z * s
    # double smallest eigenvalue (a line): any unit vector orthogonal to the largest row
    n0 = r0x * r0x + r0y * r0y + r0z * r0z
    n1 = r1x * r1x + r1y * r1y + r1z * r1z
    n2 = r2x * r2x + r2y * r2y + r2z * r2z
    if n0 >= n1 and n0 >= n2:
        ux, uy, uz = r0x, r0y, r0z
    elif n1 >= n2:
        ux, uy, uz = r1x, r1y, r1z
    else:
        ux, uy, uz = r2x, r2y, r2z
    # cross with the axis least aligned with u
    ax, ay, az = abs(ux), abs(uy), abs(uz)
    if ax <= ay and ax <= az:
        vx, vy, vz = 0.0, -uz, uy
    elif ay <= az:
        vx, vy, vz = uz, 0.0, -ux
    else:
        vx, vy, vz = -uy, ux, 0.0
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    if s == 0.0:
        return 0.0, 0.0, 1.0
    return vx / s, vy / s, vz / s


@njit(cache=True, parallel=True)
def borrow_from_neighbours(pts, normals, degenerate, indptr, indices):
    """A degenerate point takes the normal of its nearest non-degenerate neighbour (if any).

    Returns the new normals and the mask of points that found none (keep their own).
    """
    n = pts.shape[0]
    out = normals.copy()
    alone = np.zeros(n, dtype=np.bool_)
    for i in prange(n):
        if not degenerate[i]:
            continue
        best = -1
        bd = np.inf
        for t in range(indptr[i], indptr[i + 1]):
            j = indices[t]
            if degenerate[j]:
                continue
            dx = pts[j, 0] - pts[i, 0]
            dy = pts[j, 1] - pts[i, 1]
            dz = pts[j, 2] - pts[i, 2]
            d = dx * dx + dy * dy + dz * dz
            if d < bd:
                bd = d
                best = j
        if best >= 0:
            out[i, 0] = normals[best, 0]
            out[i, 1] = normals[best, 1]
            out[i, 2] = normals[best, 2]
        else:
            alone[i] = True
    return out, alone


@njit(cache=True)
def _first_k(indptr, indices, i, kmax, out):
    """The first ``kmax`` neighbours of i other than i itself, into ``out``; their count."""
    c = 0
    for t in range(indptr[i], indptr[i + 1]):
        j = indices[t]
        if j != i:
            out[c] = j
            c += 1
            if c == kmax:
                break
    return c


@njit(cache=True)
def graph_edges(indptr, indices, kmax):
    """Undirected kNN graph: each edge once (i -> j kept unless j < i already lists i).

    Uses the first ``kmax`` neighbours of each point (no self loops). Returns
    (edge_indptr, dst): row i's edges are dst[edge_indptr[i]:edge_indptr[i + 1]].
    """
    n = indptr.shape[0] - 1
    eptr = np.zeros(n + 1, dtype=np.int64)
    dst = np.empty(n * kmax, dtype=np.int32)
    row = np.empty(kmax, dtype=np.int64)
    other = np.empty(kmax, dtype=np.int64)
    e = 0
    for i in range(n):
        c = _first_k(indptr, indices, i, kmax, row)
        for a in range(c):
            j = row[a]
            if j < i:
                # mutual pair: already added from row j
                cj = _first_k(indptr, indices, j, kmax, other)
                dup = False
                for b in range(cj):
                    if other[b] == i:
                        dup = True
                        break
                if dup:
                    continue
            dst[e] = j
            e += 1
        eptr[i + 1] = e
    return eptr, dst[:e].copy()


@njit(cache=True, inline="always")
def _relation(pts, normals, i, j):
    """(s, t) of an edge: its orientation agreement and how far it leaves the tangent planes.

    s = n_i . n_j (positive when consistently oriented, Hoppe), t = mean abs(n . e) over both
    ends, e the unit edge (how far the edge leaves the tangent planes: large
    for edges that jump across a thin part).
    """
    ex = pts[j, 0] - pts[i, 0]
    ey = pts[j, 1] - pts[i, 1]
    ez = pts[j, 2] - pts[i, 2]
    el = math.sqrt(ex * ex + ey * ey + ez * ez)
    dot = (
        normals[i, 0] * normals[j, 0]
        + normals[i, 1] * normals[j, 1]
        + normals[i, 2] * normals[j, 2]
    )
    if el == 0.0:
        return dot, 0.0
    ie = (normals[i, 0] * ex + normals[i, 1] * ey + normals[i, 2] * ez) / el
    je = (normals[j, 0] * ex + normals[j, 1] * ey + normals[j, 2] * ez) / el
    return dot, 0.5 * (abs(ie) + abs(je))


@njit(cache=True, parallel=True)
def edge_weights(pts, normals, eptr, dst, beta, eps):
    """MST weights 1 - |s| + beta * t + eps of every edge (see :func:`_relation`)."""
    n = eptr.shape[0] - 1
    w = np.empty(dst.shape[0])
    for i in prange(n):
        for t in range(eptr[i], eptr[i + 1]):
            s, off = _relation(pts, normals, i, dst[t])
            w[t] = 1.0 - abs(s) + beta * off + eps
    return w


@njit(cache=True)
def propagate_signs(pts, normals, order, pred, root, seed_sign):
    """Signs (+1/-1) per point from a traversal.

    ``order`` is a BFS order from the virtual node ``root``, ``pred`` the predecessors; children of
    ``root`` take ``seed_sign``.
    """
    n = pts.shape[0]
    sign = np.ones(n, dtype=np.int8)
    for k in range(order.shape[0]):
        v = order[k]
        if v == root:
            continue
        p = pred[v]
        if p == root:
            sign[v] = seed_sign[v]
        else:
            s, _ = _relation(pts, normals, v, p)
            sign[v] = sign[p] if s >= 0.0 else -sign[p]
    return sign


@njit(cache=True)
def vote_flips(pts, normals, sign, eptr, dst):
    """Per point, the confidence-weighted vote of its graph neighbours on its sign.

    Each undirected edge counts at both ends; negative means most neighbours say flip.
    """
    n = eptr.shape[0] - 1
    vote = np.zeros(n)
    for i in range(n):
        for t in range(eptr[i], eptr[i + 1]):
            j = dst[t]
            s, off = _relation(pts, normals, i, j)
            v = s * (1.0 - off) * sign[i] * sign[j]
            vote[i] += v
            vote[j] += v
    return vote


@njit(cache=True)
def degree(eptr, dst):
    """Number of undirected edges at each point."""
    n = eptr.shape[0] - 1
    deg = np.zeros(n, dtype=np.int64)
    for i in range(n):
        deg[i] += eptr[i + 1] - eptr[i]
        for t in range(eptr[i], eptr[i + 1]):
            deg[dst[t]] += 1
    return deg


@njit(cache=True, parallel=True)
def consensus(pts, normals, sign, indptr, indices, power):
    """Per point, n_i . (sum over its neighbourhood of (1 - t_ij)^power s_j n_j).

    The side its oriented neighbours agree on (t_ij as in :func:`_relation`; the point itself left
    out).
    """
    n = indptr.shape[0] - 1
    out = np.zeros(n)
    for i in prange(n):
        acc = 0.0
        for t in range(indptr[i], indptr[i + 1]):
            j = indices[t]
            if j == i:
                continue
            s, off = _relation(pts, normals, i, j)
            acc += s * sign[j] * (1.0 - off) ** power
        out[i] = acc
    return out


@njit(cache=True, parallel=True)
def pixel_knn(ps, pix, img_of, images, k, dr, dc, r2max, out, count):
    """The ``k`` nearest points among nearby pixels of each point's pixel in its image.

    Nearest by 3-D distance, at most ``r2max`` squared, among the pixels at row and column
    offsets ``dr``, ``dc``.

    ``ps`` (n, 3) points; ``pix`` (n,) each point's pixel in the concatenated images,
    ``img_of`` (n,) its image; ``images`` is ``(offs, heights, widths, img)``: the images' first
    pixel and size, and ``img`` (total pixels,) the point at each pixel (-1: none). The
    offsets go outward from (0, 0), so that the nearest are met first and most farther pixels
    are rejected by one comparison. Fills ``out`` (n, k) with neighbour indices nearest first
    (the point itself first) and ``count`` (n,).
    """
    offs, heights, widths, img = images
    n = ps.shape[0]
    for i in prange(n):
        g = img_of[i]
        w = widths[g]
        h = heights[g]
        local = pix[i] - offs[g]
        row = local // w
        col = local - row * w
        bd = np.empty(k)
        bj = np.empty(k, dtype=np.int32)
        px, py, pz = ps[i, 0], ps[i, 1], ps[i, 2]
        bd[0] = 0.0
        bj[0] = i
        m = 1
        for t0 in range(len(dr)):
            rr = row + dr[t0]
            cc = col + dc[t0]
            if rr < 0 or rr >= h or cc < 0 or cc >= w:
                continue
            j = img[offs[g] + rr * w + cc]
            if j < 0 or j == i:
                continue
            dx = ps[j, 0] - px
            dy = ps[j, 1] - py
            dz = ps[j, 2] - pz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > r2max:
                continue
            if m == k:
                if d2 >= bd[k - 1]:
                    continue
                t = k - 1
            else:
                t = m
                m += 1
            # insertion: after every equal distance (the point itself stays first)
            while t > 0 and bd[t - 1] > d2:
                bd[t] = bd[t - 1]
                bj[t] = bj[t - 1]
                t -= 1
            bd[t] = d2
            bj[t] = j
        count[i] = m
        for t in range(m):
            out[i, t] = bj[t]
