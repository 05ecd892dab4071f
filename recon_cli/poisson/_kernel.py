"""Numba kernels of the screened Poisson solver: they only compute (no validation).

Conventions shared with :mod:`recon_cli.poisson`:

- positions are in unit-cube coordinates; at level ``d`` the lattice spacing is ``2**-d``;
- a lattice point or cell ``(x, y, z)`` is keyed by ``(x << 42) | (y << 21) | z``;
- hash tables are :mod:`recon_cli._kernels.hashtable`'s (lookups return ``-1`` for a missing key);
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
from recon_cli._kernels.hashtable import lookup

SHIFT_X = 42
SHIFT_Y = 21
MASK21 = (1 << 21) - 1


@njit(cache=True, inline="always")
def _key(x, y, z):
    return (np.int64(x) << 42) | (np.int64(y) << 21) | np.int64(z)


@njit(cache=True, inline="always")
def bsearch(keys, key):
    """Index of ``key`` in sorted unique ``keys``, -1 if absent (no hash table to keep)."""
    lo = lower_bound(keys, key, 0, len(keys))
    return lo if (lo < len(keys) and keys[lo] == key) else -1


@njit(cache=True, inline="always")
def lower_bound(keys, key, lo, hi):
    """First index in [lo, hi) of sorted ``keys`` whose key is >= ``key`` (``hi`` if none)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


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
            out[i] = _key(b, c, a) if not inverse else _key(c, a, b)
        elif axis == 1:
            out[i] = _key(a, c, b)  # (x, y, z) <-> (x, z, y), its own inverse
        else:
            out[i] = k
    return out


@njit(cache=True)
def dilate_minor(keys, lo, hi, limit):
    """Sorted unique keys of ``key + t`` for t in [lo, hi] along the minor coordinate (kept in
    [0, limit]); ``keys`` sorted. One pass, since dilation stays inside each column."""
    out = np.empty(len(keys) * (hi - lo + 1), np.int64)
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
                out[m] = kk
                m += 1
                last = kk
    return out[:m]


@njit(cache=True, inline="always")
def _merge_into(queries, offset, keys, out):
    """out[i] = index of ``queries[i] + offset`` in sorted unique ``keys`` (-1 if absent);
    queries non-decreasing, so one linear merge."""
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
    """(c, 4) int32 index in sorted ``node_keys`` of corners 0..3 of each of the sorted
    ``cell_keys`` (-1 if absent): a constant offset keeps the queries sorted, so each
    corner is one linear merge."""
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
    """Nodes whose hat function is solved for: every cell of its support present (Neumann:
    those inside the cube, the faces of [0, ``top``]^3 cutting the support); Dirichlet: only
    interior nodes with all 8 cells. ``cnt``: incident cells per node."""
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
        out[i] = _key(((k >> 42) & MASK21) >> 1, ((k >> 21) & MASK21) >> 1, (k & MASK21) >> 1)
    return out


@njit(cache=True)
def double(keys):
    """Keys with every coordinate doubled (a cell's lower corner on the next finer lattice);
    order preserved."""
    out = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        k = keys[i]
        out[i] = _key(((k >> 42) & MASK21) << 1, ((k >> 21) & MASK21) << 1, (k & MASK21) << 1)
    return out


@njit(cache=True)
def prolong(cell_nodes, cell_keys, cell_parent, parent_nodes, coarse, n_nodes):
    """Values of the coarse trilinear function at the fine nodes (hat functions interpolate).

    Each node is computed once, from the first cell (in cell order) that holds it: walking
    the cells needs no per-node (cell, corner) table, which would cost 5 bytes a node.
    """
    # NaN marks a node not computed yet, so no flag array (a node whose value is NaN is
    # merely recomputed: any cell holding it gives the same terms in the same order)
    out = np.full(n_nodes, np.nan)
    for c in range(cell_nodes.shape[0]):
        k = cell_keys[c]
        o = ((k >> 42) & 1) | (((k >> 21) & 1) << 1) | ((k & 1) << 2)  # octant in the parent
        p = cell_parent[c]
        for q in range(8):
            j = corner(cell_nodes, c, q)
            if out[j] == out[j]:
                continue
            # position of the node inside the parent cell, in halves: 0, 1 or 2 per axis
            tx = ((o & 1) + (q & 1)) * 0.5
            ty = (((o >> 1) & 1) + ((q >> 1) & 1)) * 0.5
            tz = (((o >> 2) & 1) + ((q >> 2) & 1)) * 0.5
            v = 0.0
            for r in range(8):
                w = (tx if r & 1 else 1.0 - tx) * (ty if (r >> 1) & 1 else 1.0 - ty) * (tz if (r >> 2) & 1 else 1.0 - tz)
                if w != 0.0:
                    v += w * coarse[corner(parent_nodes, p, r)]
            out[j] = v
    return out


