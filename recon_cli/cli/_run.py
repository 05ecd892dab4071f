"""Running a stage from a command: load, apply, save atomically, report."""

from __future__ import annotations

import contextlib
import sys
import time
from typing import Any

import click


def make_progress(ctx: click.Context):
    """The command's progress display on stderr (off with -q or when stderr is not a terminal).

    One per command, closed when the command ends; made before the input is read, so
    that a first run's kernel compiling shows from the start.
    """
    from recon_cli.progress import Progress

    root = ctx.find_root()
    obj = root.obj if isinstance(root.obj, dict) else {}
    if obj.get("progress") is None:
        quiet = bool(obj.get("quiet"))
        obj["progress"] = Progress(stream=sys.stderr, enabled=False if quiet else None)
        root.obj = obj
        root.call_on_close(obj["progress"].close)
    return obj["progress"]


def verbosity(ctx: click.Context) -> int:
    obj = ctx.find_root().obj or {}
    return int(obj.get("verbose", 0))


def is_quiet(ctx: click.Context) -> bool:
    obj = ctx.find_root().obj or {}
    return bool(obj.get("quiet", False))


def io_formats(ctx: click.Context, input: str, output: str) -> tuple[dict, dict]:
    """``load`` and ``save`` keyword arguments from the format options and ``--points-only``.

    The options are ``--format``, ``--input-format`` and ``--output-format``; ``--format``
    applies to an end whose name does not tell (``-`` or no suffix).
    """
    import os

    meta = ctx.meta
    common = meta.get("recon.format")

    def unnamed(p: str) -> bool:
        return p == "-" or not os.path.splitext(p)[1]

    fin = meta.get("recon.input_format") or (common if unnamed(input) else None)
    fout = meta.get("recon.output_format") or (common if unnamed(output) else None)
    return {"format": fin}, {"format": fout, "points_only": bool(meta.get("recon.points_only"))}


def run_stage_command(
    ctx: click.Context,
    stage: str,
    input: str,
    output: str,
    params: dict[str, Any],
    ascii_: bool = False,
    json_: bool = False,
    plan: bool = False,
) -> dict:
    """Load IN, run ``stage`` with ``params``, write OUT atomically, print and return the report.

    With ``plan``: print the predicted peak memory instead (:func:`plan_report`), running nothing.
    """
    from recon_cli.cli._signals import immediate
    from recon_cli.errors import naming
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.load import check_destination, check_read, load_detailed, read_report, save
    from recon_cli.stages import apply_stage, get_spec, read_hint

    spec = get_spec(stage)
    checked = spec.check(params, complete=False)  # parameters before reading anything
    load_kw, save_kw = io_formats(ctx, input, output)
    if plan:
        report = plan_report(stage, input, checked, load_kw)
        emit_report(ctx, report, json_=json_)
        return report
    # a run the memory cannot hold is refused before IN is read (its header's counts)
    predicted = header_prediction(stage, input, checked, load_kw)
    hint = read_hint(stage, checked)  # what the stage keeps of IN: a COPC file reads only that
    check_destination(output, spec.gives)  # and the output path: a wrong one is known now
    progress = make_progress(ctx)  # before reading: a first run's compiling shows from the start
    # Ctrl-C / SIGTERM leave at once, even inside a numba kernel or while numba loads one:
    # nothing is written before save()
    if spec.from_files is not None:
        import importlib

        from recon_cli.errors import naming

        mod, _, fn = spec.from_files.partition(":")
        with naming(input):
            report = getattr(importlib.import_module(mod), fn)(
                input,
                output,
                checked,
                load_kw=load_kw,
                save_kw=save_kw,
                ascii=ascii_,
                progress=progress,
            )
        if report is not None:
            from recon_cli.stages.memory_model import entry

            report["memory"] = entry(predicted)  # the largest of this process and its workers
            emit_report(ctx, report, json_=json_, data_on_stdout=(output == "-"))
            return report
    with immediate():
        t0 = time.perf_counter()
        data, details, _ = load_detailed(input, hint=hint, **load_kw)
        check_read(data, input)
        t1 = time.perf_counter()
        if stage == "normals" and isinstance(data, TriangleMesh):
            from recon_cli.io.text import warn

            warn(
                f"{input}: a mesh: normals are estimated at its {len(data.vertices)} vertices "
                "and the vertices only are written (faces dropped)"
            )
    from recon_cli.cli import _process

    _process.resume()  # start-up ends here: imports, numba's first load, the input
    # a stage that keeps its best result on Ctrl-C (fit-sdf) gets the Python-level handler while it
    # runs
    with contextlib.nullcontext() if spec.keeps_partial else immediate():
        with naming(input):
            result = apply_stage(stage, data, params, progress=progress)
        t2 = time.perf_counter()
    save(result.output, output, ascii=ascii_, **save_kw)
    t3 = time.perf_counter()
    report = dict(result.report)
    read = read_report(data, details)  # invalid points dropped, a COPC window: never silently
    if read:
        report["read"] = read
    report["timings"] = {"read": t1 - t0, "stage": t2 - t1, "write": t3 - t2}
    if isinstance(report.get("memory"), dict):  # the peak of the stage and the write
        from recon_cli.stages.memory_model import peak_bytes

        report["memory"]["peak_bytes"] = peak_bytes()
    report["output"] = "<stdout>" if output == "-" else output
    emit_report(ctx, report, json_=json_, data_on_stdout=(output == "-"))
    return report


