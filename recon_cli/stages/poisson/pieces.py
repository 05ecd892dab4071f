"""The closed pieces of an extraction: their boxes and how far they reach from the largest.

What the single process's extraction and the slabs' merge (:mod:`.distributed`) decide the
noise's pieces with (specks, islands, folds).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

log = logging.getLogger("recon")


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


def reach_vertices(
    verts: np.ndarray,
    faces: np.ndarray,
    labels: np.ndarray,
    which: np.ndarray,
    anchor: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> dict:
    """The vertices that decide the folds: what :func:`piece_reach` measures.

    ``labels`` (nf,) the faces' pieces, ``which`` (p,) the candidate each piece is (-1: none),
    ``anchor`` (p,) bool the pieces that stay whatever, ``lo``/``hi`` (k, 3) the candidates'
    boxes grown by the reach. Returns the candidates' vertices (``points``, ``ids``) and the
    anchors' vertices in those boxes (``targets``); a vertex no face uses belongs to no piece.
    """
    from recon_cli.stages.poisson.octree import indices_in_boxes

    vlab = vertex_labels(faces, labels, len(verts))
    used = vlab >= 0
    ids = np.full(len(vlab), -1, np.int64)
    ids[used] = which[vlab[used]]
    mine = np.flatnonzero(ids >= 0)
    near = indices_in_boxes(verts, lo, hi)
    near = near[used[near]]
    near = near[anchor[vlab[near]]]
    return {"points": verts[mine], "ids": ids[mine], "targets": verts[near]}


def noise_pieces(
    lo: np.ndarray,
    hi: np.ndarray,
    largest: int,
    cell: float,
    speck: float,
    fold: tuple[float, float] | None,
    count_points: Callable[[np.ndarray, np.ndarray], np.ndarray],
    farthest: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which closed pieces are specks, islands and folds: (n,) bool each, never ``largest``.

    The rules of :func:`recon_cli.stages.poisson.steps.drop_bubbles`, for the single process and the
    slabs' merge alike, on the pieces' boxes ``lo``/``hi`` (n, 3) (the largest's need not be
    set), ``cell`` the finest cell, ``speck`` (:func:`.speck_cells`) and ``fold``
    (:func:`.fold_cells`) in cells. The two measures come from the caller: ``count_points(lo,
    hi)`` the input points in each box (k,), and ``farthest(which, anchor, lo, hi)`` the farthest
    a candidate's vertex lies from the anchors' (:func:`piece_reach`; ``which`` (n,) each piece's
    candidate index or -1, ``anchor`` (n,) bool, the boxes grown by the reach).
    """
    from recon_cli.stages.poisson import BUBBLE_CELLS, ISLAND_POINTS

    n = len(lo)
    span = (hi - lo).max(axis=1)
    specks = span < speck * cell
    specks[largest] = False
    islands = np.zeros(n, bool)
    cand = np.flatnonzero(~specks)
    cand = cand[cand != largest]
    if len(cand):
        pad = BUBBLE_CELLS * cell
        islands[cand] = count_points(lo[cand] - pad, hi[cand] + pad) < ISLAND_POINTS
    folds = np.zeros(n, bool)
    if fold is not None:
        small = ~(specks | islands) & (span < fold[0] * cell)
        small[largest] = False
        cand = np.flatnonzero(small)
        if len(cand):
            reach = fold[1] * cell
            which = np.full(n, -1, np.int64)
            which[cand] = np.arange(len(cand))
            anchor = ~(specks | islands | small)
            far = farthest(which, anchor, lo[cand] - reach, hi[cand] + reach)
            folds[cand] = far <= reach
    if specks.any() or islands.any() or folds.any():
        log.info(
            "poisson: %d pieces under %.3g cells across, %d around fewer than %d points and %d "
            "folds of the noise band dropped",
            int(specks.sum()),
            speck,
            int(islands.sum()),
            ISLAND_POINTS,
            int(folds.sum()),
        )
    return specks, islands, folds
