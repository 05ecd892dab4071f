"""Numba kernels of one level's linear system.

Trilinear stiffness and screening operators, prolongation from the coarser level,
Jacobi-preconditioned conjugate gradients.

They only compute; conventions in :mod:`recon_cli.stages.poisson._octree`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli.stages.poisson._octree import bsearch, corner, lattice_key


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
                w = (
                    (tx if r & 1 else 1.0 - tx)
                    * (ty if (r >> 1) & 1 else 1.0 - ty)
                    * (tz if (r >> 2) & 1 else 1.0 - tz)
                )
                if w != 0.0:
                    v += w * coarse[corner(parent_nodes, p, r)]
            out[j] = v
    return out


@njit(cache=True)
def stiffness_matvec(cell_nodes, ke, cell_screen, x, out):
    """Out += sum over cells of the element matrix ``ke`` (8x8) applied to the corner values.

    Plus the cell's own (8x8) screening matrix when ``cell_screen`` (c, 8, 8) is not empty.

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
    """Per cell, the screening matrix sum_p w_p B_a(p) B_b(p) of the samples in it (c, 8, 8).

    Applying it costs per cell, not per sample, where samples outnumber cells.
    """
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
    """Diagonal of the stiffness matrix at a node with k (0..8) incident cells.

    Summed cell by cell as an assembly would. Every corner has the same ``ke[a, a]`` (the cube's
    symmetry), so the diagonal is a function of k alone: the solver looks it up instead of
    keeping an (n,) vector.
    """
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
        cell[i] = bsearch(cell_keys, lattice_key(c0, c1, c2))
        loc[i, 0] = pos[i, 0] * scale - c0
        loc[i, 1] = pos[i, 1] * scale - c1
        loc[i, 2] = pos[i, 2] * scale - c2
    return cell, loc


@njit(cache=True, inline="always")
def _tri_w(loc, i, r):
    tx = loc[i, 0]
    ty = loc[i, 1]
    tz = loc[i, 2]
    return (
        (tx if r & 1 else 1.0 - tx)
        * (ty if (r >> 1) & 1 else 1.0 - ty)
        * (tz if (r >> 2) & 1 else 1.0 - tz)
    )


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
    """Out += sum_p weight_p B_i(p) sum_j B_j(p) x_j."""
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
    """Diagonal of the screening operator, and rhs += its right-hand side, in place.

    The right-hand side is sum_p w_p t B_i(p).

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


@njit(cache=True)
def level_matvec(cell_nodes, ke, cell_screen, scell, sloc, sw, x, out):
    """Out = A x: stiffness, per-cell screening matrices if any, per-sample screening if any."""
    out[:] = 0.0
    stiffness_matvec(cell_nodes, ke, cell_screen, x, out)
    if len(sw):
        screening_matvec(scell, sloc, cell_nodes, sw, x, out)


@njit(cache=True)
def _residual_update(x, r, p, q, a, ncell, stiff, inv_stiff, sd_nodes, sd_vals, unknown):
    """X += a p, r -= a q, q = the preconditioned residual; returns (r.r, r.z).

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


@njit(cache=True, nogil=True)  # the progress display keeps drawing while it runs
def level_pcg(
    cell_nodes, ke, cell_screen, samples, rhs, ncell, sd_nodes, sd_vals, unknown, tol, max_iter
):
    """Jacobi-preconditioned conjugate gradients on the unknown nodes (others stay 0).

    The diagonal is not stored: it is the stiffness diagonal at each node's incident-cell
    count ``ncell`` (:func:`stiffness_diag_table`) plus the sparse screening diagonal
    (``sd_nodes`` sorted, ``sd_vals``), inverted in each pass; ``rhs`` is overwritten by the
    residual. At the finest level every (n,) vector is tens of MB, so the solver keeps only
    x, p, q besides. ``samples`` is the screening's ``(scell, sloc, sw)`` and ``cell_screen``
    its per-cell part (:func:`level_matvec`). Returns (x, iterations, relative residual).
    """
    scell, sloc, sw = samples
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
        rr, rz_new = _residual_update(
            x, r, p, q, a, ncell, stiff, inv_stiff, sd_nodes, sd_vals, unknown
        )
        it += 1
        rel = np.sqrt(rr) / bn
        if rel < tol:
            break
        beta = rz_new / rz
        for i in range(n):
            p[i] = q[i] + beta * p[i]
        rz = rz_new
    return x, it, rel
