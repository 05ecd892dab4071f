"""Numba kernels of :mod:`recon_cli.stages.repair`.

They only compute; validation lives in repair.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@njit(cache=True)
def choose_edge_pairs(nm_edges, edge_ptr, edge_half_edges, support):
    """For each non-manifold edge keep two faces; return a keep flag per half-edge slot.

    The kept faces are the two with most manifold neighbours (``support`` per face), ties
    going to the first in face order. Windings play no part: they are fixed later, and a
    choice that ignores them is the same again when the repaired mesh is repaired again.
    """
    keep = np.zeros(edge_half_edges.shape[0], np.bool_)
    for i in range(nm_edges.shape[0]):
        e = nm_edges[i]
        s = edge_ptr[e]
        t = edge_ptr[e + 1]
        for _ in range(2):
            best = -1
            for j in range(s, t):
                if keep[j]:
                    continue
                if (
                    best < 0
                    or support[edge_half_edges[j] // 3] > support[edge_half_edges[best] // 3]
                    or (
                        support[edge_half_edges[j] // 3] == support[edge_half_edges[best] // 3]
                        and edge_half_edges[j] < edge_half_edges[best]
                    )
                ):
                    best = j
            keep[best] = True
    return keep


@njit(cache=True)
def _has_edge(keys, a, b, n):
    lo = min(a, b)
    hi = max(a, b)
    k = lo * n + hi
    i = np.searchsorted(keys, k)
    return i < keys.shape[0] and keys[i] == k


@njit(cache=True)
def fill_loops(loop_verts, loop_ptr, vertices, edge_keys, n_vertices, min_area):
    """Minimum-area triangulation of each boundary loop (dynamic programming, O(k^3) per loop).

    ``loop_verts[loop_ptr[i]:loop_ptr[i+1]]`` follows the boundary half-edges. A chord that
    is already a mesh edge is forbidden (it would become non-manifold), and so is a triangle
    of area at most ``min_area`` (it would be degenerate). Triangles are wound
    against the loop, i.e. consistently with the faces around the hole. Per loop: the allowed
    chords (:func:`_allowed_chords`), the cheapest splits (:func:`_min_area_splits`), the
    triangles they make (:func:`_unwind`).

    Returns ``(faces, filled)``: new triangles, and per loop whether it was filled.
    """
    n_loops = loop_ptr.shape[0] - 1
    total = 0
    for i in range(n_loops):
        total += loop_ptr[i + 1] - loop_ptr[i] - 2
    out = np.empty((max(total, 0), 3), np.int64)
    filled = np.zeros(n_loops, np.bool_)
    nout = 0
    for li in range(n_loops):
        v = loop_verts[loop_ptr[li] : loop_ptr[li + 1]]
        k = v.shape[0]
        if k < 3:
            continue
        allowed = _allowed_chords(v, edge_keys, n_vertices)
        best = _min_area_splits(v, vertices, allowed, min_area)
        if best[0, k - 1] < 0:
            continue
        filled[li] = True
        nout = _unwind(v, best, out, nout)
    return out[:nout], filled


@njit(cache=True)
def _allowed_chords(v, edge_keys, n_vertices):
    """``allowed[i, j]`` (i < j): loop ``v``'s sides, and the chords that are no mesh edge."""
    k = v.shape[0]
    allowed = np.zeros((k, k), np.bool_)
    for i in range(k):
        for j in range(i + 1, k):
            if j == i + 1 or (i == 0 and j == k - 1):
                allowed[i, j] = True
            else:
                allowed[i, j] = not _has_edge(edge_keys, v[i], v[j], n_vertices)
    return allowed


@njit(cache=True)
def _min_area_splits(v, vertices, allowed, min_area):
    """``best[i, j]``: the apex of the least-area triangulation of the polygon ``v[i..j]``.

    -1 where none exists (forbidden chords, degenerate triangles).
    """
    k = v.shape[0]
    inf = np.inf
    cost = np.full((k, k), inf)
    best = np.full((k, k), -1, np.int64)
    for i in range(k - 1):
        cost[i, i + 1] = 0.0
    for gap in range(2, k):
        for i in range(k - gap):
            j = i + gap
            if not allowed[i, j]:
                continue
            pi = vertices[v[i]]
            pj = vertices[v[j]]
            for m in range(i + 1, j):
                c = cost[i, m] + cost[m, j]
                if c == inf:
                    continue
                pm = vertices[v[m]]
                ax = pm[0] - pi[0]
                ay = pm[1] - pi[1]
                az = pm[2] - pi[2]
                bx = pj[0] - pi[0]
                by = pj[1] - pi[1]
                bz = pj[2] - pi[2]
                cx = ay * bz - az * by
                cy = az * bx - ax * bz
                cz = ax * by - ay * bx
                a = 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)
                if a <= min_area:
                    continue
                c += a
                if c < cost[i, j]:
                    cost[i, j] = c
                    best[i, j] = m
    return best


@njit(cache=True)
def _unwind(v, best, out, nout):
    """Write the triangles of the split table ``best`` of loop ``v`` at ``out[nout:]``.

    An explicit stack, from the whole loop down; returns the new ``nout``.
    """
    k = v.shape[0]
    stack = np.empty((k, 2), np.int64)
    stack[0, 0] = 0
    stack[0, 1] = k - 1
    sp = 1
    while sp > 0:
        sp -= 1
        i = stack[sp, 0]
        j = stack[sp, 1]
        if j - i < 2:
            continue
        m = best[i, j]
        out[nout, 0] = v[i]
        out[nout, 1] = v[j]
        out[nout, 2] = v[m]
        nout += 1
        stack[sp, 0] = i
        stack[sp, 1] = m
        sp += 1
        stack[sp, 0] = m
        stack[sp, 1] = j
        sp += 1
    return nout