@njit(cache=True)
def stiffness_matvec(cell_nodes, ke, cell_screen, x, out):
    """out += sum over cells of the element matrix ``ke`` (8x8) applied to the corner values,
    plus the cell's own (8x8) screening matrix when ``cell_screen`` (c, 8, 8) is not empty.

    ``ke`` is the trilinear (Q1) stiffness of a cube: ``ke[a, a]`` on the diagonal, 0 between
    corners sharing an edge and one value ``f`` for every other pair, so
    ``(ke x)_a = ke[a, a] x_a + f (S - x_a - E_a)`` with ``S`` the sum of the 8 corner values
    and ``E_a`` that of the 3 edge neighbours: 5 operations a corner instead of 8 products.
    """
    xe = np.empty(8)
    kd = ke[0, 0]
    f = ke[0, 7]
    screen = cell_screen.shape[0] > 0
    for c in range(cell_nodes.shape[0]):
        for q in range(4):
            j = cell_nodes[c, q]
            xe[q] = x[j]
            xe[q + 4] = x[j + 1]
        s = 0.0
        for q in range(8):
            s += xe[q]
        for a in range(8):
            v = kd * xe[a] + f * (s - xe[a] - xe[a ^ 1] - xe[a ^ 2] - xe[a ^ 4])
            if screen:
                for b in range(8):
                    v += cell_screen[c, a, b] * xe[b]
            out[corner(cell_nodes, c, a)] += v


@njit(cache=True)
def cell_screening(cell, loc, weight, n_cells):
    """Per cell, the screening matrix sum_p w_p B_a(p) B_b(p) of the samples in it (c, 8, 8):
    applying it costs per cell, not per sample, where samples outnumber cells."""
    out = np.zeros((n_cells, 8, 8))
    wr = np.empty(8)
    for i in range(len(cell)):
        c = cell[i]
        for r in range(8):
            wr[r] = _tri_w(loc, i, r)
        for a in range(8):
            wa = weight[i] * wr[a]
            for b in range(8):
                out[c, a, b] += wa * wr[b]
    return out


@njit(cache=True)
def stiffness_diag_table(ke):
    """Diagonal of the stiffness matrix at a node with k (0..8) incident cells, summed cell
    by cell as an assembly would. Every corner has the same ``ke[a, a]`` (the cube's
    symmetry), so the diagonal is a function of k alone: the solver looks it up instead of
    keeping an (n,) vector."""
    out = np.zeros(9)
    for k in range(1, 9):
        out[k] = out[k - 1] + ke[0, 0]
    return out


@njit(cache=True)
def sample_cells(pos, level, cell_keys):
    """Cell index (at ``level``) holding each sample and its local coordinates in [0, 1)."""
    n = pos.shape[0]
    scale = float(1 << level)
    cell = np.empty(n, np.int64)
    loc = np.empty((n, 3))
    top = (1 << level) - 1
    for i in range(n):
        c0 = min(max(int(np.floor(pos[i, 0] * scale)), 0), top)
        c1 = min(max(int(np.floor(pos[i, 1] * scale)), 0), top)
        c2 = min(max(int(np.floor(pos[i, 2] * scale)), 0), top)
        cell[i] = bsearch(cell_keys, _key(c0, c1, c2))
        loc[i, 0] = pos[i, 0] * scale - c0
        loc[i, 1] = pos[i, 1] * scale - c1
        loc[i, 2] = pos[i, 2] * scale - c2
    return cell, loc


