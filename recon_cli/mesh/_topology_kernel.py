"""Numba kernels of :mod:`recon_cli.mesh.topology`: the loops that do not vectorise.

They only compute.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.unionfind import union_min


@njit(cache=True)
def trace_boundary_loops(src, dst, n_vertices):
    """Walk boundary edges into loops.

    ``src[i] -> dst[i]`` are boundary half-edges. The walk is undirected (a flipped face
    reverses its boundary half-edge) but prefers the edge leaving the current vertex in
    the half-edge direction, so an oriented manifold boundary gives its true loops.

    Returns ``(order, verts, starts)``: ``order`` lists edge indices loop after loop,
    ``verts`` (same length) the vertex each edge was entered from, so loop ``i`` visits
    ``verts[starts[i]:starts[i + 1]]``. Open chains (only on non-manifold input) are walked
    from an end and count as one loop each.
    """
    k = src.shape[0]
    ptr, inc = _incidence(src, dst, n_vertices)
    used = np.zeros(k, np.bool_)
    order = np.empty(k, np.int64)
    verts = np.empty(k, np.int64)
    starts = np.empty(k + 1, np.int64)
    n_loops = 0
    pos = 0
    # open chains (non-manifold input) are walked from an end, so each counts once
    for it in range(2 * k):
        e0 = it % k
        if used[e0]:
            continue
        v = src[e0]
        if it < k:
            if (ptr[src[e0] + 1] - ptr[src[e0]]) % 2 == 1:
                v = src[e0]
            elif (ptr[dst[e0] + 1] - ptr[dst[e0]]) % 2 == 1:
                v = dst[e0]
            else:
                continue
        starts[n_loops] = pos
        n_loops += 1
        e = e0
        first = v
        while True:
            used[e] = True
            order[pos] = e
            verts[pos] = v
            pos += 1
            w = dst[e] if src[e] == v else src[e]
            if w == first:
                break
            e = _next_boundary_edge(ptr, inc, src, used, w)
            if e < 0:
                break
            v = w
    starts[n_loops] = pos
    return order, verts, starts[: n_loops + 1]


@njit(cache=True)
def _incidence(src, dst, n_vertices):
    """The edges at each vertex: ``inc[ptr[v]:ptr[v + 1]]``, in edge order."""
    k = src.shape[0]
    deg = np.zeros(n_vertices + 1, np.int64)
    for i in range(k):
        deg[src[i] + 1] += 1
        deg[dst[i] + 1] += 1
    ptr = deg  # running sum in place (np.cumsum would load numba.np.arraymath with the kernel)
    for v in range(n_vertices):
        ptr[v + 1] += ptr[v]
    fill = ptr[:-1].copy()
    inc = np.empty(2 * k, np.int64)
    for i in range(k):
        inc[fill[src[i]]] = i
        fill[src[i]] += 1
        inc[fill[dst[i]]] = i
        fill[dst[i]] += 1
    return ptr, inc


@njit(cache=True)
def _next_boundary_edge(ptr, inc, src, used, w):
    """The next unused edge at ``w``, preferring one leaving ``w`` in half-edge direction; -1."""
    nxt = -1
    for j in range(ptr[w], ptr[w + 1]):
        c = inc[j]
        if not used[c]:
            if src[c] == w:
                return c
            if nxt < 0:
                nxt = c
    return nxt


# ---- edge grouping -------------------------------------------------------------------------
@njit(cache=True)
def counting_sort(keys, n_keys, index_proto):
    """Stable counting sort of keys in ``0..n_keys-1``: ``(ptr (n_keys+1,) int64, order)``."""
    ptr = np.zeros(n_keys + 1, np.int64)
    for i in range(keys.shape[0]):
        ptr[keys[i] + 1] += 1
    for k in range(n_keys):
        ptr[k + 1] += ptr[k]
    fill = ptr[:-1].copy()
    order = np.empty(keys.shape[0], index_proto.dtype)
    for i in range(keys.shape[0]):
        k = keys[i]
        order[fill[k]] = i
        fill[k] += 1
    return ptr, order


@njit(cache=True)
def consistently_oriented(flat, edge_ptr, edge_half_edges):
    """True if no two half-edges of one edge run the same way."""
    for e in range(edge_ptr.shape[0] - 1):
        fwd = 0
        bwd = 0
        for j in range(edge_ptr[e], edge_ptr[e + 1]):
            h = edge_half_edges[j]
            nxt = h + 1 if h % 3 != 2 else h - 2
            if flat[h] < flat[nxt]:
                fwd += 1
            else:
                bwd += 1
        if fwd > 1 or bwd > 1:
            return False
    return True


# ---- union-find ----------------------------------------------------------------------------
@njit(cache=True)
def _label_in_place(parent):
    """Turn a union-find forest (root = smallest member) into labels numbered by first member."""
    k = 0
    for i in range(parent.shape[0]):
        p = parent[i]
        if p == i:
            parent[i] = k
            k += 1
        else:
            # p < i was already relabelled, and carries the label of i's root
            parent[i] = parent[p]
    return k


@njit(cache=True)
def _link_corners(parent, flat, a, b):
    # join the two faces' corners across the shared edge of half-edges a and b
    ea = a + 1 if a % 3 != 2 else a - 2
    eb = b + 1 if b % 3 != 2 else b - 2
    if flat[a] == flat[b]:
        union_min(parent, a, b)
        union_min(parent, ea, eb)
    else:
        union_min(parent, a, eb)
        union_min(parent, ea, b)


@njit(cache=True)
def fan_labels_pairs(parent, flat, link_a, link_b):
    """Corner fans joined across half-edge pairs ``(link_a[i], link_b[i])``; labels in ``parent``.

    ``parent`` must hold ``0..3m-1``; on return it holds the fan of each corner, numbered in
    order of first corner. Returns the number of fans.
    """
    for i in range(link_a.shape[0]):
        _link_corners(parent, flat, link_a[i], link_b[i])
    return _label_in_place(parent)


@njit(cache=True)
def fan_labels_groups(parent, flat, edge_ptr, edge_half_edges):
    """Like :func:`fan_labels_pairs`, joining consecutive half-edges of every edge."""
    for e in range(edge_ptr.shape[0] - 1):
        for j in range(edge_ptr[e] + 1, edge_ptr[e + 1]):
            _link_corners(parent, flat, edge_half_edges[j - 1], edge_half_edges[j])
    return _label_in_place(parent)


@njit(cache=True)
def face_labels_groups(parent, edge_ptr, edge_half_edges):
    """Faces joined through every edge (any number of faces); labels in ``parent`` (``0..m-1``)."""
    for e in range(edge_ptr.shape[0] - 1):
        for j in range(edge_ptr[e] + 1, edge_ptr[e + 1]):
            union_min(parent, edge_half_edges[j - 1] // 3, edge_half_edges[j] // 3)
    return _label_in_place(parent)


@njit(cache=True)
def orient_faces(flat, he_edge, edge_ptr, edge_half_edges):
    """Breadth-first 2-colouring of faces across manifold (two-face) edges.

    ``flip[f]`` makes windings agree with the root of ``f``'s component (its first face);
    across an edge both faces must traverse it in opposite directions. Components are
    numbered in order of first face; ``conflict[e]`` marks manifold edges whose parity
    contradicts the colouring (non-orientable cycles).

    Returns ``(flip (m,) bool, component (m,), conflict (E,) bool)``.
    """
    m = flat.shape[0] // 3
    flip = np.zeros(m, np.bool_)
    comp = np.full(m, -1, he_edge.dtype)
    conflict = np.zeros(edge_ptr.shape[0] - 1, np.bool_)
    queue = np.empty(m, he_edge.dtype)
    n_comp = 0
    for f0 in range(m):
        if comp[f0] >= 0:
            continue
        comp[f0] = n_comp
        head = 0
        tail = 1
        queue[0] = f0
        while head < tail:
            f = queue[head]
            head += 1
            for k in range(3):
                h = 3 * f + k
                e = he_edge[h]
                if e < 0:
                    continue
                s = edge_ptr[e]
                if edge_ptr[e + 1] - s != 2:
                    continue
                o = edge_half_edges[s]
                if o == h:
                    o = edge_half_edges[s + 1]
                g = o // 3
                want = flip[f] ^ (flat[h] == flat[o])
                if comp[g] < 0:
                    comp[g] = n_comp
                    flip[g] = want
                    queue[tail] = g
                    tail += 1
                elif flip[g] != want:
                    conflict[e] = True
        n_comp += 1
    return flip, comp, conflict


# ---- bounded-memory grouping (bucket by smallest vertex, then sort each small bucket) -------
@njit(cache=True)
def _other_end(flat, h):
    return flat[h + 1] if h % 3 != 2 else flat[h - 2]


@njit(cache=True)
def _stable_sort_bucket(items, s, e, keys):
    """Sort ``items[s:e]`` by ``keys`` (parallel to that slice), stably, in place."""
    k = e - s
    if k <= 24:
        for i in range(s + 1, e):
            it = items[i]
            key = keys[i - s]
            j = i - 1
            while j >= s and keys[j - s] > key:
                items[j + 1] = items[j]
                keys[j + 1 - s] = keys[j - s]
                j -= 1
            items[j + 1] = it
            keys[j + 1 - s] = key
        return
    order = np.argsort(keys[:k], kind="mergesort")
    tmp = items[s:e].copy()
    tk = keys[:k].copy()
    for i in range(k):
        items[s + i] = tmp[order[i]]
        keys[i] = tk[order[i]]


@njit(cache=True)
def _bucket_ptr_inplace_shift(ptr, n):
    # after a scatter that used ptr[v] as the cursor of bucket v, ptr[v] is the end of v
    for v in range(n, 0, -1):
        ptr[v] = ptr[v - 1]
    ptr[0] = 0


@njit(cache=True)
def _bucket_width(n_keys, n_items):
    # keys per bucket: one when there are no more keys than items, else enough that there are
    # at most ``n_items + 1`` buckets (a mesh with far more vertices than corners)
    return max(1, (n_keys + n_items) // (n_items + 1))


@njit(cache=True)
def group_half_edges(flat, n_vertices, index_proto):
    """Edge groups of the half-edges of ``flat`` (the faces' corners), sorted by ``(lo, hi)``.

    The same groups as sorting the keys ``lo * n + hi`` stably, without a key per half-edge:
    a counting sort by the smaller end, then each bucket (the edges of one vertex, a few
    half-edges) sorted stably by the larger end. Self-loop half-edges belong to no edge.
    With more vertices than half-edges a bucket spans several vertices (``O(3m)`` memory).

    Returns ``(edge_ptr (E + 1,), edge_half_edges (H,))`` in the dtype of ``index_proto``:
    the half-edges of edge ``e`` are ``edge_half_edges[edge_ptr[e]:edge_ptr[e + 1]]``, in
    increasing order. Temporaries: one index per bucket and the largest bucket's keys.
    """
    nh = flat.shape[0]
    q = _bucket_width(n_vertices, nh)
    nb = (n_vertices + q - 1) // q
    ptr, he, max_bucket = _bucket_half_edges(flat, q, nb, index_proto)
    n_valid = he.shape[0]
    keys = np.empty(max(max_bucket, 1), np.int64)
    n_edges = 0
    for v in range(nb):
        s = ptr[v]
        e = ptr[v + 1]
        if e - s > 1:
            # stable by the larger end, then (buckets of several vertices) by the smaller
            for j in range(s, e):
                h = he[j]
                keys[j - s] = max(flat[h], _other_end(flat, h))
            _stable_sort_bucket(he, s, e, keys)
            if q > 1:
                for j in range(s, e):
                    h = he[j]
                    keys[j - s] = min(flat[h], _other_end(flat, h))
                _stable_sort_bucket(he, s, e, keys)
        for j in range(s, e):
            if j == s or not _same_edge(flat, he[j], he[j - 1]):
                n_edges += 1
    edge_ptr = np.empty(n_edges + 1, index_proto.dtype)
    k = 0
    for v in range(nb):
        for j in range(ptr[v], ptr[v + 1]):
            if j == ptr[v] or not _same_edge(flat, he[j], he[j - 1]):
                edge_ptr[k] = j
                k += 1
    edge_ptr[n_edges] = n_valid
    return edge_ptr, he


@njit(cache=True)
def _bucket_half_edges(flat, q, nb, index_proto):
    """The half-edges (self-loops left out) counting-sorted into buckets by smaller end // ``q``.

    Returns ``(ptr (nb + 1,), he, largest bucket)``: bucket ``b`` is ``he[ptr[b]:ptr[b + 1]]``.
    """
    nh = flat.shape[0]
    ptr = np.zeros(nb + 1, index_proto.dtype)
    for h in range(nh):
        a = flat[h]
        b = _other_end(flat, h)
        if a != b:
            ptr[min(a, b) // q + 1] += 1
    max_bucket = 0
    for v in range(nb):
        max_bucket = max(max_bucket, ptr[v + 1])
        ptr[v + 1] += ptr[v]
    he = np.empty(ptr[nb], index_proto.dtype)
    for h in range(nh):
        a = flat[h]
        b = _other_end(flat, h)
        if a != b:
            k = min(a, b) // q
            he[ptr[k]] = h
            ptr[k] += 1
    _bucket_ptr_inplace_shift(ptr, nb)
    return ptr, he, max_bucket


@njit(cache=True)
def _same_edge(flat, h, g):
    a = flat[h]
    b = _other_end(flat, h)
    c = flat[g]
    d = _other_end(flat, g)
    return min(a, b) == min(c, d) and max(a, b) == max(c, d)


@njit(cache=True)
def edge_of_half_edges(edge_ptr, edge_half_edges, n_half_edges):
    """(n_half_edges,) edge of each half-edge, -1 for those in no edge (self-loops)."""
    out = np.full(n_half_edges, -1, edge_half_edges.dtype)
    for e in range(edge_ptr.shape[0] - 1):
        for j in range(edge_ptr[e], edge_ptr[e + 1]):
            out[edge_half_edges[j]] = e
    return out


@njit(cache=True)
def edges_with_count(edge_ptr, lo, hi):
    """int64 indices of the edges with ``lo <= count <= hi`` half-edges, increasing."""
    n = 0
    for e in range(edge_ptr.shape[0] - 1):
        c = edge_ptr[e + 1] - edge_ptr[e]
        if lo <= c <= hi:
            n += 1
    out = np.empty(n, np.int64)
    n = 0
    for e in range(edge_ptr.shape[0] - 1):
        c = edge_ptr[e + 1] - edge_ptr[e]
        if lo <= c <= hi:
            out[n] = e
            n += 1
    return out


@njit(cache=True)
def _sorted_triple(faces, f):
    a = np.int64(faces[f, 0])
    b = np.int64(faces[f, 1])
    c = np.int64(faces[f, 2])
    lo = min(a, b, c)
    hi = max(a, b, c)
    return lo, a + b + c - lo - hi, hi


@njit(cache=True)
def duplicate_face_flags(faces, n_vertices, index_proto):
    """(m,) bool: the face's sorted vertex triple equals that of an earlier face.

    Faces are bucketed by their smallest vertex (counting sort), each bucket sorted stably
    by the other two: the same verdicts as one stable sort of the sorted triples.
    """
    m = faces.shape[0]
    q = _bucket_width(n_vertices, m)
    nb = (n_vertices + q - 1) // q
    ptr = np.zeros(nb + 1, index_proto.dtype)
    for f in range(m):
        ptr[_sorted_triple(faces, f)[0] // q + 1] += 1
    max_bucket = 0
    for v in range(nb):
        max_bucket = max(max_bucket, ptr[v + 1])
        ptr[v + 1] += ptr[v]
    order = np.empty(m, index_proto.dtype)
    for f in range(m):
        k = _sorted_triple(faces, f)[0] // q
        order[ptr[k]] = f
        ptr[k] += 1
    _bucket_ptr_inplace_shift(ptr, nb)
    dup = np.zeros(m, np.bool_)
    keys = np.empty(max(max_bucket, 1), np.int64)
    for v in range(nb):
        s = ptr[v]
        e = ptr[v + 1]
        if e - s < 2:
            continue
        # stable passes from the last key to the first: sorted by the triple, then by index
        for i in range(2, -1 if q > 1 else 0, -1):
            for j in range(s, e):
                keys[j - s] = _sorted_triple(faces, order[j])[i]
            _stable_sort_bucket(order, s, e, keys)
        for j in range(s + 1, e):
            if _sorted_triple(faces, order[j]) == _sorted_triple(faces, order[j - 1]):
                dup[order[j]] = True
    return dup


@njit(cache=True)
def fans_per_vertex(labels, flat, n_vertices):
    """(n,) int64 number of fans at each vertex, from corner fan labels numbered by first corner."""
    out = np.zeros(n_vertices, np.int64)
    nxt = 0
    for c in range(labels.shape[0]):
        if labels[c] == nxt:  # the first corner of fan ``nxt``
            out[flat[c]] += 1
            nxt += 1
    return out


@njit(cache=True)
def component_counts(comp, n_comp, flat, edge_ptr, edge_half_edges, n_vertices):
    """``(vertices, edges, faces)`` of each component, (c,) int64 each.

    A vertex counts once in every component with a face at it: most vertices have all their
    faces in one component, so only the corners of the others are listed and deduplicated.
    """
    fc = np.zeros(n_comp, np.int64)
    for f in range(comp.shape[0]):
        fc[comp[f]] += 1
    ec = np.zeros(n_comp, np.int64)
    for e in range(edge_ptr.shape[0] - 1):
        ec[comp[edge_half_edges[edge_ptr[e]] // 3]] += 1
    vc = np.zeros(n_comp, np.int64)
    first = np.full(n_vertices, -1, comp.dtype)
    n_extra = 0
    for c in range(flat.shape[0]):
        v = flat[c]
        k = comp[c // 3]
        if first[v] < 0:
            first[v] = k
            vc[k] += 1
        elif first[v] != k:
            n_extra += 1
    if n_extra:
        extra = np.empty(n_extra, np.int64)
        i = 0
        for c in range(flat.shape[0]):
            v = flat[c]
            k = comp[c // 3]
            if first[v] != k:
                extra[i] = np.int64(k) * n_vertices + v
                i += 1
        extra.sort()
        for i in range(n_extra):
            if i == 0 or extra[i] != extra[i - 1]:
                vc[extra[i] // n_vertices] += 1
    return vc, ec, fc


@njit(cache=True)
def component_defects(comp, n_comp, flat, edge_ptr, edge_half_edges, conflict_edges, fan_count):
    """(c,) bool: the component has a defect.

    A boundary or non-manifold edge, a non-manifold vertex, an orientation conflict or a
    repeated-index face.
    """
    bad = np.zeros(n_comp, np.bool_)
    for e in range(edge_ptr.shape[0] - 1):
        if edge_ptr[e + 1] - edge_ptr[e] != 2:
            bad[comp[edge_half_edges[edge_ptr[e]] // 3]] = True
    for i in range(conflict_edges.shape[0]):
        bad[comp[edge_half_edges[edge_ptr[conflict_edges[i]]] // 3]] = True
    for c in range(flat.shape[0]):
        if fan_count[flat[c]] > 1:
            bad[comp[c // 3]] = True
    for f in range(flat.shape[0] // 3):
        a = flat[3 * f]
        b = flat[3 * f + 1]
        c = flat[3 * f + 2]
        if a == b or b == c or a == c:
            bad[comp[f]] = True
    return bad


@njit(cache=True)
def referenced_bbox(vertices, referenced):
    """``(lo, hi, count)``: bounds of the referenced vertices with three finite coordinates."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    count = 0
    for i in range(vertices.shape[0]):
        if not referenced[i]:
            continue
        x = vertices[i, 0]
        y = vertices[i, 1]
        z = vertices[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        count += 1
        lo[0] = min(lo[0], x)
        lo[1] = min(lo[1], y)
        lo[2] = min(lo[2], z)
        hi[0] = max(hi[0], x)
        hi[1] = max(hi[1], y)
        hi[2] = max(hi[2], z)
    return lo, hi, count
