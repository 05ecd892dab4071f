"""Poisson in slabs from files: the workers read IN by chunks, nothing holds the cloud or mesh.

Each worker scans its chunks of IN (binary PLY rows, LAS/LAZ points, or whole tiles), then
sorts their rows per sub-slab into the job's temporary folder; the slabs read their ranges
from there (:func:`reconstruct_files`), and the output is written a block of rows at a time
from the slabs' parts (:func:`write_parts_ply`). :func:`run_from_files` is the stage's entry.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.slabs.plan import sub_slab
from recon_cli.slabs.runners import Overall, map_tasks
from recon_cli.slabs.spill import spill_folder
from recon_cli.stages.poisson import (
    PoissonOptions,
    PoissonResult,
    stitch,
    takes_options,
)
from recon_cli.stages.poisson import distributed as D
from recon_cli.stages.poisson import slab as S


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
    grid: Any = None


@takes_options
def reconstruct_files(
    inputs,
    *,
    client: Any,
    partitions: int | None = None,
    attributes: Any = "all",
    envelope: Any = None,
    temp_dir: str | None = None,
    output: str | None = None,
    history: list[str] | None = None,
    budget: int | None = None,
    progress: Any = None,
    **options: Any,
) -> PoissonResult | Streamed:
    """:func:`distributed_poisson` from files that no process reads whole.

    ``inputs``: a file, folder or pattern, or a list of them (:mod:`recon_cli.io.chunks`);
    ``options``: the algorithm's parameters (:class:`.PoissonOptions`, degree 2). The
    workers read the chunks, write them per sub-slab into a temporary folder (``temp_dir``, which
    the workers must share; removed at the end), and each slab reads its rows. Returns the
    :class:`.PoissonResult`; with ``output`` (a binary PLY path) the mesh is streamed there from the
    slabs' files instead (``history`` its comments, after the input's) and the result's mesh is
    None. ``attributes``: the input's properties carried onto the vertices
    (:func:`.attributes.select`). ``envelope`` (a checked :class:`.envelope.Envelope`): as
    :func:`.screened_poisson`'s. ``partitions`` None: as many slabs as the workers' memory needs,
    or without a ``client`` this process's ``budget`` of bytes (:func:`slab_count`, once the
    chunks' points are counted).
    """
    from recon_cli.io.chunks import plan_chunks
    from recon_cli.slabs.runners import note_phase

    opts = PoissonOptions.of("reconstruct_files", options)
    depth, params = opts.depth, D.slab_params(opts, partitions)
    t0 = time.perf_counter()
    chunks = plan_chunks(inputs)
    scans = _scan_chunks(client, chunks, progress)
    scan_phase: dict = {}
    note_phase(scan_phase, "scan", scans, time.perf_counter() - t0)
    kept, rows, names, keep_colors, dtypes, color_type = _checked_scans(scans, attributes)
    parts, slab_choice = D.slab_count(partitions, kept, client, budget, depth)
    D.seam_params(params, depth, parts)
    nworkers = slab_choice["workers"]
    if opts.confidence:
        params["weight_mean"] = sum(s["length_sum"] for s in scans) / kept
    made = (*_scanned_box(scans), opts.scale, parts, depth, params, envelope)
    job, perm, envelope = D.job_of(*made)
    nsub = 1 << min(S.SUB_DEPTH, job.depth)
    carry = bool(names) or color_type is not None
    weights = D.job_weights(
        opts, from_files=True, carry=carry, write=output is not None, envelope=bool(envelope)
    )
    runner = None
    with spill_folder(temp_dir, "poisson") as tmp:
        with D.job_task(progress, "poisson: the whole job", sum(weights.values())) as job_bar:
            overall = Overall(job_bar, weights)
            files, counts, sort_phase = _sort_into_slabs(
                client,
                chunks,
                (job.origin, job.size, perm, nsub),
                tmp,
                keep_colors,
                names,
                overall,
                progress,
            )
            read_s = time.perf_counter() - t0
            parts, job, envelope = D.refitted_job(
                partitions, slab_choice, job, envelope, counts, made
            )
            plan = D.plan_slabs(job, counts, parts)
            slabs = [S.slab_of(job, k, parts, *plan[k]) for k in range(parts)]
            # more slabs than workers: a worker (this process) keeps only the slab it runs
            spill = os.path.join(tmp, "states") if parts > max(nworkers, 1) else None
            if spill is not None:
                os.mkdir(spill)
            runner = D.make_runner(
                client, slabs, progress, overall, spill, loads=D.slab_loads(plan, counts)
            )
            try:
                runner.phases.update(scan_phase)
                runner.phases.update(sort_phase)
                loaded = runner.run(
                    "load", S.load_files, lambda k: (files, nsub, color_type, tuple(names), dtypes)
                )
                out = D.reconstruct(
                    runner,
                    job,
                    loaded,
                    progress,
                    tmp if output is not None else None,
                    carry=carry,
                    envelope=envelope,
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
        mesh = stitch.assemble(out, job, perm, color_type is not None)
        mesh.point_dtype = point_dtype
        mesh.history = hist
    rep = out["report"]
    rep.update(_read_report(scans, rows, kept, names, color_type))
    rep["timings"].update(read=read_s, total=time.perf_counter() - t0)
    rep["distributed"].update(chunks=len(chunks), partitions=slab_choice)
    grid = D.grid_in_input_axes(out, job, perm)
    if grid is not None:
        grid.point_dtype, grid.history = point_dtype, list(hist)
    if mesh is None:
        return Streamed(rep, grid=grid)
    return PoissonResult(mesh, rep, grid)


def _scanned_box(scans: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The chunks' ``scans``' box: their points' least and greatest coordinates (input axes)."""
    lo = np.min([s["lo"] for s in scans if "lo" in s], axis=0)
    hi = np.max([s["hi"] for s in scans if "lo" in s], axis=0)
    if not (hi - lo).max() > 0:
        raise InputError("all points coincide: there is no surface to reconstruct")
    return lo, hi


