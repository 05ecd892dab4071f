"""Trimming of a Poisson surface by the samples' density: a cut along a density contour.

An open scan's Poisson surface is closed by a sheet far from any sample; the samples'
kernel density at the surface tells the two apart. :func:`trim_by_density` cuts the mesh
along the contour ``density = threshold`` (every triangle the contour crosses is split at
the linearly interpolated crossings, as PoissonRecon's SurfaceTrimmer does), keeps the high
side, keeps small low islands inside it (so a sparse patch on the scanned surface does
not become a hole) and drops small high islands (outliers in the sheet), unless told they
hold data (``mass``). The threshold is a
fraction of the median density at the samples, so the same value serves any scan, depth
and tessellation (a vertex quantile, Open3D's documented recipe, depends on how many
vertices the sheet happens to have).

:func:`support_ratio` gives the value cut by ``--trim auto``: how far each vertex lies from
the samples relative to their local spacing (see its docstring for the rule);
:func:`trim_auto` makes that cut, keeping every island a sample lies nearest to.

On a closed, edge- and vertex-manifold input the output is edge- and vertex-manifold by
construction: every face around a kept vertex keeps a piece containing it, and each cut
vertex lies inside an edge shared by two faces whose kept pieces meet along it.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3)
(the SurfaceTrimmer of its code: trim at a density value, split along the iso-contour,
area ratio for islands).
Amenta, N., Choi, S. & Kolluri, R. (2001). The power crust. Solid Modeling (a surface is
supported where it lies within a fraction of the local feature size of the samples: the
sampling condition behind :func:`support_ratio`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.topology import Connectivity
from recon_cli.tolerances import tol

# islands (high pieces in the sheet, low holes in the surface) below this fraction of the kept area
# are dropped / filled (SurfaceTrimmer's --aRatio default, which it takes of the whole area)
ISLAND_AREA_RATIO = 1e-3
# --trim auto: the local spacing of a sample is its distance to its SUPPORT_K-th nearest
# sample ...
SUPPORT_K = 8
# ... and the surface is kept within this many local spacings of the nearest sample (a lattice's
# gaps are within 0.5; a depth camera's noise and disparity steps put the surface between
# layers of samples, up to about one spacing from them: bench/calibration.md) ...
SUPPORT_RATIO = 1.0
# ... a spacing counting as at most this many times the samples' median spacing (sparse
# strays, such as a depth camera's flying pixels, keep no wide sheet around them; the kept
# band around sparse ground stays within SUPPORT_RATIO * SPACING_CAP median spacings)
SPACING_CAP = 1.4


@dataclass
class Trimmed:
    """What :func:`trim_by_density` returns."""

    mesh: TriangleMesh
    density: np.ndarray  # (n,) per output vertex (the threshold on cut vertices)
    removed_area: float  # fraction of the input's area removed
    threshold: float
    untouched_faces: int  # input faces kept whole (the others were cut or removed)
    carried: np.ndarray | None = None  # (n,) ``carry`` at the output vertices, if given


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
    carry: np.ndarray | None = None,
    mass: np.ndarray | None = None,
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
    carry : (n,) float, optional
        Another per-vertex value (a density attribute) taken to the output vertices,
        interpolated at the cut vertices as the positions are.
    mass : (n,) float, optional
        The data each vertex stands for (:func:`nearest_counts`: the samples nearest it). A
        small kept island holding any stays (scanned surface, however small: a near object,
        a fragment between noisy samples); without ``mass`` every small kept island goes.

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
        return Trimmed(mesh, d, 0.0, threshold, len(f), carry)

    verts, faces, side, dens, edges = cut_by_density(v, f, d, threshold, high, nh)
    if carry is not None:
        carry = carried_at_cut(carry, d, edges, threshold)

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
        if want and mass is not None:
            small &= ~_holding(lab, faces[part], mass)
        keep[part[small[lab]]] = not want

    out_f = faces[keep]
    referenced = np.zeros(len(verts), bool)
    referenced[out_f] = True
    used = np.flatnonzero(referenced)  # np.unique's answer without its sort
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    out = TriangleMesh(vertices=verts[used], faces=remap[out_f], history=list(mesh.history))
    removed = float(area[~keep].sum()) / total if total > 0 else 0.0
    untouched = int(
        (nh == 3).sum() + keep[int((nh == 3).sum()) : int((nh == 3).sum() + (nh == 0).sum())].sum()
    )
    return Trimmed(
        out, dens[used], removed, threshold, untouched, None if carry is None else carry[used]
    )


def _holding(lab: np.ndarray, faces: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """(c,) True for the face components ``lab`` (f,) of ``faces`` (f, 3) with mass at a corner.

    ``mass`` is per input vertex; cut vertices, numbered from ``len(mass)``, hold none.
    """
    held = np.concatenate([np.asarray(mass, dtype=np.float64) > 0, np.zeros(1, bool)])
    corners = held[np.minimum(faces, len(mass))].any(axis=1)
    return np.bincount(lab, weights=corners, minlength=int(lab.max()) + 1) > 0


def nearest_counts(samples: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """(n,) how many of the ``samples`` (s, 3) lie nearest each of the ``verts`` (n, 3)."""
    from scipy.spatial import cKDTree

    j = cKDTree(np.asarray(verts, dtype=np.float64)).query(
        np.asarray(samples, dtype=np.float64), workers=-1
    )[1]
    return np.bincount(j, minlength=len(verts)).astype(np.float64)


def trim_auto(mesh: TriangleMesh, samples: np.ndarray, carry: np.ndarray | None = None) -> Trimmed:
    """``--trim auto``: cut ``mesh`` where :func:`support_ratio` is :data:`SUPPORT_RATIO`.

    Holes below :data:`ISLAND_AREA_RATIO` of the kept area are kept; of the small kept
    islands only those no sample lies nearest to go (pieces of the sheet).

    Parameters
    ----------
    mesh : TriangleMesh
        (n, 3) vertices, (m, 3) faces.
    samples : (s, 3) float
        The samples, merged per finest cell of the tree (:func:`support_ratio`).
    carry : (n,) float, optional
        A per-vertex value taken to the output vertices (:func:`trim_by_density`).

    Returns
    -------
    Trimmed
        Its ``density`` is minus the support ratio at the output vertices.
    """
    ratio = support_ratio(samples, mesh.vertices)[0]
    mass = nearest_counts(samples, mesh.vertices)
    return trim_by_density(mesh, -ratio, -SUPPORT_RATIO, carry=carry, mass=mass)


def merge_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
    """(s, 3) the mean of the ``points`` (n, 3) in each cell of a lattice of side ``cell``."""
    points = np.asarray(points, dtype=np.float64)
    lo = points.min(axis=0)
    ijk = np.floor((points - lo) / cell).astype(np.int64)
    _, inv, cnt = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out = np.empty((len(cnt), 3))
    for a in range(3):
        out[:, a] = np.bincount(inv, weights=points[:, a], minlength=len(cnt)) / cnt
    return out


def support_ratio(
    samples: np.ndarray, verts: np.ndarray, k: int = SUPPORT_K
) -> tuple[np.ndarray, np.ndarray]:
    """How far each vertex lies from the samples, in local sample spacings (``--trim auto``).

    The closing sheet of an open scan lies far from every sample *relative to the local
    sample spacing*; a real surface, however sparsely sampled (a depth image's far floor,
    ground under canopy), lies within a fraction of the spacing of its samples. So the rule
    needs no density threshold:

    - each sample's spacing ``s`` is its distance to its ``k``-th nearest sample, made
      robust as the median of that distance over the sample and its ``k`` neighbours (an
      outlier among dense samples takes their spacing, not its own large gap), and capped
      at :data:`SPACING_CAP` times the median spacing of all samples (strays far sparser
      than the cloud, like a depth camera's flying pixels in an occlusion shadow, support
      no wide sheet around them);
    - a vertex's value is ``d / s``, ``d`` its distance to its nearest sample and ``s``
      that sample's spacing; the surface is cut where this is :data:`SUPPORT_RATIO`.

    Every point of a surface sampled on a square lattice has a sample within half the 8th
    neighbour's distance (``sqrt(2)`` lattice steps; on a 3:1 lattice, a grazing view's,
    within 0.53 of it), and a random sampling leaves about ``exp(-k c**2)`` of its area
    farther than ``c`` times the ``k``-th neighbour's distance from every sample (small
    holes, which the trim's island rule fills). A depth camera's samples are noisier: its
    noise and disparity steps spread them over layers a few cells apart, and the smooth
    surface passes between the layers, up to about one spacing from the nearest sample. A
    cut at one spacing keeps every sampled region, sparse and noisy ones included, and the
    sheet only within one spacing of the scan's edge. Density cuts (SurfaceTrimmer's value,
    Open3D's quantile, a fraction of the median density) cut sparse real regions along with
    the sheet, their density being as low.

    Parameters
    ----------
    samples : (s, 3) float
        The samples, merged per finest cell of the tree (so the spacing is never below the
        cell the surface is resolved at).
    verts : (n, 3) float
        Mesh vertices, same units.
    k : int
        Neighbour rank defining the spacing (>= 1, < s).

    Returns
    -------
    ratio : (n,) float
        Distance over local spacing per vertex (cut at :data:`SUPPORT_RATIO`).
    spacing : (s,) float
        The samples' local spacing.

    References
    ----------
    Amenta, N., Choi, S. & Kolluri, R. (2001). The power crust. Solid Modeling.
    """
    from scipy.spatial import cKDTree

    samples = np.asarray(samples, dtype=np.float64)
    tree = cKDTree(samples)
    spacing = local_spacing(tree, k)[0]
    spacing = capped_spacing(spacing, float(np.median(spacing)))
    return spacing_ratio(tree, spacing, verts), spacing


def local_spacing(tree: Any, k: int = SUPPORT_K) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's robust local spacing (:func:`support_ratio`), before the cap.

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over the (s, 3) samples.
    k : int
        Neighbour rank defining the spacing.

    Returns
    -------
    spacing : (s,) float
        The median over the sample and its ``k`` nearest of their distance to their ``k``-th.
    reach : (s,) float
        How far from each sample that figure looked: its ``k``-th neighbour's distance plus the
        largest of its neighbours' (samples within it decide the spacing).
    """
    k = min(k, tree.n - 1)
    dist, idx = tree.query(tree.data, k=k + 1, workers=-1)
    rk = dist[:, k]
    return np.median(rk[idx], axis=1), rk + rk[idx].max(axis=1)


