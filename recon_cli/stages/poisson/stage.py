"""The ``poisson`` stage as the CLI and pipelines run it: where the work runs, files in and out.

:func:`run_stage` picks the path for the :func:`recon_cli.execution.current` execution: in slabs
on its Dask cluster, in slabs in this process (states spilled to files) when the cloud needs
more than its memory in one piece, else :func:`~recon_cli.stages.poisson.screened_poisson`; or
a reference backend (Open3D, PyMeshLab) when asked for by ``--backend``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.execution import current
from recon_cli.geometry import PointCloud, TriangleMesh, as_point_cloud, local_origin
from recon_cli.stages.poisson import (
    SPEC,
    check_inputs,
    command_report,
    screened_poisson,
)

if TYPE_CHECKING:
    from recon_cli.stages import StageResult

log = logging.getLogger("recon")


def run_from_files(input: str, output: str, params: dict, **kw: Any) -> dict | None:
    """The stage's ``from_files``: a run in slabs from IN's chunks, never holding the cloud.

    On a cluster (``--workers``, ``--scheduler``), or in this process when IN is too large for
    the memory in one piece (:func:`local_slabs`): :func:`.files.run_from_files` then.
    Else None (the command loads IN and runs the stage). A single-process run never imports the
    distributed solve (nor, through it, Dask).
    """
    ex = current()
    if not ex.distributed:
        if input == "-" or kw.get("load_kw", {}).get("format"):
            return None
        from recon_cli.io.chunks import plan_chunks

        chunks = plan_chunks(input)
        if any(c.kind == "whole" for c in chunks):
            return None  # rows not known before reading: loaded whole, the solve in slabs
        depth = SPEC.check(params, complete=True)["depth"]
        if local_slabs(sum(c.stop - c.start for c in chunks), ex, depth) == 1:
            return None
    from recon_cli.stages.poisson.files import run_from_files as run

    return run(input, output, params, **kw)


def local_slabs(npoints: int, ex: Any, depth: int) -> int:
    """The slabs of a run in this process: 1 when the memory holds the whole solve.

    ``ex``: the :class:`recon_cli.execution.Execution` (its ``partitions`` or its memory budget);
    ``depth``: the solve's (a slab's memory at that depth, :mod:`.memory`). Refuses a memory too
    small for the most slabs (one line with the least that would do).
    """
    if ex.partitions is not None:
        return int(ex.partitions)
    from recon_cli.stages.poisson.distributed import slab_count

    return slab_count(None, npoints, None, ex.budget(), depth)[0]


@SPEC.runner
def run_stage(
    data: Any,
    *,
    degree: int,
    attributes: Any,
    envelope: Any,
    grid: Any,
    estimate_normals: bool,
    backend: str,
    progress: Any = None,
    **solve: Any,
) -> StageResult:
    """Stage ``poisson``: screened Poisson reconstruction of an oriented cloud.

    Where it runs is the :func:`recon_cli.execution.current` execution's: in slabs on its Dask
    cluster, in slabs in this process (their states spilled to files) when the cloud needs more
    than its memory in one piece, else the single-process solve.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Oriented points (a mesh's vertices and vertex normals are used).
    depth, scale, point_weight, samples_per_node, degree, boundary, confidence, density, trim
        See :func:`screened_poisson` (all but ``degree`` arrive in ``solve``).
    attributes : str or list of str
        ``all`` (every property of the input and its colours), ``none``, or names
        separated by commas (``colors`` for the colours): carried onto the vertices
        (:mod:`.attributes`; with a reference backend, Open3D's colours are its own).
    envelope : path or None
        A closed mesh file (any format recon reads) the surface must lie in
        (:mod:`.envelope`; native only).
    grid : path or None
        Also write the solved field here as a grid file (:mod:`.field`; native only).
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
        ``iso_value``, ``solver_iterations``, ``residual``, ``bubbles_removed``,
        ``islands_removed``, ``folds_removed``, ``trimmed_faces``, ``trimmed_area``, ``backend``
        (the solver keys are None for the reference backends).
    """
    from recon_cli.stages import StageResult

    ex = current()
    grid_path, env = _check_run_options(backend, degree, solve, envelope, grid)
    cloud, history, props, keep_colors = _stage_input(data, attributes, estimate_normals, progress)
    colors = cloud.colors if keep_colors else None
    local = not ex.distributed and backend == "native"
    slabs = local_slabs(len(cloud.points), ex, solve["depth"]) if local else None
    if ex.distributed or (slabs or 1) > 1:
        from recon_cli.stages.poisson import distributed as D

        # the cloud is in memory: its normals were estimated above unless the run is on a cluster
        D.check_slab_options(
            backend, degree, estimate_normals and ex.distributed, D.slab_reason(ex)
        )
        mesh, report = _run_distributed(
            cloud, colors, props, solve, ex, slabs, grid_path, history, progress, env
        )
    elif backend == "native":
        mesh, report = _run_native(
            cloud, colors, props, solve, degree, env, grid_path, history, progress
        )
    else:
        mesh, report = _run_reference(cloud, keep_colors, props, solve, backend, history)
    mesh.history = history
    mesh.obj_info = list(cloud.obj_info)  # a LAS file's header and coordinate system
    mesh.point_dtype = (
        cloud.point_dtype
    )  # double in, double out (float32 in: see geometry.storage_dtype)
    report["backend"] = backend
    return StageResult(output=mesh, report=report)


def _check_run_options(
    backend: str, degree: int, solve: dict[str, Any], envelope: Any, grid: Any
) -> tuple[str | None, Any]:
    """The stage's checks of its options together; returns the grid's path and the envelope.

    ``solve``: the solve's options by name (``boundary``, ``confidence``, ``density``, ``trim``).
    """
    boundary, confidence = solve["boundary"], solve["confidence"]
    if backend == "pymeshlab" and (solve["density"] or solve["trim"] != 0):
        raise ParameterError(
            "the pymeshlab backend gives no densities: --density/--trim need native or open3d"
        )
    # ---- PoissonRecon parity options (free boundary, confidence, grid): the native solver only
    if backend != "native":
        for name, used in (
            ("--boundary free", boundary == "free"),
            ("--confidence", confidence),
            ("--grid", grid not in (None, "")),
            ("--envelope", envelope not in (None, "")),
        ):
            if used:
                raise ParameterError(f"{name} needs the native backend")
    from recon_cli.stages.poisson.field import checked_grid_path

    grid_path = checked_grid_path(grid)
    env = None
    if envelope not in (None, ""):
        if degree != 2:
            raise ParameterError("--envelope needs --degree 2")
        from recon_cli.stages.poisson.envelope import load_envelope

        env = load_envelope(envelope)
    return grid_path, env


def _stage_input(
    data: Any, attributes: Any, estimate_normals: bool, progress: Any
) -> tuple[PointCloud, list[str], dict[str, np.ndarray], bool]:
    """The oriented cloud, its history, the properties carried and whether colours are."""
    cloud = as_point_cloud(data)
    from recon_cli.stages.poisson.attributes import select

    prop_names, keep_colors = select(attributes, list(cloud.attributes), cloud.colors is not None)
    props = {k: cloud.attributes[k] for k in prop_names}
    history = list(cloud.history)
    if estimate_normals:
        try:
            from recon_cli.stages import normals as normals_mod
        except ModuleNotFoundError:
            raise ParameterError(
                "--estimate-normals needs the normals stage, which is not available"
            ) from None
        est = normals_mod.run_stage(PointCloud(points=cloud.points), progress=progress)
        cloud = cloud.copy()
        cloud.normals = est.output.normals
    if cloud.normals is None:
        raise InputError(
            "the cloud has no normals: run 'recon normals' first (or pass --estimate-normals)"
        )
    return cloud, history, props, keep_colors


def _run_distributed(
    cloud: PointCloud,
    colors: np.ndarray | None,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    ex: Any,
    slabs: int | None,
    grid_path: str | None,
    history: list[str],
    progress: Any,
    env: Any = None,
) -> tuple[TriangleMesh, dict]:
    """The cloud in slabs (:mod:`.distributed`): on ``ex``'s Dask cluster, or in this process.

    ``slabs``: their number in this process (None on a cluster: its workers' memory decides,
    or ``ex.partitions``). ``env``: the checked envelope, or None. Returns the mesh and the
    report; the grid written to ``grid_path``.
    """
    from recon_cli.stages.poisson.distributed import distributed_poisson

    assert cloud.normals is not None  # _stage_input refuses a cloud without
    with ex.cluster() as (client, info):
        res = distributed_poisson(
            cloud.points,
            cloud.normals,
            partitions=slabs if slabs is not None else ex.partitions,
            **solve,
            colors=colors,
            properties=props,
            with_grid=grid_path is not None,
            envelope=env,
            client=client,
            temp_dir=ex.spill_parent(),
            progress=progress,
        )
    rep = res.report
    report = command_report(rep, env is not None)
    report["distributed"] = {"cluster": info, **rep["distributed"]}
    if grid_path is not None:
        report.update(_write_grid(res, grid_path, solve, history, cloud.point_dtype))
    return res.mesh, report


def _run_native(
    cloud: PointCloud,
    colors: np.ndarray | None,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    degree: int,
    env: Any,
    grid_path: str | None,
    history: list[str],
    progress: Any,
) -> tuple[TriangleMesh, dict]:
    """:func:`screened_poisson` on the cloud, the grid written; returns the mesh and report.

    With room in the execution's memory budget the run keeps its freed memory for its next
    arrays (:func:`recon_cli.memory.heap_kept`): fewer page faults, a higher peak.
    """
    from recon_cli.memory import heap_kept
    from recon_cli.stages.poisson.memory import heap_room

    assert cloud.normals is not None  # _stage_input refuses a cloud without
    room = heap_room(len(cloud.points), solve["depth"], current().budget())
    with heap_kept(room):
        res = screened_poisson(
            cloud.points,
            cloud.normals,
            **solve,
            degree=degree,
            colors=colors,
            properties=props,
            with_grid=grid_path is not None,
            envelope=env,
            progress=progress,
        )
    rep = res.report
    report = command_report(rep, env is not None)
    if grid_path is not None:
        report.update(_write_grid(res, grid_path, solve, history, cloud.point_dtype))
    return res.mesh, report


def _write_grid(res: Any, path: str, solve: dict, history: list[str], point_dtype) -> dict:
    """Write the result's grid (:func:`.field.write_solved_grid`); the report's entries."""
    from recon_cli.stages.poisson.field import write_solved_grid

    if res.grid is not None:
        res.grid.history, res.grid.point_dtype = list(history), point_dtype
    iso = res.report["iso_value"]
    return write_solved_grid(res.grid, path, solve["depth"], solve["boundary"], iso)


def _run_reference(
    cloud: PointCloud,
    keep_colors: bool,
    props: dict[str, np.ndarray],
    solve: dict[str, Any],
    backend: str,
    history: list[str],
) -> tuple[TriangleMesh, dict]:
    """A reference library's Poisson, then our trim and attributes; returns the mesh, report."""
    depth, scale, trim = solve["depth"], solve["scale"], solve["trim"]
    pts, nrm, keep = check_inputs(cloud.points, cloud.normals)
    # the references about a local origin (Open3D's Poisson loses digits at UTM offsets)
    centre = local_origin(pts)
    clean = PointCloud(
        points=pts - centre,
        normals=nrm,
        colors=None if cloud.colors is None or not keep_colors else cloud.colors[keep],
        history=history,
    )
    from recon_cli.backends import backend_module

    mod = backend_module(backend)
    if backend == "open3d":
        mesh, dens = mod.poisson(clean, depth=depth, scale=scale)
    else:
        mesh, dens = (
            mod.poisson(
                clean,
                depth=depth,
                scale=scale,
                samples_per_node=solve["samples_per_node"],
                point_weight=solve["point_weight"],
            ),
            None,
        )
    mesh.vertices = mesh.vertices + centre
    trimmed, trimmed_area = 0, 0.0
    if trim == "auto" and len(mesh.faces):
        from recon_cli.stages.poisson.trim import merge_per_cell, trim_auto

        cell = float((pts.max(axis=0) - pts.min(axis=0)).max()) * scale / (1 << depth)
        cut = trim_auto(mesh, merge_per_cell(pts, cell), carry=dens)
        if len(cut.mesh.faces) == 0:
            raise InputError("trim auto removes the whole surface: no part lies near the samples")
        trimmed = len(mesh.faces) - cut.untouched_faces
        mesh, dens, trimmed_area = cut.mesh, cut.carried, cut.removed_area
    elif trim != "auto" and trim > 0 and len(mesh.faces):
        from scipy.spatial import cKDTree

        from recon_cli.stages.poisson.trim import trim_by_density

        # the density at the samples: Open3D's at the vertex nearest each sample
        at_samples = dens[cKDTree(mesh.vertices).query(pts, workers=-1)[1]]
        cut = trim_by_density(mesh, dens, trim * float(np.median(at_samples)))
        if len(cut.mesh.faces) == 0:
            raise ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value")
        trimmed = len(mesh.faces) - cut.untouched_faces
        mesh, dens, trimmed_area = cut.mesh, cut.density, cut.removed_area
    fallback = 0
    if props and len(mesh.faces):
        from recon_cli.stages.poisson.attributes import transfer

        e = mesh.vertices[mesh.faces[:, [0, 1]]]
        sigma = float(np.median(np.linalg.norm(e[:, 0] - e[:, 1], axis=1)))
        kept = {k: v[keep] for k, v in props.items()}
        moved = transfer(pts, nrm, kept, None, mesh.vertices, mesh.faces, sigma)
        mesh.attributes.update(moved.values)
        fallback = moved.fallback
    if solve["density"] and dens is not None:
        mesh.attributes["density"] = dens
    report = {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "depth": depth,
        "iso_value": None,
        "solver_iterations": None,
        "residual": None,
        "bubbles_removed": None,
        "islands_removed": None,
        "folds_removed": None,
        "trimmed_faces": int(trimmed),
        "trimmed_area": trimmed_area,
        "noise": None,
        "attributes": sorted(props) + (["colors"] if mesh.colors is not None else []),
        "attribute_fallback_vertices": fallback,
    }
    return mesh, report
