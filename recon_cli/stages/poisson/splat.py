"""The samples and their splats.

Points merged per finest cell, the kernel density of the samples (area per sample, splat level), the
normals' splat items.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon_cli._kernels.hashtable import build_table
from recon_cli.stages.poisson import _splat as S
from recon_cli.stages.poisson._luts import B2_PLANE_DENSITY
from recon_cli.stages.poisson.octree import dilate, pack_keys, unique_keys, unpack_keys

log = logging.getLogger("recon")

# the kernel-density level is this much coarser than the finest (PoissonRecon's kernelDepth)
KERNEL_OFFSET = 2
# bands of cells splatted in parallel by spread (many more than threads: balance)
SPLAT_BANDS = 16
# a sample's depth is extrapolated from the finest level where its density is at least this
# many times samples-per-node (one level coarser than where it reaches samples-per-node): at
# the first level that merely reaches it, the estimate is noisy and biased up (the samples
# that pass there are the locally dense ones), and would depend on the nominal depth
ESTIMATE_FACTOR = 4.0


@dataclass
class Samples:
    """Points merged per finest cell (as PoissonRecon does), unit-cube coordinates."""

    # screened_poisson drops ``keys`` and ``normal`` once the splats and the tree are made
    keys: np.ndarray | None  # (s,) int64 sorted keys of the finest cells holding points
    pos: np.ndarray  # (s, 3) mean position
    normal: np.ndarray | None  # (s, 3) summed unit normals
    count: np.ndarray  # (s,) float points merged
    depth: int  # the level of ``keys``


@dataclass
class Splats:
    """The normals' splat items and the screening weights."""

    # screened_poisson drops ``pos``, ``vec`` and ``level`` once the tree is built
    pos: np.ndarray | None  # (k, 3) item position (count-weighted mean of its samples' shares)
    vec: np.ndarray | None  # (k, 3) summed normal times area (sign included: chi's gradient is -n)
    level: np.ndarray | None  # (k,) int64 splat level
    screen_w: np.ndarray  # (s,) screening weight per sample
    alpha: float
    tree_depth: int  # the finest splat level: the tree goes no deeper
    # the kernel density (level, hash table of its cells, per-cell density), kept only for
    # the output densities
    density: tuple | None = None
    # the right-hand side's field: the splat items' vectors shared among the 27 cells around
    # them with quadratic B-spline weights, per level (:func:`spread_fields`)
    rhs_fields: dict | None = None
    # (s,) how clean each sample's neighbourhood is, 1 clean .. 0 noisy (noise_fraction); None
    # until measured (screened as clean)
    clean: np.ndarray | None = None

    def screening(self, clean_scale: float, noisy_scale: float) -> np.ndarray:
        """(s,) screening weight per sample.

        ``screen_w`` times ``clean_scale`` where the samples are clean, ``noisy_scale`` where they
        are noisy (:func:`noise_fraction`), in between as their measured noise says; each basis has
        its pair (the system's and the B-splines' solve).
        """
        if self.clean is None:
            return self.screen_w * clean_scale
        return self.screen_w * (noisy_scale + (clean_scale - noisy_scale) * self.clean)


def merge_samples(
    unit: np.ndarray, nrm: np.ndarray, depth: int, weight: np.ndarray | None = None
) -> Samples:
    """Merge the points ``unit`` (n, 3), unit normals ``nrm``, per cell of level ``depth``.

    The points are in the unit cube. With ``weight`` (n,) each point counts that much
    (PoissonRecon's ``--confidence``: its position and normal weighted, the sample's count the sum).
    """
    res = 1 << depth
    cxyz = np.clip(np.floor(unit * res).astype(np.int64), 0, res - 1)
    skeys, inv = np.unique(pack_keys(cxyz), return_inverse=True)
    inv = inv.reshape(-1)
    ns = len(skeys)
    count = np.bincount(inv, weights=weight, minlength=ns).astype(np.float64)
    spos = np.empty((ns, 3))
    snrm = np.empty((ns, 3))
    for a in range(3):
        w = unit[:, a] if weight is None else unit[:, a] * weight
        spos[:, a] = np.bincount(inv, weights=w, minlength=ns) / count
        w = nrm[:, a] if weight is None else nrm[:, a] * weight
        snrm[:, a] = np.bincount(inv, weights=w, minlength=ns)
    return Samples(skeys, spos, snrm, count, depth)


