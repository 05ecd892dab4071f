"""Stage registry: the library side of every subcommand and pipeline step.

A stage is a function ``run_stage(data, *, <params>, progress=None) -> StageResult`` in
its algorithm module. Its keyword names are the CLI option names (``--knn`` -> ``knn``,
``--point-weight`` -> ``point_weight``), so a pipeline file uses the same names as the
command line. Stage functions accept the CLI's string forms too (``"0,0,1"`` for a
vector), so a pipeline value may be written either way.
"""

from __future__ import annotations

import importlib
import inspect
import json
from dataclasses import dataclass, field
from typing import Any, Callable

from recon_cli import __version__
from recon_cli.errors import ParameterError

# stage name -> "module:function"; a module that does not exist yet means "not built yet"
STAGES: dict[str, str] = {
    "normals": "recon_cli.normals:run_stage",
    "poisson": "recon_cli.poisson:run_stage",
    "ballpivot": "recon_cli.ballpivot:run_stage",
    "repair": "recon_cli.repair:run_stage",
    "sdf": "recon_cli.sdf:run_stage",
    "mcubes": "recon_cli.mcubes:run_stage",
    "fit-sdf": "recon_cli.learned:run_stage",
}

# parameters every stage function takes that are not user parameters
_INTERNAL = {"data", "progress"}


@dataclass
class StageResult:
    """What a stage returns.

    Attributes
    ----------
    output : PointCloud, TriangleMesh or Grid
        The result, with ``history`` already carrying the input's lines (the runner
        appends this stage's provenance line).
    report : dict
        JSON-serialisable figures for the one-screen report and ``--json``.
    """

    output: Any
    report: dict = field(default_factory=dict)


def get_stage(name: str) -> Callable[..., StageResult]:
    """The stage function called ``name``.

    Raises
    ------
    ParameterError
        Unknown stage name, or a stage whose module is not built yet.
    """
    if name not in STAGES:
        raise ParameterError(f"unknown stage {name!r} (stages: {', '.join(sorted(STAGES))})")
    module, func = STAGES[name].split(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            raise ParameterError(f"stage {name!r} is not available in this version of recon yet") from None
        raise
    fn = getattr(mod, func, None)
    if fn is None:
        raise ParameterError(f"stage {name!r} is not available in this version of recon yet")
    return fn


def stage_parameters(name: str) -> dict[str, Any]:
    """User parameter names of stage ``name`` and their defaults."""
    sig = inspect.signature(get_stage(name))
    return {
        k: (None if p.default is inspect.Parameter.empty else p.default)
        for k, p in sig.parameters.items()
        if k not in _INTERNAL and p.kind is not inspect.Parameter.VAR_KEYWORD
    }


def provenance_line(name: str, params: dict[str, Any]) -> str:
    """``recon <version> <stage> <parameters>`` as written in PLY comments."""
    parts = []
    for k in sorted(params):
        v = params[k]
        if v is None:
            continue
        if isinstance(v, (list, tuple)):
            v = ",".join(str(x) for x in v)
        parts.append(f"{k.replace('_', '-')}={v}")
    return " ".join(["recon", __version__, name, *parts]).replace("\n", " ")


def apply_stage(name: str, data: Any, params: dict[str, Any] | None = None, progress: Any = None) -> StageResult:
    """Run stage ``name`` on ``data`` with ``params`` and record its provenance.

    Raises
    ------
    ParameterError
        Unknown stage or parameter name.
    """
    params = dict(params or {})
    fn = get_stage(name)
    known = stage_parameters(name)
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ParameterError(
            f"stage {name!r} has no parameter {unknown[0]!r} (parameters: {', '.join(sorted(known))})"
        )
    kwargs = dict(params)
    if "progress" in inspect.signature(fn).parameters:
        kwargs["progress"] = progress
    result = fn(data, **kwargs)
    effective = {**known, **params}
    extra = result.report.get("provenance") if isinstance(result.report, dict) else None
    if isinstance(extra, dict):
        effective.update(extra)
    history = getattr(result.output, "history", None)
    if history is not None:
        history.append(provenance_line(name, effective))
    result.report.setdefault("stage", name)
    return result


def report_json(report: dict) -> str:
    """``report`` as JSON (numpy scalars converted)."""
    return json.dumps(report, default=_jsonable, indent=2, sort_keys=False)


def _jsonable(x: Any) -> Any:
    import numpy as np

    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)
