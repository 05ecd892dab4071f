"""Numba kernels of :mod:`recon_cli.stages.filter`: they only compute, the stage validates.

Cells of a regular grid are found in an open-addressing hash table (linear probing, at most
half full) keyed by the cell's integer coordinates packed into one int64 (``ix + nx * (iy +
ny * iz)``) when the points' box holds fewer than 2**62 cells, else by the three coordinates
(a slower table for extreme ratios of extent to cell size), so any extent and cell works.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.hashtable import probe, table_bits

_P1 = np.uint64(0x9E3779B97F4A7C15)
_P2 = np.uint64(0xC2B2AE3D27D4EB4F)
_P3 = np.uint64(0x165667B19E3779F9)
# boxes of fewer cells than this get packed int64 keys
_PACKED = 2.0**62


@njit(cache=True)
def bounds(pts):
    """The minimum and maximum corners (3,) of ``pts`` (n >= 1, finite), in one pass."""
    lo = pts[0].copy()
    hi = pts[0].copy()
    for i in range(1, pts.shape[0]):
        for a in range(3):
            v = pts[i, a]
            if v < lo[a]:
                lo[a] = v
            elif v > hi[a]:
                hi[a] = v
    return lo, hi


@njit(cache=True)
def finite_rows(pts):
    """Whether each row of ``pts`` (n, 3) has three finite coordinates."""
    n = pts.shape[0]
    out = np.empty(n, np.bool_)
    for i in range(n):
        out[i] = math.isfinite(pts[i, 0]) and math.isfinite(pts[i, 1]) and math.isfinite(pts[i, 2])
    return out


# box_codes' codes
KEPT = 0
INVALID = 1
OUTSIDE = 2


@njit(cache=True)
def box_codes(pts, box):
    """A code per row of ``pts`` (n, 3): 0 kept, 1 a NaN or infinite coordinate, 2 outside.

    ``box`` (x0, y0, z0, x1, y1, z1): a finite row is inside when each coordinate lies
    between the two bounds, faces included (an infinite box keeps every finite row). One pass
    for the invalid points and the crop.
    """
    n = pts.shape[0]
    out = np.empty(n, np.uint8)
    for i in range(n):
        x = pts[i, 0]
        y = pts[i, 1]
        z = pts[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            out[i] = INVALID
        elif (
            x >= box[0]
            and x <= box[3]
            and y >= box[1]
            and y <= box[4]
            and z >= box[2]
            and z <= box[5]
        ):
            out[i] = KEPT
        else:
            out[i] = OUTSIDE
    return out


@njit(cache=True, inline="always")
def _coord(pts, i, a, lo, size):
    return np.int64(math.floor((pts[i, a] - lo[a]) / size))


@njit(cache=True)
def _shape(pts, lo, size):
    """Cells along each axis from ``lo`` to the farthest point, as floats (3,)."""
    _, hi = bounds(pts)
    out = np.empty(3)
    for a in range(3):
        out[a] = math.floor((hi[a] - lo[a]) / size) + 1.0
    return out


# ---- packed keys ---------------------------------------------------------------------------
@njit(cache=True)
def _packed_cells(pts, lo, size, shape):
    n = pts.shape[0]
    nx = np.int64(shape[0])
    ny = np.int64(shape[1])
    bits = table_bits(min(n, np.int64(shape[0] * shape[1] * shape[2])))
    tk = np.full(1 << bits, -1, np.int64)
    tv = np.empty(1 << bits, np.int64)
    cell = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        key = _coord(pts, i, 0, lo, size) + nx * (
            _coord(pts, i, 1, lo, size) + ny * _coord(pts, i, 2, lo, size)
        )
        s = probe(tk, bits, key)
        if tk[s] == -1:
            tk[s] = key
            tv[s] = m
            first[m] = i
            m += 1
        cell[i] = tv[s]
    return cell, first[:m].copy(), tk, tv, bits


# ---- three-coordinate keys -----------------------------------------------------------------
@njit(cache=True, inline="always")
def _slot3(ix, iy, iz, bits):
    h = np.uint64(ix) * _P1 ^ np.uint64(iy) * _P2 ^ np.uint64(iz) * _P3
    h ^= h >> np.uint64(29)
    return np.int64((h * _P1) >> np.uint64(64 - bits))


@njit(cache=True, inline="always")
def _find3(tk, bits, ix, iy, iz):
    """The slot of cell (ix, iy, iz), or the empty slot where it would go (``tk[s, 0] == -1``)."""
    mask = (1 << bits) - 1
    s = _slot3(ix, iy, iz, bits)
    while tk[s, 0] != -1 and (tk[s, 0] != ix or tk[s, 1] != iy or tk[s, 2] != iz):
        s = (s + 1) & mask
    return s


@njit(cache=True)
def _triple_cells(pts, lo, size):
    n = pts.shape[0]
    bits = table_bits(n)
    tk = np.full((1 << bits, 3), -1, np.int64)
    tv = np.empty(1 << bits, np.int64)
    cell = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        ix = _coord(pts, i, 0, lo, size)
        iy = _coord(pts, i, 1, lo, size)
        iz = _coord(pts, i, 2, lo, size)
        s = _find3(tk, bits, ix, iy, iz)
        if tk[s, 0] == -1:
            tk[s, 0] = ix
            tk[s, 1] = iy
            tk[s, 2] = iz
            tv[s] = m
            first[m] = i
            m += 1
        cell[i] = tv[s]
    return cell, first[:m].copy(), tk, tv, bits


@njit(cache=True)
def grid_cells(pts, lo, size):
    """The grid cell of every point, numbered in the order of each cell's first point.

    Parameters
    ----------
    pts : (n, 3) float64
    lo : (3,) float64
        Corner of cell (0, 0, 0); every point is at or above it.
    size : float64
        Cell edge; cell ``floor((p - lo) / size)``.

    Returns
    -------
    cell : (n,) int64
        The cell index of each point.
    first : (m,) int64
        The first point of each cell.
    """
    shape = _shape(pts, lo, size)
    if shape[0] * shape[1] * shape[2] < _PACKED:
        cell, first, _, _, _ = _packed_cells(pts, lo, size, shape)
        return cell, first
    cell, first, _, _, _ = _triple_cells(pts, lo, size)
    return cell, first


# ---- voxel thinning ------------------------------------------------------------------------
@njit(cache=True)
def voxel_grid(pts, size):
    """Open3D's voxel cells of ``pts`` (n >= 1, finite) and their centroids.

    Cells are anchored at ``min - size / 2``: cell ``floor((p - anchor) / size)``, the same
    float64 operations as Open3D's ``VoxelDownSample``. Centroids are summed about the centre
    of the bounding box (digits kept far from the origin).

    Returns
    -------
    cell : (n,) int64
        Each point's cell, cells numbered in the order of their first point.
    first : (m,) int64
        The first point of each cell.
    count : (m,) int64
    centroid : (m, 3) float64
    cells_along : float64
        The largest extent of the anchored box in cells (nothing else is computed above
        2**31 - 1, Open3D's limit, which the caller refuses).
    """
    lo, hi = bounds(pts)
    anchor = lo - size * 0.5
    top = hi + size * 0.5
    along = max(top[0] - anchor[0], top[1] - anchor[1], top[2] - anchor[2]) / size
    if along > 2147483647.0:
        e = np.empty(0, np.int64)
        return e, e, e, np.empty((0, 3)), along
    origin = 0.5 * (lo + hi)
    cell, first = grid_cells(pts, anchor, size)
    m = first.shape[0]
    count = np.zeros(m, np.int64)
    acc = np.zeros((m, 3))
    for i in range(pts.shape[0]):
        c = cell[i]
        count[c] += 1
        for a in range(3):
            acc[c, a] += pts[i, a] - origin[a]
    for c in range(m):
        for a in range(3):
            acc[c, a] = acc[c, a] / count[c] + origin[a]
    return cell, first, count, acc, along


@njit(cache=True)
def cell_means(cell, count, values, skip_nan_rows):
    """Mean of the rows of ``values`` (n, k) float64 in each cell (``count`` (m,) points each).

    With ``skip_nan_rows`` a row holding a NaN adds nothing but still counts (Open3D's
    averaging of normals).
    """
    m = count.shape[0]
    n, k = values.shape
    acc = np.zeros((m, k))
    for i in range(n):
        if skip_nan_rows:
            bad = False
            for a in range(k):
                if math.isnan(values[i, a]):
                    bad = True
            if bad:
                continue
        c = cell[i]
        for a in range(k):
            acc[c, a] += values[i, a]
    for c in range(m):
        for a in range(k):
            acc[c, a] /= count[c]
    return acc


@njit(cache=True)
def _grouped(cell, count):
    """Points grouped by cell (a counting sort): ``start`` (m + 1,), ``members`` (n,)."""
    m = count.shape[0]
    start = np.zeros(m + 1, np.int64)
    for c in range(m):
        start[c + 1] = start[c] + count[c]
    fill = start[:-1].copy()
    members = np.empty(cell.shape[0], np.int64)
    for i in range(cell.shape[0]):
        members[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return start, members


@njit(cache=True)
def cell_modes(cell, count, values):
    """The most frequent of ``values`` (int64) among each cell's points; ties go to the smallest."""
    m = count.shape[0]
    start, members = _grouped(cell, count)
    out = np.empty(m, np.int64)
    buf = np.empty(cell.shape[0], np.int64)
    for c in range(m):
        a, b = start[c], start[c + 1]
        run_values = buf[a:b]
        for t in range(a, b):
            run_values[t - a] = values[members[t]]
        run_values.sort()
        best = run_values[0]
        best_run = 0
        run = 0
        for t in range(b - a):
            run = run + 1 if t > 0 and run_values[t] == run_values[t - 1] else 1
            if run > best_run:  # a strictly longer run: the smaller value keeps a tie
                best_run = run
                best = run_values[t]
        out[c] = best
    return out


# ---- radius outliers -----------------------------------------------------------------------
@njit(cache=True, inline="always")
def _count_cell(pts, start, members, nb, k, c, r2, more_than, keep):
    """Decide every point of cell ``c`` from the points of its ``k`` neighbour cells ``nb``."""
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


@njit(cache=True, parallel=True)
def radius_keep(pts, size, radius, more_than):
    """Whether more than ``more_than`` points lie strictly closer than ``radius`` to each point.

    The point itself is counted.
    ``size`` >= ``radius`` is the edge of the grid that finds the candidates (the 27 cells
    around a point's own); a point's count stops as soon as it exceeds ``more_than``.
    """
    n = pts.shape[0]
    lo, _ = bounds(pts)
    shape = _shape(pts, lo, size)
    r2 = radius * radius
    keep = np.zeros(n, np.bool_)
    if shape[0] * shape[1] * shape[2] < _PACKED:
        nx = np.int64(shape[0])
        ny = np.int64(shape[1])
        nz = np.int64(shape[2])
        cell, first, tk, tv, bits = _packed_cells(pts, lo, size, shape)
        m = first.shape[0]
        start, members = _grouped(cell, np.bincount(cell, minlength=m))
        for c in prange(m):
            nb = np.empty(27, np.int64)
            k = 0
            i0 = first[c]
            ix = _coord(pts, i0, 0, lo, size)
            iy = _coord(pts, i0, 1, lo, size)
            iz = _coord(pts, i0, 2, lo, size)
            for x in range(max(ix - 1, 0), min(ix + 2, nx)):
                for y in range(max(iy - 1, 0), min(iy + 2, ny)):
                    for z in range(max(iz - 1, 0), min(iz + 2, nz)):
                        s = probe(tk, bits, x + nx * (y + ny * z))
                        if tk[s] != -1:
                            nb[k] = tv[s]
                            k += 1
            _count_cell(pts, start, members, nb, k, c, r2, more_than, keep)
        return keep
    cell, first, tk3, tv, bits = _triple_cells(pts, lo, size)
    m = first.shape[0]
    start, members = _grouped(cell, np.bincount(cell, minlength=m))
    for c in prange(m):
        nb = np.empty(27, np.int64)
        k = 0
        i0 = first[c]
        ix = _coord(pts, i0, 0, lo, size)
        iy = _coord(pts, i0, 1, lo, size)
        iz = _coord(pts, i0, 2, lo, size)
        for x in range(ix - 1, ix + 2):
            for y in range(iy - 1, iy + 2):
                for z in range(iz - 1, iz + 2):
                    s = _find3(tk3, bits, x, y, z)
                    if tk3[s, 0] != -1:
                        nb[k] = tv[s]
                        k += 1
        _count_cell(pts, start, members, nb, k, c, r2, more_than, keep)
    return keep


# ---- statistical outliers ------------------------------------------------------------------
@njit(cache=True)
def row_means(d):
    """Mean of each row of ``d`` (n, k), summed left to right."""
    n, k = d.shape
    out = np.empty(n)
    for i in range(n):
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