def _density_table(smp: Samples, level: int) -> tuple:
    """The samples' kernel density at ``level``.

    (level, hash table of the cells within one of a sample's cell, density per cell); counts
    splatted with quadratic B-splines centred on cells (the only cells they reach).
    """
    shift = smp.depth - level
    assert smp.keys is not None  # kept until the density is made
    keys = unique_keys(pack_keys(unpack_keys(smp.keys) >> shift))
    for axis in range(3):
        keys = dilate(keys, axis, -1, 1, (1 << level) - 1)
    tab = build_table(keys)
    return level, tab, spread(smp.pos, smp.count[:, None], level, tab, len(keys))[:, 0]


def spread(pos: np.ndarray, vec: np.ndarray, level: int, table: tuple, n_cells: int) -> np.ndarray:
    """The items' rows of ``vec`` (n, k) shared among the 27 cells of ``level`` around them.

    ``pos`` (n, 3) unit-cube positions, ``table`` the cells' hash table
    (:func:`recon_cli._kernels.hashtable.build_table` of their keys, ``n_cells`` of them).
    Returns (n_cells, k) the sums per cell (quadratic B-spline weights), summed in the items'
    order in every cell: the cells in :data:`SPLAT_BANDS` bands of x holding equal shares of
    the items, a band a thread (:func:`._splat.spread_splat`), the same sums for any count.
    """
    n = 1 << level
    cx = np.floor(pos[:, 0] * n) if len(pos) else np.zeros(1)
    inner = np.quantile(cx, np.linspace(0.0, 1.0, SPLAT_BANDS + 1)[1:-1], method="lower")
    xcuts = np.unique(np.concatenate([[-1], inner.astype(np.int64), [n + 1]]))
    return S.spread_splat(pos, vec, level, *table, n_cells, xcuts)


def _eval_density(table: tuple, pos: np.ndarray) -> np.ndarray:
    level, tab, dens = table
    return S.density_eval(pos, level, *tab, dens)