def capped_spacing(spacing: np.ndarray, median: float) -> np.ndarray:
    """``spacing`` (s,) kept within ``[tiny, SPACING_CAP * median]`` (``median``: of all)."""
    return np.clip(spacing, np.finfo(float).tiny, SPACING_CAP * median)


def spacing_ratio(tree: Any, spacing: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """(n,) each vertex's distance to its nearest sample over that sample's ``spacing``."""
    d, j = tree.query(np.asarray(verts, dtype=np.float64), workers=-1)
    return d / spacing[j]


def carried_at_cut(
    carry: np.ndarray, density: np.ndarray, edges: np.ndarray, threshold: float
) -> np.ndarray:
    """``carry`` (n,) at the vertices :func:`cut_by_density` made, after the old ones.

    ``edges`` (c, 2) are the cut vertices' edges: each takes ``carry`` where ``density`` (n,)
    crosses ``threshold`` along its edge, as its position was placed.
    """
    e0, e1 = edges[:, 0], edges[:, 1]
    d = density
    t = np.clip((threshold - d[e0]) / (d[e1] - d[e0]), tol.contour, 1.0 - tol.contour)
    carry = np.asarray(carry, dtype=np.float64)
    return np.concatenate([carry, carry[e0] + t * (carry[e1] - carry[e0])])
