"""Stage registry: the library side of every stage command and pipeline step.

A stage is declared by a :class:`~recon_cli.params.StageSpec` (its parameters, what it
takes and gives) whose ``run`` is the stage function ``run_stage(data, *, <params>,
progress=None) -> StageResult``. :data:`STAGES` maps a stage name to where that lives,
``"module:attribute"``; the attribute is the ``StageSpec`` (or, for small plugins and
tests, a bare stage function, whose keyword defaults are then its declaration).

Third-party packages add stages through the entry-point group ``recon.stages``
(``name = "package.module:SPEC"``), read once on first use, as rasterio's ``rio`` finds
its commands; :func:`register_stage` is the same registration for code that is already
imported (a test's toy stage). The modules are imported only when a stage is used, so
``recon --help`` stays instant.
"""

from __future__ import annotations

import importlib
import inspect
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from recon_cli import __version__
from recon_cli.errors import ParameterError
from recon_cli.params import KINDS, Param, StageSpec

ENTRY_POINT_GROUP = "recon.stages"

#: stage name -> ``"module:attribute"`` (a StageSpec, or a bare stage function)
STAGES: dict[str, str] = {
    "normals": "recon_cli.stages.normals:SPEC",
    "poisson": "recon_cli.stages.poisson:SPEC",
    "ballpivot": "recon_cli.stages.ballpivot:SPEC",
    "repair": "recon_cli.stages.repair:SPEC",
    "simplify": "recon_cli.stages.simplify:SPEC",
    "smooth": "recon_cli.stages.smooth:SPEC",
    "sdf": "recon_cli.stages.sdf:SPEC",
    "mcubes": "recon_cli.stages.mcubes:SPEC",
    "fit-sdf": "recon_cli.stages.learned:SPEC",
    "filter": "recon_cli.stages.filter:SPEC",
    "tiles": "recon_cli.stages.tiles:SPEC",
}
BUILTIN = tuple(STAGES)

# specs registered as objects (register_stage) and specs already loaded from their targets
_OBJECTS: dict[str, StageSpec] = {}
_LOADED: dict[str, tuple[str, StageSpec]] = {}
_entry_points_read = False

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


# ---- registration -------------------------------------------------------------------------------
def register_stage(spec: StageSpec | str, name: str | None = None) -> None:
    """Add a stage to this process's registry.

    Parameters
    ----------
    spec : StageSpec or str
        The declaration (its ``run`` set by :meth:`~recon_cli.params.StageSpec.runner`), or its
        ``"module:attribute"`` target (what an entry point names).
    name : str, optional
        Registered name (default: the spec's own).

    Raises
    ------
    ParameterError
        The name is a built-in stage's, or a target string is malformed.
    """
    if isinstance(spec, str):
        if name is None or spec.count(":") != 1:
            raise ParameterError(
                f"a stage target must be 'module:attribute' with a name, got {spec!r}"
            )
        if name in BUILTIN and STAGES.get(name) != spec:
            raise ParameterError(f"stage {name!r} is built in and cannot be replaced by {spec!r}")
        STAGES[name] = spec
        _LOADED.pop(name, None)
        return
    if not isinstance(spec, StageSpec):
        raise ParameterError(f"register_stage takes a StageSpec, got {type(spec).__name__}")
    name = name or spec.name
    if name in BUILTIN:
        raise ParameterError(f"stage {name!r} is built in and cannot be replaced")
    if spec.run is None:
        raise ParameterError(
            f"stage {name!r} has no implementation (decorate its run_stage with @SPEC.runner)"
        )
    _OBJECTS[name] = spec
    STAGES[name] = f"<registered>:{name}"
    _LOADED.pop(name, None)


def unregister_stage(name: str) -> None:
    """Remove a stage added by :func:`register_stage` (built-in stages stay)."""
    if name in BUILTIN:
        raise ParameterError(f"stage {name!r} is built in")
    STAGES.pop(name, None)
    _OBJECTS.pop(name, None)
    _LOADED.pop(name, None)


def _read_entry_points() -> None:
    global _entry_points_read
    if _entry_points_read:
        return
    _entry_points_read = True
    from importlib.metadata import entry_points

    try:
        eps = entry_points(group=ENTRY_POINT_GROUP)
    except Exception:  # pragma: no cover - a broken metadata directory must not stop recon
        return
    for ep in eps:
        if ep.name not in STAGES:
            STAGES[ep.name] = ep.value


def stage_names() -> list[str]:
    """Every registered stage, built-in ones first, then plugins in name order."""
    _read_entry_points()
    return [*BUILTIN, *sorted(n for n in STAGES if n not in BUILTIN)]


# ---- lookup -------------------------------------------------------------------------------------
def declaring_module(spec: StageSpec) -> Any:
    """The module that declares ``spec``: its registry target's, else its runner's (or None).

    A stage's runner may live in another module of its package (poisson's ``stage.py``); its
    docstring's References and its public functions are the declaring module's.
    """
    module = STAGES.get(spec.name, "").partition(":")[0]
    if not module or module.startswith("<"):  # registered in this process as an object
        module = getattr(spec.run, "__module__", "") or ""
    return sys.modules.get(module) if module else None


