"""Signed distance grids: from a triangle mesh (exact) or an oriented point cloud (IMLS).

Mesh: exact unsigned distance to the nearest triangle (:mod:`recon_cli.mesh.distance`), signed
by the generalised winding number (:mod:`recon_cli.mesh.winding`; robust to holes) or by
angle-weighted pseudonormals (exact on watertight meshes). On a closed, manifold,
consistently oriented mesh the two signs agree off the surface (the winding number is 0
or 1 there), so ``sign="winding"`` takes the pseudonormal sign, which the distance search
yields for free, once winding numbers on a coarse lattice confirm it (they do not on an
inside-out mesh; a closed mesh that intersects itself is caught only where the lattice
sees its winding number leave 0/1). Otherwise the winding number is only
evaluated where needed: at samples within one voxel of the surface, and on a coarse
subset of each connected region of the other samples (two neighbouring samples farther
than one voxel from the mesh cannot have the surface between them, so such a region has
one side); a region whose subset disagrees is evaluated everywhere.

Cloud: implicit moving least squares (Kolluri 2005; Hoppe 1992 with smoothing): the
Gaussian-weighted mean of the signed distances to the tangent planes of the ``knn``
nearest points. Samples farther than a few point spacings (and two voxels) from every
point are unknown (NaN), so marching cubes makes no sheet far from data.

The ``.npz`` grid format is described in :mod:`recon_cli.grid`.
"""

from __future__ import annotations


import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.params import Param, StageSpec

_SIGNS = ("winding", "pseudonormal")
_SLAB_CELLS = 500_000  # eikonal_check works on slabs of about this many samples

SPEC = StageSpec(
    name="sdf",
    summary="Signed distance grid (.npz) of a mesh or oriented cloud.",
    description="""Signed distance grid (.npz, negative inside) of a mesh or an oriented point cloud.

    Clouds need normals; samples far from every point are unknown (NaN) and `recon mcubes`
    leaves them out.""",
    takes=("mesh", "oriented"),
    gives=("grid",),
    backends=("native", "open3d"),
    output_suffix=".npz",
    params=(
        Param("resolution", "int", 128, "Cells along the longest side of the padded box.", unit="cells",
              min=2, max=2048),
        Param("voxel_size", "float", None, "Sample spacing (overrides --resolution).", unit="input units",
              min=0.0, min_open=True, words={"auto": None}),
        Param("padding", "float", 0.05, "Margin around the bounding box.", unit="fraction of the longest side", min=0.0),
        Param("sign", "choice", "winding", "Meshes: inside by generalised winding number (robust to holes) or "
              "pseudonormals (watertight).", choices=_SIGNS),
        Param("band", "float", None, "Meshes: exact distances only within this many voxels.", unit="voxels",
              min=0.0, min_open=True),
        Param("knn", "int", 10, "Clouds: neighbours averaged per sample (IMLS).", unit="points", min=1),
    ),
)


