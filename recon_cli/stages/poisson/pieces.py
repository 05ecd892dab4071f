"""The closed pieces of an extraction: their boxes and how far they reach from the largest.

What the single process's extraction and the slabs' merge (:mod:`.distributed`) decide the
noise's pieces with (specks, islands, folds).
"""

from __future__ import annotations

import numpy as np


def piece_boxes(
    verts: np.ndarray, faces: np.ndarray, labels: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each piece's faces and bounding box.

    Parameters
    ----------
    verts : (nv, 3) float
    faces : (nf, 3) int
    labels : (nf,) int
        The faces' pieces, in ``0..n-1``.
    n : int

    Returns
    -------
    count : (n,) int64
        Faces per piece.
    lo, hi : (n, 3) float64
        Corners of each piece's box (inf, -inf for a piece with no face).
    """
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    flab = np.repeat(labels, 3)
    corner = verts[faces.reshape(-1)]
    for ax in range(3):
        np.minimum.at(lo[:, ax], flab, corner[:, ax])
        np.maximum.at(hi[:, ax], flab, corner[:, ax])
    return np.bincount(labels, minlength=n).astype(np.int64), lo, hi


def vertex_labels(faces: np.ndarray, labels: np.ndarray, nv: int) -> np.ndarray:
    """(nv,) int64 the piece of each vertex, from its faces' ``labels`` (nf,); -1 if unused."""
    vlab = np.full(nv, -1, np.int64)
    vlab[faces.reshape(-1)] = np.repeat(labels, 3)
    return vlab


def piece_reach(points: np.ndarray, ids: np.ndarray, n: int, targets: np.ndarray) -> np.ndarray:
    """How far each piece's vertices reach from the ``targets``: (n,) float64.

    Parameters
    ----------
    points : (m, 3) float
        The pieces' vertices.
    ids : (m,) int
        Their pieces, in ``0..n-1``.
    n : int
    targets : (t, 3) float
        The vertices to measure from (the largest piece's near the others).

    Returns
    -------
    (n,) float64
        The largest distance from a vertex of each piece to its nearest target (same units;
        inf with no target, -inf for a piece with no vertex). Vertex to vertex: at most a mesh
        edge more than to the surface, so it bounds the distance to the surface from above.
    """
    out = np.full(n, -np.inf)
    if not len(points):
        return out
    if not len(targets):
        out[np.unique(ids)] = np.inf
        return out
    from scipy.spatial import cKDTree

    d = cKDTree(targets).query(points)[0]
    np.maximum.at(out, ids, d)
    return out
