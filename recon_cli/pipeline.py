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
``point_weight``). The whole file is checked before anything runs (:func:`check_pipeline`),
each error naming the file and line: an unknown stage or parameter, a value of the wrong
type (``depth = true``, ``depth = "8"``) or out of range, and stages that do not fit
together (``normals`` then ``mcubes``: a grid is needed, a point cloud is given). Values
are checked by each stage's declaration (:mod:`recon_cli.params`), the same rules as on
the command line, where text is parsed (``--set 2.depth=9``).
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
from recon_cli.params import describe_data, describe_kinds
from recon_cli.stages import StageResult, apply_stage, get_spec, read_hint


@dataclass
class PipelineStep:
    """One stage of a pipeline with its parameters and the line it starts at."""

    name: str
    params: dict[str, Any]
    line: int
    param_lines: dict[str, int] = field(default_factory=dict)
    # parameters given as text (``--set``, name -> the override): parsed as on the command line
    text_params: dict[str, str] = field(default_factory=dict)


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
        raise ParameterError(
            f"{path}:{_line_of_key(text, key, 0, None)}: unknown top-level key {key!r} "
            "(expected [[stage]] tables)"
        )
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
            if norm in params:
                raise ParameterError(
                    f"{path}:{_line_of_key(text, key, start, end)}: "
                    f"parameter {key!r} is given twice"
                )
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


def check_pipeline(pipe: Pipeline, input_kinds: frozenset[str] | None = None) -> None:
    """Check every stage, parameter and value, and that each stage takes what the last gives.

    Values are replaced by their checked, typed form. ``input_kinds`` (from
    :func:`recon_cli.params.kinds_of`) also checks the first stage against the input.

    Raises
    ------
    ParameterError
        The first problem, as ``FILE:LINE: ...``.
    """
    given = input_kinds
    source = "the input"
    for i, step in enumerate(pipe.steps, start=1):
        where = f"{pipe.path}:{step.line}"
        try:
            spec = get_spec(step.name)
        except ParameterError as exc:
            raise ParameterError(f"{where}: {exc}") from None
        for key in list(step.params):
            line = step.param_lines.get(key, step.line)
            at = (
                f"--set {step.text_params[key]}"
                if key in step.text_params
                else f"{pipe.path}:{line}"
            )
            if key not in spec.defaults():
                known = ", ".join(p.dashed for p in spec.params) or "none"
                raise ParameterError(
                    f"{at}: stage {i} ({step.name}) has no parameter {key.replace('_', '-')!r} "
                    f"(parameters: {known})"
                )
            try:
                p = spec.param(key)
                value = p.coerce(step.params[key], text_ok=key in step.text_params)
            except ParameterError as exc:
                raise ParameterError(f"{at}: stage {i} ({step.name}): {exc}") from None
            del step.params[key]
            step.params[p.name] = value
            step.param_lines[p.name] = line
            if key in step.text_params:
                step.text_params[p.name] = step.text_params.pop(key)
        _check_read_hint(pipe, i, step)
        if spec.declared and given is not None:
            want = spec.input_kinds(step.params)
            if not given & set(want):
                raise ParameterError(
                    f"{where}: stage {i} ({step.name}) needs {describe_kinds(want)}, "
                    f"but {source} gives "
                    f"{describe_data(given)}"
                )
        given = spec.output_kinds(given) if spec.declared else None
        source = f"stage {i} ({step.name})"


def _check_read_hint(pipe: Pipeline, i: int, step: PipelineStep) -> None:
    """The read options of step ``i`` agree, and only the first stage chooses octree levels."""
    try:
        hint = read_hint(step.name, step.params)
    except ParameterError as exc:
        raise ParameterError(f"{pipe.path}:{step.line}: stage {i} ({step.name}): {exc}") from None
    if i > 1 and hint is not None and hint.wants_levels:
        raise ParameterError(
            f"{pipe.path}:{step.line}: stage {i} ({step.name}): --level and --resolution choose "
            "the octree levels of a COPC file as it is read: only the first stage reads it"
        )


def input_hint(pipe: Pipeline) -> Any:
    """What the pipeline's first stage keeps of IN (a ReadHint for the loader), or None."""
    return read_hint(pipe.steps[0].name, pipe.steps[0].params) if pipe.steps else None


def apply_overrides(pipe: Pipeline, overrides: list[str] | tuple[str, ...]) -> None:
    """Apply ``--set STAGE.PARAM=VALUE`` overrides (``STAGE`` a name or a 1-based index).

    A name must be unambiguous (``--set 2.depth=9`` when two stages share a name). Values
    are text, parsed as on the command line when the pipeline is checked.

    Raises
    ------
    ParameterError
        Malformed override, unknown or ambiguous stage.
    """
    for item in overrides:
        m = re.fullmatch(r"\s*([A-Za-z0-9_-]+)\.([A-Za-z0-9_-]+)\s*=(.*)", item, re.S)
        if not m:
            raise ParameterError(
                f"--set {item!r}: expected STAGE.PARAM=VALUE (e.g. poisson.depth=9 or 2.depth=9)"
            )
        stage, key, value = m.group(1), m.group(2).replace("-", "_"), m.group(3).strip()
        if stage.isdigit():
            k = int(stage)
            if not 1 <= k <= len(pipe.steps):
                raise ParameterError(
                    f"--set {item!r}: the pipeline has stages 1..{len(pipe.steps)}"
                )
            step = pipe.steps[k - 1]
        else:
            matches = [s for s in pipe.steps if s.name == stage]
            if not matches:
                names = ", ".join(s.name for s in pipe.steps)
                raise ParameterError(
                    f"--set {item!r}: no stage {stage!r} in {pipe.path} (stages: {names})"
                )
            if len(matches) > 1:
                raise ParameterError(
                    f"--set {item!r}: {len(matches)} stages are called {stage!r}; use its number"
                )
            step = matches[0]
        step.params[key] = value
        step.text_params[key] = item


def load_pipeline(
    path: str | os.PathLike, overrides: list[str] | tuple[str, ...] = (), check: bool = True
) -> Pipeline:
    """Read the pipeline file at ``path``, apply ``--set`` overrides, and check it."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise InputError("no such pipeline file", str(path)) from None
    except UnicodeDecodeError:
        raise InputError("pipeline file is not UTF-8 text", str(path)) from None
    pipe = parse_pipeline(text, str(path), check=False)
    apply_overrides(pipe, overrides)
    if check:
        check_pipeline(pipe)
    return pipe


def check_input(pipe: Pipeline, data: Any, input_path: str) -> None:
    """Check that the first stage takes ``data`` (read from ``input_path``)."""
    if not pipe.steps:
        return
    try:
        get_spec(pipe.steps[0].name).check_input(data, pipe.steps[0].params)
    except InputError as exc:
        raise InputError(f"{exc} (stage 1 of {pipe.path})", input_path) from None


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
