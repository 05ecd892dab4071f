"""Screened Poisson reconstruction of one cloud over many processes (a Dask cluster), in slabs.

The cube of the single-process solve is cut along its longest axis into slabs with padding;
the coordinator sums the global values over the slabs (box, coarse density, tree depth,
screening weight, exact medians, iso-value) and solves the coarse levels for the whole cube;
each slab solves its finer levels on that coarse chi, takes its neighbours' coefficients next
to each seam so both sides evaluate the same chi, extracts the leaves it owns and writes its
part; the coordinator joins pieces across seams (noise pieces, trimming) and writes the mesh a
block of rows at a time. It follows Kazhdan & Hoppe's distributed PoissonRecon (2023) on this
stage's own solver (:mod:`.bspline`, degree 2), with Dask (or this process, states spilled to
files) as the engine. The design, step by step, and the measured figures are in
``docs/notes/distributed-poisson.md``.

References
----------
Kazhdan, M. & Hoppe, H. (2023). Distributed Poisson surface reconstruction. Computer
Graphics Forum 42(6).
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import ParameterError, StageFailed
from recon_cli.slabs import plan
from recon_cli.slabs.plan import choose_seams, sub_slab
from recon_cli.slabs.runners import Overall
from recon_cli.slabs.spill import spill_folder
from recon_cli.stages.poisson import PoissonOptions, checked_envelope, takes_options
from recon_cli.stages.poisson import slab as S
from recon_cli.stages.poisson import slab_envelope as E
from recon_cli.stages.poisson import slab_surface as M
from recon_cli.stages.poisson.splat import KERNEL_OFFSET, screening_alpha
from recon_cli.stages.poisson.stitch import (
    assemble,
    merge_pieces,
    seams_used,
    trim_across,
    trim_auto_across,
)

if TYPE_CHECKING:
    pass

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


def slab_count(
    partitions: int | None, npoints: int, client: Any, budget: int | None, depth: int
) -> tuple[int, dict]:
    """The Poisson slabs of a run and why (:func:`recon_cli.slabs.plan.slab_count`).

    A slab's bytes per point: :func:`.memory.slab_bytes` of the cloud at ``depth``.
    """
    from recon_cli.stages.poisson.memory import slab_bytes, tree_estimate

    per = slab_bytes(npoints, tree_estimate(npoints, depth), 1) / max(npoints, 1)
    return plan.slab_count(
        partitions,
        npoints,
        client,
        per,
        S.MAX_PARTITIONS,
        "poisson",
        f"the seams are level-{S.FINE_PARTITION_DEPTH} planes",
        budget,
    )


def fitted_slab_count(
    partitions: int | None, parts: int, entry: dict, job: S.Job, sub_counts: np.ndarray
) -> int:
    """The slabs of a run on workers, once the points per sub-slab (``sub_counts``) are known.

    :func:`slab_count` sizes a slab as an even share of the points; the seams lie on level-5 (or
    6) planes, so the densest slab of an uneven cloud reads more than that share with its pads,
    and a worker holds the whole cube's coarse levels beside it. Unless ``partitions`` was
    given, the fewest slabs, ``parts`` or more and a multiple of the workers, whose largest
    slab's worker (:func:`.memory.worker_bytes` of the points it reads, :func:`plan_slabs`) fits
    :data:`.memory.WORKER_PEAK_SHARE` of a worker's memory limit. When none does (a plane of
    the seams' lattice holds too many points), the count whose largest slab is the smallest,
    with a warning. The report's ``entry`` (:func:`slab_count`'s) gets the count, why, the
    largest slab's points read and its worker's estimate.
    """
    from recon_cli.stages.poisson.memory import WORKER_PEAK_SHARE, tree_estimate, worker_bytes

    memory = entry.get("memory_per_worker")
    if partitions is not None or not memory or parts <= 1:
        return parts
    npoints = max(int(sub_counts.sum()), 1)
    tree = tree_estimate(npoints, job.depth - (job.domain is not None) - job.grown)
    nworkers = max(int(entry.get("workers") or 1), 1)

    def need(p: int) -> tuple[int, int]:
        pj = dataclasses.replace(job, seam_depth=S.seam_depth(p))
        most = int(max(slab_loads(plan_slabs(pj, sub_counts, p), sub_counts)))
        return worker_bytes(npoints, tree, most / npoints), most

    p, (est, most) = parts, need(parts)
    best = (est, p, most)
    while est > WORKER_PEAK_SHARE * memory and p < S.MAX_PARTITIONS:
        p = min(p + nworkers, S.MAX_PARTITIONS)
        est, most = need(p)
        best = min(best, (est, p, most))
    est, p, most = best
    entry["worker_bytes_estimate"] = int(est)
    entry["largest_slab_points"] = most
    fits = est <= WORKER_PEAK_SHARE * memory
    if not fits:
        log.warning(
            "poisson: the largest of %d slabs reads %d points, about %.3g GiB of a worker's "
            "memory, over %.0f%% of its %.3g GiB: it may be restarted (give the workers more "
            "memory, or use fewer, larger ones)",
            p,
            most,
            est / 2**30,
            100 * WORKER_PEAK_SHARE,
            memory / 2**30,
        )
    if p != parts or not fits:
        rounds = f"{p // nworkers} per worker" if p % nworkers == 0 else f"{p} slabs"
        entry.update(
            count=p,
            why=f"{rounds}: the largest slab reads {most} points with its pads, a worker "
            f"~{est / 2**30:.3g} GiB of its {memory / 2**30:.3g} GiB"
            + ("" if fits else " (over its share: the least the seams' planes allow)"),
        )
    return p


def refitted_job(
    partitions: int | None, entry: dict, job: S.Job, envelope: Any, sub_counts, made: tuple
) -> tuple[int, S.Job, Any]:
    """The slabs, job and envelope once the points per sub-slab (``sub_counts``) are known.

    ``made``: :func:`job_of`'s arguments ``job`` and ``envelope`` (turned) came from, its slab
    count among them; ``partitions`` and ``entry`` as :func:`fitted_slab_count`'s. More slabs:
    the same cube and axes, maybe another seams' level (``made``'s parameters updated).
    """
    lo, hi, scale, parts, depth, params, given = made
    fitted = fitted_slab_count(partitions, parts, entry, job, sub_counts)
    if fitted == parts:
        return parts, job, envelope
    seam_params(params, depth, fitted)
    job, _, envelope = job_of(lo, hi, scale, fitted, depth, params, given)
    return fitted, job, envelope


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
    "envelope": 4.0,
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
    "grid": 4.0,
}


def job_weights(
    opts: PoissonOptions, *, from_files: bool, carry: bool, write: bool, envelope: bool
) -> dict:
    """The phases a run goes through and their weights (:data:`PHASE_WEIGHTS`).

    ``opts`` says whether it screens (the noise phase), trims and writes a grid; ``carry``
    whether it carries attributes, ``write`` whether the slabs write the mesh.
    """
    skip = set() if opts.with_grid else {"grid"}
    if not envelope:
        skip.add("envelope")
    if not from_files:
        skip.add("sort")
    if not opts.point_weight > 0:
        skip.add("noise")
    if opts.trim == 0:
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


def frame_of(
    lo: np.ndarray, hi: np.ndarray, scale: float, parts: int
) -> tuple[np.ndarray, float, tuple]:
    """The single-process solve's cube (origin, size) for the kept points' box.

    And the cyclic turn of the axes that makes the longest one ``x``, the slabs' axis, for a cut
    into ``parts`` slabs. One slab is not cut: it keeps the input's axes, as one process does
    (the solve's rounding depends on the axes' order: turned, one slab's mesh would not be the
    single process's to the bit).
    """
    size = float((hi - lo).max()) * scale
    origin = 0.5 * (lo + hi) - 0.5 * size
    axis = int(np.argmax(hi - lo)) if parts > 1 else 0
    perm = (axis, (axis + 1) % 3, (axis + 2) % 3)
    return origin, size, perm


def job_of(
    lo: np.ndarray,
    hi: np.ndarray,
    scale: float,
    parts: int,
    depth: int,
    params: dict,
    envelope: Any = None,
) -> tuple[S.Job, tuple, Any]:
    """The job of the kept points' box ``lo``..``hi`` (input axes) in ``parts`` slabs.

    The single process's cube (:func:`frame_of`), grown to hold a checked ``envelope``
    (:func:`.slab_envelope.grown_cube`). Returns the job, the axes' turn and the envelope
    turned to the job's axes (None without one).
    """
    origin, size, perm = frame_of(lo, hi, scale, parts)
    if envelope is not None:
        origin, size, depth, envelope = E.grown_cube(envelope, origin, size, depth, perm, params)
    return make_job(origin, size, perm, depth, params), perm, envelope


def make_job(origin, size, perm, depth, p: dict) -> S.Job:
    """The job every slab shares: the cube in the turned axes, the depths, the parameters.

    With the free boundary the solve's cube is twice the points' one around it, one level deeper
    (:func:`.steps.solve_cube`).
    """
    from recon_cli.stages.poisson.free import FREE_DOMAIN

    domain = None
    if p["boundary"] == "free":
        origin, size, depth, domain = origin - 0.5 * size, 2.0 * size, depth + 1, FREE_DOMAIN
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
        trim=0.0 if p["trim"] == "auto" else p["trim"],
        weight_mean=p.get("weight_mean"),
        seam_depth=sd,
        trim_auto=p["trim"] == "auto",
        domain=domain,
        grid=bool(p.get("grid")),
        grown=int(p.get("grown", 0)),
    )


def reconstruct(
    runner,
    job: S.Job,
    loaded: list[dict],
    progress: Any = None,
    out_dir: str | None = None,
    carry: bool = False,
    envelope: Any = None,
) -> dict:
    """Every step after the slabs' ``load`` (whose messages are ``loaded``).

    Returns the mesh's parts per slab (in ``out_dir``'s files when given) and the report (module
    docstring); ``carry``: the slabs carry the input's properties or colours onto their vertices;
    ``envelope``: the checked :class:`.envelope.Envelope` in the job's axes (:mod:`.slab_envelope`).
    """
    timings: dict[str, float] = {}
    tables: dict[int, tuple] = {}
    solved = _solve(runner, job, loaded, tables, timings, envelope)
    surface = _surface(runner, job, solved, timings)
    t = time.perf_counter()
    parts, trimmed = _output(runner, job, loaded, tables, solved, surface, out_dir, carry, timings)
    timings["finish"] = time.perf_counter() - t - timings.get("trim", 0.0)  # trim apart
    report = _report(job, loaded, solved, surface, parts, trimmed, timings)
    out = {"parts": parts, "report": report, "phases": getattr(runner, "phases", {})}
    if surface.get("grid") is not None:
        out["grid"] = surface["grid"]
    return out


def _field_grid(runner, job: S.Job, solved: _Solved, extracted: list[dict]) -> tuple | None:
    """The solved field around the surface (``--grid``, :mod:`.field`), in the job's frame.

    Its box from the slabs' kept vertices, its scale from about :data:`.field.GRADIENT_VERTICES`
    of them (each slab its share), its planes from the slabs that own them. Returns (the grid,
    its first lattice point (3,), the lattice's cells a side), or None when the surface is empty.
    """
    # by its full name: the package's ``field`` is dataclasses' (PoissonResult's)
    import recon_cli.stages.poisson.field as F

    nv = [m["vertices"] for m in extracted]
    takes = [math.ceil(F.GRADIENT_VERTICES * n / max(sum(nv), 1)) for n in nv]
    sm = runner.run("grid", M.grid_scale, lambda k: (takes[k],))
    boxes = [m["box"] for m in sm if m["box"] is not None]
    if not boxes:
        return None
    corners = np.array(
        [np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)]
    )
    res = 1 << solved.tree_depth
    origin = np.asarray(job.origin)
    i0, shape = F.grid_shape(corners, origin, job.size, res, job.domain or (0.0, 1.0))
    F.check_allocation(shape)
    g = F.scale_of(np.concatenate([m["norms"] for m in sm]))
    del sm
    sdf = np.empty(shape, np.float32)
    for m in runner.run("grid", M.grid_block, lambda k: (i0, shape, g, solved.iso)):
        sdf[m["x0"] : m["x0"] + len(m["block"])] = m["block"]
    if job.domain is None:
        F.close_cube_faces(sdf, i0, res, g)
    return sdf, i0, res


def grid_in_input_axes(out: dict, job: S.Job, perm) -> Any:
    """The :class:`~recon_cli.grid.Grid` of :func:`reconstruct`'s ``out``, axes turned back.

    None without one; else its shape goes in the report (``grid_shape``).
    """
    from recon_cli.stages.poisson.field import grid_of

    if out.get("grid") is None:
        return None
    sdf, i0, res = out["grid"]
    inv = np.argsort(perm)
    sdf = np.ascontiguousarray(sdf.transpose(inv))
    out["report"]["grid_shape"] = list(sdf.shape)
    return grid_of(sdf, np.asarray(i0)[inv], np.asarray(job.origin)[inv], job.size, res)


@dataclass
class _Solved:
    """What the solve leaves for the extraction and the report."""

    tree_depth: int
    noise: float | None
    coarse_depth: int
    iso: float
    levels: list
    iterations: int
    residual: float
    bands: list
    envelope: Any = None  # --envelope: its .slab_envelope.EnvelopeRun


def _solve(
    runner, job: S.Job, loaded: list[dict], tables: dict, timings: dict, envelope: Any = None
) -> _Solved:
    """Splat depths, noise, the envelope's carving, the trees, the coarse and finer solves."""
    t0 = time.perf_counter()
    # ---- the samples' splat depths: the slabs' own density levels, then the global ones
    tree_depth, alpha = _splat_depths(runner, job, loaded, tables)
    timings["samples"] = time.perf_counter() - t0
    # ---- noise: the median of the measured values stands in for the others
    t = time.perf_counter()
    fallback = 0.0
    if alpha > 0:
        nm = runner.run("noise", S.noise, lambda k: (tree_depth,))
        if sum(m["missing"] for m in nm):
            med = S.exact_median(runner, "sigma", S.noise_values, [m["hist"] for m in nm], "noise")
            fallback = 0.0 if med is None else med
    timings["noise"] = time.perf_counter() - t
    env_run = None
    if envelope is not None:  # the samples inside, the carving, the tree's items along both
        t = time.perf_counter()
        env_run = E.envelope_round(runner, job, envelope, tree_depth, [m["usable"] for m in loaded])
        timings["envelope"] = time.perf_counter() - t
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
    timings["solve"] = time.perf_counter() - t
    n = len(sm)
    return _Solved(
        tree_depth=tree_depth,
        noise=noise_med,
        coarse_depth=dc,
        iso=sum(m["iso_sum"] for m in sm) / sum(m["iso_count"] for m in sm),
        levels=cstats + [s for m in sm for s in m["levels"]],
        iterations=cit + sum(m.get("iterations", 0) for m in sm),
        residual=max([m.get("residual", 0.0) for m in sm] + [cres]),
        # each slab's neighbours' bands next to its seams
        bands=[
            (
                sm[k - 1]["band_right"] if k > 0 else None,
                sm[k + 1]["band_left"] if k < n - 1 else None,
            )
            for k in range(n)
        ],
        envelope=env_run,
    )


def _surface(runner, job: S.Job, solved: _Solved, timings: dict) -> dict:
    """Chi at the slabs' nodes, their surfaces, the noise pieces decided across slabs."""
    from recon_cli.stages.poisson import fold_cells, speck_cells

    t = time.perf_counter()
    bands, solved.bands = solved.bands, []  # released as the slabs get theirs
    fm = runner.run("field", M.field, lambda k: (solved.iso, *bands[k], solved.envelope))
    bands = []  # the closure above held them
    # as the single-process extraction decides: at the leaves' own size when a coarse leaf
    # holds surface, else on the finest lattice (the same surface, faster)
    at_leaves = any(m["coarse"] for m in fm)
    em = runner.run("extract", M.extract, lambda k: (solved.iso, at_leaves, solved.envelope))
    cell = job.size / (1 << solved.tree_depth)
    drop, dropped, seam_dev = merge_pieces(
        runner, em, cell, speck_cells(solved.noise), fold_cells(solved.noise)
    )
    timings["extract"] = time.perf_counter() - t
    return {
        "at_leaves": at_leaves,
        "extracted": em,
        "drop": drop,
        "dropped": dropped,
        "seam_deviation": seam_dev,
        "cell": cell,
    }


def _output(
    runner, job, loaded, tables, solved: _Solved, surface: dict, out_dir, carry, timings
) -> tuple[list[dict], tuple[int, float, int]]:
    """Each slab's part: density, trimming across seams, seam normals, its files or arrays.

    Returns the parts' messages and (faces trimmed, area trimmed, the samples of ``--trim auto``
    whose spacing may read past their pad).
    """
    dens_spec = _density_spec(runner, job, solved.tree_depth, tables)
    usable = [m["usable"] for m in loaded]

    def dens_part(k):
        if dens_spec is None or len(dens_spec) == 1:
            return dens_spec
        return (dens_spec[0], *table_part(*dens_spec[1:], dens_spec[0], usable[k]))

    drop = surface["drop"]
    env = None if solved.envelope is None else solved.envelope.env
    pm = runner.run("prepare", M.prepare, lambda k: (drop[k], dens_part(k), job.trim > 0, env))
    surface["pulled"] = None if env is None else sum(m.get("pulled", 0) for m in pm)
    if job.grid:
        surface["grid"] = _field_grid(runner, job, solved, surface["extracted"])
    seam_keep: list[dict | None] = list(seams_used([m["seam_use"] for m in pm]))
    trimmed, trimmed_area, inexact = 0, 0.0, 0
    t = time.perf_counter()
    if job.trim > 0:
        seam_keep, trimmed, trimmed_area = trim_across(runner, job.trim, pm, seam_keep)
    elif job.trim_auto:
        seam_keep, trimmed, trimmed_area, inexact = trim_auto_across(runner, seam_keep)
    if job.trim > 0 or job.trim_auto:
        timings["trim"] = time.perf_counter() - t
    del pm
    left = [None] * len(seam_keep)
    if carry:
        # the surface's normal at a seam vertex sums both slabs' faces (the attributes' side)
        nm = runner.run("seams", M.seam_normals, lambda k: (seam_keep[k],))
        left = [None] + [m["right"] for m in nm[:-1]]
        seam_keep = [None] * len(seam_keep)
        del nm
    fm = runner.run(
        "attributes" if carry else "export",
        M.export,
        lambda k: (
            seam_keep[k],
            None if out_dir is None else os.path.join(out_dir, f"s{k:03d}"),
            left[k],
        ),
    )
    return fm, (trimmed, trimmed_area, inexact)


def _report(job, loaded, solved: _Solved, surface: dict, parts, trimmed, timings) -> dict:
    """The run's report (keys as the single process's, plus ``distributed``)."""
    astats = [m.pop("attribute_stats", None) for m in parts]
    specks, islands, folds = surface["dropped"]
    # the free boundary's solve is one level deeper, an envelope's cube may be deeper still
    free = int(job.domain is not None) + job.grown
    env_run = solved.envelope
    return {
        "depth": job.depth - free,
        "tree_depth": solved.tree_depth - free,
        "iso_value": solved.iso,
        "solver_iterations": int(solved.iterations),
        "residual": float(solved.residual),
        "bubbles_removed": specks,
        "islands_removed": islands,
        "folds_removed": folds,
        "trimmed_faces": int(trimmed[0]),
        "trimmed_area": float(trimmed[1]),
        "noise": solved.noise,
        "samples": int(sum(m["own_samples"] for m in loaded)),
        "attribute_fallback_vertices": sum(a["fallback"] for a in astats if a),
        "finest_cell": surface["cell"],
        "envelope_outside_points": None if env_run is None else env_run.outside_points,
        "envelope_pulled_vertices": surface.get("pulled"),
        "levels": solved.levels,
        "timings": timings,
        "distributed": {
            "coarse_depth": solved.coarse_depth,
            "extraction": "leaves" if surface["at_leaves"] else "finest",
            "seam_max_deviation": surface["seam_deviation"],
            # vertices whose attribute neighbours may lie past their slab's pad
            "attribute_inexact_vertices": sum(a["inexact"] for a in astats if a),
            # --trim auto: own samples whose spacing may read samples past their slab's pad
            "trim_inexact_samples": int(trimmed[2]),
            "slabs": [
                {
                    "own": lm["own"],
                    "points": lm["own_points"],
                    "points_read": lm["points"],  # with its pads'
                    "samples": lm["own_samples"],
                    "faces": e["faces"],
                    "seam_vertices": len(e["seam_left"][0]),
                }
                for lm, e in zip(loaded, surface["extracted"], strict=True)
            ],
        },
    }


def _splat_depths(runner, job: S.Job, loaded: list[dict], tables: dict[int, tuple]) -> tuple:
    """The samples' splat depths over the slabs: (the tree's depth, the screening weight alpha).

    Each slab places its samples at its own density levels, then at the global ones, coarser
    level by level; ``tables`` gets each level's summed density table.
    """
    msgs = loaded
    usable = [m["usable"] for m in loaded]
    # from the kernel's level down, as one process does: at a depth where the kernel's level
    # is the coordinator's or coarser, the slabs hold no level of their own
    level = min(job.local_density, max(job.depth - KERNEL_OFFSET, 0))
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
        noise_med = S.exact_median(
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


@takes_options
def distributed_poisson(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    partitions: int | None = 2,
    colors: np.ndarray | None = None,
    properties: dict[str, np.ndarray] | None = None,
    envelope: Any = None,
    client: Any = None,
    seams: list[int] | None = None,
    temp_dir: str | None = None,
    budget: int | None = None,
    progress: Any = None,
    **options: Any,
):
    """Screened Poisson reconstruction in ``partitions`` slabs, the cloud given in memory.

    See the module docstring. ``options``: the algorithm's parameters, as
    :func:`.screened_poisson`'s (:class:`.PoissonOptions`; degree 2 only). On the Dask
    ``client``'s cluster, or else all in this process
    (:class:`recon_cli.slabs.runners.LocalRunner`).
    ``partitions`` None: as many as the workers' memory needs, or without a cluster this
    process's ``budget`` of bytes (:func:`slab_count`). With more slabs than workers (than one,
    in this process), the slabs' states wait in a temporary folder in ``temp_dir`` (default: the
    system's; the workers must share it) between their steps. Returns a :class:`.PoissonResult`
    like :func:`.screened_poisson`'s (``colors``, ``properties``, ``envelope`` as there), whose
    report has a ``distributed`` part (``partitions``: how many slabs and why).
    """
    from recon_cli.stages.poisson import PoissonResult, check_inputs, kept_attributes

    opts = PoissonOptions.of("distributed_poisson", options)
    depth, params = opts.depth, slab_params(opts, partitions)
    env = None if envelope is None else checked_envelope(envelope)
    t0 = time.perf_counter()
    lengths: list = []
    pts, _, keep = check_inputs(points, normals, lengths)
    asked = partitions
    partitions, slab_choice = slab_count(partitions, len(pts), client, budget, depth)
    seam_params(params, depth, partitions)
    if opts.confidence:
        params["weight_mean"] = float(lengths[0].mean())
    del lengths
    # the slabs get the normals as given (a slab weighs each point by its normal's length, and
    # normalises them as the check did: normalising twice moved them by an ulp)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)[keep]
    colors, props = kept_attributes(keep, colors, properties)
    made = (pts.min(axis=0), pts.max(axis=0), opts.scale, partitions, depth, params, env)
    job, perm, env = job_of(*made)
    pts = pts[:, list(perm)]
    nrm = nrm[:, list(perm)]
    nsub = 1 << min(S.SUB_DEPTH, job.depth)
    sub = sub_slab((pts[:, 0] - job.origin[0]) / job.size, nsub)
    sub_counts = np.bincount(sub, minlength=nsub)
    partitions, job, env = refitted_job(asked, slab_choice, job, env, sub_counts, made)
    plan = plan_slabs(job, sub_counts, partitions, seams)
    slabs = [S.slab_of(job, k, partitions, *plan[k]) for k in range(partitions)]
    carry = bool(props) or colors is not None
    weights = job_weights(
        opts, from_files=False, carry=carry, write=False, envelope=env is not None
    )

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
        with job_task(progress, "poisson: the whole job", sum(weights.values())) as bar:
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
                out = reconstruct(runner, job, loaded, progress, carry=carry, envelope=env)
            finally:
                runner.close()
    mesh = assemble(out, job, perm, colors is not None)
    rep = out["report"]
    rep["distributed"]["partitions"] = slab_choice
    rep["ignored_points"] = int((~keep).sum())
    rep["attributes"] = sorted(props) + (["colors"] if colors is not None else [])
    rep["timings"]["total"] = time.perf_counter() - t0
    return PoissonResult(mesh, rep, grid_in_input_axes(out, job, perm))


def slab_params(opts: PoissonOptions, partitions: int | None) -> dict[str, Any]:
    """The slabs' parameters of ``opts`` (a run in slabs: degree 2).

    ``partitions`` is checked against the depth now when given; a default slab count is, once
    the points are counted (:func:`seam_params`).
    """
    if opts.degree != 2:
        raise ParameterError("a run in slabs uses degree 2: leave out --degree 1")
    params: dict[str, Any] = {
        "samples_per_node": opts.samples_per_node,
        "point_weight": opts.point_weight,
        "boundary": opts.boundary,
        "full_depth": min(opts.full_depth, opts.depth),
        "cg_tolerance": opts.cg_tolerance,
        "density": opts.density,
        "trim": opts.trim,
        "grid": opts.with_grid,
    }
    check_distributed(opts.depth, params["full_depth"], 1 if partitions is None else partitions)
    return params


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


def check_distributed(depth: int, full_depth: int, partitions: int) -> None:
    """Refuse a slab count out of range, or a depth too shallow for its seams."""
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


def seam_params(params: dict, depth: int, partitions: int) -> None:
    """Check a run of ``partitions`` slabs; set its seams' level, raising ``full_depth`` to it.

    Beyond 32 slabs the seams are level-6 planes: level 6 made complete, no leaf crosses one
    (a fuller tree than the single-process solve's there: chi moves within the solve's tolerance).
    """
    check_distributed(depth, params["full_depth"], partitions)
    sd = S.seam_depth(partitions)
    params["seam_depth"] = sd
    params["full_depth"] = max(params["full_depth"], sd)


def job_task(progress: Any, name: str, total: float) -> Any:
    """The whole job's progress bar (its total the phases' weights)."""
    from recon_cli.progress import task

    return task(progress, name, total=total)


def check_slab_options(backend: str, degree: int, estimate_normals: bool, where: str) -> None:
    """What a run in slabs does not take (one line each); ``where`` says why it is in slabs."""
    if backend != "native":
        raise ParameterError(f"{where} runs the native solver: leave out --backend")
    if degree != 2:
        raise ParameterError(f"{where} uses degree 2: leave out --degree 1")
    if estimate_normals:
        raise ParameterError(f"--estimate-normals {where}: run 'recon normals' first")


def slab_reason(ex: Any) -> str:
    """Why a run is in slabs, for messages."""
    if ex.distributed:
        return "with --workers/--scheduler"
    if ex.partitions is not None:
        return "in slabs (--partitions)"
    return "in slabs (the cloud does not fit the memory in one piece)"
