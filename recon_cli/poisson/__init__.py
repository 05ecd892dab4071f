"""Screened Poisson surface reconstruction (Kazhdan & Hoppe 2013), our own, adaptive.

The oriented samples define a vector field ``W`` (normals splatted with a quadratic
B-spline kernel, weighted by the area each sample stands for); the indicator ``chi`` (about
1 inside, 0 outside) minimises

    int |grad chi - W|^2  +  alpha * sum_p w_p (chi(p) - 1/2)^2,

discretised with trilinear (Q1) hat functions on a sparse multilevel grid: level ``d``
holds the cells of the ``2**d`` lattice within two cells of a sample (every cell up to
``full_depth``), complete in siblings, so memory grows with the surface. ``chi`` is the sum
of the levels' functions; it is solved cascadically, coarse to fine, each level by
Jacobi-preconditioned conjugate gradients on the residual left by the coarser ones (as
PoissonRecon does). The surface is the level set of ``chi`` at the weighted mean of its
values at the samples, extracted by :func:`recon_cli.mcubes.marching_cubes_sparse` on the
finest lattice: each leaf of the tree is refined (exactly, ``chi`` being trilinear in it)
down to the finest cells only where it straddles the iso-value, and every lattice value
is computed once, so there are no cracks between cells of different sizes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, as_point_cloud
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task

if TYPE_CHECKING:
    from recon_cli.stages import StageResult

log = logging.getLogger("recon")

BOUNDARIES = ("neumann", "dirichlet")
BACKENDS = ("native", "open3d", "pymeshlab")
MAX_DEPTH = 14
# cells kept around each occupied cell at every level (PoissonRecon keeps the B-spline support);
# _build_levels builds this ring as the children of the parents within 1 of an occupied parent,
# which holds for 2 only
_RING = 2
# the kernel-density level is this much coarser than the finest (PoissonRecon's kernelDepth)
_KERNEL_OFFSET = 2
# sparse samples are splatted at most this many levels coarser than the finest
_MAX_SPLAT_OFFSET = 2
_TARGET = 0.5
# how far below the iso-value chi is clamped on the cube's faces (chi jumps by about 1)
_FACE_MARGIN = 1e-3


@dataclass
class PoissonResult:
    """What :func:`screened_poisson` returns.

    Attributes
    ----------
    mesh : TriangleMesh
        The surface; ``attributes["density"]`` when asked for, ``colors`` when the input
        had colours.
    report : dict
        ``vertices``, ``faces``, ``depth``, ``iso_value``, ``solver_iterations``,
        ``residual`` (relative residual of the finest level), ``trimmed_faces`` and details
        (``samples``, ``nodes`` per level, ``timings``).
    """

    mesh: TriangleMesh
    report: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# the declaration (every option's type, default and range) and validation
SPEC = StageSpec(
    name="poisson",
    summary="Screened Poisson reconstruction of an oriented cloud.",
    description="""Screened Poisson reconstruction (Kazhdan & Hoppe 2013) on a sparse octree.

    IN must carry normals (run 'recon normals' first, or pass --estimate-normals). Colours
    on IN are interpolated onto the output vertices. With -v the solver's iterations and
    residual per level are logged.""",
    takes=("oriented",),
    takes_when=lambda p: ("cloud", "mesh") if p["estimate_normals"] else ("oriented",),
    gives=("mesh",),
    backends=BACKENDS,
    params=(
        Param("depth", "int", 8, "Finest octree level: the finest cell is the reconstruction cube / 2^depth.",
              min=1, max=MAX_DEPTH),
        Param("scale", "float", 1.1, "Reconstruction cube / largest side of the bounding box.", unit="ratio", min=1.0),
        Param("point_weight", "float", 4.0, "Screening weight (0 = classic unscreened Poisson).", min=0.0),
        Param("samples_per_node", "float", 1.5, "Fewer samples per finest cell than this: splat coarser (smoother).",
              unit="samples", min=0.0, min_open=True),
        Param("boundary", "choice", "neumann", "Condition on the faces of the cube.", choices=BOUNDARIES),
        Param("density", "bool", False, "Write the per-vertex sampling density as vertex property 'density'."),
        Param("trim", "float", 0.0, "Remove the surface whose density is in the lowest Q quantile.",
              unit="quantile", min=0.0, max=1.0, max_open=True, metavar="Q"),
        Param("estimate_normals", "bool", False, "Estimate and orient normals first (as 'recon normals' does)."),
    ),
)
# options of the library function only
_FULL_DEPTH = Param("full_depth", "int", 5, "Levels up to this one are complete grids.", min=0, max=7)
_CG_TOLERANCE = Param("cg_tolerance", "float", 1e-3, "Relative residual at which each level's CG stops.",
                      min=0.0, max=1.0, min_open=True)


def _check_options(depth, scale, point_weight, samples_per_node, boundary, density, trim) -> tuple:
    """Validate and convert the options shared by :func:`screened_poisson` and :func:`run_stage`."""
    v = SPEC.check(dict(depth=depth, scale=scale, point_weight=point_weight, samples_per_node=samples_per_node,
                        boundary=boundary, density=density, trim=trim), complete=False)
    return v["depth"], v["scale"], v["point_weight"], v["samples_per_node"], v["boundary"], v["density"], v["trim"]


def _check_inputs(points: Any, normals: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Finite (n, 3) points and unit normals; returns (points, normals, kept mask)."""
    if normals is None:
        raise InputError("the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)")
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    if nrm.shape != pts.shape:
        raise InputError(f"normals must have shape {pts.shape}, got {nrm.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("points contain NaN or infinite coordinates")
    if not np.all(np.isfinite(nrm)):
        raise InputError("normals contain NaN or infinite values")
    length = np.linalg.norm(nrm, axis=1)
    keep = length > 0
    if not keep.any():
        raise InputError("every normal has zero length: run 'recon normals' to estimate them")
    if keep.sum() < 4:
        raise InputError(f"poisson needs at least 4 points with non-zero normals, got {int(keep.sum())}")
    pts = pts[keep]
    nrm = nrm[keep] / length[keep, None]
    extent = pts.max(axis=0) - pts.min(axis=0)
    if not extent.max() > 0:
        raise InputError("all points coincide: there is no surface to reconstruct")
    return pts, nrm, keep


# ---------------------------------------------------------------------------------------------
# the sparse multilevel grid
@dataclass
class _Level:
    depth: int
    # lookups are binary searches in the sorted keys: hash tables would double the memory
    cell_keys: np.ndarray  # (c,) int64 sorted keys
    node_keys: np.ndarray | None  # (m,) int64 sorted keys (dropped once the level is set up)
    n_nodes: int
    cell_nodes: np.ndarray  # (c, 4) int32: corners 0..3, corner q + 4 is node cell_nodes[c, q] + 1
    unknown: np.ndarray | None  # (m,) bool: hat functions solved for at this level
    ncell: np.ndarray | None  # (m,) int8: cells incident to each node (the stiffness diagonal)
    cell_parent: np.ndarray | None = None  # (c,) int32 index in the coarser level
    # set by the solve, for the extraction: the nodes on the cube's faces and the leaf cells
    face_nodes: np.ndarray | None = None
    leaf: np.ndarray | None = None


def _pack(xyz: np.ndarray) -> np.ndarray:
    xyz = xyz.astype(np.int64)
    return (xyz[:, 0] << 42) | (xyz[:, 1] << 21) | xyz[:, 2]


def _dilate(keys: np.ndarray, axis: int, lo: int, hi: int, limit: int) -> np.ndarray:
    """Unique keys within [lo, hi] of ``keys`` along ``axis`` (sorted along that axis)."""
    from recon_cli.poisson import _kernel as K

    k = np.sort(K.rekey(keys, axis, False))
    return K.rekey(K.dilate_minor(k, lo, hi, limit), axis, True)


def _build_levels(sample_keys_finest: np.ndarray, depth: int, full_depth: int, boundary: str) -> list[_Level]:
    from recon_cli.poisson import _kernel as K

    levels: list[_Level] = []
    occ_keys = sample_keys_finest
    occ = [None] * (depth + 1)
    for d in range(depth, full_depth, -1):
        occ[d] = occ_keys
        occ_keys = np.unique(K.halve(occ_keys))  # halving breaks the x-major order
    for d in range(depth + 1):
        top = (1 << d) - 1
        if d <= full_depth:
            r = np.arange(top + 1, dtype=np.int64)
            g = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
            keys = _pack(g)
        else:
            # the cells within _RING (= 2) of an occupied cell, completed in siblings, are the
            # children of the parents within 1 of an occupied parent (floor((o +- 2) / 2) =
            # floor(o / 2) +- 1 for either parity): dilate at the coarser level, 8x fewer keys,
            # and emit the children already sorted, with their parent index
            keys = occ[d - 1] if d - 1 > full_depth else np.unique(K.halve(occ[d]))
            for axis in range(3):
                keys = _dilate(keys, axis, -1, 1, top >> 1)  # valid for _RING == 2 only
            # (the last dilation, along z, leaves the keys sorted and unique)
            par_idx = K.merge_lookup(keys, levels[-1].cell_keys)
            # the nodes of the children of parent p are 2p + {0, 1, 2}^3
            nodes = K.double(keys)
            keys, cell_parent = K.children_sorted(keys, par_idx)
            del par_idx
            for axis in range(3):
                nodes = _dilate(nodes, axis, 0, 2, top + 1)
        if d <= full_depth:
            nodes = keys
            for axis in range(3):
                nodes = _dilate(nodes, axis, 0, 1, top + 1)
        # sorted queries (a constant offset keeps the order): linear merges, no hashing;
        # int32 and 4 corners of 8: a quarter of (c, 8) int64, the largest array
        cell_nodes = K.corner_nodes(keys, nodes)
        ncell = K.node_cell_count(cell_nodes, len(nodes))
        unknown = K.unknown_nodes(nodes, ncell, top + 1, boundary == "dirichlet")
        lev = _Level(d, keys, nodes, len(nodes), cell_nodes, unknown, ncell)
        if d > 0:
            lev.cell_parent = cell_parent if d > full_depth else K.bsearch_many(levels[-1].cell_keys, K.halve(keys))
        levels.append(lev)
    return levels


# ---------------------------------------------------------------------------------------------
def screened_poisson(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    depth: int = SPEC.param("depth").default,
    scale: float = SPEC.param("scale").default,
    point_weight: float = SPEC.param("point_weight").default,
    samples_per_node: float = SPEC.param("samples_per_node").default,
    boundary: str = SPEC.param("boundary").default,
    density: bool = SPEC.param("density").default,
    trim: float = SPEC.param("trim").default,
    colors: np.ndarray | None = None,
    full_depth: int = _FULL_DEPTH.default,
    cg_tolerance: float = _CG_TOLERANCE.default,
    progress: Any = None,
) -> PoissonResult:
    """Screened Poisson reconstruction of an oriented point set.

    Parameters
    ----------
    points : (n, 3) float
        Sample positions (world units). Points with a zero-length normal are ignored.
    normals : (n, 3) float
        Outward normals (any non-zero length; normalised here).
    depth : int
        Finest level: the finest cell is the bounding cube (largest extent times ``scale``)
        divided by ``2**depth``. 1 to 14.
    scale : float
        Ratio of the reconstruction cube to the bounding box's largest side (>= 1).
    point_weight : float
        Screening weight alpha (>= 0; 0 = classic unscreened Poisson).
    samples_per_node : float
        Minimum number of samples per finest cell under which samples are splatted at a
        coarser level (smoother over sparse regions), > 0.
    boundary : {"neumann", "dirichlet"}
        Condition on the cube's faces (Dirichlet: ``chi = 0``, the outside).
    density : bool
        Add the per-vertex kernel density of the samples as ``attributes["density"]``.
    trim : float
        Remove the faces whose mean vertex density is in the lowest ``trim`` quantile
        (0 <= trim < 1; 0 keeps everything), splitting vertices left non-manifold.
    colors : (n, 3) or (n, 4) array or None
        Per-point colours, interpolated onto the output vertices.
    full_depth : int
        Levels up to this one are complete grids.
    cg_tolerance : float
        Relative residual at which each level's conjugate gradients stop.
    progress : Progress or None

    Returns
    -------
    PoissonResult
    """
    depth, scale, point_weight, samples_per_node, boundary, density, trim = _check_options(
        depth, scale, point_weight, samples_per_node, boundary, density, trim
    )
    full_depth = _FULL_DEPTH.coerce(full_depth)
    cg_tolerance = _CG_TOLERANCE.coerce(cg_tolerance)
    pts, nrm, keep = _check_inputs(points, normals)
    if colors is not None:
        colors = np.asarray(colors)
        if len(colors) != len(keep):
            raise InputError(f"colors has {len(colors)} rows, expected {len(keep)}")
        colors = colors[keep]

    from recon_cli._kernels.hashtable import build_table
    from recon_cli.memory import release_free_heap
    from recon_cli.poisson import _kernel as K
    from recon_cli.poisson._luts import B2_PLANE_DENSITY, UNIT_STIFFNESS

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    full_depth = min(full_depth, depth)

    # ---- unit cube and samples (points merged per finest cell, as PoissonRecon does)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    size = float((hi - lo).max()) * scale
    origin = 0.5 * (lo + hi) - 0.5 * size
    unit = (pts - origin) / size
    res = 1 << depth
    cxyz = np.clip(np.floor(unit * res).astype(np.int64), 0, res - 1)
    skeys, inv = np.unique(_pack(cxyz), return_inverse=True)
    inv = inv.reshape(-1)
    ns = len(skeys)
    count = np.bincount(inv, minlength=ns).astype(np.float64)
    spos = np.empty((ns, 3))
    snrm = np.empty((ns, 3))
    for a in range(3):
        spos[:, a] = np.bincount(inv, weights=unit[:, a], minlength=ns) / count
        snrm[:, a] = np.bincount(inv, weights=nrm[:, a], minlength=ns)
    del unit, cxyz, inv
    timings["samples"] = time.perf_counter() - t0

    # ---- tree
    t = time.perf_counter()
    with task(progress, "poisson: tree"):
        levels = _build_levels(skeys, depth, full_depth, boundary)
    timings["tree"] = time.perf_counter() - t
    log.info("poisson: %d points, %d samples, depth %d, nodes per level %s", len(pts), ns, depth, [len(lv.node_keys) for lv in levels])

    # ---- kernel density -> area per point and splat level
    t = time.perf_counter()
    kd = max(depth - _KERNEL_OFFSET, 0)
    klev = levels[kd]
    ktab = build_table(klev.cell_keys)  # a coarse level: its hash table is small
    dens_cells = K.density_splat(spos, count, kd, *ktab, len(klev.cell_keys))
    rho = K.density_eval(spos, kd, *ktab, dens_cells)
    hk = 1.0 / (1 << kd)
    area_pt = B2_PLANE_DENSITY * hk * hk / np.maximum(rho, 1e-12)  # unit-cube area per point
    per_node = (rho / B2_PLANE_DENSITY) * 4.0 ** (kd - depth)  # samples per finest cell
    splat = np.full(ns, float(depth))
    sparse = per_node < samples_per_node
    splat[sparse] = depth - 0.5 * np.log2(samples_per_node / per_node[sparse])
    splat = np.clip(splat, max(depth - _MAX_SPLAT_OFFSET, 0), depth)
    s_lo = np.floor(splat).astype(np.int64)
    s_frac = splat - s_lo
    s_frac[s_lo == depth] = 0.0
    s_lo = np.minimum(s_lo, depth)
    normal_w = -(area_pt * 1.0)[:, None] * snrm  # chi is 1 inside: its gradient is -n
    # splat items: each sample's share at its two levels, merged per cell of that level (as
    # PoissonRecon merges samples per node), so coarse splats cost per cell, not per sample
    it_pos, it_vec, it_lvl = _merge_splats(spos, normal_w, count, s_lo, s_frac)
    log.info("poisson: %d splats from %d samples", len(it_pos), ns)
    mean_area = float((area_pt * count).sum() / count.sum())
    # calibrated against the references: with alpha = w * mean_area * 2**depth our fit at
    # weight w matched Open3D's (PoissonRecon's code, weight 2) at w = 1 on noisy samples
    # (Chamfer ratio 0.99-1.0 on armadillo, kitten, bunny at depth 9), so the same nominal
    # weight means half that alpha here
    alpha = 0.5 * point_weight * mean_area * (1 << depth)
    screen_w = alpha * count
    del klev
    if not (density or trim > 0):
        del ktab, dens_cells  # only the output densities need them
    timings["density"] = time.perf_counter() - t

    # ---- cascadic solve
    # each level's arrays go as soon as no later step needs them: at the finest level the
    # peak is the level's cells plus the solver's (n,) vectors, tens of MB each
    t = time.perf_counter()
    total_it = 0
    last_res = 0.0
    gvals: list[np.ndarray] = []
    per_level = []
    with task(progress, "poisson: solve", total=depth + 1) as tk:
        for lev in levels:
            release_free_heap()
            tl = time.perf_counter()
            d = lev.depth
            nn = lev.n_nodes
            ke = UNIT_STIFFNESS / (1 << d)
            # (n,) vectors are updated in place
            rhs = K.splat_rhs(it_pos, it_vec, it_lvl, np.zeros(len(it_lvl)), d, lev.node_keys, lev.unknown, nn)
            # past the right-hand side only the nodes on the cube's faces are needed (for the
            # extraction's clamp), not the node keys
            lev.face_nodes = K.face_nodes(lev.node_keys, 1 << d)
            lev.node_keys = None
            scell, sloc = K.sample_cells(spos, d, lev.cell_keys)
            # the diagonal, for the preconditioner: a table by incident-cell count (lev.ncell)
            # plus the sparse screening part, not an (n,) vector
            if alpha > 0:
                sd_nodes, sd_vals = K.screening_diag_rhs(scell, sloc, lev.cell_nodes, screen_w, _TARGET, rhs)
            else:
                sd_nodes, sd_vals = np.zeros(0, np.int64), np.zeros(0)
            sw = screen_w if alpha > 0 else np.zeros(0)
            cscr = np.zeros((0, 8, 8))
            if alpha > 0 and 4 * len(lev.cell_keys) <= len(sw) and len(lev.cell_keys) <= 1 << 19:
                # coarse levels: samples outnumber cells, so sum each cell's samples into its
                # own 8x8 screening matrix once (exact) and let a CG step cost O(cells);
                # (c, 8, 8) floats, so only up to 2**19 cells (256 MB)
                cscr = K.cell_screening(scell, sloc, sw, len(lev.cell_keys))
                sw = np.zeros(0)
            par = levels[d - 1] if d > 0 else None
            if par is not None:
                # the coarser levels' chi at this level's nodes; prolonged again after the
                # solve rather than kept: one (n,) vector fewer during the conjugate gradients
                G = K.prolong(lev.cell_nodes, lev.cell_keys, lev.cell_parent, par.cell_nodes, gvals[-1], nn)
                AG = np.empty(nn)
                K.level_matvec(lev.cell_nodes, ke, cscr, scell, sloc, sw, G, AG)
                del G
                rhs -= AG
                del AG
            exact = d <= full_depth
            release_free_heap()  # the set-up's temporaries: not resident while the solver runs
            x, it, rel = K.level_pcg(
                lev.cell_nodes, ke, cscr, scell, sloc, sw, rhs, lev.ncell, sd_nodes, sd_vals, lev.unknown,
                1e-7 if exact else cg_tolerance, 2000 if exact else 200,
            )
            del rhs, sd_nodes, sd_vals, scell, sloc, cscr
            if par is not None:
                G = K.prolong(lev.cell_nodes, lev.cell_keys, lev.cell_parent, par.cell_nodes, gvals[-1], nn)
                # the coarser level's leaves are its cells without children here
                par.leaf = ~K.cell_has_child(lev.cell_parent, len(par.cell_keys))
                lev.cell_parent = None
            else:
                G = np.zeros(nn)
            G += x
            del x
            gvals.append(G)
            total_it += it
            last_res = rel
            n_unknown = int(lev.unknown.sum())
            lev.unknown = lev.ncell = None
            per_level.append({"depth": d, "nodes": nn, "unknowns": n_unknown, "iterations": it, "residual": rel,
                              "seconds": time.perf_counter() - tl})
            log.info("poisson: level %2d  nodes %9d  unknowns %9d  cg iterations %4d  residual %.2e  %.2f s", d, nn, n_unknown, it, rel, time.perf_counter() - tl)
            tk.advance(1)
    del G, par
    levels[-1].leaf = np.ones(len(levels[-1].cell_keys), bool)
    timings["solve"] = time.perf_counter() - t

    # ---- iso-value: weighted mean of chi at the samples
    fin = levels[-1]
    scell, sloc = K.sample_cells(spos, depth, fin.cell_keys)
    chi_s = K.eval_at_samples(scell, sloc, fin.cell_nodes, gvals[-1])
    iso = float((chi_s * count).sum() / count.sum())
    del fin, scell, sloc, chi_s
    log.info("poisson: iso-value %.6f", iso)

    # ---- extraction: leaves refined to the finest lattice where they straddle the iso-value
    t = time.perf_counter()
    from recon_cli.mcubes import marching_cubes_sparse

    for lev, g in zip(levels, gvals):
        # the cube's faces count as outside, so a surface running into them is closed there
        # (in place: chi is not needed after the extraction)
        K.clamp_on_faces(lev.face_nodes, g, iso - _FACE_MARGIN)
    # only leaves whose corner range reaches the iso-value can hold surface: count their
    # finest cells first, then write them straight into arrays of the exact size (per-level
    # parts and their concatenation would hold the cells twice)
    none_xyz, none_val = np.zeros((0, 3), np.int64), np.zeros((0, 8))
    counts = [K.refine_leaves(lev.cell_keys, lev.cell_nodes, lev.leaf, g, lev.depth, depth, iso, 1e-9, none_xyz, none_val)
              for lev, g in zip(levels, gvals)]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cells = np.empty((int(offsets[-1]), 3), np.int64)
    vals = np.empty((int(offsets[-1]), 8))
    # finest first, freeing each level once written: it holds most of the memory
    for d in range(depth, -1, -1):
        lev = levels.pop()
        K.refine_leaves(lev.cell_keys, lev.cell_nodes, lev.leaf, gvals.pop(), d, depth, iso, 1e-9,
                        cells[offsets[d]:offsets[d + 1]], vals[offsets[d]:offsets[d + 1]])
    del levels, gvals, lev, g
    # one value per lattice point whichever leaf computed it (they agree up to rounding)
    ckeys = K.corner_keys(cells)
    # one unstable argsort and a linear pass: np.unique's stable sort and inverse cost 4x more
    order = np.argsort(ckeys)
    K.unify_corner_values(vals, ckeys[order], order)
    del ckeys, order
    verts, faces = marching_cubes_sparse(cells, vals, -iso, origin=tuple(origin), spacing=size / res)
    del cells, vals
    timings["extract"] = time.perf_counter() - t

    mesh = TriangleMesh(vertices=verts, faces=faces)
    vdens = None
    if density or trim > 0:
        vdens = K.density_eval((verts - origin) / size, kd, *ktab, dens_cells)
    trimmed = 0
    if trim > 0 and len(faces):
        mesh, vdens, trimmed = _trim(mesh, vdens, trim)
    if density:
        mesh.attributes["density"] = vdens
    if colors is not None and len(mesh.vertices):
        mesh.colors = _interpolate_colors(pts, colors, mesh.vertices, size / res)
    timings["total"] = time.perf_counter() - t0
    report = {
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "depth": depth,
        "iso_value": iso,
        "solver_iterations": int(total_it),
        "residual": float(last_res),
        "trimmed_faces": int(trimmed),
        "samples": int(ns),
        "ignored_points": int((~keep).sum()),
        "finest_cell": size / res,
        "levels": per_level,
        "timings": timings,
    }
    return PoissonResult(mesh, report)


def _merge_splats(pos, vec, count, s_lo, s_frac):
    """Per level, the samples' shares merged per cell: (count-weighted mean position, summed
    vector, level)."""
    parts = [(s_lo, 1.0 - s_frac), (s_lo + 1, s_frac)]
    out_p, out_v, out_l = [], [], []
    for lvl_arr, w in parts:
        for lvl in np.unique(lvl_arr[w > 0]):
            sel = (lvl_arr == lvl) & (w > 0)
            p = pos[sel]
            ww = w[sel]
            keys = _pack(np.floor(p * (1 << int(lvl))).astype(np.int64))
            _, inv = np.unique(keys, return_inverse=True)
            inv = inv.reshape(-1)
            m = int(inv.max()) + 1
            cw = count[sel] * ww
            tot = np.bincount(inv, weights=cw, minlength=m)
            mp = np.stack([np.bincount(inv, weights=p[:, a] * cw, minlength=m) / tot for a in range(3)], axis=1)
            mv = np.stack([np.bincount(inv, weights=vec[sel, a] * ww, minlength=m) for a in range(3)], axis=1)
            out_p.append(mp)
            out_v.append(mv)
            out_l.append(np.full(m, int(lvl), np.int64))
    return np.concatenate(out_p), np.concatenate(out_v), np.concatenate(out_l)


def _trim(mesh: TriangleMesh, vdens: np.ndarray, q: float) -> tuple[TriangleMesh, np.ndarray, int]:
    """Drop the surface of the lowest-density ``q`` fraction of vertices; keep it manifold.

    A vertex is low when its density is at most the ``q`` quantile of the vertex densities;
    a face goes when at least two of its vertices are low; vertices left with several fans
    are split, unreferenced ones removed. A plateau at the threshold goes whole: on an
    open scan most of the closing sheet has density exactly 0, and ranking ties by index
    would keep an arbitrary part of it.
    """
    low = vdens <= np.quantile(vdens, q)
    keepf = low[mesh.faces].sum(axis=1) < 2
    faces = mesh.faces[keepf]
    faces, src = _split_nonmanifold_vertices(faces, len(mesh.vertices))
    used = np.unique(faces)
    remap = np.full(len(src), -1, np.int64)
    remap[used] = np.arange(len(used))
    out = TriangleMesh(vertices=mesh.vertices[src[used]], faces=remap[faces], history=list(mesh.history))
    return out, vdens[src[used]], int((~keepf).sum())


def _split_nonmanifold_vertices(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Give each fan of faces around a vertex its own copy of the vertex.

    Returns the new faces and, per new vertex, its source vertex.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(faces)
    if m == 0:
        return faces, np.arange(n_vertices)
    # corners (face, k) sharing a vertex are linked when their faces share an edge at it
    corner_v = faces.reshape(-1)
    ids = np.arange(3 * m)
    # each half-edge (a -> b) of face f links corner (f, a) with the corner of vertex a in the
    # face across the edge, found through the sorted edge key
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    lo_ = np.minimum(a, b)
    hi_ = np.maximum(a, b)
    ekey = lo_ * n_vertices + hi_
    order = np.argsort(ekey, kind="stable")
    ek = ekey[order]
    same = np.nonzero(ek[1:] == ek[:-1])[0]
    h1 = order[same]
    h2 = order[same + 1]
    # half-edge h = 3f + k goes from corner 3f + k to corner 3f + (k+1)%3
    def corner_of(h, v):
        f = h // 3
        k = np.where(faces[f, 0] == v, 0, np.where(faces[f, 1] == v, 1, 2))
        return 3 * f + k

    rows, cols = [], []
    for end in (lo_, hi_):
        v1 = end[h1]
        rows.append(corner_of(h1, v1))
        cols.append(corner_of(h2, v1))
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * m, 3 * m))
    _, lab = connected_components(g, directed=False)
    # one new vertex per (vertex, fan)
    key = corner_v.astype(np.int64) * (3 * m) + lab
    _, first, newv = np.unique(key, return_index=True, return_inverse=True)
    src = np.concatenate([corner_v[first], np.setdiff1d(np.arange(n_vertices), corner_v)])
    del ids
    return newv.reshape(-1, 3).astype(np.int64), src


