"""Numba kernels of the software rasteriser: visibility only (no colour logic).

Both kernels fill, per pixel, the nearest primitive's depth and index (z-buffer); the
triangle kernel also fills the barycentric coordinates, from which :mod:`recon_cli.eval.render`
interpolates colours or scalars with numpy.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def rasterize_triangles(sx, sy, sz, faces, depth, face_id, bary):
    """Z-buffer the triangles ``faces`` with screen vertices (``sx``, ``sy``) and depth ``sz``.

    A pixel (row i, column j) is covered when its centre (j + 0.5, i + 0.5) is inside the
    triangle (either winding, so back faces of open meshes show). Smaller depth is nearer.
    ``depth`` (H, W) starts at +inf, ``face_id`` (H, W) at -1; ``bary`` is (H, W, 3).
    """
    h, w = depth.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        x0, y0, z0 = sx[a], sy[a], sz[a]
        x1, y1, z1 = sx[b], sy[b], sz[b]
        x2, y2, z2 = sx[c], sy[c], sz[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0 or not np.isfinite(area):
            continue
        # pixel range whose centres can be inside
        jmin = max(int(np.ceil(min(x0, x1, x2) - 0.5)), 0)
        jmax = min(int(np.floor(max(x0, x1, x2) - 0.5)), w - 1)
        imin = max(int(np.ceil(min(y0, y1, y2) - 0.5)), 0)
        imax = min(int(np.floor(max(y0, y1, y2) - 0.5)), h - 1)
        inv = 1.0 / area
        for i in range(imin, imax + 1):
            py = i + 0.5
            for j in range(jmin, jmax + 1):
                px = j + 0.5
                w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
                w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * z0 + w1 * z1 + w2 * z2
                if z < depth[i, j]:
                    depth[i, j] = z
                    face_id[i, j] = f
                    bary[i, j, 0] = w0
                    bary[i, j, 1] = w1
                    bary[i, j, 2] = w2


@njit(cache=True)
def splat_points(sx, sy, sz, radius, depth, point_id):
    """Z-buffer points drawn as discs of ``radius`` pixels (clouds)."""
    h, w = depth.shape
    r2 = radius * radius
    for p in range(sx.shape[0]):
        x, y, z = sx[p], sy[p], sz[p]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        jmin = max(int(np.ceil(x - radius - 0.5)), 0)
        jmax = min(int(np.floor(x + radius - 0.5)), w - 1)
        imin = max(int(np.ceil(y - radius - 0.5)), 0)
        imax = min(int(np.floor(y + radius - 0.5)), h - 1)
        for i in range(imin, imax + 1):
            dy = i + 0.5 - y
            for j in range(jmin, jmax + 1):
                dx = j + 0.5 - x
                if dx * dx + dy * dy <= r2 and z < depth[i, j]:
                    depth[i, j] = z
                    point_id[i, j] = p


@njit(cache=True)
def draw_segments(sx, sy, sz, edges, tol, half_width, depth, code, value):
    """Mark the visible pixels of the segments ``edges`` (k, 2) with ``value`` in ``code``.

    A segment is walked in steps of at most half a pixel; every pixel centre within
    ``half_width`` pixels (square pen) of a step is marked when the step's depth is at most
    ``depth[i, j] + tol`` (the segment lies on, or in front of, the visible surface).
    ``code`` (H, W) int8 keeps the largest value written (later kinds win ties).
    """
    h, w = depth.shape
    for e in range(edges.shape[0]):
        a, b = edges[e, 0], edges[e, 1]
        x0, y0, z0 = sx[a], sy[a], sz[a]
        x1, y1, z1 = sx[b], sy[b], sz[b]
        if not (np.isfinite(x0) and np.isfinite(y0) and np.isfinite(x1) and np.isfinite(y1)):
            continue
        steps = int(max(abs(x1 - x0), abs(y1 - y0)) * 2.0) + 1
        for s in range(steps + 1):
            t = s / steps
            x = x0 + t * (x1 - x0)
            y = y0 + t * (y1 - y0)
            z = z0 + t * (z1 - z0)
            jmin = max(int(np.ceil(x - half_width - 0.5)), 0)
            jmax = min(int(np.floor(x + half_width - 0.5)), w - 1)
            imin = max(int(np.ceil(y - half_width - 0.5)), 0)
            imax = min(int(np.floor(y + half_width - 0.5)), h - 1)
            for i in range(imin, imax + 1):
                for j in range(jmin, jmax + 1):
                    if z <= depth[i, j] + tol and code[i, j] < value:
                        code[i, j] = value