@njit(cache=True, inline="always")
def _tri_w(loc, i, r):
    tx = loc[i, 0]
    ty = loc[i, 1]
    tz = loc[i, 2]
    return (tx if r & 1 else 1.0 - tx) * (ty if (r >> 1) & 1 else 1.0 - ty) * (tz if (r >> 2) & 1 else 1.0 - tz)


@njit(cache=True)
def eval_at_samples(cell, loc, cell_nodes, x):
    n = len(cell)
    out = np.empty(n)
    for i in range(n):
        c = cell[i]
        v = 0.0
        for r in range(8):
            v += _tri_w(loc, i, r) * x[corner(cell_nodes, c, r)]
        out[i] = v
    return out


@njit(cache=True)
def screening_matvec(cell, loc, cell_nodes, weight, x, out):
    """out += sum_p weight_p B_i(p) sum_j B_j(p) x_j."""
    for i in range(len(cell)):
        c = cell[i]
        v = 0.0
        for r in range(8):
            v += _tri_w(loc, i, r) * x[corner(cell_nodes, c, r)]
        v *= weight[i]
        if v != 0.0:
            for r in range(8):
                out[corner(cell_nodes, c, r)] += _tri_w(loc, i, r) * v


@njit(cache=True)
def screening_diag_rhs(cell, loc, cell_nodes, weight, target, rhs):
    """Diagonal of the screening operator, and rhs += its right-hand side sum_p w_p t B_i(p)
    in place.

    The diagonal is returned sparse, (sorted nodes, values) over the nodes the samples
    touch: at the finest level they are few. Each node's share is summed apart first, then
    added, so the result rounds as adding a full screening vector would.
    """
    # compact slot of each touched node, in first-touch order (an int32 map: sorting the
    # samples' corners instead is 20x slower on a million samples)
    slot = np.full(len(rhs), -1, np.int32)
    nodes = np.empty(8 * len(cell), np.int64)
    m = 0
    for i in range(len(cell)):
        for r in range(8):
            j = corner(cell_nodes, cell[i], r)
            if slot[j] < 0:
                slot[j] = m
                nodes[m] = j
                m += 1
    sd = np.zeros(m)
    sr = np.zeros(m)
    for i in range(len(cell)):
        c = cell[i]
        for r in range(8):
            w = _tri_w(loc, i, r)
            k = slot[corner(cell_nodes, c, r)]
            sd[k] += weight[i] * w * w
            sr[k] += weight[i] * target * w
    for k in range(m):
        rhs[nodes[k]] += sr[k]
    # sorted by node for the solver's sequential passes: set the touched slots' values in
    # node order by walking the map once
    out_n = np.empty(m, np.int64)
    out_d = np.empty(m)
    t = 0
    for j in range(len(slot)):
        if slot[j] >= 0:
            out_n[t] = j
            out_d[t] = sd[slot[j]]
            t += 1
    return out_n, out_d


# ---- the vector field: normals splatted with a quadratic B-spline centred at each sample ----
@njit(cache=True, inline="always")
def _pos(v):
    return v if v > 0.0 else 0.0


@njit(cache=True, inline="always")
def _cube(x):
    t = x if x > 0.0 else 0.0
    return t * t * t


@njit(cache=True, inline="always")
def _quart(x):
    t = x if x > 0.0 else 0.0
    t *= t
    return t * t


@njit(cache=True)
def _b2_int1(x):
    """Antiderivative of the centred quadratic B-spline (support [-1.5, 1.5]): its CDF."""
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return 1.0
    return (_cube(x + 1.5) - 3.0 * _cube(x + 0.5) + 3.0 * _cube(x - 0.5)) / 6.0


@njit(cache=True)
def _b2_int2(x):
    """Second antiderivative of the centred quadratic B-spline (x for x >= 1.5)."""
    if x <= -1.5:
        return 0.0
    if x >= 1.5:
        return x
    return (_quart(x + 1.5) - 3.0 * _quart(x + 0.5) + 3.0 * _quart(x - 0.5)) / 24.0


