"""Screened Poisson reconstruction of one cloud over many processes (a Dask cluster), in slabs.

Design, after Kazhdan & Hoppe's distributed PoissonRecon (2023: a coarse solve of the whole
domain on a server, the finer levels in slabs along one axis with padding on clients, and a
merge of the slabs into one seamless mesh), on this stage's own solver (:mod:`.bspline`,
degree 2) and Dask, the engine ``recon batch`` already uses.

**Partition.** The cube of the single-process solve (the same origin and size) is cut along
its longest axis into slabs whose seams are planes of the level-5 lattice
(:data:`.slab.PARTITION_DEPTH`; the slabs' axis becomes ``x`` by a cyclic turn of the axes,
so a slab's cells are a run of the x-major lattice keys). Levels up to ``full_depth`` (5)
are complete grids, so no leaf of the tree crosses a seam. Seams are chosen to balance the
slabs' points. More than 32 slabs (up to 64, when the workers' memory needs them) put the
seams on level-6 planes and make level 6 complete (``full_depth`` raised to 6: the same rule).
A slab reads its own points and those within a pad beyond each seam (whole
sub-slabs of level 8): ``PAD_CELLS`` cells of the first level the slabs solve, plus the reach
of the kernel density, so that every sample it splats has exactly the single-process splat.
The coordinator never holds the cloud: from a file each worker reads the rows of its
chunks and writes them per sub-slab (:func:`read_chunk`), each slab then reads its range.

**Global values.** What the single-process solve sums over all samples the coordinator sums
over the slabs, each slab giving its own samples' share: the bounding box, the kernel
density at the coarse levels (the finest one, ``depth - 2``, is a slab's own, exact within
the pad), the tree's depth and the mean area per sample (the screening weight), the noise
median that stands in where no fit answers (exact, by a histogram of the values' bit
patterns and a second round for the values in the median's bins), the iso-value (the
samples' mean chi). Each slab places its samples at their splat depths from these.

**Coarse solve.** Levels up to ``coarse_depth = depth - 3`` (between 5 and 9) are solved by
the coordinator for the whole cube, as the single-process solve does: its tree is built from the
slabs' own coarse items and, for the finer ones, the cells of level ``coarse_depth + 1``
they occupy (all the coarse levels depend on); the right-hand side is the coarse items'
field plus the finer items' part restricted onto level ``coarse_depth``, which each slab
computes for its own items; the screening is the samples summed per cell. Its chi is every
slab's starting point: the slabs' finer levels are solved on top of the same coarse chi.

**Fine solve.** Each slab builds the tree's finer levels from its items (own and pad: the
tree near a seam is the same in both slabs), and solves them cascadically, coarse to fine,
each level's correction on the residual the coarser ones leave, as the single-process solve
does; beyond its pad the corrections are zero. The cascade makes this local: the coarse chi
carries the low frequencies, each finer level's correction is a few cells wide.

**Seams, exactly.** After the solve each slab takes, from its neighbour, the coefficients of
the neighbour's column of parent cells next to the seam at every finer level (chi at a point
reads the 27 cells around it, one parent column on each side of the seam). So both slabs of
a seam evaluate the same chi, with the same coefficients and the same tree, anywhere within
a cell of it: the neighbour's coefficients on its side, their own on theirs; chi at the
tree's nodes (within two cells of the slab) is then the same bits on both sides. Each slab
extracts the leaves it owns (lower x in its range) as the single-process solve would: at
the leaves' own size (:func:`.extract.extract_leaves`, restricted to the slab's leaves)
when a coarse leaf holds surface anywhere (every slab says, the coordinator decides), else
on the finest lattice (:func:`.extract.extract_finest`'s steps, the points on a seam plane
given one rule both slabs compute alike: :func:`.slab.plane_values`). A face on a seam has
the same node values on both sides, hence the same crossings, the same vertices (the same
root along the same edge, then chi's root along it: same numbers, same bits) and the same
pairing of its segments. Vertices on a seam are welded by their position on the lattice
(the coordinator checks the two sides' lists are equal, else the run fails): the right
slab owns them, the left one refers to them by rank. The mesh is one surface, closed and
manifold where the single-process mesh is, with no vertex twice.

**Merge.** Pieces are joined across seams by their seam vertices (union-find over the
slabs' pieces); specks and islands (:func:`._drop_bubbles`' rules) are decided on the
joined pieces, the largest always kept. ``trim`` cuts each slab's faces at the global
threshold (the exact median of the samples' density: two rounds of histograms), the new
vertices on a seam's edges shared; holes and islands are pieces joined across seams and
decided on the global kept area (:func:`.trim.trim_by_density`'s rules). Each slab then
writes its vertices and faces: the input's properties and colours carried as the
single-process run carries them (:mod:`.attributes`: the points near each vertex on its
side, from the slab's points and pad; the surface's normal at a seam vertex summed over
both slabs' faces; the report counts the vertices whose neighbours may lie past the pad,
``attribute_inexact_vertices``), the density. The coordinator writes a binary PLY a block
of rows at a time from the slabs' files (face indices offset, references to the right seam
resolved, axes turned back), atomically: a failed run leaves no output. It never holds the
cloud nor the mesh.

**Workers.** Every slab step is a deterministic function of the slab's inputs and the global
values before it; a slab whose worker dies is rebuilt by running its steps again on
another worker (:class:`recon_cli.slabs.runners.DaskRunner`), the global values being the
coordinator's. With more slabs than workers, a slab's state goes to a file in the job's
temporary folder between its steps (the runner's spill folder), so a worker holds only the
slab it runs: more slabs, less memory a worker. Unless told, a run takes the fewest slabs, a
multiple of the workers, whose one slab fits a share of a worker's memory limit
(:func:`default_partitions`); the report's ``distributed.partitions`` says how many and why.

**Progress and report.** One bar over the whole job (:class:`recon_cli.slabs.runners.Overall`:
each phase its measured share, advanced as each slab finishes it, with the time left);
the report's ``distributed.phases`` gives per phase the wall seconds, the slowest slab's
seconds, the CPU seconds, the largest worker's peak memory and the bytes moved between the
coordinator and the workers.

Differences from the single-process output: the finer levels' corrections near a seam are
solved in the two slabs' pads (the seam takes the owner's), and sums are added in another
order: with one slab the mesh is the single-process one to rounding, with more the
vertices near the seams move by a small fraction of a finest cell. ``--boundary free``,
``--envelope`` and ``--grid`` are not distributed (refused).

References
----------
Kazhdan, M. & Hoppe, H. (2023). Distributed Poisson surface reconstruction. Computer
Graphics Forum 42(6).
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.slabs import plan
from recon_cli.slabs.plan import choose_seams, sub_slab
from recon_cli.slabs.runners import Overall, map_tasks
from recon_cli.slabs.spill import spill_folder
from recon_cli.stages.poisson import slab as S
from recon_cli.stages.poisson.splat import KERNEL_OFFSET, screening_alpha

if TYPE_CHECKING:
    from recon_cli.stages.poisson import PoissonResult

log = logging.getLogger("recon")


# ---------------------------------------------------------------------------------------------
# the plan


def plan_slabs(
    job: S.Job, sub_counts: np.ndarray, parts: int, seams: list[int] | None = None
) -> list[tuple]:
    """Per slab: own, pad (points read) and usable (samples splatted) x ranges (unit cube).

    ``seams``: the seams' planes of level ``job.seam_depth`` (1..31 for level 5, increasing),
    else balanced by the counts.
    """
    nsub = len(sub_counts)
    per = nsub >> job.seam_depth
    counts = sub_counts.reshape(-1, per).sum(axis=1)
    if seams is None:
        seams = choose_seams(counts, parts)
    elif (
        len(seams) != parts - 1
        or list(seams) != sorted(set(seams))
        or (seams and not (1 <= seams[0] and seams[-1] < len(counts)))
    ):
        raise ParameterError(f"seams must be {parts - 1} increasing planes in 1..{len(counts) - 1}")
    seams = [0] + [int(s) for s in seams] + [1 << job.seam_depth]
    first_fine = job.coarse_depth + 1
    pad_items = math.ceil(S.PAD_CELLS * nsub / (1 << first_fine))
    reach = math.ceil(S.DENSITY_REACH * nsub / (1 << (job.local_density + 1)))
    out = []
    for k in range(parts):
        a, b = seams[k] * per, seams[k + 1] * per
        ua, ub = max(a - pad_items, 0), min(b + pad_items, nsub)
        pa, pb = max(ua - reach, 0), min(ub + reach, nsub)
        out.append(((a / nsub, b / nsub), (pa / nsub, pb / nsub), (ua / nsub, ub / nsub)))
    return out


def slab_loads(plan: list[tuple], sub_counts: np.ndarray) -> list[float]:
    """The points each slab of ``plan`` (:func:`plan_slabs`) reads: its work, to spread them."""
    nsub = len(sub_counts)
    cum = np.concatenate([[0], np.cumsum(sub_counts)])
    return [float(cum[round(p[1][1] * nsub)] - cum[round(p[1][0] * nsub)]) for p in plan]


# a slab's peak memory per point of its own, its pads' points included
# (bench/calibration.md, SLAB_BYTES_PER_POINT: 4103 at depth 11 in 4 slabs on 2 workers)
SLAB_BYTES_PER_POINT = 4096


def slab_count(
    partitions: int | None, npoints: int, client: Any, budget: int | None = None
) -> tuple[int, dict]:
    """The Poisson slabs of a run and why (:func:`recon_cli.slabs.plan.slab_count`)."""
    return plan.slab_count(
        partitions,
        npoints,
        client,
        SLAB_BYTES_PER_POINT,
        S.MAX_PARTITIONS,
        "poisson",
        f"the seams are level-{S.FINE_PARTITION_DEPTH} planes",
        budget,
    )


def coarse_depth_for(depth: int, seam_depth: int = S.PARTITION_DEPTH) -> int:
    """The levels the coordinator solves.

    ``depth - COARSE_OFFSET``, at least the seams' level, at most :data:`.slab.COARSE_MAX` (the
    coarse tree stays small at any depth; the slabs solve the rest).
    """
    return min(depth, max(seam_depth, min(depth - S.COARSE_OFFSET, S.COARSE_MAX)))


# ---------------------------------------------------------------------------------------------
# the coordinator's steps

# each phase's share of a run's wall time, for the progress bar over the whole job (measured
# on the bench's runs: bench/bench_distributed.py; a phase that does not run adds nothing)
PHASE_WEIGHTS = {
    "sort": 6.0,
    "load": 6.0,
    "density": 1.0,
    "place": 1.0,
    "noise": 8.0,
    "items": 10.0,
    "restrict": 6.0,
    "coarse tree": 1.0,
    "coarse solve": 5.0,
    "solve": 25.0,
    "field": 6.0,
    "extract": 12.0,
    "prepare": 1.0,
    "trim": 4.0,
    "seams": 1.0,
    "attributes": 8.0,
    "export": 2.0,
    "write": 4.0,
}


def job_weights(from_files: bool, noise: bool, trim: bool, carry: bool, write: bool) -> dict:
    """The phases a run goes through and their weights (:data:`PHASE_WEIGHTS`)."""
    skip = set()
    if not from_files:
        skip.add("sort")
    if not noise:
        skip.add("noise")
    if not trim:
        skip.add("trim")
    skip.update(("export",) if carry else ("seams", "attributes"))
    if not write:
        skip.add("write")
    return {k: w for k, w in PHASE_WEIGHTS.items() if k not in skip}


def _coordinator_step(runner, name: str):
    """The coordinator's own step ``name``, on the job's bar (when there is one)."""
    import contextlib

    overall = getattr(runner, "overall", None)
    return overall.step(name) if overall is not None else contextlib.nullcontext()


def _sum_tables(msgs: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    keys = np.concatenate([m["keys"] for m in msgs])
    dens = np.concatenate([m["dens"] for m in msgs])
    uk, inv = np.unique(keys, return_inverse=True)
    return uk, np.bincount(inv.reshape(-1), weights=dens, minlength=len(uk))


def _sum_fields(parts: list[dict]) -> dict:
    out = {}
    levels = sorted({d for p in parts for d in p})
    for d in levels:
        keys = np.concatenate([p[d][0] for p in parts if d in p])
        vec = np.concatenate([p[d][1] for p in parts if d in p])
        uk, inv = np.unique(keys, return_inverse=True)
        inv = inv.reshape(-1)
        out[d] = (uk, np.stack([np.bincount(inv, vec[:, a], len(uk)) for a in range(3)], axis=1))
    return out


def _sum_screening(parts: list[dict]) -> dict:
    out = {}
    for d in sorted({d for p in parts for d in p}):
        keys = np.concatenate([p[d][0] for p in parts if d in p])
        sw = np.concatenate([p[d][1] for p in parts if d in p])
        sp = np.concatenate([p[d][2] for p in parts if d in p])
        uk, inv = np.unique(keys, return_inverse=True)
        inv = inv.reshape(-1)
        w = np.bincount(inv, sw, len(uk))
        p3 = np.stack([np.bincount(inv, sp[:, a], len(uk)) for a in range(3)], axis=1)
        out[d] = (S.merged_positions(w, p3), w)
    return out


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


def solve_coarse(
    levels: list, job: S.Job, fields: dict, finer: np.ndarray | None, screening: dict
) -> tuple[list, list[dict], int, float]:
    """The coordinator's solve of the coarse levels.

    Returns each level's coefficients (None for level 0), per-level figures, iterations, last
    residual.
    """
    from recon_cli.stages.poisson.bspline import NormalRHS, level_fields

    dc = len(levels) - 1
    lfs, arrays = level_fields(levels, job.boundary)
    # the finer levels' part enters the restriction where the single solve's does (a sum
    # restricted, not two restrictions summed: the same rounding)
    nrhs = NormalRHS(fields, lfs, finer=finer)

    def scr(d):
        return screening.get(d)

    stats, it, rel = S.solve_levels(
        levels, lfs, arrays, nrhs, scr, 1, job.full_depth, job.cg_tolerance, job.boundary
    )
    coefs: list[np.ndarray | None] = [None]
    for d in range(1, dc + 1):
        lf = lfs[d]
        assert lf is not None and lf.coef is not None  # solved above
        coefs.append(lf.coef.copy())
    return coefs, stats, it, rel


# ---------------------------------------------------------------------------------------------
# the whole run


def frame_of(lo: np.ndarray, hi: np.ndarray, scale: float) -> tuple[np.ndarray, float, tuple]:
    """The single-process solve's cube (origin, size) for the kept points' box.

    And the cyclic turn of the axes that makes the longest one ``x``.
    """
    size = float((hi - lo).max()) * scale
    origin = 0.5 * (lo + hi) - 0.5 * size
    axis = int(np.argmax(hi - lo))
    perm = (axis, (axis + 1) % 3, (axis + 2) % 3)
    return origin, size, perm


def make_job(origin, size, perm, depth, p: dict) -> S.Job:
    """The job every slab shares: the cube in the turned axes, the depths, the parameters."""
    sd = p.get("seam_depth", S.PARTITION_DEPTH)
    dc = coarse_depth_for(depth, sd)
    o = np.asarray(origin, dtype=np.float64)[list(perm)]
    return S.Job(
        origin=(float(o[0]), float(o[1]), float(o[2])),
        size=size,
        depth=depth,
        samples_per_node=p["samples_per_node"],
        point_weight=p["point_weight"],
        boundary=p["boundary"],
        full_depth=p["full_depth"],
        cg_tolerance=p["cg_tolerance"],
        coarse_depth=dc,
        local_density=dc,
        density=p["density"],
        trim=p["trim"],
        weight_mean=p.get("weight_mean"),
        seam_depth=sd,
    )


def reconstruct(
    runner,
    job: S.Job,
    loaded: list[dict],
    progress: Any = None,
    out_dir: str | None = None,
    carry: bool = False,
) -> dict:
    """Every step after the slabs' ``load`` (whose messages are ``loaded``).

    Returns the mesh's parts per slab (in ``out_dir``'s files when given) and the report (module
    docstring); ``carry``: the slabs carry the input's properties or colours onto their vertices.
    """
    from recon_cli.stages.poisson import fold_cells, speck_cells

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    # ---- the samples' splat depths: the slabs' own density levels, then the global ones
    tables: dict[int, tuple] = {}
    tree_depth, alpha = _splat_depths(runner, job, loaded, tables)
    timings["samples"] = time.perf_counter() - t0
    # ---- noise: the median of the measured values stands in for the others
    t = time.perf_counter()
    fallback = 0.0
    if alpha > 0:
        nm = runner.run("noise", S.noise, lambda k: (tree_depth,))
        if sum(m["missing"] for m in nm):
            med = exact_median(runner, "sigma", S.noise_values, [m["hist"] for m in nm], "noise")
            fallback = 0.0 if med is None else med
    timings["noise"] = time.perf_counter() - t
    # ---- items, fields, the slabs' trees; the coarse levels' data
    t = time.perf_counter()
    dc = min(job.coarse_depth, tree_depth)
    coarse, cmsg, coarse_fields, screening, finer, noise_med = _coarse_tree(
        runner, job, tree_depth, dc, alpha, fallback
    )
    timings["tree"] = time.perf_counter() - t
    # ---- the coarse solve, then the slabs' finer levels
    t = time.perf_counter()
    with _coordinator_step(runner, "coarse solve"):
        coefs, cstats, cit, cres = solve_coarse(coarse, job, coarse_fields, finer, screening)
    del finer, screening
    timings["coarse_solve"] = time.perf_counter() - t
    t = time.perf_counter()
    sm = runner.run("solve", S.solve, lambda k: (coefs, cmsg, coarse_fields))
    iso = sum(m["iso_sum"] for m in sm) / sum(m["iso_count"] for m in sm)
    timings["solve"] = time.perf_counter() - t
    # ---- extraction, each slab with its neighbours' bands
    t = time.perf_counter()
    n = len(sm)
    bands = [
        (sm[k - 1]["band_right"] if k > 0 else None, sm[k + 1]["band_left"] if k < n - 1 else None)
        for k in range(n)
    ]
    levels_stats = cstats + [s for m in sm for s in m["levels"]]
    iterations = cit + sum(m.get("iterations", 0) for m in sm)
    residual = max([m.get("residual", 0.0) for m in sm] + [cres])
    del sm
    fm = runner.run("field", S.field, lambda k: (iso, *bands[k]))
    bands = []  # released: the slabs have theirs
    # as the single-process extraction decides: at the leaves' own size when a coarse leaf
    # holds surface, else on the finest lattice (the same surface, faster)
    at_leaves = any(m["coarse"] for m in fm)
    em = runner.run("extract", S.extract, lambda k: (iso, at_leaves))
    cell = job.size / (1 << tree_depth)
    drop, (specks, islands, folds), seam_dev = _merge_pieces(
        runner, em, cell, speck_cells(noise_med), fold_cells(noise_med)
    )
    timings["extract"] = time.perf_counter() - t
    # ---- each slab's output
    t = time.perf_counter()
    dens_spec = _density_spec(runner, job, tree_depth, tables)
    usable = [m["usable"] for m in loaded]

    def dens_part(k):
        if dens_spec is None or len(dens_spec) == 1:
            return dens_spec
        return (dens_spec[0], *table_part(*dens_spec[1:], dens_spec[0], usable[k]))

    pm = runner.run("prepare", S.prepare, lambda k: (drop[k], dens_part(k), job.trim > 0))
    seam_keep: list[dict | None] = list(_seams_used([m["seam_use"] for m in pm]))
    timings["finish"] = time.perf_counter() - t
    trimmed, trimmed_area = 0, 0.0
    if job.trim > 0:
        t = time.perf_counter()
        seam_keep, trimmed, trimmed_area = _trim(runner, job.trim, pm, seam_keep)
        timings["trim"] = time.perf_counter() - t
    del pm
    t = time.perf_counter()
    left = [None] * len(seam_keep)
    if carry:
        # the surface's normal at a seam vertex sums both slabs' faces (the attributes' side)
        nm = runner.run("seams", S.seam_normals, lambda k: (seam_keep[k],))
        left = [None] + [m["right"] for m in nm[:-1]]
        seam_keep = [None] * len(seam_keep)
        del nm
    fm = runner.run(
        "attributes" if carry else "export",
        S.export,
        lambda k: (
            seam_keep[k],
            None if out_dir is None else os.path.join(out_dir, f"s{k:03d}"),
            left[k],
        ),
    )
    timings["finish"] += time.perf_counter() - t
    astats = [m.pop("attribute_stats", None) for m in fm]
    report = {
        "depth": job.depth,
        "tree_depth": tree_depth,
        "iso_value": iso,
        "solver_iterations": int(iterations),
        "residual": float(residual),
        "bubbles_removed": specks,
        "islands_removed": islands,
        "folds_removed": folds,
        "trimmed_faces": int(trimmed),
        "trimmed_area": float(trimmed_area),
        "noise": noise_med,
        "samples": int(sum(m["own_samples"] for m in loaded)),
        "attribute_fallback_vertices": sum(a["fallback"] for a in astats if a),
        "finest_cell": cell,
        "levels": levels_stats,
        "timings": timings,
        "distributed": {
            "coarse_depth": dc,
            "extraction": "leaves" if at_leaves else "finest",
            "seam_max_deviation": seam_dev,
            # vertices whose attribute neighbours may lie past their slab's pad
            "attribute_inexact_vertices": sum(a["inexact"] for a in astats if a),
            "slabs": [
                {
                    "own": lm["own"],
                    "points": lm["own_points"],
                    "points_read": lm["points"],  # with its pads'
                    "samples": lm["own_samples"],
                    "faces": e["faces"],
                    "seam_vertices": len(e["seam_left"][0]),
                }
                for lm, e in zip(loaded, em, strict=True)
            ],
        },
    }
    return {"parts": fm, "report": report, "phases": getattr(runner, "phases", {})}


def _splat_depths(runner, job: S.Job, loaded: list[dict], tables: dict[int, tuple]) -> tuple:
    """The samples' splat depths over the slabs: (the tree's depth, the screening weight alpha).

    Each slab places its samples at its own density levels, then at the global ones, coarser
    level by level; ``tables`` gets each level's summed density table.
    """
    msgs = loaded
    usable = [m["usable"] for m in loaded]
    level = job.local_density
    while sum(m["unplaced"] for m in msgs) and level >= 0:
        keys, dens = _sum_tables(runner.run("density", S.own_table, lambda k, lv=level: (lv,)))
        tables[level] = (keys, dens)
        msgs = runner.run(
            "place",
            S.place,
            lambda k, lv=level, ks=keys, ds=dens: (lv, *table_part(ks, ds, lv, usable[k])),
        )
        level -= 1
    if sum(m["unplaced"] for m in msgs):
        raise StageFailed("distributed poisson: samples left without a splat depth")
    tree_depth = max(max(m["max_level"] for m in msgs), 1)
    if tree_depth < job.seam_depth:
        raise ParameterError(
            f"the samples support a tree of depth {tree_depth} only: too sparse to cut into "
            f"slabs (that needs {job.seam_depth}); run in one piece (without --workers, "
            "--scheduler or --partitions)"
        )
    count = sum(m["count"] for m in msgs)
    mean_area = sum(m["area_count"] for m in msgs) / count
    return tree_depth, screening_alpha(job.point_weight, mean_area, tree_depth)


def _coarse_tree(
    runner, job: S.Job, tree_depth: int, dc: int, alpha: float, fallback: float
) -> tuple:
    """The slabs' items and trees, and the coarse levels' data on the coordinator.

    Returns the coarse levels (to ``dc``), their summed fields and screening, the finer items'
    right-hand side restricted to level ``dc`` (or None) and the noise median (None unscreened).
    """
    im = runner.run("items", S.items, lambda k: (tree_depth, alpha, fallback))
    noise_med = None
    if alpha > 0:
        noise_med = exact_median(
            runner, "noise", S.noise_report_values, [m["noise_hist"] for m in im], "noise"
        )
    coarse_fields = _sum_fields([m["coarse_fields"] for m in im])
    screening = _sum_screening([m["screening"] for m in im]) if alpha > 0 else {}
    cpos, clvl, finer_cells = S.coarse_item_set(im, dc)
    del im
    with _coordinator_step(runner, "coarse tree"):
        coarse = S.build_coarse_levels(cpos, clvl, finer_cells, tree_depth, job)
    del cpos, clvl, finer_cells
    # one message for every slab (the runner writes a large argument all slabs share once)
    cmsg = S.level_message(coarse)
    # states spilled between steps: the system is made again by the solve, not written
    step = S.restrict_message if getattr(runner, "spill_dir", None) else S.restrict
    rm = runner.run("restrict", step, lambda k: (cmsg, coarse_fields))
    finer = None
    parts = [m["finer"] for m in rm if "finer" in m]
    if parts:
        from recon_cli.stages.poisson.bspline import level_parents

        finer = np.zeros(8 * len(level_parents(coarse[dc])[0]))
        for idx, val in parts:
            np.add.at(finer, idx, val)
    return coarse, cmsg, coarse_fields, screening, finer, noise_med


def table_part(keys: np.ndarray, dens: np.ndarray, level: int, usable) -> tuple:
    """The cells of a summed density table (sorted ``keys``, ``dens``) a slab reads.

    Those within one cell of level ``level`` of its ``usable`` x range (unit cube): every sample
    it places and every vertex it owns is in that range, and a density reads the cells around
    its own (:func:`.splat.eval_density`). A slab holds its part, not the whole cube's table.
    """
    n = 1 << level
    a = max(math.floor(usable[0] * n) - 1, 0)
    b = min(math.ceil(usable[1] * n) + 1, n)
    lo = np.searchsorted(keys, np.int64(a) << 42)
    hi = np.searchsorted(keys, np.int64(b) << 42)
    return keys[lo:hi], dens[lo:hi]


def _density_spec(runner, job: S.Job, tree_depth: int, tables: dict[int, tuple]) -> tuple | None:
    """What the slabs need for the vertices' densities (``--density``, ``--trim``), else None.

    The kernel's level alone when the slabs hold it, else with its summed table.
    """
    if not (job.density or job.trim > 0):
        return None
    ko = max(tree_depth - KERNEL_OFFSET, 0)
    if ko > job.local_density:
        return (ko,)
    if ko not in tables:
        tables[ko] = _sum_tables(runner.run("density", S.own_table, lambda k: (ko,)))
    return (ko, *tables[ko])


def _seams_used(uses: list[dict]) -> list[dict]:
    """Per slab, the seam vertices either slab of each of its seams uses.

    The two export the same ones: ``{"left": mask, "right": mask}``.
    """
    n = len(uses)
    out = [{"left": u["left"].copy(), "right": u["right"].copy()} for u in uses]
    for k in range(1, n):
        both = uses[k - 1]["right"] | uses[k]["left"]
        out[k - 1]["right"] = both
        out[k]["left"] = both.copy()
    return out


def _join(parts: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join the slabs' pieces across the seams' edges.

    The pieces are ``{"areas": (n_k,), "links": {side: (edge keys, labels)}}``. Returns the global
    piece of each slab's piece (concatenated, slab offsets) and the pieces' summed areas.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sizes = [len(p["areas"]) for p in parts]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(off[-1])
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for k in range(1, len(parts)):
        rk, rl = parts[k - 1]["links"]["right"]
        lk, ll = parts[k]["links"]["left"]
        _, ia, ib = np.intersect1d(rk, lk, return_indices=True)
        rows.append(rl[ia] + off[k - 1])
        cols.append(ll[ib] + off[k])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r)), (r, c)), shape=(total, total))
    ncomp, comp = connected_components(g, directed=False)
    areas = np.bincount(comp, weights=np.concatenate([p["areas"] for p in parts]), minlength=ncomp)
    return comp, off, areas


def _trim(
    runner, trim: float, pm: list[dict], seam_keep: list[dict | None]
) -> tuple[list[dict | None], int, float]:
    """The trim over the slabs.

    :func:`.trim.trim_by_density`'s steps, its islands and holes joined across seams; returns the
    seam vertices kept, the trimmed faces and the fraction of the area removed.
    """
    from recon_cli.stages.poisson.trim import ISLAND_AREA_RATIO

    med = exact_median(runner, "density", S.density_values, [m["hist"] for m in pm], "trim")
    if med is None:  # no sample to measure: nothing is below the threshold
        return seam_keep, 0, 0.0
    threshold = trim * float(med)
    cm = runner.run("trim", S.trim_cut, lambda k: (threshold,))
    faces_before = sum(m["faces"] for m in cm)
    n = len(cm)
    if not any(m["cut"] for m in cm):
        # nothing below the threshold: the mesh as it is
        return seam_keep, 0, 0.0
    total = sum(m["area"] for m in cm)
    kept_area = sum(m["kept_area"] for m in cm)
    # small low pieces are holes in a sparse patch: kept
    comp, off, areas = _join(cm)
    small = areas < ISLAND_AREA_RATIO * kept_area
    flip = [np.flatnonzero(small[comp[off[k] : off[k + 1]]]) for k in range(n)]
    km = runner.run("trim", S.trim_keep, lambda k: (flip[k],))
    # small kept pieces are islands in the closing sheet: dropped
    comp, off, areas = _join(km)
    small = areas < ISLAND_AREA_RATIO * kept_area
    drop = [np.flatnonzero(small[comp[off[k] : off[k + 1]]]) for k in range(n)]
    use = []
    for k, m in enumerate(km):
        u = {}
        for side, (ranks, labels) in m["seam_pieces"].items():
            alive = ~np.isin(labels, drop[k])
            mask = np.zeros(m["seam_counts"][side], bool)
            mask[ranks[alive]] = True
            u[side] = mask
        use.append(u)
    keep = _seams_used(use)
    dm = runner.run("trim", S.trim_drop, lambda k: (drop[k], keep[k]))
    removed = sum(m["removed_area"] for m in dm)
    untouched = sum(m["untouched"] for m in dm)
    if sum(m["faces"] for m in dm) == 0:
        raise ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value")
    return [None] * n, faces_before - untouched, removed / total if total > 0 else 0.0


def _merge_pieces(
    runner, em: list[dict], cell: float, speck: float, fold: tuple[float, float] | None
) -> tuple[list[np.ndarray], tuple[int, int, int], float]:
    """Join the slabs' pieces across the seams, decide the specks, islands and folds.

    Pieces join through their seam vertices; the specks (under ``speck`` cells across:
    :func:`.speck_cells` of the noise median), islands and folds (``fold``: :func:`.fold_cells`
    of it) are decided on the joined pieces by :func:`.pieces.noise_pieces`, as in one process,
    the islands' points counted and the folds' vertices sent by the slabs. Returns per slab the
    local labels to drop,
    the counts of specks, islands and folds, and the largest distance between the two slabs'
    positions of a seam vertex (0: the same bits).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from recon_cli.stages.poisson.pieces import noise_pieces, piece_reach

    n = len(em)
    sizes = [len(m["pieces"][0]) for m in em]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(off[-1])
    rows, cols = [], []
    dev = 0.0
    for k in range(1, n):
        lyz, lpos, llab = em[k - 1]["seam_right"]
        ryz, rpos, rlab = em[k]["seam_left"]
        if len(lyz) != len(ryz) or not np.array_equal(lyz, ryz):
            raise StageFailed(
                f"distributed poisson: slabs {k - 1} and {k} disagree on their seam's vertices "
                f"({len(lyz)} against {len(ryz)})"
            )
        if len(lpos):
            dev = max(dev, float(np.abs(lpos - rpos).max()))
        ok = (llab >= 0) & (rlab >= 0)
        rows.append(llab[ok] + off[k - 1])
        cols.append(rlab[ok] + off[k])
    if total == 0:
        return [np.zeros(0, np.int64)] * n, (0, 0, 0), dev
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    g = coo_matrix((np.ones(len(r)), (r, c)), shape=(total, total))
    ncomp, comp = connected_components(g, directed=False)
    faces = np.zeros(ncomp, np.int64)
    lo = np.full((ncomp, 3), np.inf)
    hi = np.full((ncomp, 3), -np.inf)
    for k, m in enumerate(em):
        cnt, plo, phi = m["pieces"]
        gid = comp[off[k] : off[k + 1]]
        np.add.at(faces, gid, cnt)
        for ax in range(3):
            np.minimum.at(lo[:, ax], gid, plo[:, ax])
            np.maximum.at(hi[:, ax], gid, phi[:, ax])
    largest = int(np.argmax(faces))
    local = [comp[off[k] : off[k + 1]] for k in range(n)]

    def count_points(a, b):
        im = runner.run("islands", S.island_points, lambda k: (a, b))
        return np.sum([m["counts"] for m in im], axis=0)

    def farthest(which, anchor, a, b):
        fm = runner.run(
            "folds", S.fold_vertices, lambda k: (which[local[k]], anchor[local[k]], a, b)
        )
        return piece_reach(
            np.concatenate([m["points"] for m in fm]),
            np.concatenate([m["ids"] for m in fm]),
            len(a),
            np.concatenate([m["targets"] for m in fm]),
        )

    specks, islands, folds = noise_pieces(
        lo, hi, largest, cell, speck, fold, count_points, farthest
    )
    gone = specks | islands | folds
    drop = [np.flatnonzero(gone[local[k]]) for k in range(n)]
    counts = (int(specks.sum()), int(islands.sum()), int(folds.sum()))
    return drop, counts, dev


