"""Numba kernels of :mod:`recon_cli.topology`: the loops that do not vectorise. They only compute."""

from __future__ import annotations

import numpy as np
from numba import njit


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
    ptr = np.cumsum(deg)
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


@njit(cache=True)
def propagate_orientation(n_faces, adj_ptr, adj_face, adj_same, seed_order):
    """Breadth-first 2-colouring of faces: ``flip[f]`` makes windings agree across adjacencies.

    ``adj_face[adj_ptr[f]:adj_ptr[f+1]]`` are the faces adjacent to ``f`` across manifold
    edges and ``adj_same`` says whether the two faces traverse that edge the same way (then
    exactly one of them must flip). Components start from faces in ``seed_order``.

    Returns ``(flip, component, conflict)``; ``conflict[j]`` marks adjacency ``j`` whose
    parity contradicts the colouring (non-orientable cycles).
    """
    flip = np.zeros(n_faces, np.bool_)
    comp = np.full(n_faces, -1, np.int64)
    conflict = np.zeros(adj_face.shape[0], np.bool_)
    queue = np.empty(n_faces, np.int64)
    n_comp = 0
    for s in range(seed_order.shape[0]):
        f0 = seed_order[s]
        if comp[f0] >= 0:
            continue
        comp[f0] = n_comp
        head = 0
        tail = 1
        queue[0] = f0
        while head < tail:
            f = queue[head]
            head += 1
            for j in range(adj_ptr[f], adj_ptr[f + 1]):
                g = adj_face[j]
                want = flip[f] ^ adj_same[j]
                if comp[g] < 0:
                    comp[g] = n_comp
                    flip[g] = want
                    queue[tail] = g
                    tail += 1
                elif flip[g] != want:
                    conflict[j] = True
        n_comp += 1
    return flip, comp, conflict