def header_prediction(stage: str, input: str, checked: dict, load_kw: dict) -> int | None:
    """The stage's peak memory from IN's header (None: not told), refused when over budget."""
    from recon_cli.execution import current
    from recon_cli.stages import get_spec
    from recon_cli.stages import memory_model as MM

    size = MM.size_from_header(input, load_kw.get("format"))
    if size is None:
        return None
    ex = current()
    predicted = MM.predict(stage, size, {**get_spec(stage).defaults(), **checked}, ex)
    MM.check_fits(stage, predicted, ex.budget(), "<stdin>" if input == "-" else input)
    return predicted


def plan_report(stage: str, input: str, checked: dict, load_kw: dict) -> dict:
    """What a run would take: IN's size (its header's, else IN read) and the predicted peak.

    Keys ``stage``, ``input``, ``points``, ``faces``, ``cells``, ``from`` (``header`` or
    ``data``), ``memory`` (``predicted_bytes``, ``budget_bytes``) and ``fits``.
    """
    from recon_cli.errors import naming
    from recon_cli.execution import current
    from recon_cli.io.load import check_read, load
    from recon_cli.stages import get_spec, read_hint
    from recon_cli.stages import memory_model as MM

    ex = current()
    params = {**get_spec(stage).defaults(), **checked}
    size, data = MM.size_from_header(input, load_kw.get("format")), None
    if size is None or (stage == "poisson"):  # Poisson's finest cells: counted on the points
        with naming(input):
            data = check_read(load(input, hint=read_hint(stage, checked), **load_kw), input)
        size = MM.size_of(data)
    predicted = MM.predict(stage, size, params, ex, data)
    budget = ex.budget()
    return {
        "stage": stage,
        "input": "<stdin>" if input == "-" else input,
        "points": size.points,
        "faces": size.faces,
        "cells": size.cells,
        "from": "header" if data is None else "data",
        "memory": {"predicted_bytes": predicted, "budget_bytes": budget},
        "fits": None if predicted is None or budget is None else predicted <= budget,
    }


def emit_report(
    ctx: click.Context, report: dict, json_: bool = False, data_on_stdout: bool = False
) -> None:
    """Print ``report``: JSON on stdout (stderr if stdout carries data) or a table on stderr."""
    from recon_cli.stages import report_json

    if json_:
        click.echo(report_json(report), err=data_on_stdout)
        return
    if is_quiet(ctx):
        return
    click.echo(format_report(report, verbose=verbosity(ctx)), err=True)


def format_report(report: dict, verbose: int = 0) -> str:
    """A one-screen text rendering of a report dict."""
    lines = []
    for key, value in report.items():
        if key == "timings" and not verbose:
            continue
        if isinstance(value, dict):
            lines.append(f"{key}:")
            for k, v in value.items():
                lines.append(f"  {k:<24} {_fmt(v)}")
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            # a pipeline's per-stage reports: one indented block each
            for i, sub in enumerate(value, start=1):
                lines.append(f"{key} {i}: {sub.get('stage', '')}")
                body = format_report({k: v for k, v in sub.items() if k != "stage"}, verbose)
                lines += ["  " + ln for ln in body.splitlines()]
        else:
            lines.append(f"{key:<26} {_fmt(value)}")
    return "\n".join(lines)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x) for x in v)
    if isinstance(v, dict):  # a sub-report (a COPC read's window): its keys on one line
        return "; ".join(f"{k} {_fmt(x)}" for k, x in v.items())
    return str(v)