def assemble(out: dict, job: S.Job, perm: tuple, colors: bool):
    """The mesh from the slabs' parts (in memory).

    Vertices concatenated in slab order, face references to a right seam resolved to the next slab's
    vertices, axes turned back.
    """
    from recon_cli.geometry import TriangleMesh

    parts = out["parts"]
    nv = [len(p["vertices"]) for p in parts]
    off = np.concatenate([[0], np.cumsum(nv)]).astype(np.int64)
    faces = []
    for k, p in enumerate(parts):
        f = p["faces"]
        g = np.where(f >= 0, f + off[k], off[min(k + 1, len(parts) - 1)] + (-1 - f))
        faces.append(g)
    inv = np.argsort(perm)
    verts = np.concatenate([p["vertices"] for p in parts])[:, inv] if parts else np.zeros((0, 3))
    mesh = TriangleMesh(
        vertices=np.ascontiguousarray(verts),
        faces=np.concatenate(faces).astype(np.int64) if faces else np.zeros((0, 3), np.int64),
    )
    for name in parts[0]["attributes"] if parts else ():
        mesh.attributes[name] = np.concatenate([p["attributes"][name] for p in parts])
    if colors:
        mesh.colors = np.concatenate([p["colors"] for p in parts if "colors" in p])
    rep = out["report"]
    rep["vertices"] = len(mesh.vertices)
    rep["faces"] = len(mesh.faces)
    rep["distributed"]["phases"] = out.get("phases", {})
    return mesh


