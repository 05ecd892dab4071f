"""Pipeline files: a declarative list of stages in TOML.

Format::

    description = "optional text"

    [[stage]]
    name = "normals"
    knn = 30
    orient = "mst"

    [[stage]]
    name = "poisson"
    depth = 8

Parameter names are the CLI option names of the stage (``point-weight`` or
``point_weight``). The whole file is checked before anything runs: an unknown stage or
parameter is an error naming the file and line.
"""

from __future__ import annotations

import os
import re
import sys
import time
from dataclasses import dataclass, field
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from recon_cli.errors import InputError, ParameterError
from recon_cli.stages import StageResult, apply_stage, get_stage, stage_parameters


@dataclass
class PipelineStep:
    """One stage of a pipeline with its parameters and the line it starts at."""

    name: str
    params: dict[str, Any]
    line: int
    param_lines: dict[str, int] = field(default_factory=dict)


@dataclass
class Pipeline:
    """A parsed, validated pipeline file."""

    path: str
    steps: list[PipelineStep]
    description: str = ""


_HEADER = re.compile(r"^\s*\[\[\s*stage\s*\]\]")


def parse_pipeline(text: str, path: str = "<pipeline>", check: bool = True) -> Pipeline:
    """Parse pipeline TOML ``text``; with ``check``, verify stage and parameter names.

    Raises
    ------
    InputError
        Not valid TOML, or not of the pipeline form.
    ParameterError
        Unknown or unavailable stage, unknown parameter (message names file and line).
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    unknown_top = sorted(set(doc) - {"stage", "description"})
    if unknown_top:
        key = unknown_top[0]
        raise ParameterError(f"{path}:{_line_of_key(text, key, 0, None)}: unknown top-level key {key!r} (expected [[stage]] tables)")
    stages = doc.get("stage", [])
    if not isinstance(stages, list) or not stages or not all(isinstance(s, dict) for s in stages):
        raise InputError("no [[stage]] tables", path)
    lines = text.splitlines()
    headers = [i + 1 for i, ln in enumerate(lines) if _HEADER.match(ln)]
    steps = []
    for k, table in enumerate(stages):
        start = headers[k] if k < len(headers) else 1
        end = headers[k + 1] if k + 1 < len(headers) else None
        if "name" not in table:
            raise ParameterError(f"{path}:{start}: stage has no 'name'")
        name = table["name"]
        params = {}
        plines = {}
        for key, value in table.items():
            if key == "name":
                continue
            norm = key.replace("-", "_")
            params[norm] = value
            plines[norm] = _line_of_key(text, key, start, end)
        steps.append(PipelineStep(name=str(name), params=params, line=start, param_lines=plines))
    pipe = Pipeline(path=path, steps=steps, description=str(doc.get("description", "")))
    if check:
        check_pipeline(pipe)
    return pipe


def _line_of_key(text: str, key: str, start: int, end: int | None) -> int:
    pat = re.compile(r"^\s*[\"']?" + re.escape(key) + r"[\"']?\s*=")
    for i, ln in enumerate(text.splitlines(), start=1):
        if i < start or (end is not None and i >= end):
            continue
        if pat.match(ln):
            return i
    return start


def check_pipeline(pipe: Pipeline) -> None:
    """Verify that every stage exists and takes every parameter given."""
    for step in pipe.steps:
        try:
            get_stage(step.name)
        except ParameterError as exc:
            raise ParameterError(f"{pipe.path}:{step.line}: {exc}") from None
        known = stage_parameters(step.name)
        for key in step.params:
            if key not in known:
                raise ParameterError(
                    f"{pipe.path}:{step.param_lines.get(key, step.line)}: stage {step.name!r} has no parameter "
                    f"{key.replace('_', '-')!r} (parameters: {', '.join(k.replace('_', '-') for k in sorted(known))})"
                )


def load_pipeline(path: str | os.PathLike) -> Pipeline:
    """Read and check the pipeline file at ``path``."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise InputError("no such pipeline file", str(path)) from None
    except UnicodeDecodeError:
        raise InputError("pipeline file is not UTF-8 text", str(path)) from None
    return parse_pipeline(text, str(path))


def run_pipeline(pipe: Pipeline, data: Any, progress: Any = None) -> tuple[Any, list[dict]]:
    """Run every step of ``pipe`` on ``data``; return the final output and one report per step.

    Each report gains ``seconds`` (wall time of the step).
    """
    reports = []
    for step in pipe.steps:
        t0 = time.perf_counter()
        result: StageResult = apply_stage(step.name, data, step.params, progress=progress)
        rep = dict(result.report)
        rep["seconds"] = time.perf_counter() - t0
        reports.append(rep)
        data = result.output
    return data, reports