def grid_frame(
    lo: np.ndarray, hi: np.ndarray, resolution: int | None = 128, voxel_size: float | None = None, padding: float = 0.05
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
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ext = float((hi - lo).max())
    if not ext > 0:
        ext = 1.0 if voxel_size is None else float(voxel_size)
    pad = padding * ext
    org = lo - pad
    size = hi - lo + 2 * pad
    h = float(voxel_size) if voxel_size is not None else float(size.max()) / int(resolution)
    shape = tuple(int(s) for s in np.ceil(size / h - 1e-9).astype(np.int64) + 1)
    # centre the data in the (slightly larger) sampled box
    org = org - 0.5 * ((np.array(shape) - 1) * h - size)
    return org, h, shape


def grid_points(origin: np.ndarray, h: float, shape: tuple[int, int, int], mask: np.ndarray | None = None) -> np.ndarray:
    """World coordinates ((k, 3)) of all samples, or of those where ``mask``."""
    if mask is None:
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
    sign: str = "winding",
    band: float | None = None,
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
    band : float, optional
        Half-width in voxels: only samples within it get exact distances, the rest
        ``±band * voxel_size``.

    Returns
    -------
    sdf : (nx, ny, nz) float64
        Negative inside.
    info : dict
        ``winding_evaluations`` (samples where the winding number was computed),
        ``regions`` (connected regions of samples away from the surface),
        ``sign_method`` ("winding" or "pseudonormal": how the sign was found; with
        ``sign="winding"`` on a closed, manifold, consistently oriented mesh, where the
        two agree, the pseudonormal sign is used once a coarse lattice of winding numbers
        confirms it).
    """
    from scipy import ndimage

    from recon_cli.mesh.distance import build_bvh, distance_grid
    from recon_cli.mesh.winding import WindingTree

    h = float(voxel_size)
    cap = np.inf if band is None else float(band) * h
    bvh = build_bvh(vertices, faces)
    # on a closed, manifold, consistently oriented mesh the winding number is exactly 0
    # or 1 off the surface and its sign is the pseudonormal sign, which the distance
    # search gives at almost no cost; the winding number is then only checked on a
    # coarse lattice (which catches an inward orientation or a self-intersecting shell)
    closed = sign == "winding" and _closed_oriented(faces, len(vertices))
    use_pn = sign == "pseudonormal" or closed
    dist, pn_sign = distance_grid(vertices, faces, origin, h, shape, band=cap, pseudonormal=use_pn, bvh=bvh)
    tree = None
    info = {"winding_evaluations": 0, "regions": 0, "sign_method": sign}

    def winding_at(mask: np.ndarray) -> np.ndarray:
        nonlocal tree
        if tree is None:
            tree = WindingTree(vertices, faces, bvh=bvh)
        info["winding_evaluations"] += int(mask.sum())
        return tree(grid_points(origin, h, shape, mask))

    if closed:
        step = max(2, -(-max(shape) // 32))  # about 32 lattice samples per axis
        check = np.zeros(shape, dtype=bool)
        check[::step, ::step, ::step] = True
        check &= (pn_sign != 0) & (dist > h)
        agree = np.array_equal(winding_at(check) > 0.5, pn_sign[check] < 0)
        info["sign_method"] = "pseudonormal" if agree else "winding"
        use_pn = agree

    near = dist <= h
    if use_pn:
        inside = pn_sign < 0
        far = pn_sign == 0  # beyond the band: no pseudonormal sign
        far &= ~near
        del pn_sign
    else:
        inside = np.zeros(shape, dtype=bool)
        inside[near] = winding_at(near) > 0.5
        far = ~near
    del near
    labels, n = ndimage.label(far) if far.any() else (None, 0)
    info["regions"] = int(n)
    if n:
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
        win = winding_at(pick_mask) > 0.5
        n_in = np.bincount(lab, weights=win, minlength=n + 1)
        n_all = np.bincount(lab, minlength=n + 1)
        uniform_in = (n_in == n_all) & (n_all > 0)
        uniform_out = (n_in == 0) & (n_all > 0)
        inside |= uniform_in[labels] & far
        mixed = ~(uniform_in | uniform_out)
        mixed[0] = False
        if mixed.any():  # a region open through a hole: evaluate all its samples
            redo = mixed[labels]
            inside[redo] = winding_at(redo) > 0.5
    # negate in place: no second full-size array
    sdf = dist
    np.negative(sdf, out=sdf, where=inside)
    return sdf, info


def _closed_oriented(faces: np.ndarray, n_vertices: int) -> bool:
    """Every edge has exactly two faces, every vertex one fan, and the faces are
    consistently oriented: a mesh whose winding number is 0 or 1 off the surface
    (unless it intersects itself)."""
    from recon_cli.mesh.topology import Connectivity

    c = Connectivity(faces, n_vertices)
    return bool(
        c.n_faces > 0
        and np.all(c.edge_face_count == 2)
        and len(c.non_manifold_vertices) == 0
        and c.is_consistently_oriented
    )


def cloud_sdf(
    points: np.ndarray,
    normals: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    shape: tuple[int, int, int],
    knn: int = 10,
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
    (for a ``--band`` grid: the samples inside the band). Works slab by slab along the
    first axis, so its temporaries stay small next to the grid (a 256^3 grid is checked
    in about 20 MB besides 4 bytes per sample for the gradient norms kept for the median).

    Returns
    -------
    dict
        ``mean``, ``median`` of ‖∇s‖, ``fraction_within_0.1`` (share with
        |‖∇s‖ − 1| ≤ 0.1) and ``cells`` (number of samples used).
    """
    empty = {"mean": None, "median": None, "fraction_within_0.1": None, "cells": 0}
    s = np.asarray(grid.sdf)
    h = float(grid.voxel_size)
    nx = s.shape[0]
    if min(s.shape) < 3:
        return empty
    step = max(1, _SLAB_CELLS // (s.shape[1] * s.shape[2]))
    # the band's cap: the largest finite |s|
    top = 0.0
    for i0 in range(0, nx, step):
        blk = np.abs(s[i0 : i0 + step].astype(np.float64))
        blk = blk[np.isfinite(blk)]
        if blk.size:
            top = max(top, float(blk.max()))
    lim = top * (1 - 1e-6)
    c = (slice(1, -1),) * 3
    # gradient norms of the used samples (float32: only the median needs them all);
    # the mean and the share within 0.1 are summed per slab in float64
    g = np.empty((nx - 2) * (s.shape[1] - 2) * (s.shape[2] - 2), np.float32)
    n = 0
    total = 0.0
    within = 0
    for i0 in range(1, nx - 1, step):
        blk = s[i0 - 1 : min(nx, i0 + step + 1)].astype(np.float64)
        usable = np.abs(blk) < lim  # False at NaN
        ok = usable[c].copy()
        g2 = np.zeros(ok.shape)
        for ax in range(3):
            lo = [slice(1, -1)] * 3
            hi = [slice(1, -1)] * 3
            lo[ax] = slice(0, -2)
            hi[ax] = slice(2, None)
            ok &= usable[tuple(lo)] & usable[tuple(hi)]
            diff = np.where(ok, blk[tuple(hi)] - blk[tuple(lo)], 0.0) / (2 * h)
            g2 += diff * diff
        norm = np.sqrt(g2[ok])
        total += float(norm.sum())
        within += int(np.count_nonzero(np.abs(norm - 1) <= 0.1))
        g[n : n + len(norm)] = norm
        n += len(norm)
    if n == 0:
        return empty
    g = g[:n]
    half = n // 2
    g.partition(half if n % 2 else [half - 1, half])  # in place: no copy of the norms
    median = float(g[half]) if n % 2 else 0.5 * (float(g[half - 1]) + float(g[half]))
    return {
        "mean": total / n,
        "median": median,
        "fraction_within_0.1": within / n,
        "cells": int(n),
    }


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
    """Stage ``sdf``: a mesh or an oriented cloud -> a signed distance :class:`~recon_cli.grid.Grid`.

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
        ``winding_evaluations`` and ``regions`` (see :func:`mesh_sdf`).
    """
    from recon_cli.geometry import TriangleMesh, float64
    from recon_cli.grid import Grid
    from recon_cli.progress import task
    from recon_cli.stages import StageResult

    # parameters and the input's kind: checked by SPEC
    data = float64(data)
    voxel, band_v = voxel_size, band
    is_mesh = isinstance(data, TriangleMesh) and len(data.faces) > 0
    if backend == "open3d" and not is_mesh:
        raise ParameterError("the open3d backend computes distances to meshes only (a cloud needs --backend native)")
    pts = data.vertices[np.unique(data.faces)] if is_mesh else data.points
    if len(pts) == 0:
        raise InputError("input has no points")
    if not np.isfinite(pts).all():
        raise InputError("input has non-finite coordinates")
    if not is_mesh and data.normals is None:
        raise InputError("point cloud has no normals (run 'recon normals' first)")
    origin, h, shape = grid_frame(pts.min(axis=0), pts.max(axis=0), resolution, voxel, padding)
    cells = int(np.prod(shape))
    if cells > 2048**3:
        raise ParameterError(f"grid of {shape} samples is too large; lower the resolution")

    with task(progress, "signed distance", 1) as t:
        if backend == "open3d":
            from recon_cli.backends import open3d_backend

            ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
            sdf = open3d_backend.signed_distance(data, origin + ijk * h).reshape(shape)
            info = {}
            sign = "open3d"
        elif is_mesh:
            sdf, info = mesh_sdf(data.vertices, data.faces, origin, h, shape, sign=sign, band=band_v)
        else:
            sdf, info = cloud_sdf(data.points, data.normals, origin, h, shape, knn=knn)
        t.advance(1)
    grid = Grid(sdf=sdf.astype(np.float32), origin=origin, voxel_size=h, history=list(data.history))
    del sdf  # the float64 field: free it before the report's passes over the grid
    known = int(np.count_nonzero(np.isfinite(grid.sdf)))
    report = {
        "source": "mesh" if is_mesh else "cloud",
        "shape": list(shape),
        "voxel_size": h,
        "origin": origin.tolist(),
        "sign": sign if is_mesh else "normals",
        "backend": backend,
        "band": band_v,
        "inside_samples": int(np.count_nonzero(grid.sdf < 0)),  # NaN < 0 is False
        "unknown_samples": int(grid.sdf.size - known),
        **info,
        "eikonal": eikonal_check(grid),
        "provenance": {"voxel_size": round(h, 12), **({"sign": "open3d"} if backend == "open3d" else {})},
    }
    return StageResult(output=grid, report=report)