def distributed_poisson(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    partitions: int | None = 2,
    depth: int = 8,
    scale: float = 1.1,
    point_weight: float = 4.0,
    samples_per_node: float = 1.5,
    boundary: str = "neumann",
    density: bool = False,
    trim: float = 0.0,
    confidence: bool = False,
    colors: np.ndarray | None = None,
    properties: dict[str, np.ndarray] | None = None,
    full_depth: int = 5,
    cg_tolerance: float = 1e-3,
    client: Any = None,
    seams: list[int] | None = None,
    temp_dir: str | None = None,
    budget: int | None = None,
    progress: Any = None,
):
    """Screened Poisson reconstruction in ``partitions`` slabs, the cloud given in memory.

    See the module docstring. On the Dask ``client``'s cluster, or else all in this process
    (:class:`recon_cli.slabs.runners.LocalRunner`). ``partitions`` None: as many as the workers'
    memory needs, or without a cluster this process's ``budget`` of bytes (:func:`slab_count`).
    With more slabs than workers (than one, in this process), the slabs' states wait in a
    temporary folder in ``temp_dir`` (default: the system's; the workers must share it) between
    their steps. Returns a :class:`.PoissonResult` like :func:`.screened_poisson`'s
    (``confidence``, ``colors``, ``properties`` as there), whose report has a ``distributed``
    part (``partitions``: how many slabs and why).
    """
    from recon_cli.stages.poisson import (
        SPEC,
        PoissonResult,
        check_inputs,
        check_options,
        kept_attributes,
    )

    depth, scale, point_weight, samples_per_node, _, boundary, density, trim = check_options(
        depth, scale, point_weight, samples_per_node, 2, boundary, density, trim
    )
    params: dict[str, Any] = dict(
        samples_per_node=samples_per_node,
        point_weight=point_weight,
        boundary=boundary,
        full_depth=min(int(full_depth), depth),
        cg_tolerance=float(cg_tolerance),
        density=density,
        trim=trim,
    )
    _check_distributed(depth, params["full_depth"], 1 if partitions is None else partitions)
    t0 = time.perf_counter()
    lengths: list = []
    pts, _, keep = check_inputs(points, normals, lengths)
    partitions, slab_choice = slab_count(partitions, len(pts), client, budget)
    _seam_params(params, depth, partitions)
    if SPEC.param("confidence").coerce(confidence):
        params["weight_mean"] = float(lengths[0].mean())
    del lengths
    # the slabs get the normals as given (a slab weighs each point by its normal's length, and
    # normalises them as the check did: normalising twice moved them by an ulp)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)[keep]
    colors, props = kept_attributes(keep, colors, properties)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    origin, size, perm = frame_of(lo, hi, scale)
    job = make_job(origin, size, perm, depth, params)
    pts = pts[:, list(perm)]
    nrm = nrm[:, list(perm)]
    nsub = 1 << min(S.SUB_DEPTH, depth)
    sub = sub_slab((pts[:, 0] - job.origin[0]) / size, nsub)
    sub_counts = np.bincount(sub, minlength=nsub)
    plan = plan_slabs(job, sub_counts, partitions, seams)
    slabs = [S.slab_of(job, k, partitions, *plan[k]) for k in range(partitions)]
    carry = bool(props) or colors is not None
    weights = job_weights(False, point_weight > 0, trim > 0, carry, False)

    def load_args(k):
        pa, pb = (int(round(v * nsub)) for v in plan[k][1])
        sel = (sub >= pa) & (sub < pb)
        return (
            pts[sel],
            nrm[sel],
            None if colors is None else colors[sel],
            {name: v[sel] for name, v in props.items()},
        )

    # more slabs than workers: a worker (this process) keeps only the slab it runs in memory
    spilling = partitions > max(slab_choice["workers"], 1)
    with spill_folder(temp_dir, "poisson") if spilling else contextlib.nullcontext() as spill:
        with _task(progress, "poisson: the whole job", sum(weights.values())) as bar:
            runner = make_runner(
                client,
                slabs,
                progress,
                Overall(bar, weights),
                spill,
                loads=slab_loads(plan, sub_counts),
            )
            try:
                loaded = runner.run("load", S.load, load_args)
                out = reconstruct(runner, job, loaded, progress, carry=carry)
            finally:
                runner.close()
    mesh = assemble(out, job, perm, colors is not None)
    rep = out["report"]
    rep["distributed"]["partitions"] = slab_choice
    rep["ignored_points"] = int((~keep).sum())
    rep["attributes"] = sorted(props) + (["colors"] if colors is not None else [])
    rep["timings"]["total"] = time.perf_counter() - t0
    return PoissonResult(mesh, rep)


