"""One slab of a distributed Poisson reconstruction: what a worker computes.

:mod:`.distributed` holds the design (read it first) and the coordinator. Each function
here takes the slab's state (:class:`Slab`, kept in the worker between steps) and returns a
small message for the coordinator, which sums the messages of all slabs and hands the
global values to the next step. Every step is a deterministic function of the slab's
inputs and of those global values, so a slab whose worker died is rebuilt by running its
steps again (:func:`replay`).

Coordinates are the job's frame (:class:`Job`): the input's axes turned cyclically so that
the slabs' axis is ``x`` (the lattice keys are x-major: a slab's cells are a run of keys),
and the unit cube of the single-process solve.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.errors import StageFailed
from recon_cli.geometry import oriented_rows
from recon_cli.memory import release_free_heap
from recon_cli.slabs.runners import reads_only, register_dask_sizes, timed
from recon_cli.stages.poisson import _octree as O
from recon_cli.stages.poisson.bspline import (
    SCREEN_CLEAN,
    SCREEN_NOISY,
    ChiField,
    NormalRHS,
    field_views,
    level_fields,
    solve_level,
)
from recon_cli.stages.poisson.octree import (
    Level,
    build_levels,
    pack_keys,
    unique_keys,
    unpack_keys,
)
from recon_cli.stages.poisson.splat import (
    KERNEL_OFFSET,
    Samples,
    Splats,
    clean_fraction,
    density_table,
    eval_density,
    merge_samples,
    merge_splats,
    noise_sigma,
    splat_at_level,
    spread_fields,
)

# seams lie on the planes of this level's lattice: the levels up to full_depth (5 by default)
# are complete grids, so no leaf of the tree crosses a seam
PARTITION_DEPTH = 5
# more slabs than its planes allow (a worker's memory needs them): seams on this level's planes,
# the levels up to it made complete (full_depth raised), so that still no leaf crosses a seam
FINE_PARTITION_DEPTH = 6
MAX_PARTITIONS = 1 << FINE_PARTITION_DEPTH
# slabs and their pads are made of whole sub-slabs, the cells of this level along x
SUB_DEPTH = 8
# the coordinator solves the levels up to depth - COARSE_OFFSET for the whole cube, at most
# COARSE_MAX (a 512^3 lattice: its tree stays small whatever the depth; at depth 12 the pads,
# PAD_CELLS of the first fine level, are then as wide in finest cells as at depth 11, half of
# what level 9 gave: a thin slab reads half as many of its neighbours' points)
COARSE_OFFSET = 3
COARSE_MAX = 9
# a slab solves its finer levels over its own cells and this many cells of the first fine
# level (coarse depth + 1) beyond each seam
PAD_CELLS = 8
# a sample's kernel density reads the samples within this many cells of the density's level
DENSITY_REACH = 3


@dataclass(frozen=True)
class Job:
    """What every slab of one reconstruction shares."""

    origin: tuple[float, float, float]  # the unit cube's corner, in the job's frame
    size: float  # the unit cube's side
    depth: int
    samples_per_node: float
    point_weight: float
    boundary: str
    full_depth: int
    cg_tolerance: float
    coarse_depth: int  # the levels the coordinator solves for the whole cube
    local_density: int  # kernel-density levels above this one are a slab's own, the rest global
    density: bool
    trim: float  # T > 0: cut at T times the samples' median density
    # --confidence: each point's weight is its normal's length over this (the mean length), divided
    # as the single process divides (a product by its reciprocal differs by an ulp)
    weight_mean: float | None = None
    seam_depth: int = PARTITION_DEPTH  # the level whose planes the seams lie on
    trim_auto: bool = False  # --trim auto (trim is then 0)
    grid: bool = False  # --grid: the field on the finest lattice around the surface
    grown: int = 0  # --envelope: the levels the cube grew to hold it (the finest lattice kept)
    # --boundary free: the reconstruction cube's bounds (unit cube, every axis) inside the solve's
    # cube, twice as large and one level deeper (:mod:`.free`); the mesh is clipped to it
    domain: tuple[float, float] | None = None


def seam_depth(partitions: int) -> int:
    """The level whose lattice planes hold the seams of ``partitions`` slabs.

    :data:`PARTITION_DEPTH` up to its 32 slabs, else :data:`FINE_PARTITION_DEPTH` (the levels
    up to it must then be complete grids: the run's ``full_depth`` is raised to it).
    """
    return PARTITION_DEPTH if partitions <= (1 << PARTITION_DEPTH) else FINE_PARTITION_DEPTH


@dataclass
class Slab:
    """A slab's state.

    ``own`` is the x range (unit cube) whose cells and output it owns, ``pad`` the range of points
    it reads, ``usable`` the range whose samples it splats (their kernel density is exact: all the
    samples it reads are within ``pad``).
    """

    job: Job
    index: int
    count: int
    own: tuple[float, float]
    pad: tuple[float, float]
    usable: tuple[float, float]
    # filled by the steps in order: Any, as a step reads only what an earlier step set
    pts: Any = None  # (n, 3) kept points, job frame (the own ones only after items, no attributes)
    own_pt: Any = None
    colors: np.ndarray | None = None
    props: dict | None = None  # per-point properties carried onto the vertices (kept rows)
    unit_nrm: Any = None  # (n, 3) the kept points' unit normals (for props)
    vn_sum: Any = None  # (nv, 3) the faces' normals summed at each vertex
    smp: Any = None
    own_s: Any = None
    use_s: Any = None
    splat: Any = None  # (s,) fractional splat depth, NaN until placed
    area: Any = None
    tables: dict = dataclasses.field(default_factory=dict)  # kernel-density tables by level
    sigma: Any = None
    noise: np.ndarray | None = None  # (s,) noise in finest cells of the tree
    screen_w: Any = None
    tree_depth: int = 0
    fine_levels: list = dataclasses.field(default_factory=list)
    fine_fields: dict = dataclasses.field(default_factory=dict)
    normal_rhs: Any = None
    levels: Any = None
    node_keys: Any = None
    gvals: Any = None
    lfs: Any = None
    arrays: Any = None
    chi: Any = None
    verts: Any = None
    faces: Any = None
    seam: dict = dataclasses.field(default_factory=dict)
    labels: Any = None
    vdens: np.ndarray | None = None
    at_samples: Any = None
    trim: Any = None
    # --trim auto: the samples' local spacing, then the vertices' value cut and the own samples
    # nearest each vertex
    spacing: Any = None
    support: np.ndarray | None = None
    mass: np.ndarray | None = None
    # --grid: what chi_at reads (:func:`.system.chi_levels`), kept from the extraction
    grid_levels: Any = None
    # --envelope (:mod:`.slab_envelope`): (s,) the samples inside it (they screen and make the
    # iso-value), and the items the tree is refined along (positions (m, 3), levels (m,))
    sample_ok: np.ndarray | None = None
    tree_items: tuple | None = None

    def __getstate__(self) -> dict:
        # a pickled view is a copy: the levels' fields (views of ``arrays``, shared with the
        # right-hand side) are made again from the arrays when the state is read back
        state = dict(self.__dict__)
        lfs, arrays, nrhs = state["lfs"], state["arrays"], state["normal_rhs"]
        if lfs is not None and arrays is not None and all(f is None or f.coef is None for f in lfs):
            state["lfs"] = ("views", len(lfs))
            if nrhs is not None and all(a is b for a, b in zip(nrhs.lf, lfs, strict=True)):
                nrhs = copy.copy(nrhs)
                nrhs.lf = None
                state["normal_rhs"] = nrhs
        return state

    def __setstate__(self, state: dict) -> None:
        lfs = state["lfs"]
        if isinstance(lfs, tuple):
            fields = field_views(state["arrays"], state["job"].boundary, lfs[1] - 1)
            state["lfs"] = fields
            if state["normal_rhs"] is not None and state["normal_rhs"].lf is None:
                state["normal_rhs"].lf = list(fields)
        self.__dict__.update(state)

    @property
    def res(self) -> int:
        """Cells along an axis at the finest level."""
        return 1 << self.job.depth

    def x_range(self, bounds: tuple[float, float], scale: int) -> tuple[int, int]:
        """``bounds`` (unit cube) in cells of a lattice of ``scale`` cells along x."""
        return int(round(bounds[0] * scale)), int(round(bounds[1] * scale))


def slab_of(job: Job, index: int, count: int, own, pad, usable) -> Slab:
    """Slab ``index`` of ``count``, its ranges as :class:`Slab` holds them."""
    return Slab(job, index, count, tuple(own), tuple(pad), tuple(usable))


# ---------------------------------------------------------------------------------------------
# samples and their depths


def _own_samples(slab: Slab) -> Samples:
    s, m = slab.smp, slab.own_s
    return Samples(s.keys[m], s.pos[m], None, s.count[m], s.depth)


def _splat_stats(slab: Slab) -> dict:
    """The slab's share of the global splat figures (its own samples)."""
    own = slab.own_s & ~np.isnan(slab.splat)
    sp = np.clip(slab.splat[own], 0.0, slab.job.depth)
    lo = np.floor(sp)
    top = int((lo + ((sp - lo) > 0) * (lo < slab.job.depth)).max()) if own.any() else 0
    c = slab.smp.count[own]
    return {
        "max_level": top,
        "area_count": float((slab.area[own] * c).sum()),
        "count": float(c.sum()),
        "unplaced": int((np.isnan(slab.splat) & slab.use_s).sum()),
    }


def _place(slab: Slab, table: tuple, level: int) -> None:
    """Place the usable samples not placed yet whose density at ``level`` suffices."""
    todo = np.flatnonzero(np.isnan(slab.splat) & slab.use_s)
    if not len(todo):
        return
    rho = eval_density(table, slab.smp.pos[todo])
    ok, dep, area = splat_at_level(rho, level, slab.job.samples_per_node)
    slab.splat[todo[ok]] = dep
    slab.area[todo[ok]] = area


def _load(
    slab: Slab,
    points: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray | None,
    props: dict | None = None,
) -> dict:
    job = slab.job
    # the single-process check's normalisation (the same length to the bit): both solves must
    # give the same mesh to rounding
    pts, nrm, length = oriented_rows(points, normals, "a slab's points have no normals")
    keep = length > 0
    pts, nrm = pts[keep], nrm[keep] / length[keep, None]
    weight = None if job.weight_mean is None else length[keep] / job.weight_mean
    slab.colors = None if colors is None else np.asarray(colors)[keep]
    slab.props = {k: np.asarray(v)[keep] for k, v in (props or {}).items()}
    # the attributes' transfer reads the points' normals after the solve
    slab.unit_nrm = nrm.copy() if (slab.props or slab.colors is not None) else None
    res = slab.res
    origin = np.asarray(job.origin)
    unit = (pts - origin) / job.size
    xc = np.clip(np.floor(unit[:, 0] * res), 0, res - 1)
    a, b = slab.x_range(slab.own, res)
    slab.own_pt = (xc >= a) & (xc < b)
    slab.pts = pts
    del xc
    smp = merge_samples(unit, nrm, job.depth, weight)
    del nrm, weight
    slab.smp = smp
    assert smp.keys is not None  # merge_samples keeps them
    sx = smp.keys >> 42
    slab.own_s = (sx >= a) & (sx < b)
    u0, u1 = slab.x_range(slab.usable, res)
    slab.use_s = (sx >= u0) & (sx < u1)
    ns = len(smp.count)
    slab.splat = np.full(ns, np.nan)
    slab.area = np.zeros(ns)
    kd = max(job.depth - KERNEL_OFFSET, 0)
    for lv in range(kd, job.local_density, -1):
        if ns:
            slab.tables[lv] = density_table(smp, lv)
            _place(slab, slab.tables[lv], lv)
    msg = _splat_stats(slab)
    msg.update(points=int(len(pts)), own_points=int(slab.own_pt.sum()), samples=ns)
    msg["own_samples"] = int(slab.own_s.sum())
    msg["ignored_points"] = int((~keep).sum())
    msg["own"] = [float(v) for v in slab.own]
    msg["usable"] = [float(v) for v in slab.usable]
    return msg


@timed
def load(
    slab: Slab,
    points: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray | None,
    props: dict | None = None,
) -> dict:
    """Read the slab's points, merge them per finest cell, place its samples.

    Points own and pad, job frame, finite; the samples placed are those the slab's own density
    levels place. Returns the splat figures.
    """
    return _load(slab, points, normals, colors, props)


@reads_only
@timed
def own_table(slab: Slab, level: int) -> dict:
    """The kernel-density table of the slab's own samples at ``level``.

    Sorted cell keys and densities; the coordinator adds the slabs' tables into the global one.
    """
    if not slab.own_s.any():
        return {"keys": np.zeros(0, np.int64), "dens": np.zeros(0)}
    _, (tk, tv, _bits), dens = density_table(_own_samples(slab), level)
    used = tk >= 0
    keys, rows = tk[used], tv[used]
    order = np.argsort(keys)
    return {"keys": keys[order], "dens": dens[rows[order]]}


def global_table(level: int, keys: np.ndarray, dens: np.ndarray) -> tuple:
    """A density table from sorted keys and summed densities.

    As :func:`.splat.density_table` makes them.
    """
    from recon_cli._kernels.hashtable import build_table

    tab = build_table(keys)
    return level, tab, dens


@timed
def place(slab: Slab, level: int, keys: np.ndarray, dens: np.ndarray) -> dict:
    """Place the samples left with the global density table at ``level``."""
    table = global_table(level, keys, dens)
    slab.tables[level] = table
    _place(slab, table, level)
    return _splat_stats(slab)


# ---------------------------------------------------------------------------------------------
# noise and the exact medians


def float_bins(values: np.ndarray) -> np.ndarray:
    """Bin of each non-negative float: the top 16 bits of its IEEE pattern (monotone)."""
    return (np.ascontiguousarray(values, dtype=np.float64).view(np.int64) >> 48).astype(np.int64)


def float_histogram(values: np.ndarray) -> dict:
    """Sparse histogram of non-negative floats by :func:`float_bins`.

    The first round of an exact distributed median.
    """
    b, c = np.unique(float_bins(values), return_counts=True)
    return {"bins": b, "counts": c, "n": int(len(values))}


def values_in(values: np.ndarray, bins: np.ndarray) -> np.ndarray:
    """The values whose bin is one of ``bins`` (the second round)."""
    return np.sort(values[np.isin(float_bins(values), bins)])


@timed
def noise(slab: Slab, tree_depth: int) -> dict:
    """Each sample's noise (:func:`.splat.noise_sigma`).

    Returns the histogram of the own samples' measured values, for the global median that stands in
    for the others.
    """
    slab.tree_depth = tree_depth
    unit = (slab.pts - np.asarray(slab.job.origin)) / slab.job.size
    slab.sigma = noise_sigma(unit, slab.smp, tree_depth)
    own = slab.sigma[slab.own_s]
    have = own[~np.isnan(own)]
    return {"hist": float_histogram(have), "missing": int(np.isnan(own).sum())}


@reads_only
@timed
def noise_values(slab: Slab, bins: np.ndarray) -> dict:
    """The own samples' measured noise values in ``bins`` (a median's second round)."""
    own = slab.sigma[slab.own_s]
    return {"values": values_in(own[~np.isnan(own)], bins)}


@reads_only
@timed
def noise_report_values(slab: Slab, bins: np.ndarray) -> dict:
    """The own samples' reported noise values in ``bins`` (a median's second round)."""
    assert slab.noise is not None  # called when the report measures the noise
    return {"values": values_in(slab.noise[slab.own_s], bins)}


# ---------------------------------------------------------------------------------------------
# items, fields, the tree


def merge_per_cell_sums(pos: np.ndarray, w: np.ndarray, level: int) -> tuple:
    """Samples summed per cell of ``level``.

    Sorted keys, summed weight, summed weight times position (the slabs' sums add up to
    :func:`.bspline._merge_per_cell`'s).
    """
    res = 1 << level
    keys = pack_keys(np.clip(np.floor(pos * res), 0, res - 1))
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    sw = np.bincount(inv, weights=w, minlength=len(uk))
    sp = np.stack(
        [np.bincount(inv, weights=pos[:, a] * w, minlength=len(uk)) for a in range(3)], axis=1
    )
    return uk, sw, sp


def merged_positions(sw: np.ndarray, sp: np.ndarray) -> np.ndarray:
    """Mean positions from summed weights ``sw`` and weighted positions ``sp``."""
    safe = np.where(sw > 0, sw, 1.0)
    return sp / safe[:, None]


@timed
def items(slab: Slab, tree_depth: int, alpha: float, fallback: float | None) -> dict:
    """The splat items, the fields, the slab's tree.

    Returns the slab's share of the coarse levels: its own items' fields there, the cells its finer
    items occupy, the screening sums of its own samples.
    """
    job = slab.job
    smp = slab.smp
    dc = min(job.coarse_depth, tree_depth)
    slab.tree_depth = tree_depth
    _drop_placement(slab, tree_depth)
    if alpha > 0:
        sig = slab.sigma
        sig[np.isnan(sig)] = fallback
        clean, slab.noise = clean_fraction(sig, job.depth, tree_depth)
        slab.sigma = None
    else:
        clean = None
    sp = Splats(None, None, None, alpha * smp.count, alpha, tree_depth, clean=clean)
    slab.screen_w = sp.screening(SCREEN_CLEAN, SCREEN_NOISY)
    if slab.sample_ok is not None:  # samples outside the envelope do not screen
        slab.screen_w = slab.screen_w * slab.sample_ok
    pos, vec, lvl, own = _splat_items(slab)
    coarse = lvl <= dc
    fine = ~coarse
    msg: dict[str, Any] = {}
    msg["coarse_fields"] = spread_fields(pos[own & coarse], vec[own & coarse], lvl[own & coarse])
    # the slab's own finer levels' fields (own + pad, and own alone for the coarse rhs)
    slab.fine_fields = spread_fields(pos[fine], vec[fine], lvl[fine]) if fine.any() else {}
    if slab.tree_items is not None:  # the tree (not the fields) refined along the envelope
        pos, lvl, own = _with_tree_items(slab, pos, lvl, own)
        coarse = lvl <= dc
        fine = ~coarse
    # the cells (level dc + 1) the slab's own finer items occupy: all the coarse tree needs of them
    rep = np.unique(
        pack_keys(np.clip(np.floor(pos[own & fine] * (1 << (dc + 1))), 0, (1 << (dc + 1)) - 1))
    )
    msg["coarse_items"] = (pos[own & coarse], lvl[own & coarse])
    msg["fine_cells"] = rep
    sums = {}
    if alpha > 0 and slab.own_s.any():
        for d in range(1, dc + 1):
            sums[d] = merge_per_cell_sums(smp.pos[slab.own_s], slab.screen_w[slab.own_s], d)
    msg["screening"] = sums
    if slab.noise is not None:
        msg["noise_hist"] = float_histogram(slab.noise[slab.own_s])
    # the slab's own finer levels' tree
    if fine.any() and tree_depth > dc:
        levels = build_levels(
            pos[fine],
            lvl[fine],
            tree_depth,
            job.full_depth,
            job.boundary,
            corners=False,
            own_ring=1,
        )
        slab.fine_levels = levels[dc + 1 :]
        for lev in slab.fine_levels:  # made again from the cells it extracts (field)
            lev.node_keys, lev.n_nodes = None, 0
    else:
        slab.fine_levels = []
    del pos, vec, lvl
    # read by no later step (the state every later step holds)
    smp.normal = None
    slab.splat = slab.area = slab.use_s = None
    release_free_heap()
    return msg


def _splat_items(slab: Slab) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The splat items of the slab's usable samples, its own first, as make_splats makes them.

    Returns their positions (i, 3), normal vectors (i, 3), levels (i,) and which are the
    slab's own (i,).
    """
    job, smp = slab.job, slab.smp
    splat = np.clip(np.nan_to_num(slab.splat), 0.0, job.depth)
    s_lo = np.floor(splat).astype(np.int64)
    s_frac = splat - s_lo
    s_frac[s_lo == job.depth] = 0.0
    normal_w = -slab.area[:, None] * smp.normal
    parts = []
    for sel in (slab.own_s, slab.use_s & ~slab.own_s):
        if sel.any():
            parts.append(
                merge_splats(
                    smp.pos[sel], normal_w[sel], smp.count[sel], s_lo[sel], s_frac[sel], False
                )
            )
        else:
            parts.append((np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)))
    n_own = len(parts[0][0])
    pos = np.concatenate([p[0] for p in parts])
    vec = np.concatenate([p[1] for p in parts])
    lvl = np.concatenate([p[2] for p in parts])
    own = np.zeros(len(pos), bool)
    own[:n_own] = True
    return pos, vec, lvl, own


def _with_tree_items(slab: Slab, pos: np.ndarray, lvl: np.ndarray, own: np.ndarray) -> tuple:
    """The items ``pos`` (m, 3), ``lvl`` (m,), ``own`` (m,) with the slab's tree-only items.

    Those :mod:`.slab_envelope` gave it (within its usable range), own where their x is in the
    slab's own range; ``slab.tree_items`` is let go.
    """
    assert slab.tree_items is not None  # given by .slab_envelope.take_tree_items
    tpos, tlvl = slab.tree_items
    slab.tree_items = None
    tx = tpos[:, 0]
    town = (tx >= slab.own[0]) & (tx < slab.own[1])
    return (
        np.concatenate([pos, tpos]),
        np.concatenate([lvl, tlvl]),
        np.concatenate([own, town]),
    )


def _drop_placement(slab: Slab, tree_depth: int) -> None:
    """Free what only the samples' placement and their noise read, before the items are made.

    The density tables but the output's (``--density``, ``--trim``), and the pad's points unless
    the slab carries attributes (the islands count its own points only).
    """
    job = slab.job
    ko = max(tree_depth - KERNEL_OFFSET, 0)
    keep = (job.density or job.trim > 0) and ko in slab.tables
    slab.tables = {ko: slab.tables[ko]} if keep else {}
    if not slab.props and slab.colors is None and slab.own_pt is not None:
        slab.pts = slab.pts[slab.own_pt]
        slab.own_pt = None


def coarse_item_set(msgs: list[dict], dc: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The coarse tree's items from the slabs' messages.

    Their own coarse items (positions, levels), and the level-``dc`` cells their finer items
    occupy (sorted unique keys: :func:`build_coarse_levels`' ``finer``).
    """
    pos = np.concatenate([m["coarse_items"][0] for m in msgs])
    lvl = np.concatenate([m["coarse_items"][1] for m in msgs])
    cells = np.concatenate([m["fine_cells"] for m in msgs])
    return pos, lvl, unique_keys(pack_keys(unpack_keys(cells) >> 1))


def build_coarse_levels(pos, lvl, finer, tree_depth: int, job: Job) -> list[Level]:
    """Levels 0..min(coarse depth, tree depth) of the whole cube's tree (the coordinator's).

    ``finer``: the level-``dc`` cells holding finer items (:func:`coarse_item_set`); the levels
    are those the finer items would give, without building level ``dc + 1`` of the whole cube.
    """
    dc = min(job.coarse_depth, tree_depth)
    if tree_depth <= dc:
        finer = None  # no finer item
    return build_levels(pos, lvl, dc, min(job.full_depth, dc), job.boundary, False, 1, finer)


def level_message(levels: list[Level]) -> list[tuple]:
    """The levels' cell keys and parents, as a message between processes.

    The nodes are not sent: a slab makes those it reads from the cells (:func:`corner_keys`).
    """
    return [(lev.cell_keys, lev.cell_parent) for lev in levels]


def levels_from_message(msg: list[tuple]) -> list[Level]:
    """The levels of :func:`level_message`'s message (without their nodes)."""
    out = []
    for d, (ck, cp) in enumerate(msg):
        out.append(Level(d, ck, None, 0, None, None, None, cp))
    return out


def _system(slab: Slab, coarse: list[tuple], coarse_fields: dict, keep: bool) -> tuple:
    """The slab's whole tree, its levels' fields and right-hand side, and the finer part's message.

    The tree holds the global coarse levels and the slab's own finer ones; the right-hand side is
    the normals' (:class:`.bspline.NormalRHS`, the coarse items' field the coordinator's). The
    message: the finer levels' part of the right-hand side on the finest coarse level at the
    cells the slab owns (every item it reaches is within the pad: the slabs' parts add up to the
    whole cube's). ``keep``: the system becomes the slab's (its fine levels and fields are used
    up: the finer levels' cells go, made again from the fields after the solve, and the
    coarse levels' nodes); else they are left as they were.

    Returns ``(levels, fields, arrays, normal_rhs, message)``.
    """
    job = slab.job
    levels = levels_from_message(coarse)
    dc = len(levels) - 1
    fine = slab.fine_levels
    if fine:
        parent = O.merge_lookup(np.unique(O.halve(fine[0].cell_keys)), levels[-1].cell_keys)
        if (parent < 0).any():
            raise StageFailed(
                f"distributed poisson: slab {slab.index}'s tree is not inside the coarse tree"
            )
        fine[0].cell_parent = O.bsearch_many(levels[-1].cell_keys, O.halve(fine[0].cell_keys))
    levels += fine
    lfs: list = [None]
    arrays = None
    if len(levels) > 1:
        lfs, arrays = level_fields(levels, job.boundary)
    msg: dict[str, Any] = {"cells": [len(lev.cell_keys) for lev in levels]}
    fields = dict(coarse_fields)
    fields.update(slab.fine_fields)
    if keep:
        slab.fine_levels, slab.fine_fields = [], {}
        for lev in levels[dc + 1 :]:  # made again from the fields after the solve (_fine_cells)
            lev.cell_keys, lev.cell_parent = np.zeros(0, np.int64), None
    normal_rhs = None
    if len(levels) - 1 > dc and dc >= 1:
        # the coarse levels' right-hand sides are the coordinator's: only their field is carried
        normal_rhs = NormalRHS(fields, lfs, lowest=dc)
        up = normal_rhs.finer[dc]
        if up is not None:
            # the children of each parent of E, in blocks of 8 (x offset: bit 0)
            f = lfs[dc]
            assert f is not None  # dc >= 1 has a field
            cx = 2 * (f.q_keys >> 42)[:, None] + (np.arange(8) & 1)[None, :]
            a, b = slab.x_range(slab.own, 1 << dc)
            mine = ((cx >= a) & (cx < b)).reshape(-1) & (up != 0)
            nz = np.flatnonzero(mine)
            msg["finer"] = (nz, up[nz])
    del fields
    return levels, lfs, arrays, normal_rhs, msg


@timed
def restrict(slab: Slab, coarse: list[tuple], coarse_fields: dict) -> dict:
    """Make the slab's whole system (:func:`_system`); return its message.

    The message: the finer levels' part of the right-hand side on the finest coarse level.
    """
    slab.levels, slab.lfs, slab.arrays, slab.normal_rhs, msg = _system(
        slab, coarse, coarse_fields, keep=True
    )
    release_free_heap()
    return msg


@reads_only
@timed
def restrict_message(slab: Slab, coarse: list[tuple], coarse_fields: dict) -> dict:
    """:func:`restrict`'s message, the system let go: the solve makes it again.

    For states that wait in spill files between steps: the slab's state over the coordinator's
    coarse solve is then its items' and tree, a third of its system's, and is not written again.
    """
    msg = _system(slab, coarse, coarse_fields, keep=False)[-1]
    release_free_heap()
    return msg


# ---------------------------------------------------------------------------------------------
# the solve


def solve_levels(
    levels: list[Level],
    lfs: list,
    arrays: tuple,
    normal_rhs: NormalRHS,
    screening: Callable[[int], tuple[np.ndarray, np.ndarray] | None],
    first: int,
    full_depth: int,
    cg_tolerance: float,
    boundary: str,
    on_level: Callable[[int], None] | None = None,
) -> tuple[list[dict], int, float]:
    """Levels ``first``.. of the cascadic degree-2 solve (:func:`.bspline.solve`'s loop).

    Each level's correction to the coarser levels' chi, whose coefficients (level ``first - 1``) are
    set, by :func:`.bspline.solve_level`. ``screening(d)`` gives the samples merged per cell of
    level ``d`` (positions, weights) or None. Returns per-level statistics, iterations and the last
    residual.
    """
    coef_all = arrays[4]
    q_off = arrays[1]
    prev = lfs[first - 1] if first > 1 else None
    stats = []
    total_it, last_res = 0, 0.0
    for d in range(1, first):
        normal_rhs.rhs(d)  # the coarser levels' field, carried to the finer ones
    for d in range(first, len(levels)):
        release_free_heap()
        tl = time.perf_counter()
        f = lfs[d]
        st, _ = solve_level(
            f,
            prev,
            functools.partial(normal_rhs.rhs, d),
            coef_all[8 * q_off[d] : 8 * q_off[d + 1]],
            screening,
            boundary,
            1e-7 if d <= full_depth else cg_tolerance,
            2000 if d <= full_depth else 200,
        )
        prev = f
        total_it += st["iterations"]
        last_res = st["residual"]
        st["iterations"] = int(st["iterations"])
        st["residual"] = float(st["residual"])
        st["seconds"] = time.perf_counter() - tl
        stats.append(st)
        if on_level is not None:
            on_level(d)
    return stats, total_it, last_res


def set_coefficients(lfs: list, arrays: tuple, coefs: list) -> None:
    """Give levels 1.. their coefficients (views into the concatenated array)."""
    q_off = arrays[1]
    for d, c in enumerate(coefs):
        if d == 0 or c is None:
            continue
        f = lfs[d]
        f.coef = arrays[4][8 * q_off[d] : 8 * q_off[d + 1]]
        f.coef[:] = c


def _band_parents(q_keys: np.ndarray, px: int) -> np.ndarray:
    """Indices of the sorted parent keys ``q_keys`` whose x is ``px``."""
    lo = np.searchsorted(q_keys, np.int64(px) << 42)
    hi = np.searchsorted(q_keys, np.int64(px + 1) << 42)
    return np.arange(lo, hi)


def band_message(slab: Slab, side: int) -> dict:
    """The coefficients of the slab's column of parents next to its seam on ``side``.

    ``side`` -1 left, +1 right; at every finer level: the neighbour reads chi there from them.
    """
    out = {}
    x = slab.own[0] if side < 0 else slab.own[1]
    for d in range(slab.job.coarse_depth + 1, len(slab.levels)):
        f = slab.lfs[d]
        px = int(round(x * (1 << (d - 1)))) - (0 if side < 0 else 1)
        rows = _band_parents(f.q_keys, px)
        coef = f.coef.reshape(-1, 8)[rows]
        out[d] = (f.q_keys[rows], f.inp[rows], coef)
    return out


def apply_band(slab: Slab, side: int, band: dict) -> None:
    """Take the neighbour's coefficients for its column of parents next to the seam on ``side``.

    The trees must agree there. Written into the field's own array (a state that moved between
    processes keeps no views into it).
    """
    x = slab.own[0] if side < 0 else slab.own[1]
    chi = slab.chi
    coef = chi.coef_all.reshape(-1, 8)
    q_off = chi.q_off
    for d in range(slab.job.coarse_depth + 1, len(slab.levels)):
        q_keys = chi.q_all[q_off[d] : q_off[d + 1]]
        q_inp = chi.inp_all[q_off[d] : q_off[d + 1]]
        px = int(round(x * (1 << (d - 1)))) - (1 if side < 0 else 0)
        rows = _band_parents(q_keys, px)
        keys, inp, band_coef = band.get(
            d, (np.zeros(0, np.int64), np.zeros(0, bool), np.zeros((0, 8)))
        )
        if not (np.array_equal(q_keys[rows], keys) and np.array_equal(q_inp[rows], inp)):
            raise StageFailed(
                f"distributed poisson: slabs {slab.index} and {slab.index + side} disagree on "
                f"the tree at their seam (level {d}): the pad is too small for this input"
            )
        coef[q_off[d] + rows] = band_coef


def _fine_cells(levels: list[Level], lfs: list, dc: int) -> None:
    """The cells of the levels finer than ``dc`` again, and their parents, from their fields.

    A level's cells are the 8 children of each of its field's flagged parents (the tree is
    complete in siblings: :func:`.bspline.level_parents`), the same keys in the same order: the
    slab keeps them out of its solve's peak.
    """
    for d in range(dc + 1, len(levels)):
        lev = levels[d]
        f = lfs[d]
        parents = f.q_keys[f.inp]
        index = O.merge_lookup(parents, levels[d - 1].cell_keys)
        lev.cell_keys, lev.cell_parent = O.children_sorted(parents, index)


@timed
def solve(slab: Slab, coefs: list, coarse: list[tuple], coarse_fields: dict) -> dict:
    """Solve the slab's finer levels on the coordinator's coarse chi.

    The slab's system is :func:`restrict`'s, or made again from its items and the coarse levels
    after :func:`restrict_message`. Returns the own samples' share of the iso-value, the per-level
    figures and the bands for the neighbours.
    """
    job = slab.job
    slab.noise = None  # its medians are taken
    if slab.levels is None:  # restrict_message let the system go
        slab.levels, slab.lfs, slab.arrays, slab.normal_rhs, _ = _system(
            slab, coarse, coarse_fields, keep=True
        )
        release_free_heap()
    levels, lfs, arrays = slab.levels, slab.lfs, slab.arrays
    dc = len(coefs) - 1
    msg: dict[str, Any] = {"levels": []}
    if arrays is None:  # a tree of one level: nothing to solve
        raise StageFailed("distributed poisson: the tree has a single level")
    set_coefficients(lfs, arrays, coefs)
    smp = slab.smp

    def screening(d):
        if job.point_weight <= 0 or not len(smp.count):
            return None
        _, sw, sp = merge_per_cell_sums(smp.pos, slab.screen_w, d)
        return merged_positions(sw, sp), sw

    if len(levels) - 1 > dc:
        normal_rhs, slab.normal_rhs = slab.normal_rhs, None
        stats, it, rel = solve_levels(
            levels,
            lfs,
            arrays,
            normal_rhs,
            screening,
            dc + 1,
            job.full_depth,
            job.cg_tolerance,
            job.boundary,
        )
        del normal_rhs
        msg["levels"] = stats
        msg["iterations"] = it
        msg["residual"] = rel
    _fine_cells(levels, lfs, dc)
    # the leaves (cells without children in the next level) and the field
    for d in range(1, len(levels)):
        levels[d - 1].leaf = ~O.cell_has_child(levels[d].cell_parent, len(levels[d - 1].cell_keys))
    levels[-1].leaf = np.ones(len(levels[-1].cell_keys), bool)
    slab.chi = ChiField([f for f in lfs[1:]], job.boundary, arrays)
    own = slab.own_s
    if own.any():
        chi_s = slab.chi.at(smp.pos[own])
        count = smp.count[own]
        if slab.sample_ok is not None:  # samples outside the envelope do not make the iso-value
            count = count * slab.sample_ok[own]
        msg["iso_sum"] = float((chi_s * count).sum())
        msg["iso_count"] = float(count.sum())
    else:
        msg["iso_sum"] = msg["iso_count"] = 0.0
    msg["band_left"] = band_message(slab, -1) if slab.index > 0 else None
    msg["band_right"] = band_message(slab, 1) if slab.index < slab.count - 1 else None
    # chi holds the levels' arrays: the fields' views of them go, and the neighbour tables (27
    # a parent, more than the coefficients) until the field step makes them again: the state
    # between the two steps, in memory or spilled, is 40 % of what it was
    slab.lfs = slab.arrays = None
    slab.chi.drop_neighbours()
    release_free_heap()
    return msg


# ---------------------------------------------------------------------------------------------
# the extraction


register_dask_sizes(Slab)


@timed
def load_files(
    slab: Slab,
    parts: list[tuple[str, np.ndarray]],
    nsub: int,
    colors: tuple | None = None,
    names: tuple = (),
    dtypes: tuple = (),
) -> dict:
    """:func:`load` from the chunks' files, the rows of the slab's pad range.

    ``(prefix, offsets)``: each chunk's rows sorted by sub-slab, ``offsets`` (nsub + 1,) where each
    sub-slab's rows start; ``colors`` (dtype, columns) when the chunks have colours, ``names`` and
    ``dtypes`` the properties carried (``prefix.a<i>.npy``).
    """
    pa, pb = slab.x_range(slab.pad, nsub)
    pts, nrm, col = [], [], []
    props: dict[str, list] = {name: [] for name in names}
    for prefix, off in parts:
        a, b = int(off[pa]), int(off[pb])
        if b <= a:
            continue
        pts.append(np.load(prefix + ".pts.npy", mmap_mode="r")[a:b])
        nrm.append(np.load(prefix + ".nrm.npy", mmap_mode="r")[a:b])
        if colors:
            col.append(np.load(prefix + ".col.npy", mmap_mode="r")[a:b])
        for i, name in enumerate(names):
            props[name].append(np.load(f"{prefix}.a{i:03d}.npy", mmap_mode="r")[a:b])
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    N = np.concatenate(nrm) if nrm else np.zeros((0, 3))
    C = (np.concatenate(col) if col else np.zeros((0, colors[1]), colors[0])) if colors else None
    A = {
        name: np.concatenate(v) if v else np.zeros(0, dtypes[i])
        for i, (name, v) in enumerate(props.items())
    }
    del pts, nrm, col, props
    return _load(slab, P, N, C, A)


def exact_median(runner, name: str, fn: Callable, hists: list[dict], phase: str) -> float | None:
    """The median (as ``np.median``) of values spread over the slabs.

    From their :func:`.slab.float_histogram` s and a second round for the values in the median's
    bins (``fn(slab, bins)`` returns them).
    """
    bins = np.concatenate([h["bins"] for h in hists])
    counts = np.concatenate([h["counts"] for h in hists])
    n = int(counts.sum())
    if n == 0:
        return None
    ub, inv = np.unique(bins, return_inverse=True)
    tot = np.bincount(inv.reshape(-1), counts, len(ub)).astype(np.int64)
    cum = np.cumsum(tot)
    ranks = [(n - 1) // 2, n // 2]
    want = np.unique([int(np.searchsorted(cum, r, side="right")) for r in ranks])
    msgs = runner.run(phase, fn, lambda k: (ub[want],))
    vals = np.sort(np.concatenate([m["values"] for m in msgs]))
    before = int(cum[want[0] - 1]) if want[0] > 0 else 0
    pick = [vals[r - before] for r in ranks]
    return float(np.mean(pick))