def splat_at_level(
    rho: np.ndarray, lv: int, samples_per_node: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which samples level ``lv``'s kernel density ``rho`` (at the samples) places.

    Returns them, their fractional splat depth and unit-cube area per point (:func:`make_splats`'
    rule; level 0 places every sample left).
    """
    per_node = rho / B2_PLANE_DENSITY  # samples per node of level lv
    ok = (per_node >= ESTIMATE_FACTOR * samples_per_node) | (lv == 0)
    pn = np.maximum(per_node[ok], 1e-12)
    h = 1.0 / (1 << lv)
    return ok, lv + 0.5 * np.log2(pn / samples_per_node), h * h / pn


def screening_alpha(point_weight: float, mean_area: float, tree_depth: int) -> float:
    """The screening weight per unit count (:func:`make_splats`).

    ``point_weight`` times the samples' mean area per point (unit cube) times ``2**tree_depth``.
    """
    # 0.75 matches Open3D's accuracy at its default weight 4 (bench/calibration.md); each basis
    # scales it by the samples' measured noise (Splats.screening)
    return 0.75 * point_weight * mean_area * (1 << tree_depth)


def make_splats(
    smp: Samples,
    depth: int,
    samples_per_node: float,
    point_weight: float,
    keep_density: bool,
    merge: bool = True,
) -> Splats:
    """The level each sample is splatted at, its area, the splat items and screening weights.

    A sample's depth is where its local density reaches ``samples_per_node`` samples per node, as
    PoissonRecon defines it: its kernel density is estimated at level ``depth - KERNEL_OFFSET``
    (PoissonRecon's kernel depth) and, while it is below ``ESTIMATE_FACTOR * samples_per_node``, at
    coarser levels; from the finest level ``l`` where it is reached, the depth is ``l + log4(samples
    per node / samples_per_node)`` (on a surface a level finer holds a quarter of the samples per
    node), at most ``depth``. So the tree follows the data: where the samples are sparse they are
    splatted coarse and no finer node is made. A fractional depth is split between the two levels
    around it. The area is the node area at ``l`` over the samples per node there; the screening
    weight is ``point_weight`` times the mean area times ``2**`` (the finest splat level).
    """
    spos, snrm, count = smp.pos, smp.normal, smp.count
    assert snrm is not None  # the samples' normals, until the splats are made
    ns = len(count)
    kd = max(depth - KERNEL_OFFSET, 0)
    splat = np.zeros(ns)
    area_pt = np.zeros(ns)
    active = np.arange(ns)
    tables = {}
    for lv in range(kd, -1, -1):
        tables[lv] = _density_table(smp, lv)
        rho = _eval_density(tables[lv], spos[active])
        ok, depth_ok, area_ok = splat_at_level(rho, lv, samples_per_node)
        splat[active[ok]] = depth_ok
        area_pt[active[ok]] = area_ok
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
    log.info(
        "poisson: %d splats from %d samples, levels %d..%d",
        len(it_pos),
        ns,
        int(it_lvl.min()),
        tree_depth,
    )
    mean_area = float((area_pt * count).sum() / count.sum())
    alpha = screening_alpha(point_weight, mean_area, tree_depth)
    screen_w = alpha * count
    dens = None
    if keep_density:
        # the output density at the tree's kernel depth (not the nominal one: on sparse data
        # a level far finer than the tree sees each sample alone)
        ko = max(tree_depth - KERNEL_OFFSET, 0)
        dens = tables[ko] if ko in tables else _density_table(smp, ko)
    return Splats(
        it_pos,
        it_vec,
        it_lvl,
        screen_w,
        alpha,
        tree_depth,
        dens,
        spread_fields(it_pos, it_vec, it_lvl),
    )


def sample_density(splats: Splats, pos: np.ndarray) -> np.ndarray:
    """The samples' kernel density at ``pos`` (m, 3) unit-cube positions."""
    assert splats.density is not None  # made with the splats
    return _eval_density(splats.density, pos)


def spread_fields(
    pos: np.ndarray, vec: np.ndarray, lvl: np.ndarray
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The items' vectors shared among the 27 cells of their level around them, per cell.

    The weights are the quadratic B-spline's at their positions: per level, (sorted cell keys
    (m,), vectors (m, 3)).

    This is PoissonRecon's normal splat (its vector field is a sum of B-splines centred on the
    cells, with the samples' normals distributed over them). Each sample's share of the field
    then is a smoothed B-spline (the B-spline weights convolved with the B-spline) rather than
    one B-spline centred on it; the field's noise from random sample positions is about 1.6x
    smaller (``docs/design/poisson.md``). Shares beyond the cube's faces are dropped.
    """
    out = {}
    for lv in np.unique(lvl):
        sel = lvl == lv
        d = int(lv)
        keys = unique_keys(pack_keys(np.floor(pos[sel] * (1 << d)).clip(0, (1 << d) - 1)))
        for axis in range(3):
            keys = dilate(keys, axis, -1, 1, (1 << d) - 1)
        keys = np.sort(keys)
        v = spread(pos[sel], vec[sel], d, build_table(keys), len(keys))
        hit = np.any(v != 0.0, axis=1)
        out[d] = (keys[hit], v[hit])
    return out


def fields_as_items(
    fields: dict[int, tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`spread_fields`'s fields as splat items.

    (cell centres (m, 3) in the unit cube, vectors (m, 3), levels (m,)).
    """
    if not fields:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    return (
        np.concatenate([(unpack_keys(k) + 0.5) / (1 << d) for d, (k, _) in fields.items()]),
        np.concatenate([v for _, v in fields.values()]),
        np.concatenate([np.full(len(k), d, np.int64) for d, (k, _) in fields.items()]),
    )


_ONES = (1 << 42) | (1 << 21) | 1  # the key of (1, 1, 1): adds 1 to each coordinate
# cells of a level per slab of NormalField.rhs, at most (the field on the cells within two of
# a slab's, with the dilation's temporaries, is ~200 bytes a cell: ~25 MB)
RHS_SLAB_CELLS = 1 << 17


class NormalField:
    """The right-hand side ``b_i = int grad(B_i) . W`` level by level, coarse to fine.

    ``W`` is the field of :func:`spread_fields` (a sum of cell-centred quadratic B-splines over the
    splat levels), exactly, in time linear in the cells.

    - Level ``d``'s own share of ``W`` and the coarser levels' (written exactly on level
      ``d``'s cells by B-spline refinement, carried from level to level) give a fixed
      4 x 4 x 4 stencil per cell (:func:`._splat.stencil_rhs`).
    - The finer levels' shares are their stencils at their own level, taken to coarser nodes
      by the hat functions' restriction (a coarse hat is a sum of finer ones), computed once
      from the finest level up when the field is made.

    So a coarse field costs per cell of the finer levels near it and a fine field per node of
    the coarser levels, not per node each item reaches (about 8x faster than splatting every
    spread item at every level; see ``docs/design/poisson.md``). The carried field is kept on
    the tree's cells and two cells around them, including the cells just beyond the cube's
    faces (all a node of the tree, or of the next level through the refinement, sees); the
    finer levels' integrals on the tree's nodes (all a finer field reaches: the tree holds two
    cells around every splat). Away from the cube's faces this equals splatting every item at
    every level to rounding (tested); at the faces the hat functions' integrals run over all
    space in the stencils (as in the direct splat) but the restriction has no finer hats
    beyond the faces, so there the coarse levels' right-hand side differs slightly (only
    fields at coarse levels reach the faces: the cube is 1.1x the samples' box).
    """

    def __init__(
        self, fields: dict[int, tuple[np.ndarray, np.ndarray]], node_keys: list[np.ndarray]
    ):
        # a level's own field is dropped once its right-hand side is made (the dict is
        # copied: the caller's is left whole; drop it there to free the arrays)
        self.fields = dict(fields)
        # (level, [(keys, vectors) per slab]): the field carried to the next level
        self.carry: tuple[int, list] | None = None
        # finer[d]: the integrals of the levels finer than d against level d's hats
        depth = len(node_keys) - 1
        self.depth = depth
        self.finer: list[np.ndarray | None] = [None] * (depth + 1)
        up = None
        for lv in range(depth, 0, -1):
            own = fields.get(lv)
            if own is not None and len(own[0]):
                b = S.stencil_rhs(own[0], own[1], lv, node_keys[lv], len(node_keys[lv]), 0)
                up = b if up is None else up + b
            if up is not None:
                up = S.restrict_nodes(node_keys[lv], up, node_keys[lv - 1])
                self.finer[lv - 1] = up

    def rhs(
        self, d: int, cell_keys: np.ndarray, node_keys: np.ndarray, unknown: np.ndarray
    ) -> np.ndarray:
        """(n_nodes,) right-hand side at level ``d``'s nodes (0 where not ``unknown``).

        Call once per level, coarse to fine.
        """
        own = self.fields.pop(d, None)
        if own is not None:
            # keys of the carried field hold each coordinate plus 1: the cells just beyond the
            # cube's faces carry B-splines that reach into it
            own = (own[0] + _ONES, own[1])
        carry, self.carry = self.carry, None
        if carry is not None and not (carry[0] == d - 1 and sum(len(k) for k, _ in carry[1]) > 0):
            carry = None
        b = np.zeros(len(node_keys))
        parts = []
        # slabs of the lattice's x (consecutive in the sorted keys): the field on every cell
        # within two of the level's is the largest array of the solve (32 bytes a cell), so
        # it is made, used and dropped a slab at a time; each node's terms still add up in
        # the cells' order (stencil_rhs_into), as in one pass
        n_slabs = max(1, -(-len(cell_keys) // RHS_SLAB_CELLS))
        bounds = np.unique(
            np.concatenate(
                [
                    [0],
                    (cell_keys[(len(cell_keys) * np.arange(1, n_slabs)) // n_slabs] >> 42) + 1,
                    [(1 << d) + 3],
                ]
            )
        )
        for x0, x1 in zip(bounds[:-1], bounds[1:], strict=True):
            keys, vec = self._slab(d, int(x0), int(x1), cell_keys, own, carry)
            if d < self.depth:  # carried to the next level: exact-size copies, slab by slab
                parts.append((keys.copy(), vec.copy()))
            S.stencil_rhs_into(keys, vec, d, node_keys, 1, b)
            del keys, vec
        del own, carry
        if parts:
            self.carry = (d, parts)
        del parts
        finer = self.finer[d]
        if finer is not None:
            b += finer
            self.finer[d] = None
        b[~unknown] = 0.0
        return b

    @staticmethod
    def _slab(
        d: int, x0: int, x1: int, cell_keys: np.ndarray, own: tuple | None, carry: tuple | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Level ``d``'s field on the cells within two of its cells whose x is in [x0, x1).

        x plus 1, as the carried field's keys and ``own``'s hold it: (sorted keys, vectors), the
        cells the field reaches only (views of arrays of the slab's size).
        """
        src = cell_keys[
            np.searchsorted(cell_keys, max(x0 - 3, 0) << 42) : np.searchsorted(
                cell_keys, max(x1 + 1, 0) << 42
            )
        ]
        rel = src + _ONES
        del src
        for axis in range(3):
            rel = dilate(rel, axis, -2, 2, 1 << d)
        # (the last dilation, along z, leaves the keys sorted and unique)
        rel = rel[np.searchsorted(rel, x0 << 42) : np.searchsorted(rel, x1 << 42)]
        if own is not None:
            lo, hi = np.searchsorted(own[0], x0 << 42), np.searchsorted(own[0], x1 << 42)
            own = own[0][lo:hi], own[1][lo:hi]
            at = np.minimum(np.searchsorted(rel, own[0]), len(rel) - 1)
            if len(rel) == 0 or not np.array_equal(rel[at], own[0]):
                rel = unique_keys(np.concatenate([rel, own[0]]))
            del at
        if carry is not None:
            # the coarser cells whose children (x 2p - 2 .. 2p + 1, coordinates plus 1) reach
            # the slab, from the coarser level's slabs (consecutive, in key order)
            pieces = []
            for pk, pv in carry[1]:
                lo = np.searchsorted(pk, max(x0 // 2 - 1, 0) << 42)
                hi = np.searchsorted(pk, (x1 // 2 + 2) << 42)
                if hi > lo:
                    pieces.append((pk[lo:hi], pv[lo:hi]))
            if len(pieces) == 1:
                pk, pv = pieces[0]
            elif pieces:
                pk, pv = (
                    np.concatenate([k for k, _ in pieces]),
                    np.concatenate([v for _, v in pieces]),
                )
            else:
                pk, pv = np.zeros(0, np.int64), np.zeros((0, 3))
            del pieces
            vec = S.refine_field(pk, pv, rel, 1)
        else:
            vec = np.zeros((len(rel), 3))
        if own is not None:
            vec[np.searchsorted(rel, own[0])] += own[1]
        # the cells the field reaches, in place
        m = S.compact_nonzero(rel, vec)
        return rel[:m], vec[:m]


def merge_splats(pos, vec, count, s_lo, s_frac, merge=True):
    """Per level, the samples' shares merged per cell.

    (count-weighted mean position, summed vector, level); with ``merge`` False each sample's share
    is an item of its own (merging moves the items of a curved surface to the inside by about its
    curvature times the squared cell size / 12, a bias the degree-2 basis resolves).
    """
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
            mp = np.stack(
                [np.bincount(inv, weights=p[:, a] * cw, minlength=m) / tot for a in range(3)],
                axis=1,
            )
            mv = np.stack(
                [np.bincount(inv, weights=vec[sel, a] * ww, minlength=m) for a in range(3)], axis=1
            )
            out_p.append(mp)
            out_v.append(mv)
            out_l.append(np.full(m, int(lvl), np.int64))
    return np.concatenate(out_p), np.concatenate(out_v), np.concatenate(out_l)


# ---- the samples' noise, for the screening weight (noise_fraction)
# noise is measured in cells of this many levels above the tree's finest (4 finest cells wide)
NOISE_LEVEL_OFFSET = 2
# ... or coarser, up to this many levels more, where a cell holds too few points or both sides
# of a thin part
NOISE_MORE_LEVELS = 3
# a cell's fit needs this many points (6 unknowns) ...
NOISE_MIN_POINTS = 16
# ... and normals this coherent (|sum of the samples' normals| / the sum of their lengths; two
# sides of a thin part cancel)
NOISE_COHERENCE = 0.5
# the noise, in finest cells, at which a sample's screening is halfway between clean and noisy
NOISE_TAU = 0.2


def _cell_noise(
    c: np.ndarray,
    unit: np.ndarray,
    pn: np.ndarray,
    sk: np.ndarray,
    snrm: np.ndarray,
    depth: int,
    shift: int,
    off: int,
) -> np.ndarray:
    """The noise of each sample's cell (NaN where it cannot be measured).

    ``c`` (k, 3) the points' finest-lattice coordinates, ``unit`` their positions, ``pn`` their
    samples' summed normals, ``sk`` (m, 3) and ``snrm`` the samples' finest coordinates and summed
    normals, both lattices of level ``depth`` (the noise is in its cells); cells are ``2**shift``
    finest cells wide, their lattice moved by ``off`` finest cells.
    """
    keys = pack_keys((c + off) >> shift)
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    del keys
    m = len(uk)
    skeys = pack_keys((sk + off) >> shift)
    scell = np.minimum(np.searchsorted(uk, skeys), m - 1)
    mine = uk[scell] == skeys
    nsum = np.stack(
        [np.bincount(scell[mine], weights=snrm[mine, a], minlength=m) for a in range(3)], axis=1
    )
    nlen = np.linalg.norm(nsum, axis=1)
    # the points of the cell's side only: on a thin part the other side's points face away
    side = np.einsum("ij,ij->i", pn, nsum[inv]) > 0
    unit, inv = unit[side], inv[side]
    cnt = np.bincount(inv, minlength=m).astype(np.float64)
    ok = (cnt >= NOISE_MIN_POINTS) & (
        nlen
        >= NOISE_COHERENCE
        * np.bincount(scell[mine], weights=np.linalg.norm(snrm[mine], axis=1), minlength=m)
    )
    cs = np.full(m, np.nan)
    if ok.any():
        cen: np.ndarray = np.stack(
            [np.bincount(inv, weights=unit[:, a], minlength=m) for a in range(3)], axis=1
        )
        cen /= np.maximum(cnt, 1.0)[:, None]
        nz = nsum / np.where(nlen > 0, nlen, 1.0)[:, None]
        e = np.zeros((m, 3))
        e[np.arange(m), np.argmin(np.abs(nz), axis=1)] = 1.0
        t1 = np.cross(nz, e)
        t1 /= np.maximum(np.linalg.norm(t1, axis=1), 1e-300)[:, None]
        frame = np.stack([t1, np.cross(nz, t1), nz], axis=1)
        # lengths in the cells' own units (the fit's conditioning)
        A, b, ww = S.height_fit_moments(unit, inv, cen, frame, float(1 << (depth - shift)), m)
        A, b = A[ok] + 1e-9 * np.eye(6), b[ok]
        beta = np.linalg.solve(A, b[:, :, None])[:, :, 0]
        cs[ok] = np.sqrt(
            np.maximum(ww[ok] - np.einsum("ij,ij->i", beta, b), 0.0) / (cnt[ok] - 6)
        ) * (1 << shift)
    out = np.full(len(sk), np.nan)
    out[mine] = cs[scell[mine]]
    return out


def noise_fraction(
    unit: np.ndarray, smp: Samples, tree_depth: int
) -> tuple[np.ndarray, np.ndarray]:
    """How clean each sample's neighbourhood is.

    (s,) ``1 / (1 + (sigma / (NOISE_TAU h))**2)`` (1 clean, towards 0 noisy) and (s,) ``sigma / h``,
    ``h`` the tree's finest cell.

    ``sigma`` is the RMS residual of the raw points ``unit`` (n, 3) (unit cube) about a
    quadratic height field fitted, by least squares, over the sample's cell of level
    ``tree_depth - NOISE_LEVEL_OFFSET`` along the cell's mean normal (the samples' summed
    normals): the points' spread across the surface that its shape does not explain. Only the
    points whose own normals face the mean's side count (on a thin part the other side's points
    face away: its thickness is not noise). Two lattices half a cell apart are fitted and the
    larger answer kept (a cell's fit sees only the part of the noise inside it: a surface along
    a face of one lattice is inside the other's cells). Where a cell holds fewer than
    :data:`NOISE_MIN_POINTS` points or normals that mostly cancel (under
    :data:`NOISE_COHERENCE` of their lengths), its parent answers, up to
    :data:`NOISE_MORE_LEVELS` levels coarser; samples still without an answer take the median
    of the others (0 if none has one).
    Requires ``smp.keys`` and ``smp.normal``.
    """
    sig = noise_sigma(unit, smp, tree_depth)
    have = ~np.isnan(sig)
    sig[~have] = float(np.median(sig[have])) if have.any() else 0.0
    return clean_fraction(sig, smp.depth, tree_depth)


def noise_sigma(unit: np.ndarray, smp: Samples, tree_depth: int) -> np.ndarray:
    """(s,) each sample's noise ``sigma`` (:func:`noise_fraction`).

    In finest cells of the samples' lattice, NaN where no cell up to :data:`NOISE_MORE_LEVELS`
    coarser answers.
    """
    ns = len(smp.count)
    sig = np.full(ns, np.nan)  # in finest cells of the samples' lattice
    dd = smp.depth
    c = np.clip(np.floor(unit * (1 << dd)), 0, (1 << dd) - 1).astype(np.int64)
    assert smp.keys is not None and smp.normal is not None  # required, as said above
    sk = unpack_keys(smp.keys)
    sidx = np.searchsorted(smp.keys, pack_keys(c))  # each point's sample
    top = max(tree_depth - NOISE_LEVEL_OFFSET, 0)
    for level in range(top, max(top - NOISE_MORE_LEVELS, 0) - 1, -1):
        todo = np.isnan(sig)
        if not todo.any():
            break
        if todo.all():  # the first level: every point (no copies)
            pc, pu, pn = c, unit, smp.normal[sidx]
        else:
            sel = todo[sidx]
            pc, pu, pn = c[sel], unit[sel], smp.normal[sidx[sel]]
            del sel
        shift = dd - level
        best = np.full(int(todo.sum()), np.nan)
        # two lattices half a cell apart: a surface along a face of one is inside the cells of
        # the other (a cell's fit sees only the part of the noise inside it)
        for off in (0, (1 << shift) >> 1):
            best = np.fmax(
                best, _cell_noise(pc, pu, pn, sk[todo], smp.normal[todo], dd, shift, off)
            )
        del pc, pu, pn
        sig[todo] = best
    return sig


def clean_fraction(
    sig: np.ndarray, sample_depth: int, tree_depth: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`noise_fraction`'s result from the noise ``sig``.

    ``sig`` is in finest cells of the samples' lattice (level ``sample_depth``): (s,) clean fraction
    and (s,) noise in finest cells of the tree.
    """
    rel = sig / (1 << (sample_depth - tree_depth))
    return 1.0 / (1.0 + (rel / NOISE_TAU) ** 2), rel


# public names of the kernel-density pieces the distributed solve (.slab) runs per slab
density_table = _density_table
eval_density = _eval_density
