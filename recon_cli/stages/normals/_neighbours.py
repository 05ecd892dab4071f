"""The neighbourhoods of the normals' estimate: a kd-tree's, or an organized cloud's pixels'.

Both give the points in a spatially coherent order and CSR neighbour lists in that order
(:func:`neighbourhoods`, :func:`pixel_neighbourhoods`); the stage (:mod:`recon_cli.stages.normals`)
checks their parameters.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from recon_cli.errors import InputError

# rows per kNN query (bounds the temporary memory)
CHUNK = 200_000
# an organized cloud's k nearest are taken among about this many times k pixels around a point
PIXEL_WINDOW = 6.0


def neighbourhoods(pts: np.ndarray, knn: int | None, radius: float | None):
    """Neighbourhoods in a spatially coherent order.

    Returns (order, ps, indptr, indices): ``ps = pts[order]`` and CSR neighbour lists
    indexing ``ps``; kNN and hybrid rows are sorted by distance (the point itself first
    unless it has duplicates).
    """
    from scipy.spatial import cKDTree

    n = len(pts)
    tree = cKDTree(pts)
    # the tree's leaf order is spatially coherent: querying and computing in it is cache friendly
    order = np.asarray(tree.indices, dtype=np.int64)
    ps = np.ascontiguousarray(pts[order])
    inv = np.empty(n + 1, dtype=np.int32)
    inv[order] = np.arange(n, dtype=np.int32)
    inv[n] = n  # cKDTree's "missing" marker
    if knn is not None:
        k = min(knn, n)
        # query in chunks: cKDTree's float64 distances and int64 indices would triple the memory
        idx = np.empty((n, k), dtype=np.int32)
        bound = np.inf if radius is None else radius
        for a in range(0, n, CHUNK):
            _, got = tree.query(ps[a : a + CHUNK], k, distance_upper_bound=bound, workers=-1)
            idx[a : a + CHUNK] = inv[np.asarray(got).reshape(-1, k)]
        if radius is None:
            return order, ps, np.arange(0, n * k + 1, k, dtype=np.int64), idx.ravel()
        valid = idx < n
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(valid.sum(axis=1), out=indptr[1:])
        return order, ps, indptr, idx[valid]
    lists = tree.query_ball_point(ps, radius, workers=-1)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=n)
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    flat = inv[np.fromiter((j for x in lists for j in x), dtype=np.int64, count=int(indptr[-1]))]
    # rows nearest first, like the kNN rows (the orientation graph takes the first few)
    row = np.repeat(np.arange(n), counts)
    d2 = np.einsum("ij,ij->i", ps[flat] - ps[row], ps[flat] - ps[row])
    return order, ps, indptr, flat[np.lexsort((d2, row))]


def pixel_neighbourhoods(pts: np.ndarray, pixels: Any, knn: int, radius: float | None):
    """Neighbourhoods of an organized cloud from its pixel grid.

    The ``knn`` nearest points (within ``radius`` when given) among the pixels of a window around
    each point's pixel, about ``PIXEL_WINDOW`` times ``knn`` pixels in all (PCL's organized
    neighbour search).

    Same returns as :func:`neighbourhoods`; ``order`` sorts the points by pixel (row-major,
    image by image), a spatially coherent order.
    """
    from recon_cli.stages.normals import _kernel as K

    n = len(pts)
    pix = pixels.pixel
    order = np.argsort(pix, kind="stable")
    ps = np.ascontiguousarray(pts[order])
    pix_s = np.ascontiguousarray(pix[order])
    if n > 1 and (pix_s[1:] == pix_s[:-1]).any():
        raise InputError("two points have the same pixel")
    offs = pixels.offsets()
    heights = np.array([h for h, _ in pixels.shapes], dtype=np.int64)
    widths = np.array([w for _, w in pixels.shapes], dtype=np.int64)
    img_of = (np.searchsorted(offs, pix_s, side="right") - 1).astype(np.int32)
    img = np.full(int(offs[-1]), -1, dtype=np.int32)
    img[pix_s] = np.arange(n, dtype=np.int32)
    k = min(knn, n)
    r = pixel_radius(k)
    # the window's offsets, nearest pixels first
    dr, dc = np.mgrid[-r : r + 1, -r : r + 1].reshape(2, -1).astype(np.int64)
    ring = np.argsort(dr * dr + dc * dc, kind="stable")[1:]
    dr, dc = np.ascontiguousarray(dr[ring]), np.ascontiguousarray(dc[ring])
    out = np.empty((n, k), dtype=np.int32)
    count = np.empty(n, dtype=np.int64)
    r2 = np.inf if radius is None else radius * radius
    K.pixel_knn(ps, pix_s, img_of, (offs, heights, widths, img), k, dr, dc, r2, out, count)
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(count, out=indptr[1:])
    if indptr[-1] == n * k:
        return order, ps, indptr, out.ravel()
    return order, ps, indptr, out[np.arange(k)[None, :] < count[:, None]]


def pixel_radius(k: int) -> int:
    """Half-width in pixels of the window the ``k`` nearest are taken from."""
    return max(1, math.ceil((math.sqrt(PIXEL_WINDOW * k) - 1) / 2))