def make_runner(
    client: Any,
    slabs: list,
    progress: Any = None,
    overall: Any = None,
    spill_dir: str | None = None,
    loads: list[float] | None = None,
):
    """The slabs' runner: on the Dask ``client``'s cluster, or in this process without one.

    ``spill_dir``: where the slabs' states wait between their steps (None: in memory);
    ``loads``: each slab's points read (:func:`slab_loads`), to spread them over the workers.
    """
    from recon_cli.slabs.runners import DaskRunner, LocalRunner

    if client is None:
        return LocalRunner(slabs, progress, "poisson", overall, spill_dir)
    return DaskRunner(client, slabs, progress, "poisson", overall, spill_dir, loads=loads)


def _check_distributed(depth: int, full_depth: int, partitions: int) -> None:
    if partitions < 1 or partitions > S.MAX_PARTITIONS:
        raise ParameterError(
            f"partitions must be 1..{S.MAX_PARTITIONS} (the seams are level-"
            f"{S.FINE_PARTITION_DEPTH} planes), got {partitions}"
        )
    sd = S.seam_depth(partitions)
    if depth < sd + 1:
        raise ParameterError(
            f"a distributed reconstruction in {partitions} slabs needs depth {sd + 1} or more "
            f"(its seams are level-{sd} planes), got {depth}"
        )
    if full_depth < S.PARTITION_DEPTH:
        raise ParameterError(
            f"a distributed reconstruction needs full_depth >= {S.PARTITION_DEPTH} "
            f"(no leaf may cross a seam), got {full_depth}"
        )


