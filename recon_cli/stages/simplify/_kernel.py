"""Numba kernels of :mod:`recon_cli.stages.simplify`: quadric edge collapse. They only compute.

The working state is a set of flat arrays (see :class:`recon_cli.stages.simplify.Decimator`):
vertex positions, quadrics (10 coefficients of a symmetric 4x4 matrix per vertex), faces and
edges rewritten in place with alive flags, vertex -> faces and vertex -> edges lists
(``start``/``count`` into ``refs``; a merged vertex's list is appended at the end, dead items
are skipped and the array is compacted when full) and an indexed heap of the edges' costs.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory)

# slots of the ``meta`` counters array shared by the kernels and the stage
M_REFS = 0  # used length of refs
M_HEAP = 1  # edges in the heap
M_FACES = 2  # faces alive
M_LOG = 3  # collapses done (rows of the log)
M_MARK = 4  # last marker stamp
M_PASSES = 5  # heap builds (a pass ends when the heap is empty)
M_PASS_DONE = 6  # collapses in the current pass
M_LINK = 7  # rejections: link condition (manifold kept), this pass
M_GEOM = 8  # rejections: a face would flip or degenerate, this pass
M_BUDGET = 9  # rejections: the collapse would remove more faces than the target allows
M_STUCK = 10  # 1 when a whole pass collapsed nothing
M_EREFS = 11  # used length of erefs
N_META = 12

# quadric coefficients: a00 a01 a02 a03 a11 a12 a13 a22 a23 a33

# added to a collapse's error per squared squared edge length (coordinates scaled to a unit
# diagonal): the error of moving an edge's square by 1e-6 of its length; orders equal errors
TIE = 1e-12
# collapses leaving a triangle of quality (4 sqrt(3) area / sum of squared edges, 1 for an
# equilateral one) below this have their error divided by quality / QUALITY (as VCG's)
QUALITY = 0.3


@njit(cache=True)
def vertex_faces(faces, n):
    """Vertex -> faces lists: ``vstart`` (n,), ``vcount`` (n,), ``refs`` (6 m,), 3 m of it used."""
    m = faces.shape[0]
    vcount = np.zeros(n, np.int64)
    for f in range(m):
        for k in range(3):
            vcount[faces[f, k]] += 1
    vstart = np.empty(n, np.int64)
    s = 0
    for v in range(n):
        vstart[v] = s
        s += vcount[v]
    refs = np.empty(max(2 * s, 16), np.int64)
    fill = vstart.copy()
    for f in range(m):
        for k in range(3):
            v = faces[f, k]
            if k > 0 and (v == faces[f, 0] or (k == 2 and v == faces[f, 1])):
                vcount[v] -= 1  # a repeated index lists the face once
                continue
            refs[fill[v]] = f
            fill[v] += 1
    return vstart, vcount, refs


@njit(cache=True)
def classify(faces, n, vstart, vcount, refs):
    """Boundary and locked vertices.

    A vertex is locked (never moved or merged) when it lies on an edge of more than two
    faces, has more than one fan of faces, or belongs to a face that repeats an index: the
    collapse tests below assume a manifold neighbourhood. Returns ``boundary`` (n,) bool,
    ``locked`` (n,) bool and the counts of non-manifold edges and vertices.
    """
    boundary = np.zeros(n, np.bool_)
    locked = np.zeros(n, np.bool_)
    cnt = np.zeros(n, np.int64)
    first = np.full(n, -1, np.int64)
    maxdeg = 1
    for v in range(n):
        maxdeg = max(maxdeg, vcount[v])
    parent = np.empty(maxdeg, np.int64)
    nm_edges = 0
    nm_vertices = 0
    _lock_repeated_corners(faces, locked)
    for u in range(n):
        if vcount[u] == 0:
            continue
        if _fans(faces, vstart, vcount, refs, u, cnt, first, parent) > 1:
            locked[u] = True
            nm_vertices += 1
        nm_edges += _edges_of_fans(faces, vstart, vcount, refs, u, cnt, first, boundary, locked)
    return boundary, locked, nm_edges, nm_vertices


@njit(cache=True)
def _lock_repeated_corners(faces, locked):
    """Lock the corners of every face that repeats an index."""
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if a == b or b == c or a == c:
            locked[a] = True
            locked[b] = True
            locked[c] = True


@njit(cache=True)
def _fans(faces, vstart, vcount, refs, u, cnt, first, parent):
    """The fans of faces around ``u``: its faces joined by the edges they share (union-find).

    Counts in ``cnt[w]`` the faces of ``u`` on the edge (u, w) and keeps in ``first[w]`` the
    first of them (for :func:`_edges_of_fans`, which resets both).
    """
    s = vstart[u]
    k = vcount[u]
    for i in range(k):
        parent[i] = i
    for i in range(k):
        f = refs[s + i]
        for j in range(3):
            w = faces[f, j]
            if w == u:
                continue
            cnt[w] += 1
            if first[w] < 0:
                first[w] = i
            else:  # the faces i and first[w] share the edge (u, w)
                a = i
                while parent[a] != a:
                    a = parent[a]
                b = first[w]
                while parent[b] != b:
                    b = parent[b]
                if a != b:
                    parent[max(a, b)] = min(a, b)
    fans = 0
    for i in range(k):
        if parent[i] == i:
            fans += 1
    return fans


@njit(cache=True)
def _edges_of_fans(faces, vstart, vcount, refs, u, cnt, first, boundary, locked):
    """Mark ``u`` boundary (an edge of one face) or locked (an edge of more than two).

    Reads and resets the counts :func:`_fans` left; returns the non-manifold edges (u, w > u).
    """
    s = vstart[u]
    nm_edges = 0
    for i in range(vcount[u]):
        f = refs[s + i]
        for j in range(3):
            w = faces[f, j]
            if w == u or first[w] < 0:
                continue
            if cnt[w] == 1:
                boundary[u] = True
            elif cnt[w] > 2:
                locked[u] = True
                locked[w] = True
                if u < w:
                    nm_edges += 1
            cnt[w] = 0
            first[w] = -1
    return nm_edges


@njit(cache=True)
def _add_plane(Q, i, nx, ny, nz, d, w):
    Q[i, 0] += w * nx * nx
    Q[i, 1] += w * nx * ny
    Q[i, 2] += w * nx * nz
    Q[i, 3] += w * nx * d
    Q[i, 4] += w * ny * ny
    Q[i, 5] += w * ny * nz
    Q[i, 6] += w * ny * d
    Q[i, 7] += w * nz * nz
    Q[i, 8] += w * nz * d
    Q[i, 9] += w * d * d


@njit(cache=True)
def _shares_edge(faces, vstart, vcount, refs, a, b, skip):
    """Whether a face other than ``skip`` holds both ``a`` and ``b``."""
    for i in range(vstart[a], vstart[a] + vcount[a]):
        f = refs[i]
        if f != skip and (faces[f, 0] == b or faces[f, 1] == b or faces[f, 2] == b):
            return True
    return False


@njit(cache=True)
def quadrics(pos, faces, vstart, vcount, refs, boundary, boundary_weight):
    """Per-vertex error quadrics (n, 10) and the faces' unit normals (m, 3).

    Each face adds its plane weighted by its area to its corners (Garland & Heckbert 1997,
    area-weighted); each boundary edge adds the plane through it perpendicular to its face,
    weighted by ``boundary_weight`` times the squared edge length, to its two ends.
    """
    n = pos.shape[0]
    Q = np.zeros((n, 10))
    fn = np.zeros((faces.shape[0], 3))
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e1x = pos[b, 0] - pos[a, 0]
        e1y = pos[b, 1] - pos[a, 1]
        e1z = pos[b, 2] - pos[a, 2]
        e2x = pos[c, 0] - pos[a, 0]
        e2y = pos[c, 1] - pos[a, 1]
        e2z = pos[c, 2] - pos[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        ln = np.sqrt(nx * nx + ny * ny + nz * nz)
        if ln == 0.0:
            continue
        nx /= ln
        ny /= ln
        nz /= ln
        fn[f, 0] = nx
        fn[f, 1] = ny
        fn[f, 2] = nz
        d = -(nx * pos[a, 0] + ny * pos[a, 1] + nz * pos[a, 2])
        area = 0.5 * ln
        _add_plane(Q, a, nx, ny, nz, d, area)
        _add_plane(Q, b, nx, ny, nz, d, area)
        _add_plane(Q, c, nx, ny, nz, d, area)
        if boundary_weight <= 0.0:
            continue
        for k in range(3):
            p = faces[f, k]
            q = faces[f, (k + 1) % 3]
            if not (boundary[p] and boundary[q]):
                continue
            if _shares_edge(faces, vstart, vcount, refs, p, q, f):
                continue
            ex = pos[q, 0] - pos[p, 0]
            ey = pos[q, 1] - pos[p, 1]
            ez = pos[q, 2] - pos[p, 2]
            # the plane holding the edge and the face normal
            mx = ey * nz - ez * ny
            my = ez * nx - ex * nz
            mz = ex * ny - ey * nx
            lm = np.sqrt(mx * mx + my * my + mz * mz)
            if lm == 0.0:
                continue
            mx /= lm
            my /= lm
            mz /= lm
            dm = -(mx * pos[p, 0] + my * pos[p, 1] + mz * pos[p, 2])
            w = boundary_weight * (ex * ex + ey * ey + ez * ez)
            _add_plane(Q, p, mx, my, mz, dm, w)
            _add_plane(Q, q, mx, my, mz, dm, w)
    return Q, fn


@njit(cache=True)
def _placement(Q, pos, u, v, out):
    """Where the merged vertex of edge (u, v) goes and its error; ``out`` (4,) gets x, y, z, t.

    The minimum of the summed quadric when its 3x3 part is well conditioned and the
    minimum lies within two edge lengths of the edge; otherwise the minimum on the segment
    (Garland & Heckbert's fallback). ``t`` is the position along u -> v of the projection.
    """
    a00 = Q[u, 0] + Q[v, 0]
    a01 = Q[u, 1] + Q[v, 1]
    a02 = Q[u, 2] + Q[v, 2]
    b0 = Q[u, 3] + Q[v, 3]
    a11 = Q[u, 4] + Q[v, 4]
    a12 = Q[u, 5] + Q[v, 5]
    b1 = Q[u, 6] + Q[v, 6]
    a22 = Q[u, 7] + Q[v, 7]
    b2 = Q[u, 8] + Q[v, 8]
    c = Q[u, 9] + Q[v, 9]
    px, py, pz = pos[u, 0], pos[u, 1], pos[u, 2]
    dx = pos[v, 0] - px
    dy = pos[v, 1] - py
    dz = pos[v, 2] - pz
    dd = dx * dx + dy * dy + dz * dz
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    tr = a00 + a11 + a22
    ok = False
    x = y = z = 0.0
    if tr > 0.0 and abs(det) > 1e-9 * tr * tr * tr:
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        x = -(c00 * b0 + c01 * b1 + c02 * b2) / det
        y = -(c01 * b0 + c11 * b1 + c12 * b2) / det
        z = -(c02 * b0 + c12 * b1 + c22 * b2) / det
        mx = x - (px + 0.5 * dx)
        my = y - (py + 0.5 * dy)
        mz = z - (pz + 0.5 * dz)
        ok = mx * mx + my * my + mz * mz <= 4.0 * dd
    if not ok:
        # minimum of the quadric on the segment u + t d, t in [0, 1]
        adx = a00 * dx + a01 * dy + a02 * dz
        ady = a01 * dx + a11 * dy + a12 * dz
        adz = a02 * dx + a12 * dy + a22 * dz
        den = dx * adx + dy * ady + dz * adz
        num = px * adx + py * ady + pz * adz + b0 * dx + b1 * dy + b2 * dz
        t = 0.5
        if den > 1e-300:
            t = min(1.0, max(0.0, -num / den))
        x = px + t * dx
        y = py + t * dy
        z = pz + t * dz
    t = 0.5
    if dd > 0.0:
        t = min(1.0, max(0.0, ((x - px) * dx + (y - py) * dy + (z - pz) * dz) / dd))
    out[0] = x
    out[1] = y
    out[2] = z
    out[3] = t
    err = (
        a00 * x * x
        + a11 * y * y
        + a22 * z * z
        + 2.0 * (a01 * x * y + a02 * x * z + a12 * y * z)
        + 2.0 * (b0 * x + b1 * y + b2 * z)
        + c
    )
    # equal errors (flat parts: none) go shortest edge first
    return max(err, 0.0) + TIE * dd * dd


# ---- edges and the heap -------------------------------------------------------------------------
# An indexed 4-ary min-heap over the edges: int64 keys holding the cost as float32 bits
# (monotone for costs >= 0) in the high half and the edge in the low half, and each edge's
# position (``hpos``, -1 when out of the heap), so a collapse updates its edges' costs in place.
LOW = 0xFFFFFFFF


@njit(cache=True)
def _key(cost, edge):
    return (np.int64(np.float32(cost).view(np.uint32)) << 32) | edge


@njit(cache=True)
def _up(hk, hpos, i):
    key = hk[i]
    while i > 0:
        p = (i - 1) >> 2
        if hk[p] <= key:
            break
        hk[i] = hk[p]
        hpos[hk[i] & LOW] = i
        i = p
    hk[i] = key
    hpos[key & LOW] = i


@njit(cache=True)
def _down(hk, hpos, i, n):
    key = hk[i]
    while True:
        k = 4 * i + 1
        if k >= n:
            break
        best = k
        for j in range(k + 1, min(k + 4, n)):
            if hk[j] < hk[best]:
                best = j
        if hk[best] >= key:
            break
        hk[i] = hk[best]
        hpos[hk[i] & LOW] = i
        i = best
    hk[i] = key
    hpos[key & LOW] = i


@njit(cache=True)
def _remove(hk, hpos, meta, e):
    i = hpos[e]
    if i < 0:
        return
    hpos[e] = -1
    n = meta[M_HEAP] - 1
    meta[M_HEAP] = n
    if i == n:
        return
    last = hk[n]
    hk[i] = last
    if i > 0 and hk[(i - 1) >> 2] > last:
        _up(hk, hpos, i)
    else:
        _down(hk, hpos, i, n)


@njit(cache=True)
def _update(hk, hpos, meta, e, key):
    i = hpos[e]
    if i < 0:
        i = meta[M_HEAP]
        meta[M_HEAP] = i + 1
        hk[i] = key
        _up(hk, hpos, i)
        return
    old = hk[i]
    hk[i] = key
    if key < old:
        _up(hk, hpos, i)
    else:
        _down(hk, hpos, i, meta[M_HEAP])


@njit(cache=True)
def vertex_edges(faces, n, vstart, vcount, refs):
    """The unique edges ``ea < eb`` (E,) and vertex -> edges lists.

    The lists are ``estart``, ``ecount`` and ``erefs`` of size 2 x 2E, half used.
    """
    mark = np.full(n, -1, np.int64)
    ecount = np.zeros(n, np.int64)
    n_edges = 0
    for u in range(n):
        for i in range(vstart[u], vstart[u] + vcount[u]):
            f = refs[i]
            for k in range(3):
                w = faces[f, k]
                if w != u and mark[w] != u:
                    mark[w] = u
                    ecount[u] += 1
                    if w > u:
                        n_edges += 1
    estart = np.empty(n, np.int64)
    s = 0
    for u in range(n):
        estart[u] = s
        s += ecount[u]
    erefs = np.empty(max(2 * s, 16), np.int64)
    fill = estart.copy()
    ea = np.empty(n_edges, np.int64)
    eb = np.empty(n_edges, np.int64)
    for u in range(n):
        mark[u] = -1
    e = 0
    for u in range(n):
        for i in range(vstart[u], vstart[u] + vcount[u]):
            f = refs[i]
            for k in range(3):
                w = faces[f, k]
                if w > u and mark[w] != u:
                    mark[w] = u
                    ea[e] = u
                    eb[e] = w
                    erefs[fill[u]] = e
                    fill[u] += 1
                    erefs[fill[w]] = e
                    fill[w] += 1
                    e += 1
    return ea, eb, estart, ecount, erefs


@njit(cache=True)
def _compact(alive, valive, start, count, refs):
    """Drop dead items and the lists of dead vertices from ``refs`` (in place); its used length.

    Loops, not slices: a slice assignment compiles numba's broadcasting and its error
    messages (seconds of a cold start).
    """
    tmp = np.empty(refs.shape[0], np.int64)
    j = 0
    for x in range(start.shape[0]):
        if not valive[x]:
            count[x] = 0
            continue
        s0 = j
        for i in range(start[x], start[x] + count[x]):
            f = refs[i]
            if alive[f]:
                tmp[j] = f
                j += 1
        start[x] = s0
        count[x] = j - s0
    for i in range(j):
        refs[i] = tmp[i]
    return j


@njit(cache=True)
def build_heap(pos, Q, locked, ea, eb, ealive, epen, hk, hpos, meta):
    """Every current edge between unlocked vertices in the heap, with its cost."""
    out = np.empty(4)
    h = 0
    for e in range(ea.shape[0]):
        hpos[e] = -1
        epen[e] = False
        if ealive[e] and not (locked[ea[e]] or locked[eb[e]]):
            hk[h] = _key(_placement(Q, pos, ea[e], eb[e], out), e)
            h += 1
    for i in range((h - 2) // 4, -1, -1):
        _down(hk, hpos, i, h)
    for i in range(h):
        hpos[hk[i] & LOW] = i
    meta[M_HEAP] = h


@njit(cache=True)
def _normal_change(pos, a, b, c, which, x, y, z, min_cos, nx, ny, nz):
    """Check of a face (a, b, c) whose corner ``which`` moves to (x, y, z).

    Returns the moved face's quality (see QUALITY) when it keeps its orientation (its
    normal turns by less than the angle whose cosine is ``min_cos`` and stays on the side of
    the input face's normal (nx, ny, nz)), -1 when it flips, turns too far or would become
    degenerate (a face already degenerate may move anywhere).
    """
    ax, ay, az = pos[a, 0], pos[a, 1], pos[a, 2]
    bx, by, bz = pos[b, 0], pos[b, 1], pos[b, 2]
    cx, cy, cz = pos[c, 0], pos[c, 1], pos[c, 2]
    n0x = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
    n0y = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
    n0z = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if which == 0:
        ax, ay, az = x, y, z
    elif which == 1:
        bx, by, bz = x, y, z
    else:
        cx, cy, cz = x, y, z
    n1x = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
    n1y = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
    n1z = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    l0 = n0x * n0x + n0y * n0y + n0z * n0z
    l1 = n1x * n1x + n1y * n1y + n1z * n1z
    # degenerate: twice the area below 1e-10 of the squared longest edge (a sliver of ~1e-10 rad)
    e = max(
        (bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2,
        (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2,
        (ax - cx) ** 2 + (ay - cy) ** 2 + (az - cz) ** 2,
    )
    # quality: 4 sqrt(3) area / sum of squared edges = 2 sqrt(3) |n1| / sum
    s2 = (
        (bx - ax) ** 2
        + (by - ay) ** 2
        + (bz - az) ** 2
        + (cx - bx) ** 2
        + (cy - by) ** 2
        + (cz - bz) ** 2
        + (ax - cx) ** 2
        + (ay - cy) ** 2
        + (az - cz) ** 2
    )
    if l1 <= 1e-20 * e * e:
        return 0.0 if l0 == 0.0 else -1.0
    quality = 3.4641016151377544 * np.sqrt(l1) / s2
    if l0 == 0.0:
        return quality
    dot = n0x * n1x + n0y * n1y + n0z * n1z
    if dot <= 0.0 or dot * dot < min_cos * abs(min_cos) * l0 * l1:
        return -1.0
    # successive turns must not add up to a face facing away from where it started
    if n1x * nx + n1y * ny + n1z * nz <= 0.0 and nx * nx + ny * ny + nz * nz > 0.0:
        return -1.0
    return quality


class Surface(NamedTuple):
    """The mesh being simplified, as :func:`collapse` rewrites it in place.

    ``pos`` (n, 3), ``faces`` (m, 3), ``falive`` (m,), ``valive`` (n,), quadrics ``Q``
    (n, 10), the input faces' unit normals ``fn`` (m, 3), ``boundary``, ``locked`` and
    ``moved`` (n,) bool.
    """

    pos: np.ndarray
    faces: np.ndarray
    falive: np.ndarray
    valive: np.ndarray
    Q: np.ndarray
    fn: np.ndarray
    boundary: np.ndarray
    locked: np.ndarray
    moved: np.ndarray


class Fans(NamedTuple):
    """Vertex -> faces lists (:func:`vertex_faces`): ``vstart``, ``vcount`` (n,), ``refs``."""

    vstart: np.ndarray
    vcount: np.ndarray
    refs: np.ndarray


class Edges(NamedTuple):
    """The edges (:func:`vertex_edges`), their vertex -> edges lists and their heap.

    ``ea``, ``eb``, ``ealive``, ``epen`` (E,) (penalised once for a poor triangle);
    ``estart``, ``ecount`` (n,), ``erefs``; the heap's keys ``hk`` and positions ``hpos`` (E,).
    """

    ea: np.ndarray
    eb: np.ndarray
    ealive: np.ndarray
    epen: np.ndarray
    estart: np.ndarray
    ecount: np.ndarray
    erefs: np.ndarray
    hk: np.ndarray
    hpos: np.ndarray


class Log(NamedTuple):
    """The collapses in order: ``u`` kept, ``v`` merged into it, ``t`` along u -> v (n,)."""

    u: np.ndarray
    v: np.ndarray
    t: np.ndarray


@njit(cache=True)
def collapse(
    surf, fans, edges, log, mark, meta, target, stop_at, min_cos, max_passes, has_boundary
):
    """Collapse edges, cheapest first, until ``stop_at`` faces remain (or none can go).

    ``target`` is the final face count (a collapse never goes below it); ``stop_at`` where
    this call returns (for progress). A collapse of (u, v) moves u to the quadric's
    minimum and removes v when: the link condition holds (the vertices adjacent to both
    are exactly the third corners of the faces on the edge, and an interior edge does not
    join two boundary vertices), which keeps a manifold mesh manifold; the edge does not
    close a tetrahedron or take the last face of a vertex; and no other face around u or v
    flips, turns by more than ``acos(min_cos)``, faces away from its input normal (``fn``)
    or becomes degenerate. A rejected edge
    leaves the heap until one of its ends changes; when the heap runs empty it is built
    again from every edge (a rejected collapse may be possible now). ``meta[M_STUCK]`` is
    set when a whole pass collapsed nothing or ``max_passes`` ran, or when one face is left
    to remove and ``has_boundary`` is False (collapses remove 2). ``mark`` (n,) int64: the
    stamps of :func:`_edge_faces`.
    """
    pos, faces, falive, valive, Q, fn, boundary, locked, moved = surf
    vstart, vcount, refs = fans
    ea, eb, ealive, epen, estart, ecount, erefs, hk, hpos = edges
    log_u, log_v, log_t = log
    out = np.empty(4)
    opp = np.empty(2, np.int64)
    shared = np.empty(2, np.int64)
    while meta[M_FACES] > stop_at:
        if meta[M_FACES] == target + 1 and not has_boundary:
            # only a boundary edge's collapse removes a single face
            meta[M_BUDGET] += 1
            meta[M_STUCK] = 1
            return
        if meta[M_HEAP] == 0 and not _new_pass(
            pos, Q, locked, ea, eb, ealive, epen, hk, hpos, meta, max_passes
        ):
            meta[M_STUCK] = 1
            return
        # pop the cheapest edge
        edge = hk[0] & LOW
        _remove(hk, hpos, meta, edge)
        u = ea[edge]
        v = eb[edge]
        k, ku = _edge_faces(faces, falive, vstart, vcount, refs, mark, meta, u, v, shared, opp)
        if k == 0 or k > 2:
            continue
        if meta[M_FACES] - k < target:
            meta[M_BUDGET] += 1
            continue
        kv = -1
        if not (k == 2 and boundary[u] and boundary[v]):
            kv = _link_condition(faces, falive, vstart, vcount, refs, mark, meta, u, v, k, ku, opp)
        if (
            kv < 0
            or (
                k == 2
                and _closes_tetrahedron(faces, falive, vstart, vcount, refs, u, v, shared, opp)
            )
            or _bares_corner(falive, vstart, vcount, refs, k, opp)
        ):
            meta[M_LINK] += 1
            continue
        cost = _placement(Q, pos, u, v, out)
        # the faces that stay: none may flip, turn too far or degenerate
        worst = _worst_quality(
            pos, faces, falive, fn, vstart, vcount, refs, u, v, shared, out, min_cos
        )
        if worst < 0.0:
            meta[M_GEOM] += 1
            continue
        if worst < QUALITY and not epen[edge]:
            # a poor triangle would follow: back in the heap at the penalised error (the
            # key only grows, so the order is the one of penalties computed up front)
            epen[edge] = True
            cost *= QUALITY / max(worst, 1e-3)
            _update(hk, hpos, meta, edge, _key(cost, edge))
            continue
        # collapse v into u: faces, edges, the vertex
        _merge_faces(
            faces, falive, valive, vstart, vcount, refs, meta, u, v, k, ku + kv - 2 * k, shared
        )
        ealive[edge] = False
        need = _move_edges(ea, eb, ealive, estart, ecount, erefs, hk, hpos, meta, u, v, opp)
        meta[M_EREFS] = _join_lists(
            ealive, valive, estart, ecount, erefs, meta[M_EREFS], u, v, need + ecount[u]
        )
        valive[v] = False
        vcount[v] = 0
        ecount[v] = 0
        _merge_vertex(pos, Q, boundary, moved, u, v, out)
        _log_collapse(log_u, log_v, log_t, meta, u, v, out[3])
        # u's edges costed again
        first = estart[u]
        _recost(pos, Q, locked, ea, eb, epen, erefs[first : first + ecount[u]], hk, hpos, meta, out)


@njit(cache=True, inline="always")
def _new_pass(pos, Q, locked, ea, eb, ealive, epen, hk, hpos, meta, max_passes):
    """Start a pass: the heap built again from every edge, the pass's counters reset.

    False when the pass would be in vain (the last one collapsed nothing, or ``max_passes``
    ran) or the heap is empty: no edge can go.
    """
    if meta[M_PASSES] > 0 and (meta[M_PASS_DONE] == 0 or meta[M_PASSES] >= max_passes):
        return False
    build_heap(pos, Q, locked, ea, eb, ealive, epen, hk, hpos, meta)
    meta[M_PASSES] += 1
    meta[M_PASS_DONE] = 0
    meta[M_LINK] = 0
    meta[M_GEOM] = 0
    meta[M_BUDGET] = 0
    return meta[M_HEAP] > 0


@njit(cache=True, inline="always")
def _edge_faces(faces, falive, vstart, vcount, refs, mark, meta, u, v, shared, opp):
    """The faces on edge (u, v): their count ``k`` and u's alive faces ``ku``.

    The first two go in ``shared`` and their third corners in ``opp`` (-1 in both past the
    edge's faces); u's neighbours get a new stamp in ``mark`` (``meta[M_MARK]``).
    """
    meta[M_MARK] += 1
    s = meta[M_MARK]
    k = 0
    ku = 0
    for i in range(vstart[u], vstart[u] + vcount[u]):
        f = refs[i]
        if not falive[f]:
            continue
        ku += 1
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if a == v or b == v or c == v:
            if k < 2:
                shared[k] = f
                opp[k] = a + b + c - u - v
            k += 1
        mark[a] = s
        mark[b] = s
        mark[c] = s
    for j in range(k, 2):
        shared[j] = -1
        opp[j] = -1
    return k, ku


@njit(cache=True, inline="always")
def _link_condition(faces, falive, vstart, vcount, refs, mark, meta, u, v, k, ku, opp):
    """The count of v's alive faces when the link condition holds for (u, v), else -1.

    v's other neighbours are not u's (``mark`` stamped ``meta[M_MARK]``) but for the third
    corners ``opp`` of the edge's ``k`` faces, and those are not the whole component.
    """
    s = meta[M_MARK]
    bad = False
    kv = 0
    for i in range(vstart[v], vstart[v] + vcount[v]):
        f = refs[i]
        if not falive[f]:
            continue
        kv += 1
        for j in range(3):
            w = faces[f, j]
            if w == u or w == v or mark[w] != s:
                continue
            if w != opp[0] and w != opp[1]:
                bad = True
    if bad or ku + kv - 2 * k == 0:
        return -1  # (or the edge's faces are the whole component)
    return kv


@njit(cache=True, inline="always")
def _closes_tetrahedron(faces, falive, vstart, vcount, refs, u, v, shared, opp):
    """Whether a face of u and a face of v hold both third corners.

    The two would become one face twice.
    """
    both = 0
    for side in range(2):
        w = u if side == 0 else v
        for i in range(vstart[w], vstart[w] + vcount[w]):
            f = refs[i]
            if falive[f] and f != shared[0] and f != shared[1]:
                a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
                if (a == opp[0] or b == opp[0] or c == opp[0]) and (
                    a == opp[1] or b == opp[1] or c == opp[1]
                ):
                    both += 1
                    break
    return both == 2


@njit(cache=True, inline="always")
def _bares_corner(falive, vstart, vcount, refs, k, opp):
    """Whether a third corner's only face is on the edge (it would be left without faces)."""
    for j in range(k):
        o = opp[j]
        alive = 0
        for i in range(vstart[o], vstart[o] + vcount[o]):
            if falive[refs[i]]:
                alive += 1
        if alive <= 1:
            return True
    return False


@njit(cache=True, inline="always")
def _worst_quality(pos, faces, falive, fn, vstart, vcount, refs, u, v, shared, out, min_cos):
    """The worst quality of the faces that stay around u and v, u moved to ``out[:3]``.

    -1 when one of them flips, turns too far or degenerates (:func:`_normal_change`).
    """
    x, y, z = out[0], out[1], out[2]
    worst = 1.0
    for side in range(2):
        w = u if side == 0 else v
        for i in range(vstart[w], vstart[w] + vcount[w]):
            f = refs[i]
            if not falive[f] or f == shared[0] or f == shared[1]:
                continue
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            which = 0 if a == w else (1 if b == w else 2)
            q = _normal_change(pos, a, b, c, which, x, y, z, min_cos, fn[f, 0], fn[f, 1], fn[f, 2])
            if q < 0.0:
                return -1.0
            worst = min(worst, q)
    return worst


@njit(cache=True, inline="always")
def _merge_faces(faces, falive, valive, vstart, vcount, refs, meta, u, v, k, need, shared):
    """The edge's ``k`` faces go; v's others turn to u; u's list holds them all (``need``)."""
    for j in range(k):
        falive[shared[j]] = False
    meta[M_FACES] -= k
    for i in range(vstart[v], vstart[v] + vcount[v]):
        f = refs[i]
        if falive[f]:
            for j in range(3):
                if faces[f, j] == v:
                    faces[f, j] = u
    meta[M_REFS] = _join_lists(falive, valive, vstart, vcount, refs, meta[M_REFS], u, v, need)


@njit(cache=True, inline="always")
def _move_edges(ea, eb, ealive, estart, ecount, erefs, hk, hpos, meta, u, v, opp):
    """Drop v's edges to the third corners (they duplicate u's), move the others to u.

    Returns how many moved.
    """
    moved = 0
    for i in range(estart[v], estart[v] + ecount[v]):
        g = erefs[i]
        if not ealive[g]:
            continue
        w = ea[g] if eb[g] == v else eb[g]
        if w == opp[0] or w == opp[1]:
            ealive[g] = False
            _remove(hk, hpos, meta, g)
            continue
        if ea[g] == v:
            ea[g] = u
        else:
            eb[g] = u
        moved += 1
    return moved


@njit(cache=True, inline="always")
def _join_lists(alive, valive, start, count, refs, used, u, v, need):
    """Make u's list its alive items then v's, appended at the end of ``refs``.

    ``used`` is the used length of ``refs``; when ``need`` more items would not fit, the lists
    are compacted first (:func:`_compact`). Returns the new used length. (The meta slot is
    not passed: a literal slot would compile a specialisation for each.)
    """
    if used + need > refs.shape[0]:
        used = _compact(alive, valive, start, count, refs)
    r = used
    for side in range(2):
        w = u if side == 0 else v
        for i in range(start[w], start[w] + count[w]):
            x = refs[i]
            if alive[x]:
                refs[r] = x
                r += 1
    start[u] = used
    count[u] = r - used
    return r


@njit(cache=True, inline="always")
def _merge_vertex(pos, Q, boundary, moved, u, v, out):
    """Move u to ``out[:3]`` with the sum of u's and v's quadrics (v merged into it)."""
    pos[u, 0] = out[0]
    pos[u, 1] = out[1]
    pos[u, 2] = out[2]
    for j in range(10):
        Q[u, j] += Q[v, j]
    boundary[u] = boundary[u] or boundary[v]
    moved[u] = True


@njit(cache=True, inline="always")
def _log_collapse(log_u, log_v, log_t, meta, u, v, t):
    """Log the collapse of v into u (``t`` along u -> v); one more this pass."""
    n_log = meta[M_LOG]
    log_u[n_log] = u
    log_v[n_log] = v
    log_t[n_log] = t
    meta[M_LOG] = n_log + 1
    meta[M_PASS_DONE] += 1


@njit(cache=True, inline="always")
def _recost(pos, Q, locked, ea, eb, epen, around, hk, hpos, meta, out):
    """Cost the edges ``around`` (a vertex's list) again and lift their penalty."""
    for g in around:
        if not locked[ea[g]] and not locked[eb[g]]:
            epen[g] = False
            _update(hk, hpos, meta, g, _key(_placement(Q, pos, ea[g], eb[g], out), g))


@njit(cache=True)
def replay(log_u, log_v, log_t, values, source):
    """Carry vertex data through the collapses, in their order.

    ``values`` (n, k) float64: the merged vertex gets ``(1 - t) value[u] + t value[v]``;
    ``source`` (n,) int64: the row whose discrete data it keeps (v's when t > 1/2).
    """
    k = values.shape[1]
    for i in range(log_u.shape[0]):
        u = log_u[i]
        v = log_v[i]
        t = log_t[i]
        for j in range(k):
            values[u, j] = (1.0 - t) * values[u, j] + t * values[v, j]
        if t > 0.5:
            source[u] = source[v]