@njit(cache=True)
def hat_b2_value(v, rho):
    """int hat(z) B2_rho(z - v) dz: a level's hat function against a kernel of width rho."""
    # rho * int2(t / rho) is the second antiderivative of B2_rho
    return rho * (_b2_int2((v + 1.0) / rho) - 2.0 * _b2_int2(v / rho) + _b2_int2((v - 1.0) / rho))


@njit(cache=True)
def hat_b2_deriv(v, rho):
    """int hat'(z) B2_rho(z - v) dz (v = sample minus node, in level cells)."""
    return -_b2_int1((-1.0 - v) / rho) + 2.0 * _b2_int1(-v / rho) - _b2_int1((1.0 - v) / rho)


@njit(cache=True)
def splat_rhs(pos, normal_w, splat_level, splat_frac, level, node_keys, unknown, n_nodes):
    """b_i = int grad(B_i) . W at the level's unknown nodes.

    ``normal_w`` (n, 3) is the sample's vector (normal times area weight, sign included);
    the sample is splatted with weight (1 - frac) at ``splat_level`` and frac one finer.
    """
    b = np.zeros(n_nodes)
    n_keys = len(node_keys)
    scale = float(1 << level)
    top = 1 << level
    lo = np.empty(3, np.int64)
    cnt = np.empty(3, np.int64)
    vx = np.empty((3, 64))
    dx = np.empty((3, 64))
    for p in range(pos.shape[0]):
        for part in range(2):
            frac = splat_frac[p]
            if part == 0:
                wpart = 1.0 - frac
                s = splat_level[p]
            else:
                wpart = frac
                s = splat_level[p] + 1
            if wpart <= 0.0:
                continue
            rho = 2.0 ** (level - s)
            reach = 1.0 + 1.5 * rho
            for a in range(3):
                u = pos[p, a] * scale
                i0 = max(int(np.ceil(u - reach)), 0)
                i1 = min(int(np.floor(u + reach)), top)
                lo[a] = i0
                cnt[a] = max(i1 - i0 + 1, 0)
                for t in range(cnt[a]):
                    v = u - (i0 + t)
                    vx[a, t] = hat_b2_value(v, rho)
                    dx[a, t] = hat_b2_deriv(v, rho) * scale
            nx = normal_w[p, 0] * wpart
            ny = normal_w[p, 1] * wpart
            nz = normal_w[p, 2] * wpart
            for tx in range(cnt[0]):
                j = -1
                for ty in range(cnt[1]):
                    fxy = vx[0, tx] * vx[1, ty]
                    gx = dx[0, tx] * vx[1, ty]
                    gy = vx[0, tx] * dx[1, ty]
                    if fxy == 0.0 and gx == 0.0 and gy == 0.0:
                        continue
                    # nodes of one (x, y) column are consecutive in the sorted keys: one
                    # binary search for the column's first key, then walk (missing nodes,
                    # common where a wide coarse splat meets the finest level, cost nothing)
                    kz0 = lo[2]
                    kst = _key(lo[0] + tx, lo[1] + ty, kz0)
                    if j < 0:
                        j = lower_bound(node_keys, kst, 0, n_keys)
                    else:
                        # the next column of the same x-plane is close: gallop from the last
                        step = 1
                        while j + step < n_keys and node_keys[j + step] < kst:
                            step <<= 1
                        j = lower_bound(node_keys, kst, j + (step >> 1), min(j + step + 1, n_keys))
                    kend = _key(lo[0] + tx, lo[1] + ty, kz0 + cnt[2] - 1)
                    while j < n_keys and node_keys[j] <= kend:
                        if unknown[j]:
                            tz = (node_keys[j] & MASK21) - kz0
                            b[j] += nx * gx * vx[2, tz] + ny * gy * vx[2, tz] + nz * fxy * dx[2, tz]
                        j += 1
    return b


# ---- kernel density: counts splatted with quadratic B-splines centred on cells ----
@njit(cache=True, inline="always")
def _b2w(t, k):
    # weight of the cell at offset k (-1, 0, 1) for a point at local coordinate t in [0, 1)
    if k == -1:
        return 0.5 * (1.0 - t) ** 2
    if k == 0:
        return 0.75 - (t - 0.5) ** 2
    return 0.5 * t * t