def _seam_params(params: dict, depth: int, partitions: int) -> None:
    """Check a run of ``partitions`` slabs; set its seams' level, raising ``full_depth`` to it.

    Beyond 32 slabs the seams are level-6 planes: level 6 made complete, no leaf crosses one
    (a fuller tree than the single-process solve's there: chi moves within the solve's tolerance).
    """
    _check_distributed(depth, params["full_depth"], partitions)
    sd = S.seam_depth(partitions)
    params["seam_depth"] = sd
    params["full_depth"] = max(params["full_depth"], sd)


# ---------------------------------------------------------------------------------------------
# from files: chunks read by the workers


def _scan_chunk(chunk) -> dict:
    """A chunk's figures for the plan.

    The box of its points with a usable normal, counts, types (each worker reads its own chunk).
    """
    from recon_cli.io.chunks import read_chunk

    cloud = read_chunk(chunk)
    where = chunk.path
    if cloud.normals is None:
        raise InputError(
            "the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)",
            where,
        )
    pts = np.asarray(cloud.points, dtype=np.float64)
    nrm = np.asarray(cloud.normals, dtype=np.float64)
    if not np.all(np.isfinite(pts)):
        raise InputError("points contain NaN or infinite coordinates", where)
    length = np.linalg.norm(nrm, axis=1)
    if not np.all(np.isfinite(length)):
        raise InputError("normals contain NaN or infinite values", where)
    keep = length > 0
    out = {
        "rows": len(pts),
        "kept": int(keep.sum()),
        "length_sum": float(length[keep].sum()),
        "invalid_dropped": int(cloud.invalid_dropped),
        "point_dtype": np.dtype(cloud.point_dtype).str,
        "colors": None if cloud.colors is None else (cloud.colors.dtype.str, cloud.colors.shape[1]),
        "attributes": tuple((k, np.asarray(v).dtype.str) for k, v in cloud.attributes.items()),
        "history": list(cloud.history),
    }
    if keep.any():
        out["lo"] = pts[keep].min(axis=0)
        out["hi"] = pts[keep].max(axis=0)
    return out


