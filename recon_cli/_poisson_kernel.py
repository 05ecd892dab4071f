"""Numba kernels of the screened Poisson solver: they only compute (no validation).

Conventions shared with :mod:`recon_cli.poisson`:

- positions are in unit-cube coordinates; at level ``d`` the lattice spacing is ``2**-d``;
- a lattice point or cell ``(x, y, z)`` is keyed by ``(x << 42) | (y << 21) | z``;
- hash tables are open-addressing arrays of keys (``-1`` = empty) and int64 values, with a
  power-of-two capacity; lookups return ``-1`` for a missing key;
- corner ``q`` (0..7) of a cell sits at offset ``(q & 1, (q >> 1) & 1, (q >> 2) & 1)``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_MULT = np.uint64(11400714819323198485)  # 2**64 / golden ratio (Fibonacci hashing)
SHIFT_X = 42
SHIFT_Y = 21
MASK21 = (1 << 21) - 1


@njit(cache=True, inline="always")
def _key(x, y, z):
    return (np.int64(x) << 42) | (np.int64(y) << 21) | np.int64(z)


@njit(cache=True, inline="always")
def _slot(key, bits):
    return np.int64((np.uint64(key) * _MULT) >> np.uint64(64 - bits))


@njit(cache=True)
def table_bits(n):
    bits = 4
    while (1 << bits) < 2 * n + 16:
        bits += 1
    return bits


@njit(cache=True)
def build_table(keys):
    """Hash table of unique ``keys`` -> their index."""
    bits = table_bits(len(keys))
    cap = 1 << bits
    tk = np.full(cap, -1, np.int64)
    tv = np.empty(cap, np.int64)
    mask = cap - 1
    for i in range(len(keys)):
        k = keys[i]
        s = _slot(k, bits)
        while tk[s] != -1 and tk[s] != k:
            s = (s + 1) & mask
        tk[s] = k
        tv[s] = i
    return tk, tv, bits


@njit(cache=True, inline="always")
def lookup(tk, tv, bits, key):
    mask = (1 << bits) - 1
    s = _slot(key, bits)
    while True:
        k = tk[s]
        if k == key:
            return tv[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@njit(cache=True)
def lookup_many(tk, tv, bits, keys):
    out = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        out[i] = lookup(tk, tv, bits, keys[i])
    return out


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
def _set_insert(tk, bits, key):
    """Insert into a key-only set; True when the key was new."""
    mask = (1 << bits) - 1
    s = _slot(key, bits)
    while True:
        k = tk[s]
        if k == key:
            return False
        if k == -1:
            tk[s] = key
            return True
        s = (s + 1) & mask


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


@njit(cache=True)
def merge_lookup(queries, keys):
    """Index of each query in sorted unique ``keys`` (-1 if absent); queries non-decreasing."""
    out = np.empty(len(queries), np.int64)
    j = 0
    n = len(keys)
    for i in range(len(queries)):
        q = queries[i]
        while j < n and keys[j] < q:
            j += 1
        out[i] = j if (j < n and keys[j] == q) else -1
    return out


@njit(cache=True)
def unpack(keys):
    n = len(keys)
    xyz = np.empty((n, 3), np.int64)
    for i in range(n):
        k = keys[i]
        xyz[i, 0] = (k >> 42) & MASK21
        xyz[i, 1] = (k >> 21) & MASK21
        xyz[i, 2] = k & MASK21
    return xyz


@njit(cache=True)
def node_incidence(cell_nodes, n_nodes):
    """Per node: number of incident cells, and one (cell, corner) that holds it."""
    cnt = np.zeros(n_nodes, np.int8)
    cell = np.empty(n_nodes, np.int32)
    corner = np.empty(n_nodes, np.int8)
    for c in range(cell_nodes.shape[0]):
        for q in range(8):
            j = cell_nodes[c, q]
            if cnt[j] == 0:
                cell[j] = c
                corner[j] = q
            cnt[j] += 1
    return cnt, cell, corner


@njit(cache=True)
def octants(cell_keys):
    out = np.empty(len(cell_keys), np.int8)
    for i in range(len(cell_keys)):
        k = cell_keys[i]
        out[i] = ((k >> 42) & 1) | (((k >> 21) & 1) << 1) | ((k & 1) << 2)
    return out


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
def prolong(node_cell, node_corner, cell_parent, cell_octant, parent_nodes, coarse):
    """Values of the coarse trilinear function at the fine nodes (hat functions interpolate)."""
    n = len(node_cell)
    out = np.empty(n, np.float64)
    for j in range(n):
        c = node_cell[j]
        q = node_corner[j]
        o = cell_octant[c]
        p = cell_parent[c]
        # position of the node inside the parent cell, in halves: 0, 1 or 2 per axis
        tx = ((o & 1) + (q & 1)) * 0.5
        ty = (((o >> 1) & 1) + ((q >> 1) & 1)) * 0.5
        tz = (((o >> 2) & 1) + ((q >> 2) & 1)) * 0.5
        v = 0.0
        for r in range(8):
            w = (tx if r & 1 else 1.0 - tx) * (ty if (r >> 1) & 1 else 1.0 - ty) * (tz if (r >> 2) & 1 else 1.0 - tz)
            if w != 0.0:
                v += w * coarse[parent_nodes[p, r]]
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
        s = 0.0
        for q in range(8):
            xe[q] = x[cell_nodes[c, q]]
            s += xe[q]
        for a in range(8):
            v = kd * xe[a] + f * (s - xe[a] - xe[a ^ 1] - xe[a ^ 2] - xe[a ^ 4])
            if screen:
                for b in range(8):
                    v += cell_screen[c, a, b] * xe[b]
            out[cell_nodes[c, a]] += v


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
def stiffness_diag(cell_nodes, ke, n_nodes):
    out = np.zeros(n_nodes)
    for c in range(cell_nodes.shape[0]):
        for a in range(8):
            out[cell_nodes[c, a]] += ke[a, a]
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
            v += _tri_w(loc, i, r) * x[cell_nodes[c, r]]
        out[i] = v
    return out


@njit(cache=True)
def screening_matvec(cell, loc, cell_nodes, weight, x, out):
    """out += sum_p weight_p B_i(p) sum_j B_j(p) x_j."""
    for i in range(len(cell)):
        c = cell[i]
        v = 0.0
        for r in range(8):
            v += _tri_w(loc, i, r) * x[cell_nodes[c, r]]
        v *= weight[i]
        if v != 0.0:
            for r in range(8):
                out[cell_nodes[c, r]] += _tri_w(loc, i, r) * v


@njit(cache=True)
def screening_diag_rhs(cell, loc, cell_nodes, weight, target, n_nodes):
    """Diagonal of the screening operator and its right-hand side sum_p w_p t B_i(p)."""
    diag = np.zeros(n_nodes)
    rhs = np.zeros(n_nodes)
    for i in range(len(cell)):
        c = cell[i]
        for r in range(8):
            w = _tri_w(loc, i, r)
            diag[cell_nodes[c, r]] += weight[i] * w * w
            rhs[cell_nodes[c, r]] += weight[i] * target * w
    return diag, rhs


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
def refine_leaves(leaf_xyz, leaf_vals, level, depth, iso, eps):
    """Finest-lattice cells (and their corner values) inside leaves that straddle ``iso``.

    A leaf at ``level`` holds a trilinear function (its 8 corner values); it is split
    into octants, evaluated exactly, down to ``depth``, keeping only octants whose corner
    range reaches ``iso`` within ``eps``.
    """
    n = leaf_xyz.shape[0]
    cap = 1024
    out_xyz = np.empty((cap, 3), np.int64)
    out_val = np.empty((cap, 8))
    m = 0
    steps = depth - level
    side = 1 << steps
    stack_xyz = np.empty((8 * (steps + 1) + 8, 3), np.int64)
    stack_lvl = np.empty(8 * (steps + 1) + 8, np.int64)
    vals = np.empty(8)
    for c in range(n):
        lo = leaf_vals[c, 0]
        hi = leaf_vals[c, 0]
        for q in range(1, 8):
            lo = min(lo, leaf_vals[c, q])
            hi = max(hi, leaf_vals[c, q])
        if lo > iso + eps or hi < iso - eps:
            continue
        # sub-cells addressed in finest units relative to the leaf's lower corner
        top = 0
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
                    v += w * leaf_vals[c, r]
                vals[q] = v
                lo = min(lo, v)
                hi = max(hi, v)
            if lo > iso + eps or hi < iso - eps:
                continue
            if sl == steps:
                if m == cap:
                    cap *= 2
                    nx = np.empty((cap, 3), np.int64)
                    nv = np.empty((cap, 8))
                    nx[:m] = out_xyz[:m]
                    nv[:m] = out_val[:m]
                    out_xyz = nx
                    out_val = nv
                out_xyz[m, 0] = leaf_xyz[c, 0] * side + sx
                out_xyz[m, 1] = leaf_xyz[c, 1] * side + sy
                out_xyz[m, 2] = leaf_xyz[c, 2] * side + sz
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
    return out_xyz[:m], out_val[:m]


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
def level_pcg(cell_nodes, ke, cell_screen, scell, sloc, sw, rhs, diag, unknown, tol, max_iter):
    """Jacobi-preconditioned conjugate gradients on the unknown nodes (others stay 0).

    ``rhs`` is overwritten by the residual and ``diag`` by the inverse diagonal: at the
    finest level every (n,) vector is tens of MB, so the solver keeps only x, p, q besides.
    Returns (x, iterations, relative residual).
    """
    n = len(rhs)
    x = np.zeros(n)
    r = rhs
    inv = diag
    bn = 0.0
    rz = 0.0
    for i in range(n):
        if not unknown[i]:
            r[i] = 0.0
        inv[i] = 1.0 / diag[i] if (unknown[i] and diag[i] > 0.0) else 0.0
        bn += r[i] * r[i]
        rz += r[i] * r[i] * inv[i]
    bn = np.sqrt(bn)
    if bn == 0.0:
        return x, 0, 0.0
    p = r * inv
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
        rr = 0.0
        rz_new = 0.0
        for i in range(n):
            x[i] += a * p[i]
            r[i] -= a * q[i]
            rr += r[i] * r[i]
            rz_new += r[i] * r[i] * inv[i]
        it += 1
        rel = np.sqrt(rr) / bn
        if rel < tol:
            break
        beta = rz_new / rz
        for i in range(n):
            p[i] = r[i] * inv[i] + beta * p[i]
        rz = rz_new
    return x, it, rel


@njit(cache=True)
def clamp_on_faces(node_keys, g, top, value):
    """g = min(g, value) at the nodes on the faces of the cube (coordinate 0 or ``top``), in place."""
    for j in range(len(node_keys)):
        k = node_keys[j]
        x = (k >> 42) & MASK21
        y = (k >> 21) & MASK21
        z = k & MASK21
        if x == 0 or y == 0 or z == 0 or x == top or y == top or z == top:
            if g[j] > value:
                g[j] = value


@njit(cache=True)
def straddling_leaves(cell_nodes, is_leaf, g, iso, eps):
    """Indices of the leaf cells whose corner values reach ``iso`` within ``eps`` (a trilinear
    cell only holds the level set if its corner range does)."""
    out = np.empty(cell_nodes.shape[0], np.int64)
    m = 0
    for c in range(cell_nodes.shape[0]):
        if not is_leaf[c]:
            continue
        lo = g[cell_nodes[c, 0]]
        hi = lo
        for q in range(1, 8):
            v = g[cell_nodes[c, q]]
            lo = min(lo, v)
            hi = max(hi, v)
        if lo <= iso + eps and hi >= iso - eps:
            out[m] = c
            m += 1
    return out[:m]


@njit(cache=True)
def children_sorted(parent_keys):
    """Sorted keys of the 8 children of each of the sorted ``parent_keys``, and the index of
    each child's parent.

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
        ie = i
        while ie < n and ((parent_keys[ie] >> 42) & MASK21) == px:
            ie += 1
        for cx in range(2):
            j = i
            while j < ie:
                py = (parent_keys[j] >> 21) & MASK21
                je = j
                while je < ie and ((parent_keys[je] >> 21) & MASK21) == py:
                    je += 1
                for cy in range(2):
                    for k in range(j, je):
                        pz = parent_keys[k] & MASK21
                        for cz in range(2):
                            out[m] = _key(2 * px + cx, 2 * py + cy, 2 * pz + cz)
                            par[m] = k
                            m += 1
                j = je
        i = ie
    return out, par


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