def _interpolate_colors(pts: np.ndarray, colors: np.ndarray, verts: np.ndarray, cell: float) -> np.ndarray:
    """Gaussian-weighted mean colour of the nearest input points (sigma = one finest cell)."""
    from scipy.spatial import cKDTree

    k = min(8, len(pts))
    dist, idx = cKDTree(pts).query(verts, k=k)
    dist = dist.reshape(len(verts), k)
    idx = idx.reshape(len(verts), k)
    w = np.exp(-0.5 * (dist / cell) ** 2)
    w[:, 0] = np.maximum(w[:, 0], 1e-300)  # the nearest point always counts
    w /= w.sum(axis=1, keepdims=True)
    c = (colors[idx].astype(np.float64) * w[:, :, None]).sum(axis=1)
    if colors.dtype.kind in "ui":
        info = np.iinfo(colors.dtype)
        return np.clip(np.round(c), info.min, info.max).astype(colors.dtype)
    return c.astype(colors.dtype)


@SPEC.runner
def run_stage(
    data: Any,
    *,
    depth: int,
    scale: float,
    point_weight: float,
    samples_per_node: float,
    boundary: str,
    density: bool,
    trim: float,
    estimate_normals: bool,
    backend: str,
    progress: Any = None,
) -> "StageResult":
    """Stage ``poisson``: screened Poisson reconstruction of an oriented cloud.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Oriented points (a mesh's vertices and vertex normals are used).
    depth, scale, point_weight, samples_per_node, boundary, density, trim
        See :func:`screened_poisson`.
    estimate_normals : bool
        Estimate and orient normals first with the ``normals`` stage (its defaults), replacing
        any the input has.
    backend : {"native", "open3d", "pymeshlab"}
        ``open3d``: ``create_from_point_cloud_poisson`` (depth, scale; its densities);
        ``pymeshlab``: ``generate_surface_reconstruction_screened_poisson`` (depth, scale,
        samples per node, point weight). ``density``/``trim`` use Open3D's densities; the
        PyMeshLab backend has none.

    Returns
    -------
    StageResult
        ``output`` a TriangleMesh; ``report`` with ``vertices``, ``faces``, ``depth``,
        ``iso_value``, ``solver_iterations``, ``residual``, ``trimmed_faces``, ``backend``
        (the solver keys are None for the reference backends).
    """
    from recon_cli.stages import StageResult

    if backend == "pymeshlab" and (density or trim > 0):
        raise ParameterError("the pymeshlab backend gives no densities: --density/--trim need native or open3d")
    cloud = as_point_cloud(data)
    history = list(cloud.history)
    if estimate_normals:
        try:
            from recon_cli import normals as normals_mod
        except ModuleNotFoundError:
            raise ParameterError("--estimate-normals needs the normals stage, which is not available") from None
        est = normals_mod.run_stage(PointCloud(points=cloud.points), progress=progress)
        cloud = cloud.copy()
        cloud.normals = est.output.normals
    if cloud.normals is None:
        raise InputError("the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)")

    if backend == "native":
        res = screened_poisson(
            cloud.points, cloud.normals, depth=depth, scale=scale, point_weight=point_weight,
            samples_per_node=samples_per_node, boundary=boundary, density=density, trim=trim,
            colors=cloud.colors, progress=progress,
        )
        mesh, rep = res.mesh, res.report
        report = {k: rep[k] for k in ("vertices", "faces", "depth", "iso_value", "solver_iterations", "residual", "trimmed_faces")}
        report["samples"] = rep["samples"]
        report["ignored_points"] = rep["ignored_points"]
    else:
        pts, nrm, keep = _check_inputs(cloud.points, cloud.normals)
        clean = PointCloud(points=pts, normals=nrm, colors=None if cloud.colors is None else cloud.colors[keep], history=history)
        from recon_cli.backends import backend_module

        mod = backend_module(backend)
        if backend == "open3d":
            mesh, dens = mod.poisson(clean, depth=depth, scale=scale)
        else:
            mesh, dens = mod.poisson(clean, depth=depth, scale=scale, samples_per_node=samples_per_node, point_weight=point_weight), None
        trimmed = 0
        if trim > 0 and len(mesh.faces):
            mesh, dens, trimmed = _trim(mesh, dens, trim)
        if density and dens is not None:
            mesh.attributes["density"] = dens
        report = {
            "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)), "depth": depth,
            "iso_value": None, "solver_iterations": None, "residual": None, "trimmed_faces": int(trimmed),
        }
    mesh.history = history
    report["backend"] = backend
    return StageResult(output=mesh, report=report)
