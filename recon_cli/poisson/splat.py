"""The samples and their splats: points merged per finest cell, the kernel density of the
samples (area per sample, splat level), the normals' splat items."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon_cli._kernels.hashtable import build_table
from recon_cli.poisson import _splat as S
from recon_cli.poisson._luts import B2_PLANE_DENSITY
from recon_cli.poisson.octree import dilate, pack_keys, unpack_keys

log = logging.getLogger("recon")

# the kernel-density level is this much coarser than the finest (PoissonRecon's kernelDepth)
KERNEL_OFFSET = 2
# a sample's depth is extrapolated from the finest level where its density is at least this
# many times samples-per-node (one level coarser than where it reaches samples-per-node): at
# the first level that merely reaches it, the estimate is noisy and biased up (the samples
# that pass there are the locally dense ones), and would depend on the nominal depth
ESTIMATE_FACTOR = 4.0


@dataclass
class Samples:
    """Points merged per finest cell (as PoissonRecon does), unit-cube coordinates."""

    keys: np.ndarray  # (s,) int64 sorted keys of the finest cells holding points
    pos: np.ndarray  # (s, 3) mean position
    normal: np.ndarray  # (s, 3) summed unit normals
    count: np.ndarray  # (s,) float points merged
    depth: int  # the level of ``keys``


@dataclass
class Splats:
    """The normals' splat items and the screening weights."""

    pos: np.ndarray  # (k, 3) item position (count-weighted mean of its samples' shares)
    vec: np.ndarray  # (k, 3) summed normal times area (sign included: chi's gradient is -n)
    level: np.ndarray  # (k,) int64 splat level
    screen_w: np.ndarray  # (s,) screening weight per sample
    alpha: float
    tree_depth: int  # the finest splat level: the tree goes no deeper
    # the kernel density (level, hash table of its cells, per-cell density), kept only for
    # the output densities
    density: tuple | None = None
    # the right-hand side's items: the splat items' vectors shared among the 27 cells around
    # them with quadratic B-spline weights, at the cells' centres (:func:`spread_items`)
    rhs_pos: np.ndarray | None = None
    rhs_vec: np.ndarray | None = None
    rhs_level: np.ndarray | None = None


def merge_samples(unit: np.ndarray, nrm: np.ndarray, depth: int) -> Samples:
    """Merge the points ``unit`` (n, 3) in the unit cube, with unit normals ``nrm``, per cell
    of level ``depth``."""
    res = 1 << depth
    cxyz = np.clip(np.floor(unit * res).astype(np.int64), 0, res - 1)
    skeys, inv = np.unique(pack_keys(cxyz), return_inverse=True)
    inv = inv.reshape(-1)
    ns = len(skeys)
    count = np.bincount(inv, minlength=ns).astype(np.float64)
    spos = np.empty((ns, 3))
    snrm = np.empty((ns, 3))
    for a in range(3):
        spos[:, a] = np.bincount(inv, weights=unit[:, a], minlength=ns) / count
        snrm[:, a] = np.bincount(inv, weights=nrm[:, a], minlength=ns)
    return Samples(skeys, spos, snrm, count, depth)


def _density_table(smp: Samples, level: int) -> tuple:
    """The samples' kernel density at ``level``: (level, hash table of the cells within one
    of a sample's cell, density per cell); counts splatted with quadratic B-splines centred
    on cells (the only cells they reach)."""
    shift = smp.depth - level
    keys = np.unique(pack_keys(unpack_keys(smp.keys) >> shift))
    for axis in range(3):
        keys = dilate(keys, axis, -1, 1, (1 << level) - 1)
    tab = build_table(keys)
    return level, tab, S.density_splat(smp.pos, smp.count, level, *tab, len(keys))


def _eval_density(table: tuple, pos: np.ndarray) -> np.ndarray:
    level, tab, dens = table
    return S.density_eval(pos, level, *tab, dens)