def _bucket_chunk(
    chunk,
    origin,
    size: float,
    perm: tuple,
    nsub: int,
    prefix: str,
    colors: bool = True,
    names: tuple = (),
) -> dict:
    """Write a chunk's rows (job frame, finite) sorted by sub-slab to ``prefix.*.npy``.

    The colours with ``colors``, the properties ``names`` as ``prefix.a<i>.npy``; returns where each
    sub-slab's rows start and the kept points per sub-slab.
    """
    from recon_cli.io.chunks import read_chunk

    cloud = read_chunk(chunk)
    pts = np.asarray(cloud.points, dtype=np.float64)[:, list(perm)]
    nrm = np.asarray(cloud.normals, dtype=np.float64)[:, list(perm)]
    sub = sub_slab((pts[:, 0] - origin[0]) / size, nsub)
    order = np.argsort(sub, kind="stable")
    sub = sub[order]
    np.save(prefix + ".pts.npy", pts[order])
    np.save(prefix + ".nrm.npy", nrm[order])
    if colors and cloud.colors is not None:
        np.save(prefix + ".col.npy", np.asarray(cloud.colors)[order])
    for i, name in enumerate(names):
        np.save(f"{prefix}.a{i:03d}.npy", np.asarray(cloud.attributes[name])[order])
    kept = np.linalg.norm(nrm[order], axis=1) > 0
    off = np.searchsorted(sub, np.arange(nsub + 1))
    return {"offsets": off, "counts": np.bincount(sub[kept], minlength=nsub)}


def _timed_task(fn: Callable) -> Callable:
    """A chunk's task that also reports its seconds and the worker's peak memory.

    As a slab's step does (:func:`.slab.timed`).
    """

    def task(*args: Any) -> dict:
        return S.timed(lambda _none, *a: fn(*a))(None, *args)

    task.__name__ = task.__qualname__ = fn.__name__.lstrip("_")
    task.__doc__ = fn.__doc__
    return task


scan_chunk = _timed_task(_scan_chunk)
bucket_chunk = _timed_task(_bucket_chunk)


@dataclass
class Streamed:
    """What :func:`reconstruct_files` returns when it streamed the mesh to ``output``."""

    report: dict
    mesh: None = None