@njit(cache=True)
def density_splat(pos, count, level, ctk, ctv, cbits, n_cells):
    dens = np.zeros(n_cells)
    scale = float(1 << level)
    for p in range(pos.shape[0]):
        c = np.empty(3, np.int64)
        t = np.empty(3)
        for a in range(3):
            u = pos[p, a] * scale
            c[a] = int(np.floor(u))
            t[a] = u - c[a]
        for kx in range(-1, 2):
            for ky in range(-1, 2):
                for kz in range(-1, 2):
                    if min(c[0] + kx, c[1] + ky, c[2] + kz) < 0:
                        continue
                    j = lookup(ctk, ctv, cbits, _key(c[0] + kx, c[1] + ky, c[2] + kz))
                    if j >= 0:
                        dens[j] += count[p] * _b2w(t[0], kx) * _b2w(t[1], ky) * _b2w(t[2], kz)
    return dens


@njit(cache=True)
def density_eval(pos, level, ctk, ctv, cbits, dens):
    n = pos.shape[0]
    out = np.zeros(n)
    scale = float(1 << level)
    for p in range(n):
        c = np.empty(3, np.int64)
        t = np.empty(3)
        for a in range(3):
            u = pos[p, a] * scale
            c[a] = int(np.floor(u))
            t[a] = u - c[a]
        v = 0.0
        for kx in range(-1, 2):
            for ky in range(-1, 2):
                for kz in range(-1, 2):
                    if min(c[0] + kx, c[1] + ky, c[2] + kz) < 0:
                        continue
                    j = lookup(ctk, ctv, cbits, _key(c[0] + kx, c[1] + ky, c[2] + kz))
                    if j >= 0:
                        v += dens[j] * _b2w(t[0], kx) * _b2w(t[1], ky) * _b2w(t[2], kz)
        out[p] = v
    return out


# ---- extraction: leaves of the tree refined down to the finest lattice where they straddle ----
@njit(cache=True)
def refine_leaves(cell_keys, cell_nodes, is_leaf, g, level, depth, iso, eps, out_xyz, out_val):
    """Finest-lattice cells (and their corner values) inside leaves that straddle ``iso``.

    A leaf at ``level`` holds a trilinear function (its 8 corner values of ``g``); a leaf
    whose corner range reaches ``iso`` within ``eps`` is split into octants, evaluated
    exactly, down to ``depth``, keeping only octants whose range reaches it too. Values are
    negated (marching cubes puts values below its iso-value inside, chi is 1 inside).
    Writes the cells' lattice coordinates into ``out_xyz`` (k, 3) and corner values into
    ``out_val`` (k, 8) and returns k; with empty outputs it only counts, so the caller can
    allocate the exact size (growing buffers would hold up to twice the cells).
    """
    count_only = out_xyz.shape[0] == 0
    m = 0
    steps = depth - level
    side = 1 << steps
    stack_xyz = np.empty((8 * (steps + 1) + 8, 3), np.int64)
    stack_lvl = np.empty(8 * (steps + 1) + 8, np.int64)
    vals = np.empty(8)
    leaf_vals = np.empty(8)
    niso = -iso
    for c in range(cell_nodes.shape[0]):
        if not is_leaf[c]:
            continue
        for q in range(4):
            j = cell_nodes[c, q]
            leaf_vals[q] = -g[j]
            leaf_vals[q + 4] = -g[j + 1]
        lo = leaf_vals[0]
        hi = leaf_vals[0]
        for q in range(1, 8):
            lo = min(lo, leaf_vals[q])
            hi = max(hi, leaf_vals[q])
        if lo > niso + eps or hi < niso - eps:
            continue
        k = cell_keys[c]
        lx = (k >> 42) & MASK21
        ly = (k >> 21) & MASK21
        lz = k & MASK21
        # sub-cells addressed in finest units relative to the leaf's lower corner
        stack_xyz[0, 0] = 0
        stack_xyz[0, 1] = 0
        stack_xyz[0, 2] = 0
        stack_lvl[0] = 0
        top = 1
        while top > 0:
            top -= 1
            sx = stack_xyz[top, 0]
            sy = stack_xyz[top, 1]
            sz = stack_xyz[top, 2]
            sl = stack_lvl[top]
            size = side >> sl
            lo = 1e300
            hi = -1e300
            for q in range(8):
                fx = (sx + (q & 1) * size) / side
                fy = (sy + ((q >> 1) & 1) * size) / side
                fz = (sz + ((q >> 2) & 1) * size) / side
                v = 0.0
                for r in range(8):
                    w = (fx if r & 1 else 1.0 - fx) * (fy if (r >> 1) & 1 else 1.0 - fy) * (fz if (r >> 2) & 1 else 1.0 - fz)
                    v += w * leaf_vals[r]
                vals[q] = v
                lo = min(lo, v)
                hi = max(hi, v)
            if lo > niso + eps or hi < niso - eps:
                continue
            if sl == steps:
                if not count_only:
                    out_xyz[m, 0] = lx * side + sx
                    out_xyz[m, 1] = ly * side + sy
                    out_xyz[m, 2] = lz * side + sz
                    for q in range(8):
                        out_val[m, q] = vals[q]
                m += 1
                continue
            half = size >> 1
            for o in range(8):
                stack_xyz[top, 0] = sx + (o & 1) * half
                stack_xyz[top, 1] = sy + ((o >> 1) & 1) * half
                stack_xyz[top, 2] = sz + ((o >> 2) & 1) * half
                stack_lvl[top] = sl + 1
                top += 1
    return m


