"""Trimming of a Poisson surface by the samples' density: a cut along a density contour.

An open scan's Poisson surface is closed by a sheet far from any sample; the samples'
kernel density at the surface tells the two apart. :func:`trim_by_density` cuts the mesh
along the contour ``density = threshold`` (every triangle the contour crosses is split at
the linearly interpolated crossings, as PoissonRecon's SurfaceTrimmer does), keeps the high
side, keeps small low islands inside it (so a sparse patch on the scanned surface does
not become a hole) and drops small high islands (outliers in the sheet). The threshold is a
fraction of the median density at the samples, so the same value serves any scan, depth
and tessellation (a vertex quantile, Open3D's documented recipe, depends on how many
vertices the sheet happens to have).

On a closed, edge- and vertex-manifold input the output is edge- and vertex-manifold by
construction: every face around a kept vertex keeps a piece containing it, and each cut
vertex lies inside an edge shared by two faces whose kept pieces meet along it.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3)
(the SurfaceTrimmer of its code: trim at a density value, split along the iso-contour,
area ratio for islands).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.topology import Connectivity
from recon_cli.tolerances import tol

# islands (high pieces in the sheet, low holes in the surface) below this fraction of the kept area
# are dropped / filled (SurfaceTrimmer's --aRatio default, which it takes of the whole area)
ISLAND_AREA_RATIO = 1e-3


@dataclass
class Trimmed:
    """What :func:`trim_by_density` returns."""

    mesh: TriangleMesh
    density: np.ndarray  # (n,) per output vertex (the threshold on cut vertices)
    removed_area: float  # fraction of the input's area removed
    threshold: float
    untouched_faces: int  # input faces kept whole (the others were cut or removed)


def cut_by_density(
    v: np.ndarray,
    f: np.ndarray,
    d: np.ndarray,
    threshold: float,
    high: np.ndarray,
    nh: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cut of :func:`trim_by_density`, both sides kept.

    Every face the contour ``d = threshold`` crosses is split at the linearly interpolated
    crossings (one new vertex per crossed edge, appended after ``v``). ``high``: the vertices
    above the threshold, ``nh`` each face's count of them. Returns the vertices, the faces (the
    whole high ones, the whole low ones, then the pieces), each face's side (True high), the
    vertices' densities (the threshold on the new ones) and the edge (ends) each new vertex lies on.
    """
    n = len(v)
    # ---- cut vertices: one per edge whose ends are on both sides
    cut = (nh == 1) | (nh == 2)
    fc = f[cut]
    a = fc.reshape(-1)
    b = fc[:, [1, 2, 0]].reshape(-1)
    cross = high[a] != high[b]
    lo, hi = np.minimum(a, b)[cross], np.maximum(a, b)[cross]
    ekeys, inv = np.unique(lo * n + hi, return_inverse=True)
    e0, e1 = ekeys // n, ekeys % n
    t = np.clip((threshold - d[e0]) / (d[e1] - d[e0]), tol.contour, 1.0 - tol.contour)
    new_v = v[e0] + t[:, None] * (v[e1] - v[e0])
    # the cut vertex of each half-edge of the cut faces (-1 when it does not cross)
    hv: np.ndarray = np.full(len(a), -1, np.int64)
    hv[cross] = n + inv
    hv = hv.reshape(-1, 3)  # hv[:, k]: the cut on edge (corner k -> corner k+1)

    # ---- the pieces of the cut faces, both sides (winding kept)
    # rotate each cut face so that corner 0 is the lone vertex (the one side alone)
    lone_high = nh[cut] == 1
    hc = high[fc]
    lone = np.where(lone_high, np.argmax(hc, axis=1), np.argmin(hc, axis=1))
    r = (lone[:, None] + np.arange(3)[None, :]) % 3
    rows = np.arange(len(fc))[:, None]
    p0, p1, p2 = (fc[rows, r][:, k] for k in range(3))
    c01 = hv[rows[:, 0], r[:, 0]]  # cut on edge lone -> next
    c20 = hv[rows[:, 0], r[:, 2]]  # cut on edge prev -> lone
    tri = np.stack([p0, c01, c20], axis=1)  # the lone vertex's side
    quad_a = np.stack([c01, p1, p2], axis=1)  # the other side, a quad (c01, p1, p2, c20)
    quad_b = np.stack([c01, p2, c20], axis=1)
    tri_high = lone_high
    # every face: (vertices, is high)
    faces = np.concatenate([f[nh == 3], f[nh == 0], tri, quad_a, quad_b])
    side = np.concatenate(
        [
            np.ones(int((nh == 3).sum()), bool),
            np.zeros(int((nh == 0).sum()), bool),
            tri_high,
            ~tri_high,
            ~tri_high,
        ]
    )
    verts = np.concatenate([v, new_v])
    dens = np.concatenate([d, np.full(len(new_v), threshold)])

    return verts, faces, side, dens, np.stack([e0, e1], axis=1)


def trim_by_density(
    mesh: TriangleMesh,
    density: np.ndarray,
    threshold: float,
    island_ratio: float = ISLAND_AREA_RATIO,
) -> Trimmed:
    """Remove the part of ``mesh`` where ``density`` is at most ``threshold``.

    ``density`` is per vertex, linear on faces.

    Parameters
    ----------
    mesh : TriangleMesh
        (n, 3) vertices, (m, 3) faces.
    density : (n,) float
        Per-vertex density.
    threshold : float
        Density at and below which the surface goes.
    island_ratio : float
        Kept islands smaller than this fraction of the kept area go; removed islands smaller
        than it stay (they are holes in a sparse patch, not the closing sheet).

    Returns
    -------
    Trimmed
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    d = np.asarray(density, dtype=np.float64)
    high = d > threshold
    nh = high[f].sum(axis=1)
    if len(f) == 0 or nh.min() == 3:
        return Trimmed(mesh, d, 0.0, threshold, len(f))

    verts, faces, side, dens, _ = cut_by_density(v, f, d, threshold, high, nh)

    # ---- islands: components of each side (faces joined across edges within the side)
    area = Connectivity(faces, len(verts), verts).face_areas
    total = float(area.sum())
    kept_area = float(area[side].sum())
    keep = side.copy()
    for want in (False, True):  # first re-admit small holes, then drop small high islands
        part = np.flatnonzero(keep == want)
        if not len(part):
            continue
        lab = Connectivity(faces[part], len(verts)).face_components
        comp_area = np.bincount(lab, weights=area[part])
        small = comp_area < island_ratio * kept_area
        keep[part[small[lab]]] = not want

    out_f = faces[keep]
    used = np.unique(out_f)
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    out = TriangleMesh(vertices=verts[used], faces=remap[out_f], history=list(mesh.history))
    removed = float(area[~keep].sum()) / total if total > 0 else 0.0
    untouched = int(
        (nh == 3).sum() + keep[int((nh == 3).sum()) : int((nh == 3).sum() + (nh == 0).sum())].sum()
    )
    return Trimmed(out, dens[used], removed, threshold, untouched)
