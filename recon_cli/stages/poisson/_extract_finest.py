"""Numba kernels of the finest-lattice extraction and of the leaves that straddle the iso-value.

Leaves refined to the finest lattice where they straddle the iso-value, one value per lattice
point (:func:`refine_leaves`, :func:`unify_corner_values`), and the test of which leaves
straddle it (:func:`straddles`); :mod:`.extract` drives them. They only compute; conventions
in :mod:`recon_cli.stages.poisson._octree`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli.stages.poisson._extract import clamp_faces
from recon_cli.stages.poisson._octree import MASK21, lattice_key


@njit(cache=True, inline="always")
def _on_face(x, y, z, res):
    return x == 0 or y == 0 or z == 0 or x == res or y == res or z == res


@njit(cache=True)
def refine_leaves(
    cell_keys, cell_nodes, is_leaf, g, level, depth, iso, eps, margin, out_xyz, out_val
):
    """Finest-lattice cells (and their corner values) inside leaves that straddle ``iso``.

    A leaf at ``level`` holds a trilinear function (its 8 corner values of ``g``); a leaf
    whose value range reaches ``iso`` within ``eps`` is split into octants, evaluated
    exactly, down to ``depth``, keeping only octants whose range reaches it too. Values are
    negated (marching cubes puts values below its iso-value inside, chi is 1 inside).
    On the faces of the cube the value is clamped to at most ``iso - margin`` (outside), so
    a surface running into them is closed there; the clamp is applied to lattice points,
    whichever leaf evaluates them, so leaves of different levels agree (clamping the nodes
    of each level would not: a finer level's nodes are prolonged from unclamped values).
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
    # the range tests: negated, the clamp (then) only raises values
    limits = (niso - eps, niso + eps, niso + margin, np.int64(1) << depth)
    for c in range(cell_nodes.shape[0]):
        if not is_leaf[c]:
            continue
        for q in range(4):
            j = cell_nodes[c, q]
            leaf_vals[q] = -g[j]
            leaf_vals[q + 4] = -g[j + 1]
        k = cell_keys[c]
        org = (((k >> 42) & MASK21) * side, ((k >> 21) & MASK21) * side, (k & MASK21) * side)
        if not _leaf_reaches(leaf_vals, org, side, limits):
            continue
        # sub-cells addressed in finest units relative to the leaf's lower corner
        stack_xyz[0, 0] = 0
        stack_xyz[0, 1] = 0
        stack_xyz[0, 2] = 0
        stack_lvl[0] = 0
        top = 1
        while top > 0:
            top -= 1
            sub = (stack_xyz[top, 0], stack_xyz[top, 1], stack_xyz[top, 2])
            sl = stack_lvl[top]
            size = side >> sl
            if not _subcell_values(leaf_vals, org, sub, size, side, limits, vals):
                continue
            if sl == steps:
                if not count_only:
                    for a in range(3):
                        out_xyz[m, a] = org[a] + sub[a]
                    for q in range(8):
                        out_val[m, q] = vals[q]
                m += 1
                continue
            half = size >> 1
            for o in range(8):
                stack_xyz[top, 0] = sub[0] + (o & 1) * half
                stack_xyz[top, 1] = sub[1] + ((o >> 1) & 1) * half
                stack_xyz[top, 2] = sub[2] + ((o >> 2) & 1) * half
                stack_lvl[top] = sl + 1
                top += 1
    return m


@njit(cache=True, inline="always")
def _leaf_reaches(leaf_vals, org, side, limits):
    """Whether a leaf's (negated) corner range reaches the iso-value (:func:`refine_leaves`).

    ``leaf_vals`` (8,) its corner values, ``org`` its lower corner and ``side`` its size
    (finest-lattice units); ``limits`` is ``(low, high, cap, res)``: the range must reach
    [low, high], a corner on the cube's faces (``res`` cells per axis) is raised to ``cap``.
    The clamp only raises values: the low end is the corners' raw minimum (a trilinear
    function's range is its corners'), the high end may be a clamped corner.
    """
    low, high, cap, res = limits
    lo = 1e300
    hi = -1e300
    for q in range(8):
        v = leaf_vals[q]
        lo = min(lo, v)
        if _on_face(
            org[0] + (q & 1) * side, org[1] + ((q >> 1) & 1) * side, org[2] + (q >> 2) * side, res
        ):
            v = max(v, cap)
        hi = max(hi, v)
    return not (lo > high or hi < low)


@njit(cache=True)
def _subcell_values(leaf_vals, org, sub, size, side, limits, vals):
    """A sub-cell's corner values into ``vals`` (8,); whether their range reaches the iso-value.

    The sub-cell of ``size`` at ``sub`` from the lower corner ``org`` of its leaf of ``side``
    (finest-lattice units), the leaf's trilinear function evaluated exactly, clamped on the
    cube's faces (``limits`` as :func:`_leaf_reaches`').
    """
    low, high, cap, res = limits
    lo = 1e300
    hi = -1e300
    for q in range(8):
        fx = (sub[0] + (q & 1) * size) / side
        fy = (sub[1] + ((q >> 1) & 1) * size) / side
        fz = (sub[2] + ((q >> 2) & 1) * size) / side
        v = 0.0
        for r in range(8):
            w = (
                (fx if r & 1 else 1.0 - fx)
                * (fy if (r >> 1) & 1 else 1.0 - fy)
                * (fz if (r >> 2) & 1 else 1.0 - fz)
            )
            v += w * leaf_vals[r]
        lo = min(lo, v)
        if _on_face(
            org[0] + sub[0] + (q & 1) * size,
            org[1] + sub[1] + ((q >> 1) & 1) * size,
            org[2] + sub[2] + ((q >> 2) & 1) * size,
            res,
        ):
            v = max(v, cap)
        vals[q] = v
        hi = max(hi, v)
    return not (lo > high or hi < low)


@njit(cache=True)
def corner_keys(cells):
    """(8c,) keys of the corners of lattice cells (c, 3), corner ``q`` of cell ``i`` at 8 i + q."""
    n = cells.shape[0]
    out = np.empty(8 * n, np.int64)
    for i in range(n):
        k = lattice_key(cells[i, 0], cells[i, 1], cells[i, 2])
        for q in range(8):
            out[8 * i + q] = k + (((q & 1) << 42) | (((q >> 1) & 1) << 21) | ((q >> 2) & 1))
    return out


@njit(cache=True)
def unify_corner_values(vals, keys, order):
    """Give every lattice point one value, whichever cell computed it, in place.

    ``vals`` (c, 8) corner values of finest-lattice cells, ``keys`` the (8c,) lattice keys
    of the corners (flat corner index ``8 * cell + corner``) and ``order`` their argsort
    (read through it: no sorted copy). Each run of equal keys takes the value of its first
    member.
    """
    n = len(order)
    i = 0
    while i < n:
        f = order[i]
        k = keys[f]
        v = vals[f >> 3, f & 7]
        j = i + 1
        while j < n and keys[order[j]] == k:
            g = order[j]
            vals[g >> 3, g & 7] = v
            j += 1
        i = j


@njit(cache=True)
def straddles(cell_keys, cell_nodes, is_leaf, g, level, depth, iso, eps, margin):
    """Whether a leaf of ``level`` has a corner range reaching ``iso`` within ``eps``.

    Chi is clamped to ``iso - margin`` at points on the cube's faces: the range is [clamped
    minimum, raw maximum]. The test of :func:`leaf_polygons`, stopping at the first such leaf.
    """
    side = np.int64(1) << (depth - level)
    R = np.int64(1) << depth
    cap = iso - margin
    for c in range(cell_nodes.shape[0]):
        if not is_leaf[c]:
            continue
        k = cell_keys[c]
        cx = (k >> 42) & MASK21
        cy = (k >> 21) & MASK21
        cz = k & MASK21
        lo = 1e300
        hi = -1e300
        for q in range(8):
            v = g[cell_nodes[c, q & 3] + (q >> 2)]
            hi = max(hi, v)
            lo = min(
                lo,
                clamp_faces(
                    v,
                    (cx + (q & 1)) * side,
                    (cy + ((q >> 1) & 1)) * side,
                    (cz + (q >> 2)) * side,
                    R,
                    cap,
                ),
            )
        if not (lo > iso + eps or hi < iso - eps):
            return True
    return False
