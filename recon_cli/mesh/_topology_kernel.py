"""Numba kernels of :mod:`recon_cli.mesh.topology`: the loops that do not vectorise.

They only compute.
"""

from __future__ import annotations

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
            # next edge at w: prefer one leaving w in half-edge direction
            nxt = -1
            for j in range(ptr[w], ptr[w + 1]):
                c = inc[j]
                if not used[c]:
                    if src[c] == w:
                        nxt = c
                        break
                    if nxt < 0:
                        nxt = c
            if nxt < 0:
                break
            e = nxt
            v = w
    starts[n_loops] = pos
    return order, verts, starts[: n_loops + 1]


# ---- edge grouping -------------------------------------------------------------------------
@njit(cache=True)
def half_edge_keys(faces, n_vertices, pack):
    """Undirected key ``lo * n + hi`` of every half-edge; with ``pack``, ``key * 3m + h``.

    Self-loop half-edges (repeated-index faces) get key ``n * n`` so they sort last. With
    ``pack`` the caller checks that ``(n * n + 1) * 3m`` fits in int64. One pass, no temporaries.
    """
    m = faces.shape[0]
    nh = 3 * m
    out = np.empty(nh, np.int64)
    sentinel = np.int64(n_vertices) * n_vertices
    for f in range(m):
        for k in range(3):
            a = np.int64(faces[f, k])
            b = np.int64(faces[f, (k + 1) % 3])
            h = 3 * f + k
            if a == b:
                key = sentinel
            elif a < b:
                key = a * n_vertices + b
            else:
                key = b * n_vertices + a
            out[h] = key * nh + h if pack else key
    return out


@njit(cache=True)
def group_sorted_keys(sorted_keys, order, n_half_edges, sentinel, index_proto):
    """Edge groups from sorted half-edge keys.

    ``sorted_keys`` are either packed keys (``order`` empty: key ``// n_half_edges``, index
    ``% n_half_edges``) or plain keys with ``order`` the sorting permutation. Keys equal to
    ``sentinel`` (self-loops) end the valid range.

    Returns ``(he_edge, ptr, he_sorted)`` in the dtype of ``index_proto``: edge of each
    half-edge (-1 for self-loops), CSR offsets of the edges (E + 1) and the half-edges
    sorted by edge (then by index).
    """
    packed = order.shape[0] == 0
    nh = n_half_edges
    n = sorted_keys.shape[0]
    he_edge = np.full(nh, -1, index_proto.dtype)
    he_sorted = np.empty(n, index_proto.dtype)
    n_valid = 0
    n_edges = 0
    prev = np.int64(-1)
    for i in range(n):
        if packed:
            key = sorted_keys[i] // nh
            h = sorted_keys[i] % nh
        else:
            key = sorted_keys[i]
            h = order[i]
        if key == sentinel:
            break
        if key != prev:
            n_edges += 1
            prev = key
        he_sorted[i] = h
        he_edge[h] = n_edges - 1
        n_valid += 1
    ptr = np.empty(n_edges + 1, index_proto.dtype)
    e = -1
    for i in range(n_valid):
        h = he_sorted[i]
        if he_edge[h] != e:
            e = he_edge[h]
            ptr[e] = i
    ptr[n_edges] = n_valid
    return he_edge, ptr, he_sorted[:n_valid]


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