@njit(cache=True)
def cell_has_child(child_parent, n_cells):
    flag = np.zeros(n_cells, np.bool_)
    for i in range(len(child_parent)):
        flag[child_parent[i]] = True
    return flag


# ---- one level's system: stiffness (element by element) plus screening, solved by PCG ----
@njit(cache=True)
def level_matvec(cell_nodes, ke, cell_screen, scell, sloc, sw, x, out):
    """out = A x: stiffness, per-cell screening matrices if any, per-sample screening if any."""
    out[:] = 0.0
    stiffness_matvec(cell_nodes, ke, cell_screen, x, out)
    if len(sw):
        screening_matvec(scell, sloc, cell_nodes, sw, x, out)


@njit(cache=True)
def _residual_update(x, r, p, q, a, ncell, stiff, inv_stiff, sd_nodes, sd_vals, unknown):
    """x += a p, r -= a q, q = the preconditioned residual; returns (r.r, r.z).

    The inverse diagonal is rebuilt on the fly: the table ``inv_stiff`` (1 / ``stiff``) off
    the nodes of the sparse screening diagonal, 1 / (stiffness + screening) on them, 0 off
    the unknowns. With ``a`` = 0 and ``p``, ``q`` zero, x and r stay as they are and ``q``
    receives the preconditioned residual (the start).
    """
    rr = 0.0
    rz = 0.0
    k = 0
    ns = len(sd_nodes)
    nxt = sd_nodes[0] if ns > 0 else -1
    for i in range(len(r)):
        if i == nxt:
            d = stiff[ncell[i]] + sd_vals[k]
            inv = 1.0 / d if (unknown[i] and d > 0.0) else 0.0
            k += 1
            nxt = sd_nodes[k] if k < ns else -1
        else:
            inv = inv_stiff[ncell[i]] if unknown[i] else 0.0
        x[i] += a * p[i]
        r[i] -= a * q[i]
        rr += r[i] * r[i]
        rz += r[i] * r[i] * inv
        q[i] = r[i] * inv  # q is free until the next product
    return rr, rz