def get_spec(name: str) -> StageSpec:
    """The declaration of stage ``name``.

    Raises
    ------
    ParameterError
        Unknown stage, or a stage whose module cannot be imported.
    """
    if name not in STAGES:  # a plugin's name: entry points cannot shadow a known stage, so
        _read_entry_points()  # a known one needs no scan of the installed packages' metadata
    if name not in STAGES:
        raise ParameterError(f"unknown stage {name!r} (stages: {', '.join(stage_names())})")
    target = STAGES[name]
    if name in _OBJECTS:
        return _OBJECTS[name]
    cached = _LOADED.get(name)
    if cached is not None and cached[0] == target:
        return cached[1]
    module, _, attr = target.partition(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and module.startswith(exc.name):
            raise ParameterError(
                f"stage {name!r} is not available: no module {exc.name!r}"
            ) from None
        raise
    obj = getattr(mod, attr, None)
    if obj is None:
        raise ParameterError(f"stage {name!r} is not available: {module} has no {attr!r}")
    if isinstance(obj, StageSpec):
        if obj.run is None:
            raise ParameterError(f"stage {name!r} declares no implementation (@SPEC.runner)")
        spec = obj
    elif callable(obj):
        spec = spec_from_function(name, obj)
    else:
        raise ParameterError(f"stage {name!r}: {target} is neither a StageSpec nor a function")
    _LOADED[name] = (target, spec)
    return spec


def stage_summary(name: str) -> str:
    """The summary line of stage ``name``'s declaration, for ``recon --help``.

    A declaration whose module is not imported yet is read from its source (the
    ``summary`` literal of ``ATTR = StageSpec(...)``), so listing the commands imports
    neither numpy nor the stages; anything else imports the declaration. A plugin that
    cannot be loaded is listed as such, not an error of the help screen.
    """
    if name in _OBJECTS:
        return _OBJECTS[name].summary
    target = STAGES.get(name, "")
    module, _, attr = target.partition(":")
    if module not in sys.modules:
        text = _summary_literal(module, attr)
        if text is not None:
            return text
    try:
        return get_spec(name).summary
    except (ParameterError, ImportError):
        return "(stage from a plugin that cannot be loaded)"


def _summary_literal(module: str, attr: str) -> str | None:
    """The literal ``summary`` of ``attr = StageSpec(...)`` in ``module``'s source, else None."""
    import ast
    import importlib.util
    import io
    import re
    import tokenize

    try:
        found = importlib.util.find_spec(module)
        if found is None or not found.origin or not found.origin.endswith(".py"):
            return None
        with open(found.origin, encoding="utf-8") as f:
            src = f.read()
    except (ImportError, OSError, ValueError):
        return None
    m = re.search(rf"^{re.escape(attr)}\s*(?::[^=\n]*)?=\s*StageSpec\(", src, re.MULTILINE)
    if m is None:
        return None
    # the call ends at its closing parenthesis: tokens, so that brackets in strings do not count
    depth, end = 0, None
    lines = src[m.start() :]
    try:
        for tok in tokenize.generate_tokens(io.StringIO(lines).readline):
            if tok.type == tokenize.OP and tok.string in "([{":
                depth += 1
            elif tok.type == tokenize.OP and tok.string in ")]}":
                depth -= 1
                if depth == 0:
                    end = tok.end
                    break
        if end is None:
            return None
        call_lines = lines.splitlines(keepends=True)[: end[0]]
        call_lines[-1] = call_lines[-1][: end[1]]
        call = ast.parse("".join(call_lines)).body[0].value  # type: ignore[attr-defined]
        node = next((k.value for k in call.keywords if k.arg == "summary"), None)
        if node is None and len(call.args) > 1:
            node = call.args[1]
        value = None if node is None else ast.literal_eval(node)
    except (SyntaxError, ValueError, tokenize.TokenError, AttributeError, IndexError):
        return None
    return value if isinstance(value, str) else None


def get_stage(name: str) -> Callable[..., StageResult]:
    """The stage function called ``name`` (checks its parameters, then runs)."""
    run = get_spec(name).run
    assert run is not None
    return run


def stage_parameters(name: str) -> dict[str, Any]:
    """User parameter names of stage ``name`` and their defaults."""
    return get_spec(name).defaults()


def spec_from_function(name: str, fn: Callable[..., Any]) -> StageSpec:
    """A declaration for a bare stage function: its keyword defaults are the parameters.

    Types follow the defaults (bool, int, float; anything else is taken as given). Such a
    stage takes and gives any kind of data, so pipelines cannot check its neighbours.
    """
    params = []
    for k, p in inspect.signature(fn).parameters.items():
        if k in _INTERNAL or p.kind in (
            inspect.Parameter.VAR_KEYWORD,
            inspect.Parameter.VAR_POSITIONAL,
        ):
            continue
        if p.kind is inspect.Parameter.POSITIONAL_ONLY or (
            p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
            and p.default is inspect.Parameter.empty
        ):
            continue  # the data argument
        d = None if p.default is inspect.Parameter.empty else p.default
        t = (
            "bool"
            if isinstance(d, bool)
            else "int"
            if isinstance(d, int)
            else "float"
            if isinstance(d, float)
            else "any"
        )
        params.append(Param(k, t, d, f"{k} (undeclared stage parameter)"))
    spec = StageSpec(
        name=name,
        summary=(fn.__doc__ or name).strip().splitlines()[0],
        takes=tuple(KINDS),
        gives=tuple(KINDS),
        params=tuple(params),
        declared=False,
    )
    accepts = set(inspect.signature(fn).parameters)

    def run(data: Any, *, progress: Any = None, **values: Any) -> Any:
        checked = spec.check(values, complete=False)
        if "progress" in accepts:
            checked["progress"] = progress
        return fn(data, **checked)

    spec.run = run
    return spec


# ---- running ------------------------------------------------------------------------------------
def provenance_line(name: str, params: dict[str, Any]) -> str:
    """``recon <version> <stage> <parameters>`` as written in PLY comments."""
    parts = []
    for k in sorted(params):
        v = params[k]
        if v is None:
            continue
        if isinstance(v, (list, tuple)):  # "0,0,1" as written, not "0.0,0.0,1.0"
            v = ",".join(
                str(int(x)) if isinstance(x, float) and x.is_integer() else str(x) for x in v
            )
        parts.append(f"{k.replace('_', '-')}={v}")
    return " ".join(["recon", __version__, name, *parts]).replace("\n", " ")


def read_hint(name: str, params: dict[str, Any] | None = None) -> Any:
    """The part of its input file stage ``name`` keeps with ``params`` (a ReadHint), or None.

    From the stage's ``read_hint`` (:class:`~recon_cli.params.StageSpec`); the parameters are
    checked first.

    Raises
    ------
    ParameterError
        Unknown stage or parameter, a value of the wrong type or out of range, or parameters
        that exclude each other.
    """
    spec = get_spec(name)
    if spec.read_hint is None:
        return None
    checked = spec.check({k.replace("-", "_"): v for k, v in (params or {}).items()})
    mod, _, fn = spec.read_hint.partition(":")
    return getattr(importlib.import_module(mod), fn)(checked)


def apply_stage(
    name: str, data: Any, params: dict[str, Any] | None = None, progress: Any = None
) -> StageResult:
    """Run stage ``name`` on ``data`` with ``params`` and record its provenance.

    Raises
    ------
    ParameterError
        Unknown stage or parameter, or a value of the wrong type or out of range.
    InputError
        ``data`` is not a kind the stage takes.
    """
    spec = get_spec(name)
    params = {k.replace("-", "_"): v for k, v in (params or {}).items()}
    checked = spec.check(params, complete=False)  # names and values, before anything runs
    assert spec.run is not None
    predicted = predicted_memory(name, data, checked)
    from recon_cli.memory import reset_peak

    reset_peak()  # the stage's own peak, not an earlier stage's of the same process
    result = spec.run(data, progress=progress, **params)
    effective = {**spec.defaults(), **checked}
    extra = result.report.get("provenance") if isinstance(result.report, dict) else None
    if isinstance(extra, dict):
        effective.update(extra)
    history = getattr(result.output, "history", None)
    if history is not None:
        history.append(provenance_line(name, effective))
    result.report.setdefault("stage", name)
    if isinstance(result.report, dict):
        from recon_cli.stages.memory_model import entry

        result.report["memory"] = entry(predicted)
    from recon_cli.geometry import precision_note

    note = precision_note(
        result.output
    )  # float32 source, double output: say so (docs/formats.md, data model)
    if note:
        result.report["precision"] = note
    return result


def predicted_memory(name: str, data: Any, checked: dict[str, Any]) -> int | None:
    """The peak bytes stage ``name`` is predicted to take on ``data``; refused when over budget.

    The budget is the execution's in force (:func:`recon_cli.execution.current`); ``checked``:
    the parameters given, checked. None where the stage has no model
    (:mod:`recon_cli.stages.memory_model`).

    Raises
    ------
    ParameterError
        The prediction exceeds the budget (one line: the figure and the least ``--memory``).
    """
    from recon_cli.stages.memory_model import predict_in_force

    return predict_in_force(name, data, {**get_spec(name).defaults(), **checked})


def report_json(report: dict | list[dict]) -> str:
    """``report`` (or a list of them) as JSON, numpy scalars converted."""
    return json.dumps(report, default=_jsonable, indent=2, sort_keys=False)


def _jsonable(x: Any) -> Any:
    import numpy as np

    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)
