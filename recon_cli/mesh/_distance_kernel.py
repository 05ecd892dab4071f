"""Numba kernels: a bounding-volume hierarchy over triangles and closest-point queries.

The BVH halves each node's triangles at the median of their centroids along the node's
longest axis; node boxes are filled bottom-up. Children are always numbered after their
parent.
Kernels only compute; :mod:`recon_cli.mesh.distance` validates.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import borrowed

LEAF_SIZE = 8  # with the cheap disk reject per triangle, 8 beats 4 (fewer node visits)
STACK = 128  # depth bound: log2(n / LEAF_SIZE) + a few, far below this for any real mesh

# closest-feature codes returned with each closest point
FACE, VERT_A, VERT_B, VERT_C, EDGE_AB, EDGE_AC, EDGE_BC = 0, 1, 2, 3, 4, 5, 6


@njit(cache=True)
def _select(order, cent, ax, lo, hi, k):
    """Reorder ``order[lo:hi]`` so that position k holds the k-th smallest ``cent[., ax]``.

    Smaller keys before it and larger after (Hoare partition, median-of-three pivot).
    """
    hi -= 1
    while hi > lo:
        m = (lo + hi) // 2
        a = cent[order[lo], ax]
        b = cent[order[m], ax]
        c = cent[order[hi], ax]
        pivot = max(min(a, b), min(max(a, b), c))
        i = lo
        j = hi
        while i <= j:
            while cent[order[i], ax] < pivot:
                i += 1
            while cent[order[j], ax] > pivot:
                j -= 1
            if i <= j:
                tmp = order[i]
                order[i] = order[j]
                order[j] = tmp
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True)
def build_median(cent, leaf_size):
    """BVH topology by median splits along the longest axis of each node's centroids.

    Returns (order, left, right, start, end): ``order`` permutes the items into tree order.
    Each level partitions its ranges around the median (quickselect): O(n log n).
    """
    n = cent.shape[0]
    order = np.arange(n)
    cap = max(1, 2 * (n // leaf_size + 1) + 1)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    end = np.zeros(cap, np.int64)
    stack = np.empty(STACK, np.int64)
    count = 1
    start[0] = 0
    end[0] = n
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        lo = start[node]
        hi = end[node]
        if hi - lo <= leaf_size:
            continue
        mn0, mn1, mn2 = np.inf, np.inf, np.inf
        mx0, mx1, mx2 = -np.inf, -np.inf, -np.inf
        for t in range(lo, hi):
            c = order[t]
            mn0 = min(mn0, cent[c, 0])
            mx0 = max(mx0, cent[c, 0])
            mn1 = min(mn1, cent[c, 1])
            mx1 = max(mx1, cent[c, 1])
            mn2 = min(mn2, cent[c, 2])
            mx2 = max(mx2, cent[c, 2])
        ax = 0
        if mx1 - mn1 > mx0 - mn0:
            ax = 1
        if mx2 - mn2 > max(mx0 - mn0, mx1 - mn1):
            ax = 2
        mid = (lo + hi) // 2
        _select(order, cent, ax, lo, hi, mid)
        if count + 2 > cap:
            cap2 = 2 * cap
            left = _grow1(left, cap2, -1)
            right = _grow1(right, cap2, -1)
            start = _grow1(start, cap2, 0)
            end = _grow1(end, cap2, 0)
            cap = cap2
        a = count
        b = count + 1
        count += 2
        left[node] = a
        right[node] = b
        start[a] = lo
        end[a] = mid
        start[b] = mid
        end[b] = hi
        stack[top] = b
        top += 1
        stack[top] = a
        top += 1
    return (
        order,
        left[:count].copy(),
        right[:count].copy(),
        start[:count].copy(),
        end[:count].copy(),
    )


@njit(cache=True)
def _grow1(a, n, fill):
    out = np.full(n, fill, a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def node_boxes(tri_lo, tri_hi, left, right, start, end):
    """Axis-aligned box of every node from the boxes of its (sorted) triangles."""
    m = left.shape[0]
    lo = np.empty((m, 3), np.float64)
    hi = np.empty((m, 3), np.float64)
    for node in range(m - 1, -1, -1):  # children have larger ids than their parent
        if left[node] < 0:
            for ax in range(3):
                lo[node, ax] = np.inf
                hi[node, ax] = -np.inf
            for t in range(start[node], end[node]):
                for ax in range(3):
                    lo[node, ax] = min(lo[node, ax], tri_lo[t, ax])
                    hi[node, ax] = max(hi[node, ax], tri_hi[t, ax])
        else:
            a = left[node]
            b = right[node]
            for ax in range(3):
                lo[node, ax] = min(lo[a, ax], lo[b, ax])
                hi[node, ax] = max(hi[a, ax], hi[b, ax])
    return lo, hi


@njit(cache=True, inline="always")
def _box_d2(p0, p1, p2, box, node):
    """Squared distance from p to node box ``box[node]`` = (lo xyz, hi xyz), 0 inside."""
    d = 0.0
    x = box[node, 0] - p0
    if x > 0:
        d += x * x
    else:
        x = p0 - box[node, 3]
        if x > 0:
            d += x * x
    x = box[node, 1] - p1
    if x > 0:
        d += x * x
    else:
        x = p1 - box[node, 4]
        if x > 0:
            d += x * x
    x = box[node, 2] - p2
    if x > 0:
        d += x * x
    else:
        x = p2 - box[node, 5]
        if x > 0:
            d += x * x
    return d


@njit(cache=True)
def _seg(p, u, w, out):
    """Closest point to p on segment uw into out; returns its squared distance."""
    e0 = w[0] - u[0]
    e1 = w[1] - u[1]
    e2 = w[2] - u[2]
    ll = e0 * e0 + e1 * e1 + e2 * e2
    s = 0.0
    if ll > 0.0:
        s = ((p[0] - u[0]) * e0 + (p[1] - u[1]) * e1 + (p[2] - u[2]) * e2) / ll
        s = min(1.0, max(0.0, s))
    out[0] = u[0] + s * e0
    out[1] = u[1] + s * e1
    out[2] = u[2] + s * e2
    return (p[0] - out[0]) ** 2 + (p[1] - out[1]) ** 2 + (p[2] - out[2]) ** 2


@njit(cache=True)
def _closest_degenerate(px, py, pz, tri, t, out):
    q = np.empty(3)
    p = np.array([px, py, pz])
    a = tri[t, 0]
    b = tri[t, 1]
    c = tri[t, 2]
    best = _seg(p, a, b, out)
    code = EDGE_AB
    d = _seg(p, a, c, q)
    if d < best:
        best = d
        code = EDGE_AC
        out[0], out[1], out[2] = q[0], q[1], q[2]
    d = _seg(p, b, c, q)
    if d < best:
        code = EDGE_BC
        out[0], out[1], out[2] = q[0], q[1], q[2]
    return code


@njit(cache=True, inline="always")
def closest_on_triangle(px, py, pz, tri, t, out):
    """Closest point to (px, py, pz) on triangle ``tri[t]`` into ``out``; returns the feature code.

    Classifies ``p`` against the Voronoi regions of the vertices, edges and face using dot
    products of the edge vectors (no square roots); degenerate triangles fall back to
    their edges. Scalars and an index rather than array views: views cost reference
    counting in the innermost loop.
    """
    a0, a1, a2 = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
    b0, b1, b2 = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
    c0, c1, c2 = tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
    ab0 = b0 - a0
    ab1 = b1 - a1
    ab2 = b2 - a2
    ac0 = c0 - a0
    ac1 = c1 - a1
    ac2 = c2 - a2
    ap0 = px - a0
    ap1 = py - a1
    ap2 = pz - a2
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0.0 and d2 <= 0.0:
        out[0], out[1], out[2] = a0, a1, a2
        return VERT_A
    bp0 = px - b0
    bp1 = py - b1
    bp2 = pz - b2
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    if d3 >= 0.0 and d4 <= d3:
        out[0], out[1], out[2] = b0, b1, b2
        return VERT_B
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        s = d1 / (d1 - d3) if d1 - d3 != 0.0 else 0.0
        out[0] = a0 + s * ab0
        out[1] = a1 + s * ab1
        out[2] = a2 + s * ab2
        return EDGE_AB
    cp0 = px - c0
    cp1 = py - c1
    cp2 = pz - c2
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    if d6 >= 0.0 and d5 <= d6:
        out[0], out[1], out[2] = c0, c1, c2
        return VERT_C
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        s = d2 / (d2 - d6) if d2 - d6 != 0.0 else 0.0
        out[0] = a0 + s * ac0
        out[1] = a1 + s * ac1
        out[2] = a2 + s * ac2
        return EDGE_AC
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        den = (d4 - d3) + (d5 - d6)
        s = (d4 - d3) / den if den != 0.0 else 0.0
        out[0] = b0 + s * (c0 - b0)
        out[1] = b1 + s * (c1 - b1)
        out[2] = b2 + s * (c2 - b2)
        return EDGE_BC
    den = va + vb + vc
    if not den > 0.0:  # degenerate (zero-area) triangle: nearest of its three edges
        return _closest_degenerate(px, py, pz, tri, t, out)
    v = vb / den
    w = vc / den
    out[0] = a0 + ab0 * v + ac0 * w
    out[1] = a1 + ab1 * v + ac1 * w
    out[2] = a2 + ab2 * v + ac2 * w
    return FACE


@njit(cache=True)
def _nearest(p, bvh, best2, scratch, seed):
    """Nearest triangle to ``p`` closer than sqrt(best2): (index or -1, d2, feature).

    ``bvh`` is ``(tri, sph, box, left, right, start, end)``, ``scratch`` ``(stack, dstack, q,
    cbest)`` (the closest point is left in ``cbest``). ``seed`` (a triangle index or -1),
    typically the answer for a nearby point, is tried first: its distance is a tight bound
    that prunes most of the tree. Each pushed node carries its box distance (``dstack``), so
    a pop re-checks it against the bound without touching the box again.
    """
    # borrowed: no reference counting around the inlined helpers in the loop
    tri, sph, box = borrowed(bvh[0]), borrowed(bvh[1]), borrowed(bvh[2])
    left, right, start, end = bvh[3], bvh[4], bvh[5], bvh[6]
    stack, dstack = borrowed(scratch[0]), borrowed(scratch[1])
    q, cbest = borrowed(scratch[2]), borrowed(scratch[3])
    best = -1
    feat = -1
    if seed >= 0:
        code = closest_on_triangle(p[0], p[1], p[2], tri, seed, q)
        d2 = (p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 + (p[2] - q[2]) ** 2
        if d2 < best2:
            best2 = d2
            best = seed
            feat = code
            cbest[0], cbest[1], cbest[2] = q[0], q[1], q[2]
    top = 0
    d0 = _box_d2(p[0], p[1], p[2], box, 0)
    if d0 < best2:
        stack[0] = 0
        dstack[0] = d0
        top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if dstack[top] >= best2:  # the bound shrank since the push
            continue
        a = left[node]
        if a >= 0:
            top = _push_children(p, box, a, right[node], best2, stack, dstack, top)
            continue
        for t in range(start[node], end[node]):
            # cheap reject by the triangle's bounding disk (sph: centre xyz, radius,
            # unit normal xyz): |p - q|^2 = plane^2 + |proj(p) - q|^2 >= plane^2 +
            # max(0, |proj(p) - c| - r)^2 for every q of the triangle. Unlike a ball
            # bound it rejects the coplanar neighbours of the nearest triangle, which
            # far samples otherwise test by the dozen.
            s0 = p[0] - sph[t, 0]
            s1 = p[1] - sph[t, 1]
            s2 = p[2] - sph[t, 2]
            pl = s0 * sph[t, 4] + s1 * sph[t, 5] + s2 * sph[t, 6]
            lb = pl * pl
            if lb >= best2:
                continue
            l2 = s0 * s0 + s1 * s1 + s2 * s2 - lb
            r = sph[t, 3]
            if l2 > r * r:
                lat = np.sqrt(l2) - r
                if lb + lat * lat >= best2:
                    continue
            code = closest_on_triangle(p[0], p[1], p[2], tri, t, q)
            d2 = (p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 + (p[2] - q[2]) ** 2
            if d2 < best2 and t != seed:
                best2 = d2
                best = t
                feat = code
                cbest[0], cbest[1], cbest[2] = q[0], q[1], q[2]
    return best, best2, feat


@njit(cache=True, inline="always")
def _push(node, d, best2, stack, dstack, top):
    """Push ``node`` at squared distance ``d`` when it is closer than the bound; the new top."""
    if d < best2:
        stack[top] = node
        dstack[top] = d
        top += 1
    return top


@njit(cache=True, inline="always")
def _push_children(p, box, a, b, best2, stack, dstack, top):
    """Push children ``a`` and ``b`` closer than the bound, the nearer on top; the new top."""
    da = _box_d2(p[0], p[1], p[2], box, a)
    db = _box_d2(p[0], p[1], p[2], box, b)
    # nearer child on top of the stack, visited first
    if da <= db:
        top = _push(b, db, best2, stack, dstack, top)
        return _push(a, da, best2, stack, dstack, top)
    top = _push(a, da, best2, stack, dstack, top)
    return _push(b, db, best2, stack, dstack, top)


@njit(cache=True, parallel=True)
def query_points(points, tri, sph, box, left, right, start, end, upper):
    """Closest point on the BVH's triangles for each row of ``points``.

    ``upper`` (k,) bounds the search radius (inf = unbounded); a point with no triangle
    within it gets index -1. Returns (d2, sorted triangle index, closest (k, 3), feature).
    """
    bvh = (tri, sph, box, left, right, start, end)
    k = points.shape[0]
    d2 = np.empty(k, np.float64)
    idx = np.empty(k, np.int64)
    feat = np.empty(k, np.int64)
    closest = np.empty((k, 3), np.float64)
    chunk = 256
    nchunks = (k + chunk - 1) // chunk
    for ci in prange(nchunks):
        out = (d2, idx, closest, feat)
        _query_chunk(points, bvh, upper, ci * chunk, min(k, (ci + 1) * chunk), out)
    return d2, idx, closest, feat


# the loops over queries are functions of their own, called once per chunk or line of the
# parallel loop: numba's parfor passes over a loop body holding the search cost seconds of compile
@njit(cache=True)
def _query_chunk(points, bvh, upper, lo, hi, out):
    """:func:`query_points` for the points ``lo..hi``, into ``out`` = (d2, idx, closest, feat)."""
    d2, idx, closest, feat = out
    stack = np.empty(STACK, np.int64)
    dstack = np.empty(STACK, np.float64)
    q = np.empty(3, np.float64)
    cb = np.empty(3, np.float64)
    seed = -1
    for s in range(lo, hi):
        u = upper[s]
        b2 = u * u if u < np.inf else np.inf
        t, dd, f = _nearest(points[s], bvh, b2, (stack, dstack, q, cb), seed)
        if t >= 0:
            seed = t
        idx[s] = t
        d2[s] = dd
        feat[s] = f
        closest[s, 0], closest[s, 1], closest[s, 2] = cb[0], cb[1], cb[2]
        if t < 0:
            closest[s, 0], closest[s, 1], closest[s, 2] = np.nan, np.nan, np.nan


@njit(cache=True, parallel=True)
def query_grid(origin, h, shape, bvh, band, pn, use_pn):
    """Unsigned distance at every sample of a regular grid, line by line along the last axis.

    ``bvh`` is the tree's ``(tri, sph, box, left, right, start, end)``, ``pn`` the
    pseudonormals ``(face, edge, vertex)`` of its triangles. The distance is 1-Lipschitz, so the
    previous sample's distance + h bounds the search for the next one (most of the tree is pruned
    at once). ``band`` caps the search: samples farther than it get ``band``. With ``use_pn`` the
    sign of each sample comes from the angle-weighted pseudonormal of the closest feature (face,
    edge, vertex). Returns (dist (nx, ny, nz) float64, sign (nx, ny, nz) int8: -1 inside, 1
    outside, 0 not known). Call it under a dynamic schedule
    (:func:`recon_cli.mesh.distance.dynamic_schedule`).
    """
    nx, ny, nz = shape[0], shape[1], shape[2]
    dist = np.empty((nx, ny, nz), np.float64)
    sign = np.zeros((nx, ny, nz), np.int8)
    for line in prange(nx * ny):
        grid = (origin, h, line // ny, line % ny)
        _grid_line(grid, bvh, band, pn, use_pn, dist, sign)
    return dist, sign


@njit(cache=True)
def _grid_line(grid, bvh, band, pn, use_pn, dist, sign):
    """:func:`query_grid` along line (i, j) of ``grid`` = (origin, h, i, j)."""
    origin, h, i, j = grid
    stack = np.empty(STACK, np.int64)
    dstack = np.empty(STACK, np.float64)
    q = np.empty(3, np.float64)
    cb = np.empty(3, np.float64)
    p = np.empty(3, np.float64)
    p[0] = origin[0] + i * h
    p[1] = origin[1] + j * h
    prev = np.inf
    seed = -1
    for k in range(dist.shape[2]):
        p[2] = origin[2] + k * h
        ub = band
        if prev < np.inf:
            ub = min(band, (prev + h) * (1.0 + 1e-9) + 1e-300)
        b2 = ub * ub if ub < np.inf else np.inf
        first = seed
        while True:
            t, dd, f = _nearest(p, bvh, b2, (stack, dstack, q, cb), first)
            if t >= 0 or ub >= band:
                break
            # bound too tight (rounding): search again unbounded
            ub = band
            b2 = band * band if band < np.inf else np.inf
            first = -1
        if t < 0:
            dist[i, j, k] = band
            prev = np.inf
            seed = -1
            continue
        seed = t
        dist[i, j, k] = np.sqrt(dd)
        prev = dist[i, j, k]
        if use_pn:
            sign[i, j, k] = _pseudonormal_side(p, cb, pn, t, f)


@njit(cache=True, inline="always")
def _pseudonormal_side(p, c, pn, t, f):
    """-1 when ``p`` lies behind feature ``f`` of triangle ``t`` (closest point ``c``), else 1."""
    pn_face, pn_edge, pn_vert = pn
    if f == FACE:
        n0, n1, n2 = pn_face[t, 0], pn_face[t, 1], pn_face[t, 2]
    elif f <= VERT_C:
        n0, n1, n2 = pn_vert[t, f - 1, 0], pn_vert[t, f - 1, 1], pn_vert[t, f - 1, 2]
    else:
        n0, n1, n2 = pn_edge[t, f - 4, 0], pn_edge[t, f - 4, 1], pn_edge[t, f - 4, 2]
    dot = (p[0] - c[0]) * n0 + (p[1] - c[1]) * n1 + (p[2] - c[2]) * n2
    return -1 if dot < 0.0 else 1


@njit(cache=True, inline="always")
def triangle_cross(tri, t):
    """(b - a) x (c - a) of triangle ``t`` of ``tri`` ((m, 3, 3)): twice its area vector."""
    e10 = tri[t, 1, 0] - tri[t, 0, 0]
    e11 = tri[t, 1, 1] - tri[t, 0, 1]
    e12 = tri[t, 1, 2] - tri[t, 0, 2]
    e20 = tri[t, 2, 0] - tri[t, 0, 0]
    e21 = tri[t, 2, 1] - tri[t, 0, 1]
    e22 = tri[t, 2, 2] - tri[t, 0, 2]
    return e11 * e22 - e12 * e21, e12 * e20 - e10 * e22, e10 * e21 - e11 * e20


@njit(cache=True)
def bounding_spheres(tri):
    """Bounding disk of each triangle.

    (m, 8) = centroid xyz, radius (to the farthest corner), unit normal xyz (zero for a degenerate
    triangle: the disk is then a ball), 0.
    """
    m = tri.shape[0]
    out = np.zeros((m, 8), np.float64)
    for t in range(m):
        for ax in range(3):
            out[t, ax] = (tri[t, 0, ax] + tri[t, 1, ax] + tri[t, 2, ax]) / 3.0
        r2 = 0.0
        for c in range(3):
            d = 0.0
            for ax in range(3):
                d += (tri[t, c, ax] - out[t, ax]) ** 2
            r2 = max(r2, d)
        out[t, 3] = np.sqrt(r2) * (1.0 + 1e-12)
        n0, n1, n2 = triangle_cross(tri, t)
        ln = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        # a sliver's normal is unreliable (direction error ~ eps * r^2 / |n|): keep the
        # ball bound (normal 0) for it
        if ln > 1e-6 * r2:
            out[t, 4] = n0 / ln
            out[t, 5] = n1 / ln
            out[t, 6] = n2 / ln
    return out
