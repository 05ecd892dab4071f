"""Numba kernels of the generalised winding number (Jacobson et al. 2013; Barill et al. 2018).

The winding number at ``p`` is the sum of the signed solid angles of the triangles seen
from ``p``, over 4 pi. The hierarchical version walks the BVH of
:mod:`recon_cli.mesh._distance_kernel`: a node far from ``p`` (distance > beta * its radius)
contributes as a dipole (its area-weighted normal sum placed at its area centroid);
near nodes are opened down to exact triangles.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli.mesh._distance_kernel import triangle_cross

FOUR_PI = 4.0 * np.pi
STACK = 128


@njit(cache=True, inline="always")
def _solid_angle(px, py, pz, tri, t):
    """Signed solid angle of triangle ``tri[t]`` seen from p (Van Oosterom & Strackee 1983).

    Takes scalars and an index: array views would cost reference counting per triangle.
    """
    a0 = tri[t, 0, 0] - px
    a1 = tri[t, 0, 1] - py
    a2 = tri[t, 0, 2] - pz
    b0 = tri[t, 1, 0] - px
    b1 = tri[t, 1, 1] - py
    b2 = tri[t, 1, 2] - pz
    c0 = tri[t, 2, 0] - px
    c1 = tri[t, 2, 1] - py
    c2 = tri[t, 2, 2] - pz
    la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
    den = la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (a0 * c0 + a1 * c1 + a2 * c2) * lb
    den += (b0 * c0 + b1 * c1 + b2 * c2) * la
    return 2.0 * np.arctan2(det, den)


@njit(cache=True, parallel=True)
def winding_exact(points, tri):
    """Exact winding number of each point: O(points x triangles)."""
    k = points.shape[0]
    out = np.empty(k, np.float64)
    for s in prange(k):
        acc = 0.0
        px, py, pz = points[s, 0], points[s, 1], points[s, 2]
        for t in range(tri.shape[0]):
            acc += _solid_angle(px, py, pz, tri, t)
        out[s] = acc / FOUR_PI
    return out


@njit(cache=True)
def node_dipoles(tri, left, right, start, end, lo, hi):
    """Per node: area vector sum (m, 3), area centroid (m, 3), radius of a ball around it."""
    m = left.shape[0]
    dip = np.zeros((m, 3), np.float64)
    cen = np.zeros((m, 3), np.float64)
    area = np.zeros(m, np.float64)
    rad = np.zeros(m, np.float64)
    for node in range(m - 1, -1, -1):  # children after parents
        if left[node] < 0:
            for t in range(start[node], end[node]):
                c0, c1, c2 = triangle_cross(tri, t)
                n0, n1, n2 = 0.5 * c0, 0.5 * c1, 0.5 * c2
                ar = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
                dip[node, 0] += n0
                dip[node, 1] += n1
                dip[node, 2] += n2
                area[node] += ar
                for ax in range(3):
                    cen[node, ax] += ar * (tri[t, 0, ax] + tri[t, 1, ax] + tri[t, 2, ax]) / 3.0
        else:
            a = left[node]
            b = right[node]
            area[node] = area[a] + area[b]
            for ax in range(3):
                dip[node, ax] = dip[a, ax] + dip[b, ax]
                cen[node, ax] = cen[a, ax] * area[a] + cen[b, ax] * area[b]
        if area[node] > 0.0:
            for ax in range(3):
                cen[node, ax] /= area[node]
        else:
            for ax in range(3):
                cen[node, ax] = 0.5 * (lo[node, ax] + hi[node, ax])
        # radius: farthest box corner from the centroid bounds every triangle of the node
        r2 = 0.0
        for ax in range(3):
            d = max(cen[node, ax] - lo[node, ax], hi[node, ax] - cen[node, ax])
            r2 += d * d
        rad[node] = np.sqrt(r2)
    return dip, cen, rad


@njit(cache=True)
def _winding_one(p, tri, left, right, start, end, dip, cen, rad, beta2, stack):
    acc = 0.0
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        d0 = cen[node, 0] - p[0]
        d1 = cen[node, 1] - p[1]
        d2 = cen[node, 2] - p[2]
        r2 = d0 * d0 + d1 * d1 + d2 * d2
        if r2 > beta2 * rad[node] * rad[node]:
            # far field: dipole term of the node's surface
            acc += (d0 * dip[node, 0] + d1 * dip[node, 1] + d2 * dip[node, 2]) / (r2 * np.sqrt(r2))
            continue
        if left[node] < 0:
            for t in range(start[node], end[node]):
                acc += _solid_angle(p[0], p[1], p[2], tri, t)
            continue
        stack[top] = left[node]
        top += 1
        stack[top] = right[node]
        top += 1
    return acc / FOUR_PI


@njit(cache=True, parallel=True)
def winding_tree(points, tri, left, right, start, end, dip, cen, rad, beta):
    """Hierarchical winding number of each point."""
    k = points.shape[0]
    out = np.empty(k, np.float64)
    chunk = 256
    nchunks = (k + chunk - 1) // chunk
    for ci in prange(nchunks):
        stack = np.empty(STACK, np.int64)
        for s in range(ci * chunk, min(k, (ci + 1) * chunk)):
            out[s] = _winding_one(
                points[s], tri, left, right, start, end, dip, cen, rad, beta * beta, stack
            )
    return out