@njit(cache=True)
def level_pcg(cell_nodes, ke, cell_screen, scell, sloc, sw, rhs, ncell, sd_nodes, sd_vals, unknown, tol, max_iter):
    """Jacobi-preconditioned conjugate gradients on the unknown nodes (others stay 0).

    The diagonal is not stored: it is the stiffness diagonal at each node's incident-cell
    count ``ncell`` (:func:`stiffness_diag_table`) plus the sparse screening diagonal
    (``sd_nodes`` sorted, ``sd_vals``), inverted in each pass; ``rhs`` is overwritten by the
    residual. At the finest level every (n,) vector is tens of MB, so the solver keeps only
    x, p, q besides. Returns (x, iterations, relative residual).
    """
    n = len(rhs)
    stiff = stiffness_diag_table(ke)
    inv_stiff = np.zeros(9)
    for c in range(1, 9):
        inv_stiff[c] = 1.0 / stiff[c]
    x = np.zeros(n)
    r = rhs
    for i in range(n):
        if not unknown[i]:
            r[i] = 0.0
    p = np.zeros(n)
    # with a = 0 (p, q = 0) x and r stay as they are and p gets the preconditioned residual
    bn, rz = _residual_update(x, r, x, p, 0.0, ncell, stiff, inv_stiff, sd_nodes, sd_vals, unknown)
    bn = np.sqrt(bn)
    if bn == 0.0:
        return x, 0, 0.0
    q = np.empty(n)
    it = 0
    rel = 1.0
    while it < max_iter:
        level_matvec(cell_nodes, ke, cell_screen, scell, sloc, sw, p, q)
        pq = 0.0
        for i in range(n):
            if not unknown[i]:
                q[i] = 0.0
            pq += p[i] * q[i]
        if pq <= 0.0:
            break
        a = rz / pq
        rr, rz_new = _residual_update(x, r, p, q, a, ncell, stiff, inv_stiff, sd_nodes, sd_vals, unknown)
        it += 1
        rel = np.sqrt(rr) / bn
        if rel < tol:
            break
        beta = rz_new / rz
        for i in range(n):
            p[i] = q[i] + beta * p[i]
        rz = rz_new
    return x, it, rel


@njit(cache=True)
def clamp_on_faces(faces, g, value):
    """g = min(g, value) at the nodes ``faces`` (those on the faces of the cube), in place."""
    for i in range(len(faces)):
        j = faces[i]
        if g[j] > value:
            g[j] = value


@njit(cache=True, inline="always")
def _run_end(keys, start, stop, shift):
    """End of the run of ``keys[start:stop]`` sharing the coordinate at bit ``shift`` with ``keys[start]``."""
    v = (keys[start] >> shift) & MASK21
    end = start
    while end < stop and ((keys[end] >> shift) & MASK21) == v:
        end += 1
    return end


@njit(cache=True)
def children_sorted(parent_keys, parent_index):
    """Sorted keys of the 8 children of each of the sorted ``parent_keys``, and each child's
    ``parent_index`` (int32) entry.

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
                            out[m] = _key(2 * px + cx, 2 * py + cy, 2 * pz + cz)
                            par[m] = parent_index[k]
                            m += 1
                j = je
        i = ie
    return out, par


@njit(cache=True)
def corner_keys(cells):
    """(8c,) keys of the corners of lattice cells (c, 3), corner ``q`` of cell ``i`` at ``8 i + q``."""
    n = cells.shape[0]
    out = np.empty(8 * n, np.int64)
    for i in range(n):
        k = _key(cells[i, 0], cells[i, 1], cells[i, 2])
        for q in range(8):
            out[8 * i + q] = k + (((q & 1) << 42) | (((q >> 1) & 1) << 21) | ((q >> 2) & 1))
    return out


@njit(cache=True)
def unify_corner_values(vals, order_keys, order):
    """Give every lattice point one value, whichever cell computed it, in place.

    ``vals`` (c, 8) corner values of finest-lattice cells, ``order_keys``
    the (8c,) lattice keys of the corners sorted and ``order`` their argsort (flat corner
    index ``8 * cell + corner``). Each run of equal keys takes the value of its first member.
    """
    n = len(order)
    i = 0
    while i < n:
        k = order_keys[i]
        f = order[i]
        v = vals[f >> 3, f & 7]
        j = i + 1
        while j < n and order_keys[j] == k:
            g = order[j]
            vals[g >> 3, g & 7] = v
            j += 1
        i = j
