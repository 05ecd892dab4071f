"""The samples and their splats: points merged per finest cell, the kernel density of the
samples (area per sample, splat level), the normals' splat items."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon_cli._kernels.hashtable import build_table
from recon_cli.poisson import _splat as S
from recon_cli.poisson._luts import B2_PLANE_DENSITY
from recon_cli.poisson.octree import Level, pack_keys

log = logging.getLogger("recon")

# the kernel-density level is this much coarser than the finest (PoissonRecon's kernelDepth)
KERNEL_OFFSET = 2
# sparse samples are splatted at most this many levels coarser than the finest
MAX_SPLAT_OFFSET = 2


@dataclass
class Samples:
    """Points merged per finest cell (as PoissonRecon does), unit-cube coordinates."""

    keys: np.ndarray  # (s,) int64 sorted keys of the finest cells holding points
    pos: np.ndarray  # (s, 3) mean position
    normal: np.ndarray  # (s, 3) summed unit normals
    count: np.ndarray  # (s,) float points merged


@dataclass
class Splats:
    """The normals' splat items and the screening weights."""

    pos: np.ndarray  # (k, 3) item position (count-weighted mean of its samples' shares)
    vec: np.ndarray  # (k, 3) summed normal times area (sign included: chi's gradient is -n)
    level: np.ndarray  # (k,) int64 splat level
    screen_w: np.ndarray  # (s,) screening weight per sample
    alpha: float
    # the kernel density (level, hash table of its cells, per-cell density), kept only for
    # the output densities
    density: tuple | None = None


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
    return Samples(skeys, spos, snrm, count)


def make_splats(levels: list[Level], smp: Samples, depth: int, samples_per_node: float, point_weight: float,
                keep_density: bool) -> Splats:
    """Kernel density of the samples at level ``depth - KERNEL_OFFSET``: the area each
    sample stands for and the level it is splatted at (coarser where the samples are
    sparser than ``samples_per_node`` per finest cell); the splat items; the screening
    weights (``point_weight`` scaled by the mean area and ``2**depth``)."""
    spos, snrm, count = smp.pos, smp.normal, smp.count
    ns = len(count)
    kd = max(depth - KERNEL_OFFSET, 0)
    klev = levels[kd]
    ktab = build_table(klev.cell_keys)  # a coarse level: its hash table is small
    dens_cells = S.density_splat(spos, count, kd, *ktab, len(klev.cell_keys))
    rho = S.density_eval(spos, kd, *ktab, dens_cells)
    hk = 1.0 / (1 << kd)
    area_pt = B2_PLANE_DENSITY * hk * hk / np.maximum(rho, 1e-12)  # unit-cube area per point
    per_node = (rho / B2_PLANE_DENSITY) * 4.0 ** (kd - depth)  # samples per finest cell
    splat = np.full(ns, float(depth))
    sparse = per_node < samples_per_node
    splat[sparse] = depth - 0.5 * np.log2(samples_per_node / per_node[sparse])
    splat = np.clip(splat, max(depth - MAX_SPLAT_OFFSET, 0), depth)
    s_lo = np.floor(splat).astype(np.int64)
    s_frac = splat - s_lo
    s_frac[s_lo == depth] = 0.0
    s_lo = np.minimum(s_lo, depth)
    normal_w = -(area_pt * 1.0)[:, None] * snrm  # chi is 1 inside: its gradient is -n
    # splat items: each sample's share at its two levels, merged per cell of that level (as
    # PoissonRecon merges samples per node), so coarse splats cost per cell, not per sample
    it_pos, it_vec, it_lvl = merge_splats(spos, normal_w, count, s_lo, s_frac)
    log.info("poisson: %d splats from %d samples", len(it_pos), ns)
    mean_area = float((area_pt * count).sum() / count.sum())
    # calibrated against the references: with alpha = w * mean_area * 2**depth our fit at
    # weight w matched Open3D's (PoissonRecon's code, weight 2) at w = 1 on noisy samples
    # (Chamfer ratio 0.99-1.0 on armadillo, kitten, bunny at depth 9), so the same nominal
    # weight means half that alpha here
    alpha = 0.5 * point_weight * mean_area * (1 << depth)
    screen_w = alpha * count
    del klev
    return Splats(it_pos, it_vec, it_lvl, screen_w, alpha, (kd, ktab, dens_cells) if keep_density else None)


def sample_density(splats: Splats, pos: np.ndarray) -> np.ndarray:
    """The samples' kernel density at ``pos`` (m, 3) unit-cube positions."""
    kd, ktab, dens_cells = splats.density
    return S.density_eval(pos, kd, *ktab, dens_cells)


def merge_splats(pos, vec, count, s_lo, s_frac):
    """Per level, the samples' shares merged per cell: (count-weighted mean position, summed
    vector, level)."""
    parts = [(s_lo, 1.0 - s_frac), (s_lo + 1, s_frac)]
    out_p, out_v, out_l = [], [], []
    for lvl_arr, w in parts:
        for lvl in np.unique(lvl_arr[w > 0]):
            sel = (lvl_arr == lvl) & (w > 0)
            p = pos[sel]
            ww = w[sel]
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