def reconstruct_files(
    inputs,
    *,
    client: Any,
    partitions: int | None = None,
    depth: int = 8,
    scale: float = 1.1,
    point_weight: float = 4.0,
    samples_per_node: float = 1.5,
    boundary: str = "neumann",
    density: bool = False,
    trim: float = 0.0,
    confidence: bool = False,
    attributes: Any = "all",
    full_depth: int = 5,
    cg_tolerance: float = 1e-3,
    temp_dir: str | None = None,
    output: str | None = None,
    history: list[str] | None = None,
    budget: int | None = None,
    progress: Any = None,
) -> PoissonResult | Streamed:
    """:func:`distributed_poisson` from files that no process reads whole.

    ``inputs``: a file, folder or pattern, or a list of them (:mod:`recon_cli.io.chunks`). The
    workers read the chunks, write them per sub-slab into a temporary folder (``temp_dir``, which
    the workers must share; removed at the end), and each slab reads its rows. Returns the
    :class:`.PoissonResult`; with ``output`` (a binary PLY path) the mesh is streamed there from the
    slabs' files instead (``history`` its comments, after the input's) and the result's mesh is
    None. ``attributes``: the input's properties carried onto the vertices
    (:func:`.attributes.select`). ``partitions`` None: as many slabs as the workers' memory
    needs, or without a ``client`` this process's ``budget`` of bytes (:func:`slab_count`, once
    the chunks' points are counted).
    """
    from recon_cli.io.chunks import plan_chunks
    from recon_cli.slabs.runners import note_phase
    from recon_cli.stages.poisson import SPEC, PoissonResult, check_options

    depth, scale, point_weight, samples_per_node, _, boundary, density, trim = check_options(
        depth, scale, point_weight, samples_per_node, 2, boundary, density, trim
    )
    params: dict[str, Any] = {
        "samples_per_node": samples_per_node,
        "point_weight": point_weight,
        "boundary": boundary,
        "full_depth": min(int(full_depth), depth),
        "cg_tolerance": float(cg_tolerance),
        "density": density,
        "trim": trim,
    }
    # the depths now, a default slab count once the points are counted
    _check_distributed(depth, params["full_depth"], 1 if partitions is None else partitions)
    t0 = time.perf_counter()
    chunks = plan_chunks(inputs)
    scans = _scan_chunks(client, chunks, progress)
    scan_phase: dict = {}
    note_phase(scan_phase, "scan", scans, time.perf_counter() - t0)
    kept, rows, names, keep_colors, dtypes, color_type = _checked_scans(scans, attributes)
    parts, slab_choice = slab_count(partitions, kept, client, budget)
    _seam_params(params, depth, parts)
    nworkers = slab_choice["workers"]
    if SPEC.param("confidence").coerce(confidence):
        params["weight_mean"] = sum(s["length_sum"] for s in scans) / kept
    lo = np.min([s["lo"] for s in scans if "lo" in s], axis=0)
    hi = np.max([s["hi"] for s in scans if "lo" in s], axis=0)
    if not (hi - lo).max() > 0:
        raise InputError("all points coincide: there is no surface to reconstruct")
    origin, size, perm = frame_of(lo, hi, scale)
    job = make_job(origin, size, perm, depth, params)
    nsub = 1 << min(S.SUB_DEPTH, depth)
    carry = bool(names) or color_type is not None
    weights = job_weights(True, point_weight > 0, trim > 0, carry, output is not None)
    runner = None
    with spill_folder(temp_dir, "poisson") as tmp:
        with _task(progress, "poisson: the whole job", sum(weights.values())) as job_bar:
            overall = Overall(job_bar, weights)
            share = overall.claim("sort") / len(chunks)
            t = time.perf_counter()
            frame = (job.origin, size, perm, nsub)
            buckets = map_tasks(
                client,
                bucket_chunk,
                [
                    (c, *frame, os.path.join(tmp, f"c{i:05d}"), keep_colors, tuple(names))
                    for i, c in enumerate(chunks)
                ],
                progress,
                "poisson: sorting the chunks into slabs",
                lambda: overall.advance(share),
            )
            sort_phase: dict = {}
            note_phase(sort_phase, "sort", buckets, time.perf_counter() - t)
            counts = np.sum([b["counts"] for b in buckets], axis=0)
            plan = plan_slabs(job, counts, parts)
            files = [(os.path.join(tmp, f"c{i:05d}"), b["offsets"]) for i, b in enumerate(buckets)]
            read_s = time.perf_counter() - t0
            slabs = [S.slab_of(job, k, parts, *plan[k]) for k in range(parts)]
            # more slabs than workers: a worker (this process) keeps only the slab it runs
            spill = os.path.join(tmp, "states") if parts > max(nworkers, 1) else None
            if spill is not None:
                os.mkdir(spill)
            runner = make_runner(
                client, slabs, progress, overall, spill, loads=slab_loads(plan, counts)
            )
            try:
                runner.phases.update(scan_phase)
                runner.phases.update(sort_phase)
                loaded = runner.run(
                    "load", S.load_files, lambda k: (files, nsub, color_type, tuple(names), dtypes)
                )
                out = reconstruct(
                    runner, job, loaded, progress, tmp if output is not None else None, carry=carry
                )
            finally:
                runner.close()
            point_types = {s["point_dtype"] for s in scans}
            point_dtype = np.float64 if np.dtype("<f8").str in point_types else np.float32
            hist = (list(scans[0]["history"]) if scans else []) + list(history or [])
            if output is not None:
                _write_streamed(out, output, overall, perm, point_dtype, color_type, hist)
    mesh = None
    if output is None:
        mesh = assemble(out, job, perm, color_type is not None)
        mesh.point_dtype = point_dtype
        mesh.history = hist
    rep = out["report"]
    rep["ignored_points"] = int(rows - kept)
    rep["invalid_dropped"] = sum(s["invalid_dropped"] for s in scans)
    rep["points_read"] = int(rows)
    rep["attributes"] = sorted(names) + (["colors"] if color_type is not None else [])
    rep["timings"]["read"] = read_s
    rep["timings"]["total"] = time.perf_counter() - t0
    rep["distributed"]["chunks"] = len(chunks)
    rep["distributed"]["partitions"] = slab_choice
    if mesh is None:
        return Streamed(rep)
    return PoissonResult(mesh, rep)


def _write_streamed(out: dict, output: str, overall, perm, point_dtype, color_type, hist) -> None:
    """Write the slabs' parts to ``output`` (a binary PLY), the figures into the report."""
    t = time.perf_counter()
    with overall.step("write"):
        write_parts_ply(output, out["parts"], perm, point_dtype, color_type, hist)
    rep = out["report"]
    rep["timings"]["write"] = time.perf_counter() - t
    rep["vertices"] = sum(p["counts"][0] for p in out["parts"])
    rep["faces"] = sum(p["counts"][1] for p in out["parts"])
    rep["distributed"]["phases"] = out.get("phases", {})


def _scan_chunks(client: Any, chunks: list, progress: Any) -> list[dict]:
    """Each chunk's box, counts and header (read on the workers), in the chunks' order."""
    return map_tasks(
        client, scan_chunk, [(c,) for c in chunks], progress, "poisson: reading the chunks' boxes"
    )


def _checked_scans(scans: list[dict], attributes: Any) -> tuple:
    """The chunks' scans, checked to agree.

    Returns the points kept, the rows, the property names, whether colours are kept, the
    properties' types and the colours' type (or None).
    """
    from recon_cli.stages.poisson.attributes import select

    kept = sum(s["kept"] for s in scans)
    rows = sum(s["rows"] for s in scans)
    if kept == 0:
        raise InputError("every normal has zero length: run 'recon normals' to estimate them")
    if kept < 4:
        raise InputError(f"poisson needs at least 4 points with non-zero normals, got {kept}")
    colors = {s["colors"] for s in scans}
    if len(colors) > 1:
        raise InputError(
            "the tiles do not all have the same colours (some have none, or other types)"
        )
    if len({s["attributes"] for s in scans}) > 1:
        raise InputError("the tiles do not all have the same properties (names and types)")
    have = dict(scans[0]["attributes"])
    names, keep_colors = select(attributes, list(have), colors != {None})
    dtypes = tuple(have[k] for k in names)
    color_type = next(iter(colors)) if keep_colors else None
    return kept, rows, names, keep_colors, dtypes, color_type


def _task(progress, name, total):
    from recon_cli.progress import task

    return task(progress, name, total=total)


