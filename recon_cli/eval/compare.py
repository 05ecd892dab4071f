"""``recon compare``: run several methods on one input, time them, diff them against a reference.

A method is written ``[BACKEND:]STAGE[:NAME=VALUE[:NAME=VALUE...]]``: ``poisson:depth=8``,
``ballpivot``, ``open3d:poisson``, ``pymeshlab:poisson:depth=9``. A comma separates methods
(``poisson:depth=8,ballpivot``); a ``NAME=VALUE`` token after a comma continues the previous method
(``poisson:depth=8,scale=1.2``); inside a value, ``;`` stands for a comma
(``ballpivot:radii=0.01;0.02``). Every method runs through :func:`recon_cli.stages.apply_stage`
(``BACKEND`` becomes its ``backend`` parameter), each in a fresh child process so that its wall time
and peak memory are its own and a crash stays its own. A stage that cannot be loaded (a plugin whose
module is missing) is reported ``unavailable``; a method that raises is reported ``failed`` with its
message; the others go on. A stage that yields a grid (``sdf`` of a cloud, ``fit-sdf``:
``fit-sdf:iterations=500``) is meshed by marching cubes at level 0 inside its measured time.

Outputs in ``DIR``: ``<method>.ply`` (each result), ``<method>.png`` (turntable of its shape,
accuracy and completeness heatmaps, and the reference), ``overview.png`` (all methods on one
colour scale), ``quality_vs_time.png`` (Chamfer-L1 and F-score against time, one point per
method), ``results.json``, ``report.md`` and ``report.html`` (:mod:`recon_cli.eval.report`).
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from recon_cli.errors import InputError, ParameterError, ReconError

STATUS_OK = "ok"
STATUS_FAILED = "failed"
STATUS_UNAVAILABLE = "unavailable"
BACKENDS = ("native", "open3d", "pymeshlab")


@dataclass
class Method:
    """One method of a comparison: a stage, its backend and parameters (CLI string forms)."""

    stage: str
    backend: str | None = None
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """``backend:stage:param=value:...``, as the command line writes a method."""
        parts = ([self.backend] if self.backend else []) + [self.stage]
        parts += [f"{k.replace('_', '-')}={v}" for k, v in self.params.items()]
        return ":".join(parts)

    @property
    def slug(self) -> str:
        """The label made safe for a file name."""
        return re.sub(r"[^A-Za-z0-9.]+", "_", self.label).strip("_")

    def stage_params(self) -> dict[str, Any]:
        """The parameters the stage is called with (the backend among them)."""
        p = dict(self.params)
        if self.backend:
            p["backend"] = self.backend
        return p


def parse_methods(spec: str | Sequence[str]) -> list[Method]:
    """Methods from ``--methods`` text (see the module docstring); a sequence is joined by commas.

    Raises
    ------
    ParameterError
        Empty text, a parameter before any method, a malformed ``NAME=VALUE``, or the
        same method twice.
    """
    if not isinstance(spec, str):
        spec = ",".join(spec)
    methods: list[Method] = []
    for raw in spec.split(","):
        token = raw.strip()
        if not token:
            continue
        if "=" in token and ":" not in token.split("=", 1)[0]:
            if not methods:
                raise ParameterError(f"method parameter {token!r} comes before any method")
            _add_param(methods[-1], token)
            continue
        parts = token.split(":")
        backend = None
        if parts[0] in BACKENDS:
            backend = None if parts[0] == "native" else parts[0]
            parts = parts[1:]
        if not parts or not parts[0] or "=" in parts[0]:
            raise ParameterError(f"method {token!r} names no stage")
        m = Method(stage=parts[0], backend=backend)
        for p in parts[1:]:
            _add_param(m, p)
        methods.append(m)
    if not methods:
        raise ParameterError("no method given (e.g. --methods poisson:depth=8,ballpivot)")
    labels = [m.label for m in methods]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ParameterError(f"method {dup[0]!r} is given twice")
    return methods


def compare_methods(
    input_path: str | os.PathLike,
    methods: Sequence[Method] | str,
    reference_path: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    samples: int = 200_000,
    seed: int = 0,
    taus: Sequence[float | str] | str | None = None,
    views: Sequence[str] | None = None,
    isolate: bool = True,
    progress: Any = None,
    vmax: float | None = None,
    unit: str | None = None,
) -> dict[str, Any]:
    """Run ``methods`` on the input file, time them, diff each output against the reference.

    Four phases: check everything that can be checked before running (:func:`_plan`), run
    each method (:func:`_run_methods`), measure each output against the reference
    (:func:`_measure`), draw (:func:`_draw`), then write the reports
    (:func:`recon_cli.eval.report.write_reports`).

    Parameters
    ----------
    input_path : path
        The input (PLY cloud, usually with normals).
    methods : sequence of Method, or str
        See :func:`parse_methods`.
    reference_path : path or None
        Ground truth mesh or cloud; None gives timings and topology only.
    out_dir : path
        Folder for the outputs (created if missing).
    samples, seed, taus
        As in :func:`recon_cli.eval.metrics.compare_meshes`.
    views : sequence of str, optional
        Views of the pictures (:func:`recon_cli.eval.render.resolve_views`; default the
        four-azimuth turntable).
    isolate : bool
        Run each method in a fresh child process (true wall time and peak memory, crash
        isolation). False runs in this process (peak memory then from ``tracemalloc``:
        Python and numpy allocations only).
    progress : Progress or None
    vmax : float, optional
        Top of the heatmaps' shared colour scale (default
        :func:`recon_cli.eval.metrics.shared_vmax` of every accuracy and completeness).
    unit : str, optional
        Unit of the coordinates, for the pictures and reports.

    Returns
    -------
    dict
        ``input``, ``reference``, ``samples``, ``seed``, ``unit``, ``reference_diagonal``,
        ``vmax`` (of the pictures), ``environment`` (:func:`recon_cli.eval.report.environment`),
        ``provenance`` (``input`` / ``reference``: :func:`recon_cli.eval.report.file_provenance`),
        ``methods`` (list of rows: ``method``, ``stage``, ``backend``, ``params`` (as given),
        ``params_resolved`` (every parameter the stage ran with: defaults, given values and
        what it resolved, e.g. automatic radii), ``stage_report`` (the stage's own report),
        ``library_calls`` (the reference-library calls and the arguments we passed, for a
        reference backend; its own defaults apply to the rest),
        ``status``, ``error``, ``seconds`` (wall time of the stage), ``process_seconds``
        (wall time of the method's child process: start-up, read, stage, write),
        ``peak_mb`` (peak resident memory above the start of the stage), ``output``,
        ``picture``, ``faces``, ``vertices``, ``metrics`` (the
        :func:`~recon_cli.eval.metrics.compare_meshes` dict or None)), ``overview`` and
        ``plot`` (picture paths or None) and ``files`` (report paths).

    Raises
    ------
    ParameterError
        Unknown stage names or parameters, bad ``samples``, ``vmax`` or views (before
        anything runs).
    InputError
        Unreadable input or reference.
    """
    from recon_cli.eval.metrics import load_geometry
    from recon_cli.eval.report import environment, file_provenance, write_reports

    methods, available, samples, vmax = _plan(methods, samples, views, vmax)
    source = load_geometry(input_path)  # fail early on an unreadable input
    reference = load_geometry(reference_path) if reference_path is not None else None
    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError("exists and is not a folder", out_dir)
    os.makedirs(out_dir, exist_ok=True)
    result: dict[str, Any] = {
        "input": os.fspath(input_path),
        "reference": None if reference_path is None else os.fspath(reference_path),
        "samples": samples,
        "seed": int(seed),
        "unit": unit,
        "reference_diagonal": None,
        "vmax": None,
        "environment": environment(),
        "provenance": {
            "input": file_provenance(input_path, source),
            "reference": None
            if reference_path is None
            else file_provenance(reference_path, reference),
        },
    }
    del source
    rows, outputs = _run_methods(input_path, methods, available, out_dir, isolate, progress)
    _measure(rows, outputs, reference, samples, seed, taus)
    result["reference_diagonal"] = next(
        (r["metrics"]["reference_diagonal"] for r in rows if r["metrics"]), None
    )
    result["methods"] = rows
    result.update(_draw(rows, outputs, reference, reference_path, out_dir, views, vmax, unit))
    result["files"] = {
        "results": os.path.join(out_dir, "results.json"),
        "markdown": os.path.join(out_dir, "report.md"),
        "html": os.path.join(out_dir, "report.html"),
    }
    write_reports(result, out_dir)
    return result


def _plan(methods, samples, views, vmax) -> tuple[list[Method], dict[str, bool], int, float | None]:
    """Everything checkable before running: methods, their parameters, samples, views, vmax.

    Returns the methods, which of them can run (label -> bool: False for a stage not built
    in this version), and the checked ``samples`` and ``vmax``.
    """
    from recon_cli.eval.figure import require_pillow
    from recon_cli.eval.metrics import check_samples, check_vmax
    from recon_cli.eval.render import resolve_views
    from recon_cli.stages import STAGES, get_stage, stage_parameters

    if isinstance(methods, str):
        methods = parse_methods(methods)
    methods = list(methods)
    if not methods:
        raise ParameterError("no method given")
    samples = check_samples(samples)
    resolve_views(views)
    require_pillow()  # the pictures are drawn after every method has run: fail before
    if vmax is not None:
        vmax = check_vmax(vmax)
    available: dict[str, bool] = {}
    for m in methods:
        if m.stage not in STAGES:
            raise ParameterError(
                f"unknown stage {m.stage!r} in method {m.label!r} "
                f"(stages: {', '.join(sorted(STAGES))})"
            )
        try:
            get_stage(m.stage)
        except ParameterError:
            available[m.label] = False
            continue
        available[m.label] = True
        known = stage_parameters(m.stage)
        for k in m.stage_params():
            if k not in known:
                raise ParameterError(
                    f"method {m.label!r}: stage {m.stage!r} has no parameter {k!r} "
                    f"(parameters: {', '.join(sorted(known))})"
                )
    return methods, available, samples, vmax


def _run_methods(
    input_path, methods, available, out_dir, isolate, progress
) -> tuple[list[dict], dict[str, Any]]:
    """Run each method (a child process each unless ``isolate`` is False).

    Rows and outputs by label.
    """
    from recon_cli.eval.metrics import load_geometry

    rows: list[dict[str, Any]] = []
    outputs: dict[str, Any] = {}
    for m in methods:
        row: dict[str, Any] = {
            "method": m.label,
            "stage": m.stage,
            "backend": m.backend or "native",
            "params": dict(m.params),
            "params_resolved": None,
            "stage_report": None,
            "library_calls": None,
            "status": STATUS_UNAVAILABLE,
            "error": None,
            "seconds": None,
            "process_seconds": None,
            "peak_mb": None,
            "output": None,
            "picture": None,
            "vertices": None,
            "faces": None,
            "metrics": None,
        }
        rows.append(row)
        if not available[m.label]:
            row["error"] = f"stage {m.stage!r} is not available (its module cannot be imported)"
            continue
        out_path = os.path.join(out_dir, m.slug + ".ply")
        with (
            progress.task(f"running {m.label}")
            if progress is not None
            else contextlib.nullcontext()
        ):
            t0 = time.perf_counter()
            res = (
                _run_isolated(input_path, m, out_path)
                if isolate
                else _run_here(input_path, m, out_path)
            )
            row["process_seconds"] = time.perf_counter() - t0
        row.update(
            {
                k: res.get(k)
                for k in (
                    "status",
                    "error",
                    "seconds",
                    "peak_mb",
                    "params_resolved",
                    "stage_report",
                    "library_calls",
                )
            }
        )
        if res["status"] != STATUS_OK:
            continue
        row["output"] = out_path
        obj = load_geometry(out_path)
        outputs[m.label] = obj
        row["vertices"] = int(len(obj.points))
        row["faces"] = int(len(getattr(obj, "faces", ())))
    return rows, outputs


def _measure(rows, outputs, reference, samples, seed, taus) -> None:
    """Fill each successful row's ``metrics`` against ``reference``.

    A failure to compare fails the row.
    """
    from recon_cli.eval.metrics import compare_meshes

    if reference is None:
        return
    for row in rows:
        if row["status"] != STATUS_OK:
            continue
        try:
            row["metrics"] = compare_meshes(
                outputs[row["method"]], reference, samples=samples, seed=seed, taus=taus
            )
        except InputError as exc:  # e.g. an empty reconstruction
            row["status"], row["error"] = STATUS_FAILED, f"cannot compare the output: {exc}"


def _draw(rows, outputs, reference, reference_path, out_dir, views, vmax, unit) -> dict[str, Any]:
    """Write ``<method>.png``, ``overview.png`` and ``quality_vs_time.png``.

    A sheet per method shows every view; the overview has all methods side by side in the first
    view. One colour scale for every heatmap: ``vmax`` or the shared default of every accuracy
    and completeness array. Returns ``overview``, ``plot`` (paths or None) and ``vmax``.
    """
    from recon_cli.eval.figure import diff_rows, overview, sheet
    from recon_cli.eval.metrics import shared_vmax, vertex_distances
    from recon_cli.eval.render import resolve_views, write_png

    good = [r for r in rows if r["status"] == STATUS_OK]
    if not good:
        return {"overview": None, "plot": None, "vmax": None}
    acc: dict[str, Any] = {r["method"]: None for r in good}
    missed: dict[str, Any] = dict(acc)
    diag = None
    if reference is not None:
        for r in good:
            acc[r["method"]] = vertex_distances(outputs[r["method"]], reference)
            missed[r["method"]] = vertex_distances(reference, outputs[r["method"]])
        measured = [r for r in good if r["metrics"]]
        diag = measured[0]["metrics"]["reference_diagonal"] if measured else None
        if vmax is None:
            tau = min((min(r["metrics"]["tau"]) for r in measured), default=None)
            vmax = shared_vmax(list(acc.values()) + list(missed.values()), tau)
    ref = (_stem(reference_path), reference) if reference is not None else None
    for r in good:
        r["picture"] = os.path.join(out_dir, _slug(r["method"]) + ".png")
        fig = sheet(
            diff_rows(
                [(r["method"], outputs[r["method"]], acc[r["method"]], missed[r["method"]])], ref
            ),
            views,
            vmax=vmax,
            unit=unit,
            diagonal=diag,
            title=f"recon compare: {r['method']}",
        )
        write_png(fig.image, r["picture"])
    overview_path = os.path.join(out_dir, "overview.png")
    fig = overview(
        [(r["method"], outputs[r["method"]], acc[r["method"]], missed[r["method"]]) for r in good],
        ref,
        resolve_views(views)[0][1],
        vmax=vmax,
        unit=unit,
        diagonal=diag,
        title="recon compare: all methods",
    )
    write_png(fig.image, overview_path)
    plot = None
    if reference is not None and any(r["metrics"] for r in good):
        plot = os.path.join(out_dir, "quality_vs_time.png")
        write_png(quality_plot(rows, unit), plot)
    return {"overview": overview_path, "plot": plot, "vmax": vmax}


def quality_plot(rows: Sequence[dict], unit: str | None = None) -> Any:
    """Chamfer-L1 and F-score (at the first tau) against stage time, one point per method.

    Returns
    -------
    (H, W, 3) uint8
    """
    import numpy as np

    from recon_cli.eval.figure import scatter_plot

    nan = float("nan")
    measured = [r for r in rows if r.get("metrics")]
    tau = measured[0]["metrics"]["tau_relative"][0] * 100 if measured else nan

    def pts(get):
        return [
            (
                r["method"],
                r["seconds"] if r["seconds"] is not None else nan,
                get(r) if r.get("metrics") else nan,
            )
            for r in rows
            if r["status"] == STATUS_OK
        ]

    left = scatter_plot(
        pts(lambda r: r["metrics"]["chamfer_l1"]),
        x_label="stage wall time [s], lower is better",
        y_label=f"Chamfer-L1 [{unit or 'model units'}], lower is better",
        title="Chamfer-L1 against time",
    )
    right = scatter_plot(
        pts(lambda r: r["metrics"]["fscore"][0]),
        x_label="stage wall time [s], lower is better",
        y_label=f"F-score @{tau:.3g}% of diagonal, higher is better",
        title="F-score against time",
    )
    return np.concatenate([left.image, right.image], axis=1)


# ----------------------------------------------------------------------------- running


def _stem(path: str | os.PathLike) -> str:
    return os.path.splitext(os.path.basename(os.fspath(path)))[0] or os.fspath(path)


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9.]+", "_", label).strip("_")


def _add_param(m: Method, token: str) -> None:
    if "=" not in token:
        raise ParameterError(f"method parameter {token!r} is not NAME=VALUE")
    k, v = token.split("=", 1)
    k = k.strip().replace("-", "_")
    if not k or not v.strip():
        raise ParameterError(f"method parameter {token!r} is not NAME=VALUE")
    m.params[k] = v.strip().replace(";", ",")


def _run_here(input_path: str | os.PathLike, m: Method, out_path: str) -> dict[str, Any]:
    import tracemalloc

    from recon_cli.io.load import load, save
    from recon_cli.stages import apply_stage

    data = load(input_path)
    calls = _reset_calls()
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        result = _surface(apply_stage(m.stage, data, m.stage_params()))
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    except ReconError as exc:
        return {
            "status": STATUS_FAILED,
            "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
            "seconds": None,
            "peak_mb": None,
        }
    finally:
        tracemalloc.stop()
    save(result.output, out_path)
    return {
        "status": STATUS_OK,
        "error": None,
        "seconds": seconds,
        "peak_mb": peak,
        **_ran_with(m.stage, m.stage_params(), result, calls),
    }


def _surface(result):
    """The method's surface: a grid (``sdf``, ``fit-sdf``) meshed at its zero level.

    Our marching cubes runs inside the method's measured time and memory.
    """
    from recon_cli.grid import Grid
    from recon_cli.stages import apply_stage

    if isinstance(result.output, Grid):
        return apply_stage("mcubes", result.output, {})
    return result


def _run_isolated(input_path: str | os.PathLike, m: Method, out_path: str) -> dict[str, Any]:
    import multiprocessing as mp

    # spawn, not fork: the parent may hold numba/OpenMP threads that a fork would break
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=_child,
        args=(send, os.fspath(input_path), m.stage, m.stage_params(), out_path),
        daemon=True,
    )
    proc.start()
    send.close()
    try:
        res = recv.recv()
    except EOFError:
        res = None
    proc.join()
    if res is None:
        return {
            "status": STATUS_FAILED,
            "error": f"the method's process died (exit code {proc.exitcode})",
            "seconds": None,
            "peak_mb": None,
        }
    return res


def _child(conn, input_path: str, stage: str, params: dict, out_path: str) -> None:
    """Child process: load, run one stage (timed, peak memory), save; send a small dict back."""
    try:
        from recon_cli import memory
        from recon_cli.io.load import load, save
        from recon_cli.stages import apply_stage

        data = load(input_path)
        calls = _reset_calls()
        memory.reset_peak()
        base = memory.rss_mb() or 0.0
        t0 = time.perf_counter()
        result = _surface(apply_stage(stage, data, params))
        seconds = time.perf_counter() - t0
        peak = max(0.0, (memory.peak_mb() or 0.0) - base)
        save(result.output, out_path)
        conn.send(
            {
                "status": STATUS_OK,
                "error": None,
                "seconds": seconds,
                "peak_mb": peak,
                **_ran_with(stage, params, result, calls),
            }
        )
    except ReconError as exc:
        conn.send(
            {
                "status": STATUS_FAILED,
                "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
                "seconds": None,
                "peak_mb": None,
            }
        )
    except BaseException as exc:  # a bug in a method must not take the comparison down
        last = traceback.format_exception_only(type(exc), exc)[-1].strip()
        conn.send(
            {
                "status": STATUS_FAILED,
                "error": f"unexpected error: {last}",
                "seconds": None,
                "peak_mb": None,
            }
        )
    finally:
        conn.close()


def _ran_with(stage: str, params: dict, result: Any, calls: Sequence[dict]) -> dict[str, Any]:
    """What a stage ran with, JSON-safe.

    Its defaults, the given values and what it resolved (its report's ``provenance``, e.g.
    automatic radii), its report, and the reference-library calls it made
    (:data:`recon_cli.backends.CALLS`).
    """
    import json

    from recon_cli.stages import get_spec, report_json

    report = result.report if isinstance(result.report, dict) else {}
    spec = get_spec(stage)
    resolved = {
        **spec.defaults(),
        **spec.check(dict(params), complete=False),
    }  # as apply_stage ran them
    if isinstance(report.get("provenance"), dict):
        resolved.update(report["provenance"])
    out = {"params_resolved": resolved, "stage_report": report, "library_calls": list(calls)}
    return json.loads(report_json(out))


def _reset_calls() -> list[dict]:
    from recon_cli.backends import CALLS

    CALLS.clear()
    return CALLS
