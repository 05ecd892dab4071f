"""Numba kernels of :mod:`recon_cli.stages.filter`: they only compute, the stage validates.

Cells of a regular grid are keyed by their three integer coordinates in an open-addressing
hash table (linear probing, at most half full), so any extent and cell size works without a
dense array or a linearised key that could overflow.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.hashtable import table_bits

_P1 = np.uint64(0x9E3779B97F4A7C15)
_P2 = np.uint64(0xC2B2AE3D27D4EB4F)
_P3 = np.uint64(0x165667B19E3779F9)


@njit(cache=True, inline="always")
def _slot(ix, iy, iz, bits):
    h = np.uint64(ix) * _P1 ^ np.uint64(iy) * _P2 ^ np.uint64(iz) * _P3
    h ^= h >> np.uint64(29)
    return np.int64((h * _P1) >> np.uint64(64 - bits))


@njit(cache=True, inline="always")
def _find(tk, bits, ix, iy, iz):
    """The slot of cell (ix, iy, iz), or the empty slot where it would go (``tk[s, 0] == -1``)."""
    mask = (1 << bits) - 1
    s = _slot(ix, iy, iz, bits)
    while tk[s, 0] != -1 and (tk[s, 0] != ix or tk[s, 1] != iy or tk[s, 2] != iz):
        s = (s + 1) & mask
    return s


@njit(cache=True)
def grid_cells(pts, lo, size):
    """The grid cell of every point, numbered in the order of each cell's first point.

    Parameters
    ----------
    pts : (n, 3) float64
    lo : (3,) float64
        Corner of cell (0, 0, 0); every point is at or above it.
    size : float64
        Cell edge.

    Returns
    -------
    cell : (n,) int64
        The cell index of each point.
    first : (m,) int64
        The first point of each cell.
    keys : (m, 3) int64
        The integer coordinates of each cell: ``floor((p - lo) / size)``.
    tk, tv, bits
        The hash table: integer coordinates -> cell index.
    """
    n = pts.shape[0]
    bits = table_bits(n)
    tk = np.full((1 << bits, 3), -1, np.int64)
    tv = np.empty(1 << bits, np.int64)
    cell = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    keys = np.empty((n, 3), np.int64)
    m = 0
    for i in range(n):
        ix = np.int64(math.floor((pts[i, 0] - lo[0]) / size))
        iy = np.int64(math.floor((pts[i, 1] - lo[1]) / size))
        iz = np.int64(math.floor((pts[i, 2] - lo[2]) / size))
        s = _find(tk, bits, ix, iy, iz)
        if tk[s, 0] == -1:
            tk[s, 0] = ix
            tk[s, 1] = iy
            tk[s, 2] = iz
            tv[s] = m
            first[m] = i
            keys[m, 0] = ix
            keys[m, 1] = iy
            keys[m, 2] = iz
            m += 1
        cell[i] = tv[s]
    return cell, first[:m].copy(), keys[:m].copy(), tk, tv, bits


@njit(cache=True)
def cell_members(cell, m):
    """Points grouped by cell: ``start`` (m + 1,) and ``members`` (n,), each cell's points in
    their input order (a counting sort)."""
    n = cell.shape[0]
    start = np.zeros(m + 1, np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for c in range(m):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(n, np.int64)
    for i in range(n):
        c = cell[i]
        members[fill[c]] = i
        fill[c] += 1
    return start, members


@njit(cache=True, parallel=True)
def cell_modes(start, members, values):
    """The most frequent of ``values`` (int64) among each cell's points; ties go to the smallest."""
    m = start.shape[0] - 1
    out = np.empty(m, np.int64)
    for c in prange(m):
        a, b = start[c], start[c + 1]
        buf = np.empty(b - a, np.int64)
        for t in range(a, b):
            buf[t - a] = values[members[t]]
        buf.sort()
        best = buf[0]
        best_run = 0
        run = 0
        for t in range(b - a):
            run = run + 1 if t > 0 and buf[t] == buf[t - 1] else 1
            if run > best_run:  # a strictly longer run: the smaller value keeps a tie
                best_run = run
                best = buf[t]
        out[c] = best
    return out


@njit(cache=True, parallel=True)
def radius_keep(pts, lo, size, radius, more_than):
    """Whether more than ``more_than`` points (the point itself included) lie at a distance
    strictly below ``radius`` of each point.

    ``size`` >= ``radius`` is the edge of the grid that finds the candidates (the 27 cells
    around a point's own); a point's count stops as soon as it exceeds ``more_than``.
    """
    n = pts.shape[0]
    cell, first, keys, tk, tv, bits = grid_cells(pts, lo, size)
    m = first.shape[0]
    start, members = cell_members(cell, m)
    r2 = radius * radius
    keep = np.zeros(n, np.bool_)
    for c in prange(m):
        # the neighbour cells once per cell, then every point of the cell against them
        nb = np.empty(27, np.int64)
        k = 0
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    s = _find(tk, bits, keys[c, 0] + dx, keys[c, 1] + dy, keys[c, 2] + dz)
                    if tk[s, 0] != -1:
                        nb[k] = tv[s]
                        k += 1
        for t in range(start[c], start[c + 1]):
            i = members[t]
            px = pts[i, 0]
            py = pts[i, 1]
            pz = pts[i, 2]
            count = 0
            for q in range(k):
                d = nb[q]
                for u in range(start[d], start[d + 1]):
                    j = members[u]
                    ex = px - pts[j, 0]
                    ey = py - pts[j, 1]
                    ez = pz - pts[j, 2]
                    if ex * ex + ey * ey + ez * ez < r2:
                        count += 1
                if count > more_than:
                    break
            keep[i] = count > more_than
    return keep


@njit(cache=True, parallel=True)
def row_means(d):
    """Mean of each row of ``d`` (n, k), summed left to right."""
    n, k = d.shape
    out = np.empty(n)
    for i in prange(n):
        s = 0.0
        for j in range(k):
            s += d[i, j]
        out[i] = s / k
    return out


@njit(cache=True)
def statistical_keep(mean_dist, std_ratio):
    """Open3D's statistical outlier rule on each point's mean neighbour distance.

    The mean and the (Bessel-corrected) standard deviation are over the positive distances
    but divided by counts of every point, summed in point order; a point is kept when its
    distance is positive and below ``mean + std_ratio * std``. Returns (keep, mean, std).
    """
    n = mean_dist.shape[0]
    s = 0.0
    for i in range(n):
        if mean_dist[i] > 0.0:
            s += mean_dist[i]
    mean = s / n
    sq = 0.0
    for i in range(n):
        x = mean_dist[i]
        if x > 0.0:
            sq += (x - mean) * (x - mean)
    std = math.sqrt(sq / (n - 1)) if n > 1 else math.nan
    threshold = mean + std_ratio * std
    keep = np.empty(n, np.bool_)
    for i in range(n):
        keep[i] = mean_dist[i] > 0.0 and mean_dist[i] < threshold
    return keep, mean, std
