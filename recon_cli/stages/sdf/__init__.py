"""Signed distance grids: from a triangle mesh (exact) or an oriented point cloud (IMLS).

Mesh: exact unsigned distance to the nearest triangle (:mod:`recon_cli.mesh.distance`);
inside where the generalised winding number (:mod:`recon_cli.mesh.winding`) is not 0.
On a closed mesh (every directed edge matched by its reverse: :func:`is_boundary_free`)
the winding number is an integer, constant off the surface between samples whose
distances add up to more than a voxel; one winding number per such class of samples
gives every sample its exact sign (:func:`closed_mesh_inside`), for a mesh wound inward
too (winding number -1: the geometric inside). On an open mesh the winding number is
evaluated at samples within one voxel of the surface, and on a coarse subset of each
connected region of the other samples (two neighbouring samples farther than one voxel
from the mesh cannot have the surface between them, so such a region has one side); a
region whose subset disagrees is evaluated everywhere. ``sign="pseudonormal"`` takes the
angle-weighted pseudonormal of the closest feature instead (no exactness guarantee in
floating point; a closed mesh wound inward is refused).

Cloud: implicit moving least squares (Kolluri 2005; Hoppe 1992 with smoothing): the
Gaussian-weighted mean of the signed distances to the tangent planes of the ``knn``
nearest points. Samples farther than a few point spacings (and two voxels) from every
point are unknown (NaN), so marching cubes makes no sheet far from data.

The ``.npz`` grid format is described in :mod:`recon_cli.grid`.

References
----------
Jacobson, A., Kavan, L. & Sorkine-Hornung, O. (2013). Robust inside-outside segmentation using
generalized winding numbers. ACM TOG 32(4).
Barill, G., Dickson, N., Schmidt, R., Levin, D. & Jacobson, A. (2018). Fast winding numbers for
soups and clouds. ACM TOG 37(4).
Bærentzen, J. A. & Aanæs, H. (2005). Signed distance computation using the angle weighted
pseudonormal. IEEE TVCG 11(3).
Kolluri, R. (2005). Provably good moving least squares. SODA (the cloud's IMLS).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.params import Param, StageSpec

_SIGNS = ("winding", "pseudonormal")
_SLAB_CELLS = 500_000  # eikonal_check works on slabs of about this many samples
#: eikonal_check's ``near`` band: |s| up to this fraction of the zero level's box diagonal
NEAR_BAND = 0.05
#: eikonal_check's ``near`` figures leave out kinks: a slope changing by more than this
#: across a sample (|s(i+1) - 2 s(i) + s(i-1)| / h on some axis)
KINK = 0.5
# peak bytes per grid sample (estimates, for refusing a grid up front): mesh = float64
# distances + int32 side classes + the float32 grid + the eikonal check's float32 norms;
# cloud = float64 field + sample coordinates and nearest distances (float64 x 4) + float32
# grid + norms; open3d = float32 coordinates + float32 distances + float64 copies
BYTES_PER_SAMPLE = {"mesh": 24, "cloud": 56, "open3d": 48}

SPEC = StageSpec(
    name="sdf",
    summary="Signed distance grid (.npz) of a mesh or oriented cloud.",
    description="""Signed distance grid (.npz, negative inside) of a mesh or an oriented cloud.

    Clouds need normals; samples far from every point are unknown (NaN) and `recon mcubes`
    leaves them out.""",
    takes=("mesh", "oriented"),
    gives=("grid",),
    backends=("native", "open3d"),
    output_suffix=".npz",
    params=(
        Param(
            "resolution",
            "int",
            128,
            "Cells along the longest side of the padded box.",
            unit="cells",
            min=2,
            max=2048,
        ),
        Param(
            "voxel_size",
            "float",
            None,
            "Sample spacing (overrides --resolution).",
            unit="input units",
            min=0.0,
            min_open=True,
            words={"auto": None},
        ),
        Param(
            "padding",
            "float",
            0.05,
            "Margin around the bounding box.",
            unit="fraction of the longest side",
            min=0.0,
        ),
        Param(
            "sign",
            "choice",
            "winding",
            "Meshes: inside where the winding number is not 0 (exact on closed "
            "meshes of either orientation; robust to holes) or by pseudonormals.",
            choices=_SIGNS,
        ),
        Param(
            "band",
            "float",
            None,
            "Meshes: exact distances only within this many voxels.",
            unit="voxels",
            min=0.0,
            min_open=True,
        ),
        Param(
            "knn", "int", 10, "Clouds: neighbours averaged per sample (IMLS).", unit="points", min=1
        ),
    ),
)


def grid_frame(
    lo: np.ndarray,
    hi: np.ndarray,
    resolution: int = SPEC.param("resolution").default,
    voxel_size: float | None = SPEC.param("voxel_size").default,
    padding: float = SPEC.param("padding").default,
) -> tuple[np.ndarray, float, tuple[int, int, int]]:
    """Origin, voxel size and shape of a grid covering the box [lo, hi].

    Parameters
    ----------
    lo, hi : (3,) float
        Bounding box of the data.
    resolution : int
        Cells along the longest side of the padded box (ignored when ``voxel_size`` given).
    voxel_size : float, optional
        Sample spacing, world units.
    padding : float
        Margin on every side as a fraction of the box's longest side.

    Returns
    -------
    origin : (3,) float64
    voxel_size : float
    shape : (nx, ny, nz)

    Raises
    ------
    ParameterError
        A value outside the declaration's range, or a voxel size too small for the box.
    """
    v = SPEC.check(
        {"resolution": resolution, "voxel_size": voxel_size, "padding": padding}, complete=False
    )
    resolution, voxel_size, padding = v["resolution"], v["voxel_size"], v["padding"]
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ext = float((hi - lo).max())
    if not ext > 0:
        ext = 1.0 if voxel_size is None else float(voxel_size)
    pad = padding * ext
    org = lo - pad
    size = hi - lo + 2 * pad
    h = float(voxel_size) if voxel_size is not None else float(size.max()) / int(resolution)
    cells = np.ceil(size / h - 1e-9)
    if not (np.isfinite(cells).all() and cells.max() < 2**52):
        raise ParameterError(
            f"voxel size {h:.6g} is too small for a box of {float(size.max()):.6g}"
        )
    nx, ny, nz = (int(s) + 1 for s in cells)
    shape = (nx, ny, nz)
    # centre the data in the (slightly larger) sampled box
    org = org - 0.5 * ((np.array(shape) - 1) * h - size)
    return org, h, shape


def grid_points(
    origin: np.ndarray,
    h: float,
    shape: tuple[int, int, int],
    mask: np.ndarray | None = None,
    flat: np.ndarray | None = None,
) -> np.ndarray:
    """World coordinates ((k, 3)) of samples: all, those where ``mask``, or those at ``flat``.

    ``flat`` holds C-order indices.
    """
    if flat is not None:
        idx = np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), shape), axis=1)
    elif mask is None:
        idx = np.indices(shape).reshape(3, -1).T
    else:
        idx = np.argwhere(mask)
    return origin + idx * h


def mesh_sdf(
    vertices: np.ndarray,
    faces: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    shape: tuple[int, int, int],
    sign: str = SPEC.param("sign").default,
    band: float | None = SPEC.param("band").default,
) -> tuple[np.ndarray, dict]:
    """Signed distance from every sample of a grid to a triangle mesh.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
        Counter-clockwise seen from outside.
    origin : (3,) float
        World position of sample [0, 0, 0].
    voxel_size : float
        Sample spacing, world units.
    shape : (nx, ny, nz)
    sign : {"winding", "pseudonormal"}
        ``winding``: inside where the winding number is not 0 (|w| > 1/2): on a closed
        mesh the geometric inside whatever the orientation, exact (see below);
        ``pseudonormal``: the angle-weighted pseudonormal of the closest feature (fast,
        right on a closed, outward, self-intersection-free mesh up to rounding; a closed
        mesh wound inward is refused).
    band : float, optional
        Half-width in voxels: only samples within it get exact distances, the rest
        ``±band * voxel_size``.

    Returns
    -------
    sdf : (nx, ny, nz) float64
        Negative inside.
    info : dict
        ``sign_method``: "classes" (closed mesh: one exact winding number per side class,
        see :func:`closed_mesh_inside`), "winding" (open mesh: winding numbers near the
        surface and on a lattice of each far region) or "pseudonormal";
        ``winding_evaluations`` (samples where the winding number was computed);
        ``regions`` (side classes, or far regions of an open mesh); on a closed mesh
        ``winding_numbers`` (the distinct winding numbers of the classes: -1 for a mesh
        wound inward, 2 where it overlaps itself).

    Raises
    ------
    InputError
        ``sign="pseudonormal"`` on a closed mesh of negative volume (wound inward).
    ParameterError
        ``sign`` or ``band`` outside the declaration's choices or range.
    """
    from recon_cli.mesh.distance import build_bvh, distance_grid

    v = SPEC.check({"sign": sign, "band": band}, complete=False)
    sign, band = v["sign"], v["band"]
    h = float(voxel_size)
    cap = np.inf if band is None else float(band) * h
    bvh = build_bvh(vertices, faces)
    closed = is_boundary_free(faces)
    if sign == "pseudonormal":
        if closed and signed_volume(vertices, faces) < 0:
            raise InputError(INWARD_MESSAGE)
        dist, pn_sign = distance_grid(
            vertices, faces, origin, h, shape, band=cap, pseudonormal=True, bvh=bvh
        )
        return _pseudonormal_sdf(vertices, faces, origin, h, shape, dist, pn_sign, bvh)
    dist, _ = distance_grid(vertices, faces, origin, h, shape, band=cap, bvh=bvh)
    if closed:
        return closed_mesh_inside(vertices, faces, origin, h, dist, bvh=bvh)
    return _open_winding_sdf(vertices, faces, origin, h, shape, dist, bvh)


INWARD_MESSAGE = (
    "the mesh is wound inward (negative volume): run `recon repair`, or use --sign winding"
)


def closed_mesh_inside(
    vertices: np.ndarray,
    faces: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    dist: np.ndarray,
    bvh=None,
) -> tuple[np.ndarray, dict]:
    """Sign a closed mesh's grid distances exactly: negative where the winding number is not 0.

    The winding number of a closed mesh (:func:`is_boundary_free`) is an integer,
    constant on each connected piece of space off the surface. Two 6-neighbour samples
    whose distances add up to more than the voxel size cannot have the surface between
    them (:func:`recon_cli.stages.sdf._kernel.side_classes`), so the samples joined this way form
    classes of equal winding number. Each class's winding number is evaluated once, at
    its sample farthest from the surface (Barill's tree, and the exact sum of solid angles
    where the tree's value is not within 0.1 of an integer), and rounded.

    Guarantee: every sample whose distance is not within rounding of zero gets the sign
    of its exact winding number (nonzero rule: the geometric inside, also for a mesh wound
    inward); a sample within half a voxel of the surface is always either joined to a
    class or evaluated on its own. Rounding margin: distances are compared against
    ``voxel * (1 + 1e-6) + 1e-12 * extent``.

    Parameters
    ----------
    vertices, faces
        A boundary-free mesh.
    origin, voxel_size
        The grid frame.
    dist : (nx, ny, nz) float64
        Unsigned distances (or lower bounds, as beyond a band); negated in place inside.

    Returns
    -------
    sdf : the same array as ``dist``
    info : dict
        ``sign_method`` ("classes"), ``regions`` (classes), ``winding_evaluations``,
        ``winding_numbers``.

    References
    ----------
    Jacobson, Kavan & Sorkine-Hornung, "Robust inside-outside segmentation using
    generalized winding numbers", SIGGRAPH 2013; Barill et al., "Fast winding numbers for
    soups and clouds", SIGGRAPH 2018.
    """
    from recon_cli.mesh.winding import WindingTree, winding_number
    from recon_cli.stages.sdf import _kernel as K

    h = float(voxel_size)
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    used = v[np.unique(f)]
    extent = (
        float(np.abs(used).max())
        + float(np.abs(np.asarray(origin, float)).max())
        + h * max(dist.shape)
    )
    link = h * (1.0 + 1e-6) + 1e-12 * extent
    n = dist.size
    classes_of = np.empty(n, np.int32 if n < 2**31 - 1 else np.int64)
    dist = np.ascontiguousarray(dist)
    count, rep = K.side_classes(dist, link, classes_of)
    pts = grid_points(origin, h, dist.shape, None, flat=rep)
    w = WindingTree(v, f, bvh=bvh)(pts)
    unsure = np.abs(w - np.round(w)) > 0.1
    if unsure.any():
        w[unsure] = winding_number(v, f, pts[unsure], method="exact")
    wn = np.round(w).astype(np.int64)
    K.negate_inside(dist, classes_of, wn != 0)
    info = {
        "sign_method": "classes",
        "regions": int(count),
        "winding_evaluations": int(count),
        "winding_numbers": sorted(int(x) for x in np.unique(wn)),
    }
    return dist, info


class _GridWinding:
    """Absolute winding number at masked grid samples.

    The tree is built on first use and the evaluations are counted.
    """

    def __init__(self, vertices, faces, origin, h, shape, bvh):
        self.args = (vertices, faces, bvh)
        self.frame: tuple[np.ndarray, float, tuple[int, int, int]] = (origin, h, shape)
        self.tree = None
        self.evaluations = 0

    def __call__(self, mask: np.ndarray) -> np.ndarray:
        from recon_cli.mesh.winding import WindingTree

        if self.tree is None:
            v, f, bvh = self.args
            self.tree = WindingTree(v, f, bvh=bvh)
        self.evaluations += int(mask.sum())
        return np.abs(self.tree(grid_points(*self.frame, mask)))


def _pseudonormal_sdf(
    vertices, faces, origin, h, shape, dist, pn_sign, bvh
) -> tuple[np.ndarray, dict]:
    """Pseudonormal signs; samples beyond the band (no closest feature) by far regions."""
    near = dist <= h
    inside = pn_sign < 0
    far = pn_sign == 0  # beyond the band: no pseudonormal sign
    far &= ~near
    del pn_sign, near
    winding = _GridWinding(vertices, faces, origin, h, shape, bvh)
    return _far_regions(dist, inside, far, winding, "pseudonormal")


def _open_winding_sdf(vertices, faces, origin, h, shape, dist, bvh) -> tuple[np.ndarray, dict]:
    """Winding numbers within a voxel of the surface, and per far region."""
    winding = _GridWinding(vertices, faces, origin, h, shape, bvh)
    near = dist <= h
    inside = np.zeros(shape, dtype=bool)
    inside[near] = winding(near) > 0.5
    far = ~near
    del near
    return _far_regions(dist, inside, far, winding, "winding")


def _far_regions(dist, inside, far, winding: _GridWinding, method: str) -> tuple[np.ndarray, dict]:
    """Sign the connected regions of ``far`` samples.

    Two neighbouring samples farther than one voxel from the mesh cannot have the surface between
    them, so such a region has one side: a coarse subset of each region is evaluated; a region whose
    subset disagrees (open through a hole) is evaluated everywhere. Negates ``dist`` in place
    inside.
    """
    from scipy import ndimage

    shape = dist.shape
    labels, n = ndimage.label(far) if far.any() else (None, 0)
    if n:
        assert labels is not None  # labelled whenever there are regions
        # a coarse lattice of samples per region; a region the lattice misses (thin or
        # small) gets its first few samples, found inside its bounding box
        pick_mask = np.zeros(shape, dtype=bool)
        pick_mask[::4, ::4, ::4] = True
        pick_mask &= far
        hit = np.bincount(labels[pick_mask], minlength=n + 1) > 0
        missing = np.flatnonzero(~hit[1:]) + 1
        if len(missing):
            boxes = ndimage.find_objects(labels)
            for r in missing:
                sl = boxes[r - 1]
                first = np.argwhere(labels[sl] == r)[:8] + [s_.start for s_ in sl]
                pick_mask[tuple(first.T)] = True
        lab = labels[pick_mask]
        win = winding(pick_mask) > 0.5
        n_in = np.bincount(lab, weights=win, minlength=n + 1)
        n_all = np.bincount(lab, minlength=n + 1)
        uniform_in = (n_in == n_all) & (n_all > 0)
        uniform_out = (n_in == 0) & (n_all > 0)
        inside |= uniform_in[labels] & far
        mixed = ~(uniform_in | uniform_out)
        mixed[0] = False
        if mixed.any():  # a region open through a hole: evaluate all its samples
            redo = mixed[labels]
            inside[redo] = winding(redo) > 0.5
    # negate in place: no second full-size array
    sdf = dist
    np.negative(sdf, out=sdf, where=inside)
    return sdf, {
        "winding_evaluations": winding.evaluations,
        "regions": int(n),
        "sign_method": method,
    }


def is_boundary_free(faces: np.ndarray) -> bool:
    """True when every directed edge a->b of ``faces`` is matched by as many b->a.

    The triangles form a closed surface (a cycle), whose winding number is an integer off the
    surface. Holds for watertight, consistently oriented meshes, also non-manifold or
    self-intersecting ones; a face flipped against its neighbours breaks it.
    """
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return False
    a = f.reshape(-1)
    b = f[:, [1, 2, 0]].reshape(-1)
    n = int(a.max()) + 1
    fwd = np.sort(a * n + b)
    rev = np.sort(b * n + a)
    return bool(np.array_equal(fwd, rev))


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed mesh, negative when it is wound inward (divergence theorem)."""
    t = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    c = t.mean(axis=(0, 1))  # relative to a local origin: no cancellation far from 0
    t = t - c
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def cloud_sdf(
    points: np.ndarray,
    normals: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    shape: tuple[int, int, int],
    knn: int = SPEC.param("knn").default,
    max_distance: float | None = None,
) -> tuple[np.ndarray, dict]:
    """Signed distance of an oriented cloud's implied surface on a grid (IMLS).

    Parameters
    ----------
    points : (n, 3) float
    normals : (n, 3) float
        Outward normals (need not be unit; zero rows are ignored).
    origin, voxel_size, shape
        The grid, as in :func:`mesh_sdf`.
    knn : int
        Neighbours averaged per sample.
    max_distance : float, optional
        Samples with no point closer than this (world units) are NaN; default
        ``2 * voxel_size + 3 * spacing`` (spacing = median nearest-neighbour distance).

    Returns
    -------
    sdf : (nx, ny, nz) float64
        NaN far from the data.
    info : dict
        ``spacing``, ``max_distance``, ``unknown`` (NaN samples).
    """
    from scipy.spatial import cKDTree

    knn = SPEC.param("knn").coerce(knn)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 0
    pts, nrm = pts[ok], nrm[ok] / ln[ok, None]
    if len(pts) < 2:
        raise InputError("cloud needs at least 2 points with non-zero normals")
    h = float(voxel_size)
    tree = cKDTree(pts)
    dnn, _ = tree.query(pts, k=2, workers=-1)
    spacing = float(np.median(dnn[:, 1]))
    maxd = float(max_distance) if max_distance is not None else 2.0 * h + 3.0 * spacing
    k = int(min(knn, len(pts)))
    sdf = np.full(shape, np.nan)
    q = grid_points(origin, h, shape)
    d1, _ = tree.query(q, k=1, distance_upper_bound=maxd, workers=-1)
    near = np.isfinite(d1)
    qn = q[near]
    d, idx = tree.query(qn, k=k, workers=-1)
    if k == 1:
        d, idx = d[:, None], idx[:, None]
    sigma = max(spacing * 2.0, 1e-12)
    # weights relative to the nearest neighbour: same ratios, no underflow far from data
    w = np.exp(-(d**2 - d[:, :1] ** 2) / sigma**2)
    plane = np.einsum("ikj,ikj->ik", qn[:, None, :] - pts[idx], nrm[idx])
    sdf.reshape(-1)[near] = (w * plane).sum(axis=1) / w.sum(axis=1)
    return sdf, {"spacing": spacing, "max_distance": maxd, "unknown": int((~near).sum())}


def eikonal_check(grid) -> dict:
    """How close a grid is to a distance field: statistics of ‖∇s‖ (central differences).

    Over interior samples whose 6 neighbours are known and not at the band's cap value
    (for a ``--band`` grid: the samples inside the band). ``near`` gives the share and
    the mean over the samples of the region where ‖∇s‖ = 1 is meaningful: near the zero
    level, |s| <= :data:`NEAR_BAND` times the diagonal of the zero level's bounding box
    (the samples next to a sign change), where a distance field is used, and not at a kink,
    where the slope changes by more than :data:`KINK` from one side of the sample to the
    other on some axis: there the stencil straddles the medial axis (or a crease) and
    central differences are no gradient, even of an exact distance. Such samples are
    counted as ``kinks``; a smooth field, a fitted one, has few. Works slab by slab along
    the first axis, so its temporaries stay small next to the grid (a 256^3 grid is checked
    in about 20 MB besides 4 bytes per sample for the gradient norms kept for the median).

    Returns
    -------
    dict
        ``mean``, ``median`` of ‖∇s‖, ``fraction_within_0.1`` (share with
        |‖∇s‖ − 1| ≤ 0.1), ``cells`` (number of samples used) and ``near``:
        ``of_diagonal`` (:data:`NEAR_BAND`), ``distance`` (the band's half-width, world
        units; None without a sign change), ``mean``, ``fraction_within_0.1`` and ``cells``
        over the samples within it but kinks, ``kinks`` (the samples within it left out).
    """
    near_empty = {
        "of_diagonal": NEAR_BAND,
        "distance": None,
        "mean": None,
        "fraction_within_0.1": None,
        "cells": 0,
        "kinks": 0,
    }
    empty = {"mean": None, "median": None, "fraction_within_0.1": None, "cells": 0}
    s = np.asarray(grid.sdf)
    h = float(grid.voxel_size)
    nx = s.shape[0]
    if min(s.shape) < 3:
        return {**empty, "near": near_empty}
    step = max(1, _SLAB_CELLS // (s.shape[1] * s.shape[2]))
    top, span = _cap_and_zero_span(s, step)
    lim = top * (1 - 1e-6)
    dist = None if span is None else NEAR_BAND * h * float(np.linalg.norm(span))
    c = (slice(1, -1),) * 3
    # gradient norms of the used samples (float32: only the median needs them all);
    # the means and the shares within 0.1 are summed per slab in float64
    g = np.empty((nx - 2) * (s.shape[1] - 2) * (s.shape[2] - 2), np.float32)
    n = near_n = near_kinks = within = near_within = 0
    total = near_total = 0.0
    for i0 in range(1, nx - 1, step):
        blk = s[i0 - 1 : min(nx, i0 + step + 1)].astype(np.float64)
        usable = np.abs(blk) < lim  # False at NaN
        ok = usable[c].copy()
        g2 = np.zeros(ok.shape)
        bend = np.zeros(ok.shape)  # the largest change of slope across the stencil
        for ax in range(3):
            lo = [slice(1, -1)] * 3
            hi = [slice(1, -1)] * 3
            lo[ax] = slice(0, -2)
            hi[ax] = slice(2, None)
            ok &= usable[tuple(lo)] & usable[tuple(hi)]
            diff = np.where(ok, blk[tuple(hi)] - blk[tuple(lo)], 0.0) / (2 * h)
            g2 += diff * diff
            turn = np.where(ok, blk[tuple(hi)] - 2 * blk[c] + blk[tuple(lo)], 0.0) / h
            np.maximum(bend, np.abs(turn), out=bend)
        norm = np.sqrt(g2[ok])
        good = np.abs(norm - 1) <= 0.1
        total += float(norm.sum())
        within += int(np.count_nonzero(good))
        g[n : n + len(norm)] = norm
        n += len(norm)
        if dist is not None:
            close = np.abs(blk[c][ok]) <= dist
            kink = bend[ok] > KINK
            near_kinks += int(np.count_nonzero(close & kink))
            close &= ~kink
            near_total += float(norm[close].sum())
            near_within += int(np.count_nonzero(good & close))
            near_n += int(np.count_nonzero(close))
    if n == 0:
        return {**empty, "near": near_empty}
    g = g[:n]
    half = n // 2
    g.partition(half if n % 2 else [half - 1, half])  # in place: no copy of the norms
    median = float(g[half]) if n % 2 else 0.5 * (float(g[half - 1]) + float(g[half]))
    near = {**near_empty, "distance": dist, "kinks": near_kinks}
    if near_n:
        near.update(
            {
                "mean": near_total / near_n,
                "fraction_within_0.1": near_within / near_n,
                "cells": near_n,
            }
        )
    return {
        "mean": total / n,
        "median": median,
        "fraction_within_0.1": within / n,
        "cells": int(n),
        "near": near,
    }


def _cap_and_zero_span(s: np.ndarray, step: int) -> tuple[float, np.ndarray | None]:
    """The band's cap (the largest finite |s|) and the zero level's extent in samples.

    The extent is the size of the bounding box of the samples next to a sign change
    (both finite), per axis; None when the grid has no sign change.
    """
    nx = s.shape[0]
    top = 0.0
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, -1)
    for i0 in range(0, nx, step):
        blk = s[i0 : min(nx, i0 + step + 1)]  # one row over: axis-0 pairs
        a = np.abs(blk[: min(step, nx - i0)])
        a = a[np.isfinite(a)]
        if a.size:
            top = max(top, float(a.max()))
        fin = np.isfinite(blk)
        neg = blk < 0
        edge = np.zeros(blk.shape, dtype=bool)
        for ax in range(3):
            a0 = [slice(None)] * 3
            a1 = [slice(None)] * 3
            a0[ax] = slice(0, -1)
            a1[ax] = slice(1, None)
            cross = fin[tuple(a0)] & fin[tuple(a1)] & (neg[tuple(a0)] != neg[tuple(a1)])
            edge[tuple(a0)] |= cross
            edge[tuple(a1)] |= cross
        idx = np.nonzero(edge)
        if len(idx[0]):
            first = np.array([int(ix.min()) for ix in idx]) + (i0, 0, 0)
            last = np.array([int(ix.max()) for ix in idx]) + (i0, 0, 0)
            lo = np.minimum(lo, first)
            hi = np.maximum(hi, last)
    if hi[0] < 0:
        return top, None
    return top, (hi - lo).astype(np.float64)


@SPEC.runner
def run_stage(
    data,
    *,
    resolution: int,
    voxel_size: float | None,
    padding: float,
    sign: str,
    band: float | None,
    knn: int,
    backend: str,
    progress=None,
):
    """Stage ``sdf``: a mesh or an oriented cloud -> signed distance :class:`~recon_cli.grid.Grid`.

    Parameters
    ----------
    data : TriangleMesh or PointCloud (with normals)
    resolution : int
        Cells along the longest side of the padded bounding box (unless ``voxel_size``).
    voxel_size : float, optional
        Sample spacing in world units (overrides ``resolution``).
    padding : float
        Margin as a fraction of the bounding box's longest side.
    sign : {"winding", "pseudonormal"}
        Inside test for meshes.
    band : float, optional
        Meshes: exact distances only within ``band`` voxels, ``±band * voxel`` beyond.
    knn : int
        Clouds: neighbours per sample.
    backend : {"native", "open3d"}
        ``open3d``: Open3D's ``RaycastingScene.compute_signed_distance`` (meshes only; its
        own inside test, ``sign`` and ``band`` do not apply).

    Returns
    -------
    StageResult
        Report keys: ``source`` ("mesh"/"cloud"), ``shape``, ``voxel_size``, ``origin``,
        ``sign``, ``band``, ``inside_samples``, ``unknown_samples``, ``eikonal`` and
        ``provenance`` (the effective voxel size); native meshes add ``sign_method``,
        ``winding_evaluations``, ``regions`` and, on closed meshes, ``winding_numbers``
        (see :func:`mesh_sdf`).

    Raises
    ------
    ParameterError
        Bad parameters, or a grid whose memory cannot be had (refused before allocating,
        with the estimate: :data:`BYTES_PER_SAMPLE`).
    InputError
        No points, non-finite coordinates, a cloud without normals, ``sign="pseudonormal"``
        on a closed mesh wound inward.
    """
    from recon_cli.geometry import float64
    from recon_cli.grid import Grid
    from recon_cli.stages import StageResult

    # parameters and the input's kind: checked by SPEC
    data = float64(data)
    is_mesh, pts = _source_points(data, backend)
    origin, h, shape = _checked_frame(pts, resolution, voxel_size, padding, backend, is_mesh)
    sdf, info, sign = _signed_distances(
        data, is_mesh, pts, origin, h, shape, sign, band, knn, backend, progress
    )
    grid = Grid(
        sdf=sdf.astype(np.float32),
        origin=origin,
        voxel_size=h,
        history=list(data.history),
        point_dtype=data.point_dtype,
    )
    del sdf  # the float64 field: free it before the report's passes over the grid
    known = int(np.count_nonzero(np.isfinite(grid.sdf)))
    report = {
        "source": "mesh" if is_mesh else "cloud",
        "shape": list(shape),
        "voxel_size": h,
        "origin": origin.tolist(),
        "sign": sign if is_mesh else "normals",
        "backend": backend,
        "band": band,
        "inside_samples": int(np.count_nonzero(grid.sdf < 0)),  # NaN < 0 is False
        "unknown_samples": int(grid.sdf.size - known),
        **info,
        "eikonal": eikonal_check(grid),
        "provenance": {
            "voxel_size": round(h, 12),
            **({"sign": "open3d"} if backend == "open3d" else {}),
        },
    }
    return StageResult(output=grid, report=report)


def _source_points(data, backend: str) -> tuple[bool, np.ndarray]:
    """Whether the input is meshed, and the points that bound the grid.

    A mesh's points are its used vertices; refuses what the stage cannot take.
    """
    from recon_cli.geometry import TriangleMesh

    is_mesh = isinstance(data, TriangleMesh) and len(data.faces) > 0
    if backend == "open3d" and not is_mesh:
        raise ParameterError(
            "the open3d backend computes distances to meshes only (a cloud needs --backend native)"
        )
    pts = data.vertices[np.unique(data.faces)] if is_mesh else data.points
    if len(pts) == 0:
        raise InputError("input has no points")
    if not np.isfinite(pts).all():
        raise InputError("input has non-finite coordinates")
    if not is_mesh and data.normals is None:
        raise InputError("point cloud has no normals (run 'recon normals' first)")
    return is_mesh, pts


def _checked_frame(pts, resolution, voxel_size, padding, backend: str, is_mesh: bool):
    """The grid's origin, voxel size and shape, checked against the memory available.

    A grid whose memory cannot be had is refused before allocating (the peak bytes per
    sample of each path).
    """
    from recon_cli.grid import allocation_problem

    origin, h, shape = grid_frame(pts.min(axis=0), pts.max(axis=0), resolution, voxel_size, padding)
    per_sample = BYTES_PER_SAMPLE[
        "open3d" if backend == "open3d" else "mesh" if is_mesh else "cloud"
    ]
    problem = allocation_problem(shape, per_sample)
    if problem:
        raise ParameterError(f"{problem}: raise --voxel-size or lower --resolution")
    return origin, h, shape


def _signed_distances(
    data, is_mesh, pts, origin, h, shape, sign, band, knn, backend, progress
) -> tuple[np.ndarray, dict, str]:
    """The signed distances (float64), the path's report keys and the sign method used."""
    from recon_cli.geometry import local_origin
    from recon_cli.progress import task

    # distances are computed about a local origin (far from the world origin squared norms and
    # cross products lose digits, Open3D computes in float32); the grid keeps the world origin
    centre = local_origin(pts)
    local = copy.copy(data)
    if is_mesh:
        local.vertices = data.vertices - centre
    else:
        local.points = data.points - centre
    with task(progress, "signed distance", 1) as t:
        if backend == "open3d":
            from recon_cli.backends import open3d_backend

            ijk = np.stack(
                np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1
            ).reshape(-1, 3)
            sdf = open3d_backend.signed_distance(local, (origin - centre) + ijk * h).reshape(shape)
            info: dict[str, Any] = {}
            sign = "open3d"
        elif is_mesh:
            sdf, info = mesh_sdf(
                local.vertices, data.faces, origin - centre, h, shape, sign=sign, band=band
            )
        else:
            sdf, info = cloud_sdf(local.points, data.normals, origin - centre, h, shape, knn=knn)
        t.advance(1)
    return sdf, info, sign