def _read_report(
    scans: list[dict], rows: int, kept: int, names: list[str], color_type: Any
) -> dict[str, Any]:
    """The report's entries on what was read: rows, those ignored, attributes carried."""
    return {
        "ignored_points": int(rows - kept),
        "invalid_dropped": sum(s["invalid_dropped"] for s in scans),
        "points_read": int(rows),
        "attributes": sorted(names) + (["colors"] if color_type is not None else []),
    }


def _sort_into_slabs(
    client, chunks, frame: tuple, tmp: str, keep_colors, names, overall, progress
) -> tuple[list, np.ndarray, dict]:
    """The workers sort their chunks' rows per sub-slab into files in ``tmp``.

    ``frame``: (the job's origin, the cube's side, the axes' turn, sub-slabs).

    Returns the files (path, offsets per sub-slab) per chunk, the points per sub-slab and the
    phase's figures.
    """
    from recon_cli.slabs.runners import note_phase

    share = overall.claim("sort") / len(chunks)
    t = time.perf_counter()
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
    files = [(os.path.join(tmp, f"c{i:05d}"), b["offsets"]) for i, b in enumerate(buckets)]
    return files, counts, sort_phase


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
    :func:`recon_cli.stages.poisson.stage.run_from_files` has decided the run goes in slabs: on the
    execution's cluster (``--workers``, ``--scheduler``), or in this process, the slabs' states
    spilled to a folder beside OUT (:func:`recon_cli.execution.current`). Writes OUT and returns
    the report.
    """
    from recon_cli.execution import current
    from recon_cli.io.load import save
    from recon_cli.stages.poisson import SPEC, command_report

    ex = current()
    v = SPEC.check(params, complete=True)
    where = D.slab_reason(ex)
    D.check_slab_options(v["backend"], v["degree"], v["estimate_normals"], where)
    from recon_cli.stages.poisson.field import checked_grid_path

    grid_path = checked_grid_path(v["grid"])
    env = None
    if v["envelope"] not in (None, ""):
        from recon_cli.stages.poisson.envelope import load_envelope

        env = load_envelope(v["envelope"])
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
    with ex.cluster() as (client, info):
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
            with_grid=grid_path is not None,
            envelope=env,
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
    report = command_report(rep, env is not None)
    if grid_path is not None:
        from recon_cli.stages.poisson.field import write_solved_grid

        report.update(
            write_solved_grid(res.grid, grid_path, v["depth"], v["boundary"], rep["iso_value"])
        )
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

    The parts are files (:func:`.slab_surface.export`); this process never holds the mesh.
    Vertices in slab order with the axes turned back, then the faces, references to a right
    seam resolved to the next slab's first vertices. Atomic: a failure leaves no file.
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
