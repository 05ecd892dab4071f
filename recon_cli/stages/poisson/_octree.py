"""Numba kernels of the Poisson octree: lattice keys, sorted-key lookups, level construction.

They only compute (validation lives in :mod:`recon_cli.stages.poisson`). Conventions shared by the
poisson package's kernels (:mod:`._system`, :mod:`._splat`, :mod:`._extract`):

- positions are in unit-cube coordinates; at level ``d`` the lattice spacing is ``2**-d``;
- a lattice point or cell ``(x, y, z)`` is keyed by ``(x << 42) | (y << 21) | z``
  (:func:`lattice_key`); a level's cell and node keys are kept sorted, lookups are binary
  searches or linear merges (hash tables would double the memory);
- corner ``q`` (0..7) of a cell sits at offset ``(q & 1, (q >> 1) & 1, (q >> 2) & 1)``;
- a level's ``cell_nodes`` (c, 4) int32 holds the node index of corners 0..3 only (z offset
  0): corner ``q + 4`` is the next node in the sorted keys, ``cell_nodes[c, q] + 1``, since
  the node at ``z + 1`` is a node too and no key falls between. Half the largest array of
  the solver; :func:`corner` gives any corner.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound

SHIFT_X = 42
SHIFT_Y = 21
MASK21 = (1 << 21) - 1


@njit(cache=True, inline="always")
def lattice_key(x, y, z):
    return (np.int64(x) << 42) | (np.int64(y) << 21) | np.int64(z)


@njit(cache=True, inline="always")
def bsearch(keys, key):
    """Index of ``key`` in sorted unique ``keys``, -1 if absent (no hash table to keep)."""
    lo = lower_bound(keys, key, 0, len(keys))
    return lo if (lo < len(keys) and keys[lo] == key) else -1


@njit(cache=True)
def bsearch_many(keys, queries):
    out = np.empty(len(queries), np.int32)
    for i in range(len(queries)):
        out[i] = bsearch(keys, queries[i])
    return out


@njit(cache=True)
def rekey(keys, axis, inverse):
    """Move coordinate ``axis`` to the minor position of the key (or back when ``inverse``)."""
    out = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        k = keys[i]
        a = (k >> 42) & MASK21
        b = (k >> 21) & MASK21
        c = k & MASK21
        if axis == 0:
            # forward (x, y, z) -> (y, z, x); inverse (y, z, x) -> (x, y, z)
            out[i] = lattice_key(b, c, a) if not inverse else lattice_key(c, a, b)
        elif axis == 1:
            out[i] = lattice_key(a, c, b)  # (x, y, z) <-> (x, z, y), its own inverse
        else:
            out[i] = k
    return out


@njit(cache=True)
def _dilate_minor_pass(keys, lo, hi, limit, out):
    """One pass of :func:`dilate_minor`.

    Writes the keys into ``out`` unless it is empty; returns how many there are.
    """
    write = len(out) > 0
    m = 0
    last = -1
    for i in range(len(keys)):
        k = keys[i]
        z = k & MASK21
        base = k - z
        z0 = max(z + lo, 0)
        z1 = min(z + hi, limit)
        for v in range(z0, z1 + 1):
            kk = base | v
            if kk > last:
                if write:
                    out[m] = kk
                m += 1
                last = kk
    return m


@njit(cache=True)
def dilate_minor(keys, lo, hi, limit):
    """Sorted unique keys of ``key + t`` for t in [lo, hi] along the minor coordinate.

    Kept in [0, limit]; ``keys`` sorted. Dilation stays inside each column: one pass counts, a
    second writes an array of the exact size (an array for every key's ``hi - lo + 1``
    neighbours, cut afterwards, held up to 5x the output while it ran).
    """
    m = _dilate_minor_pass(keys, lo, hi, limit, np.empty(0, np.int64))
    out = np.empty(m, np.int64)
    _dilate_minor_pass(keys, lo, hi, limit, out)
    return out


@njit(cache=True, inline="always")
def _merge_into(queries, offset, keys, out):
    """out[i] = index of ``queries[i] + offset`` in sorted unique ``keys`` (-1 if absent).

    Queries non-decreasing, so one linear merge.
    """
    j = 0
    n = len(keys)
    for i in range(len(queries)):
        q = queries[i] + offset
        while j < n and keys[j] < q:
            j += 1
        out[i] = j if (j < n and keys[j] == q) else -1


@njit(cache=True)
def merge_lookup(queries, keys):
    """Index of each query in sorted unique ``keys`` (-1 if absent); queries non-decreasing."""
    out = np.empty(len(queries), np.int64)
    _merge_into(queries, 0, keys, out)
    return out


@njit(cache=True, inline="always")
def corner(cell_nodes, c, q):
    """Node index of corner ``q`` (0..7) of cell ``c`` (``cell_nodes`` holds corners 0..3)."""
    return cell_nodes[c, q & 3] + (q >> 2)


@njit(cache=True)
def corner_nodes(cell_keys, node_keys):
    """(c, 4) int32 index in sorted ``node_keys`` of corners 0..3 of each of ``cell_keys``.

    ``cell_keys`` are sorted; -1 where absent. A constant offset keeps the queries sorted, so each
    corner is one linear merge.
    """
    out = np.empty((len(cell_keys), 4), np.int32)
    for q in range(4):
        _merge_into(cell_keys, ((q & 1) << 42) | (((q >> 1) & 1) << 21), node_keys, out[:, q])
    return out


@njit(cache=True)
def node_cell_count(cell_nodes, n_nodes):
    """Number of cells incident to each node (int8, at most 8)."""
    cnt = np.zeros(n_nodes, np.int8)
    for c in range(cell_nodes.shape[0]):
        for q in range(4):
            j = cell_nodes[c, q]
            cnt[j] += 1
            cnt[j + 1] += 1
    return cnt


@njit(cache=True)
def unknown_nodes(node_keys, cnt, top, dirichlet):
    """Nodes whose hat function is solved for.

    Every cell of its support present (Neumann: those inside the cube, the faces of [0, ``top``]^3
    cutting the support); Dirichlet: only interior nodes with all 8 cells. ``cnt``: incident cells
    per node.
    """
    n = len(node_keys)
    out = np.empty(n, np.bool_)
    for j in range(n):
        k = node_keys[j]
        x = (k >> 42) & MASK21
        y = (k >> 21) & MASK21
        z = k & MASK21
        inner = int(0 < x < top) + int(0 < y < top) + int(0 < z < top)
        if dirichlet:
            out[j] = inner == 3 and cnt[j] == 8
        else:
            out[j] = cnt[j] == (1 << inner)
    return out


@njit(cache=True)
def face_nodes(node_keys, top):
    """Indices of the nodes on the faces of the cube (a coordinate 0 or ``top``)."""
    out = np.empty(len(node_keys), np.int64)
    m = 0
    for j in range(len(node_keys)):
        k = node_keys[j]
        x = (k >> 42) & MASK21
        y = (k >> 21) & MASK21
        z = k & MASK21
        if x == 0 or y == 0 or z == 0 or x == top or y == top or z == top:
            out[m] = j
            m += 1
    return out[:m].copy()


@njit(cache=True)
def halve(keys):
    """Keys of the parents (coordinates shifted right by one); order preserved."""
    out = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        k = keys[i]
        out[i] = lattice_key(
            ((k >> 42) & MASK21) >> 1, ((k >> 21) & MASK21) >> 1, (k & MASK21) >> 1
        )
    return out


@njit(cache=True)
def double(keys):
    """Keys with every coordinate doubled (a cell's lower corner on the next finer lattice).

    Order preserved.
    """
    out = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        k = keys[i]
        out[i] = lattice_key(
            ((k >> 42) & MASK21) << 1, ((k >> 21) & MASK21) << 1, (k & MASK21) << 1
        )
    return out


@njit(cache=True)
def cell_has_child(child_parent, n_cells):
    flag = np.zeros(n_cells, np.bool_)
    for i in range(len(child_parent)):
        flag[child_parent[i]] = True
    return flag


@njit(cache=True, inline="always")
def _run_end(keys, start, stop, shift):
    """End of the run of ``keys[start:stop]`` sharing the coordinate at bit ``shift``.

    The coordinate is ``keys[start]``'s.
    """
    v = (keys[start] >> shift) & MASK21
    end = start
    while end < stop and ((keys[end] >> shift) & MASK21) == v:
        end += 1
    return end


@njit(cache=True)
def children_sorted(parent_keys, parent_index):
    """Sorted keys of the 8 children of each of the sorted ``parent_keys``, and their parents.

    The parents are each child's ``parent_index`` (int32) entry.

    Keys order by (x, y, z); the children of the parents of one x-run, x-plane by x-plane,
    and within it of one y-run, y-row by y-row, come out in order with no sort.
    """
    n = len(parent_keys)
    out = np.empty(8 * n, np.int64)
    par = np.empty(8 * n, np.int32)
    m = 0
    i = 0
    while i < n:
        px = (parent_keys[i] >> 42) & MASK21
        ie = _run_end(parent_keys, i, n, 42)
        for cx in range(2):
            j = i
            while j < ie:
                py = (parent_keys[j] >> 21) & MASK21
                je = _run_end(parent_keys, j, ie, 21)
                for cy in range(2):
                    for k in range(j, je):
                        pz = parent_keys[k] & MASK21
                        for cz in range(2):
                            out[m] = lattice_key(2 * px + cx, 2 * py + cy, 2 * pz + cz)
                            par[m] = parent_index[k]
                            m += 1
                j = je
        i = ie
    return out, par