def run_from_files(
    input: str,
    output: str,
    params: dict,
    *,
    load_kw: dict,
    save_kw: dict,
    ascii: bool = False,
    progress: Any = None,
) -> dict | None:
    """``recon poisson IN OUT`` in slabs from IN's chunks, on a cluster or in this process.

    The stage's ``from_files`` (:class:`recon_cli.params.StageSpec`) once
    :func:`recon_cli.stages.poisson.run_from_files` has decided the run goes in slabs: on the
    execution's cluster (``--workers``, ``--scheduler``), or in this process, the slabs' states
    spilled to a folder beside OUT (:func:`recon_cli.execution.current`). Writes OUT and returns
    the report.
    """
    import contextlib

    from recon_cli.batch.cluster import open_client
    from recon_cli.execution import current
    from recon_cli.io.load import save
    from recon_cli.stages.poisson import (
        REPORT_KEYS,
        SPEC,
        check_slab_options,
        slab_reason,
    )

    ex = current()
    v = SPEC.check(params, complete=True)
    where = slab_reason(ex)
    check_slab_options(
        v["backend"],
        v["degree"],
        v["estimate_normals"],
        v["boundary"],
        v["envelope"],
        v["grid"],
        v["trim"],
        where,
    )
    if input == "-":
        raise ParameterError(f"a run {where} reads IN by chunks: give a file, not '-'")
    if load_kw.get("format"):
        raise ParameterError(f"a run {where} reads IN by its suffix: leave out --input-format")
    from recon_cli.stages import provenance_line

    # a binary PLY file is streamed from the slabs' parts; anything else is assembled here
    fmt = save_kw.get("format")
    stream = (
        output != "-"
        and not ascii
        and not save_kw.get("points_only")
        and (fmt == "ply" or (fmt is None and output.lower().endswith(".ply")))
    )
    if stream:
        from recon_cli.io.atomic import check_output

        check_output(output)
    prov = provenance_line("poisson", {**SPEC.defaults(), **params})
    t0 = time.perf_counter()
    if ex.distributed:
        opened: Any = open_client(ex.scheduler, ex.workers, ex.worker_memory(), stealing=False)
    else:
        opened = contextlib.nullcontext((None, {"workers": 0, "memory": ex.budget()}))
    with opened as (client, info):
        res = reconstruct_files(
            input,
            client=client,
            partitions=ex.partitions,
            budget=None if client is not None else ex.budget(),
            depth=v["depth"],
            scale=v["scale"],
            point_weight=v["point_weight"],
            samples_per_node=v["samples_per_node"],
            boundary=v["boundary"],
            density=v["density"],
            trim=v["trim"],
            confidence=v["confidence"],
            attributes=v["attributes"],
            temp_dir=ex.spill_parent(output),
            output=output if stream else None,
            history=[prov],
            progress=progress,
        )
    t1 = time.perf_counter()
    if res.mesh is not None:
        res.mesh.history.append(prov)
        save(res.mesh, output, ascii=ascii, **save_kw)
    t2 = time.perf_counter()
    rep = res.report
    report = {k: rep[k] for k in REPORT_KEYS}
    if rep.get("invalid_dropped"):  # as the command's report of a reader's drops
        report["read"] = {
            "kept": rep["points_read"],
            "invalid_dropped": rep["invalid_dropped"],
        }
    report["backend"] = "native"
    report["distributed"] = {"cluster": info, **rep["distributed"]}
    report["timings"] = {
        "read": rep["timings"].get("read", 0.0),
        "stage": t1 - t0,
        "write": t2 - t1,
    }
    report["output"] = "<stdout>" if output == "-" else output
    return report


# ---------------------------------------------------------------------------------------------
# the output, streamed

# rows written at a time when streaming the slabs' parts
WRITE_ROWS = 1 << 20


def _parts_header(parts: list[dict], perm, point_dtype, colors_dtype, history):
    """The PLY header of the whole mesh, its vertex properties and colour names.

    The header follows :func:`recon_cli.io.ply.geometry_to_ply`'s layout for the same data.
    """
    from recon_cli.geometry import TriangleMesh, float32_rounding
    from recon_cli.io.ply import geometry_to_ply, header_bytes

    boxes = [p["box"] for p in parts if p["box"] is not None]
    inv = np.argsort(perm)
    lo = np.min([b[0] for b in boxes], axis=0)[inv] if boxes else np.zeros(3)
    hi = np.max([b[1] for b in boxes], axis=0)[inv] if boxes else np.zeros(3)
    double = np.dtype(point_dtype) == np.float64 or float32_rounding(np.stack([lo, hi]))[0] > 0
    dummy = TriangleMesh(
        vertices=np.zeros((1, 3)), faces=np.zeros((1, 3), np.int64), history=list(history)
    )
    dummy.point_dtype = np.float64 if double else np.float32
    for name, path in parts[0]["attributes"].items() if parts else ():
        dummy.attributes[name] = np.zeros(1, np.load(path, mmap_mode="r").dtype)
    names_before = [p.name for p in geometry_to_ply(dummy).elements[0].properties]
    if colors_dtype is not None:
        dummy.colors = np.zeros((1, colors_dtype[1]), np.dtype(colors_dtype[0]))
    ply = geometry_to_ply(dummy)
    props = ply.elements[0].properties
    color_names = [p.name for p in props if p.name not in names_before]
    ply.elements[0].count = sum(p["counts"][0] for p in parts)
    ply.elements[1].count = sum(p["counts"][1] for p in parts)
    return header_bytes(ply), props, color_names


def write_parts_ply(path: str, parts: list[dict], perm, point_dtype, colors_dtype, history) -> None:
    """Write the slabs' parts as one binary PLY mesh, a block of rows at a time.

    The parts are files (:func:`.slab.export`); this process never holds the mesh. Vertices in slab
    order with the axes turned back, then the faces, references to a right seam resolved to the next
    slab's first vertices. Atomic: a failure leaves no file.
    """
    from recon_cli.io.atomic import atomic_open

    head, props, color_names = _parts_header(parts, perm, point_dtype, colors_dtype, history)
    vdt = np.dtype([(p.name, "<" + p.dtype) for p in props])
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    inv = list(np.argsort(perm))
    nv = [p["counts"][0] for p in parts]
    off = np.concatenate([[0], np.cumsum(nv)]).astype(np.int64)
    if off[-1] >= 2**31:
        raise StageFailed(
            "the mesh has more than 2**31 vertices: PLY's int face indices cannot hold it"
        )
    with atomic_open(path) as f:
        f.write(head)
        for p in parts:
            v = np.load(p["vertices"], mmap_mode="r")
            col = np.load(p["colors"], mmap_mode="r") if "colors" in p else None
            att = {k: np.load(fn, mmap_mode="r") for k, fn in p["attributes"].items()}
            for a in range(0, len(v), WRITE_ROWS):
                rows = np.empty(min(WRITE_ROWS, len(v) - a), vdt)
                block = v[a : a + WRITE_ROWS]
                for j, c in enumerate(("x", "y", "z")):
                    rows[c] = block[:, inv[j]]
                if col is not None:
                    for j, c in enumerate(color_names):
                        rows[c] = col[a : a + WRITE_ROWS, j]
                for k, arr in att.items():
                    rows[k] = arr[a : a + WRITE_ROWS]
                f.write(rows.tobytes())
        for k, p in enumerate(parts):
            fc = np.load(p["faces"], mmap_mode="r")
            nxt = off[min(k + 1, len(parts) - 1)]
            for a in range(0, len(fc), WRITE_ROWS):
                block = np.asarray(fc[a : a + WRITE_ROWS])
                rows = np.empty(len(block), fdt)
                rows["n"] = 3
                rows["i"] = np.where(block >= 0, block + off[k], nxt + (-1 - block))
                f.write(rows.tobytes())