def make_splats(smp: Samples, depth: int, samples_per_node: float, point_weight: float, keep_density: bool,
                merge: bool = True) -> Splats:
    """The level each sample is splatted at, the area it stands for, the splat items and the
    screening weights.

    A sample's depth is where its local density reaches ``samples_per_node`` samples per
    node, as PoissonRecon defines it: its kernel density is estimated at level
    ``depth - KERNEL_OFFSET`` (PoissonRecon's kernel depth) and, while it is below
    ``ESTIMATE_FACTOR * samples_per_node``, at coarser levels; from the finest level ``l``
    where it is reached, the depth is ``l + log4(samples per node / samples_per_node)`` (on a surface a
    level finer holds a quarter of the samples per node), at most ``depth``. So the tree
    follows the data: where the samples are sparse they are splatted coarse and no finer
    node is made. A fractional depth is split between the two levels around it. The area
    is the node area at ``l`` over the samples per node there; the screening weight is
    ``point_weight`` times the mean area times ``2**`` (the finest splat level).
    """
    spos, snrm, count = smp.pos, smp.normal, smp.count
    ns = len(count)
    kd = max(depth - KERNEL_OFFSET, 0)
    splat = np.zeros(ns)
    area_pt = np.zeros(ns)
    active = np.arange(ns)
    tables = {}
    for lv in range(kd, -1, -1):
        tables[lv] = _density_table(smp, lv)
        rho = _eval_density(tables[lv], spos[active])
        per_node = rho / B2_PLANE_DENSITY  # samples per node of level lv
        ok = (per_node >= ESTIMATE_FACTOR * samples_per_node) | (lv == 0)
        idx = active[ok]
        pn = np.maximum(per_node[ok], 1e-12)
        splat[idx] = lv + 0.5 * np.log2(pn / samples_per_node)
        h = 1.0 / (1 << lv)
        area_pt[idx] = h * h / pn  # unit-cube area per point
        active = active[~ok]
        if not len(active):
            break
    splat = np.clip(splat, 0.0, depth)
    s_lo = np.floor(splat).astype(np.int64)
    s_frac = splat - s_lo
    s_frac[s_lo == depth] = 0.0
    s_lo = np.minimum(s_lo, depth)
    normal_w = -(area_pt * 1.0)[:, None] * snrm  # chi is 1 inside: its gradient is -n
    # splat items: each sample's share at its two levels, merged per cell of that level (as
    # PoissonRecon merges samples per node), so coarse splats cost per cell, not per sample
    it_pos, it_vec, it_lvl = merge_splats(spos, normal_w, count, s_lo, s_frac, merge)
    tree_depth = int(it_lvl.max())
    log.info("poisson: %d splats from %d samples, levels %d..%d", len(it_pos), ns, int(it_lvl.min()), tree_depth)
    mean_area = float((area_pt * count).sum() / count.sum())
    # calibrated against the references: with alpha = w * mean_area * 2**depth our fit at
    # weight w matched Open3D's (PoissonRecon's code, weight 2) at w = 1 on noisy samples
    # (Chamfer ratio 0.99-1.0 on armadillo, kitten, bunny at depth 9), so the same nominal
    # weight means half that alpha here
    alpha = 0.5 * point_weight * mean_area * (1 << tree_depth)
    screen_w = alpha * count
    dens = None
    if keep_density:
        # the output density at the tree's kernel depth (not the nominal one: on sparse data
        # a level far finer than the tree sees each sample alone)
        ko = max(tree_depth - KERNEL_OFFSET, 0)
        dens = tables[ko] if ko in tables else _density_table(smp, ko)
    r_pos, r_vec, r_lvl = spread_items(it_pos, it_vec, it_lvl)
    return Splats(it_pos, it_vec, it_lvl, screen_w, alpha, tree_depth, dens, r_pos, r_vec, r_lvl)


def sample_density(splats: Splats, pos: np.ndarray) -> np.ndarray:
    """The samples' kernel density at ``pos`` (m, 3) unit-cube positions."""
    return _eval_density(splats.density, pos)


def spread_items(pos: np.ndarray, vec: np.ndarray, lvl: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The items' vectors shared among the 27 cells of their level around them with the
    quadratic B-spline weights at their positions, summed per cell: (cell centres (m, 3),
    vectors (m, 3), levels (m,)).

    This is PoissonRecon's normal splat (its vector field is a sum of B-splines centred on the
    cells, with the samples' normals distributed over them). Each sample's share of the field
    then is a smoothed B-spline (the B-spline weights convolved with the B-spline) rather than
    one B-spline centred on it; the field's noise from random sample positions is about 1.6x
    smaller (a sphere, 100k samples, depth 7: the root's mean error 2.8e-4 -> 1.7e-4 of the
    radius, Open3D's linear fit 1.7e-4). The tree is still built from the items themselves: the
    spread shares reach at most a cell beyond them, and the right-hand side at the nodes the
    tree lacks there is left out (the sphere's error is the same with the tree built from the
    spread items).
    """
    out_p, out_v, out_l = [], [], []
    for lv in np.unique(lvl):
        sel = lvl == lv
        d = int(lv)
        keys = np.unique(pack_keys(np.floor(pos[sel] * (1 << d)).clip(0, (1 << d) - 1)))
        for axis in range(3):
            keys = dilate(keys, axis, -1, 1, (1 << d) - 1)
        tab = build_table(keys)
        v = S.spread_splat(pos[sel], vec[sel], d, *tab, len(keys))
        hit = np.any(v != 0.0, axis=1)
        out_p.append((unpack_keys(keys[hit]) + 0.5) / (1 << d))
        out_v.append(v[hit])
        out_l.append(np.full(int(hit.sum()), d, np.int64))
    return np.concatenate(out_p), np.concatenate(out_v), np.concatenate(out_l)


def merge_splats(pos, vec, count, s_lo, s_frac, merge=True):
    """Per level, the samples' shares merged per cell: (count-weighted mean position, summed
    vector, level); with ``merge`` False each sample's share is an item of its own (merging
    moves the items of a curved surface to the inside by about its curvature times the
    squared cell size / 12, a bias the degree-2 basis resolves)."""
    parts = [(s_lo, 1.0 - s_frac), (s_lo + 1, s_frac)]
    out_p, out_v, out_l = [], [], []
    for lvl_arr, w in parts:
        for lvl in np.unique(lvl_arr[w > 0]):
            sel = (lvl_arr == lvl) & (w > 0)
            p = pos[sel]
            ww = w[sel]
            if not merge:
                out_p.append(p)
                out_v.append(vec[sel] * ww[:, None])
                out_l.append(np.full(len(p), int(lvl), np.int64))
                continue
            keys = pack_keys(np.floor(p * (1 << int(lvl))).astype(np.int64))
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

