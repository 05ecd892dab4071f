"""Stage declarations: every stage's parameters, written once.

A stage package declares a :class:`StageSpec` (its ``SPEC``): the parameters with type,
default, range or choices, unit and help, and the kinds of data it takes and gives. From
that one declaration come

- the library's keyword defaults and checks (:meth:`StageSpec.runner` wraps ``run_stage``),
- the click options of the stage's command (``recon_cli.cli.options.stage_command``),
- the checks of a pipeline file before anything runs (:mod:`recon_cli.pipeline`),
- ``recon run --set STAGE.PARAM=VALUE`` and
- the parameter tables of the user guide's stage pages (:meth:`StageSpec.table_rows`, written
  by ``recon_cli.tools.docs`` at every build of the documentation) and
- the library's stage functions (``recon_cli.poisson(...)``, :mod:`recon_cli.api`).

Values are checked one way everywhere (:meth:`Param.coerce`). Typed values (TOML, Python)
must have the declared type — ``depth = true`` is an error, not depth 1 — and text (the
command line, ``--set``) is parsed by the same rules. Booleans written as text are
``true/false``, ``yes/no``, ``on/off`` or ``1/0``, nothing else.

This module imports nothing heavy: ``recon --help`` and ``recon run --validate`` use it.
"""

from __future__ import annotations

import functools
import inspect
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from recon_cli.errors import ParameterError

# ---- kinds of data -------------------------------------------------------------------------------
#: what a stage may take or give; a cloud with normals is both ``cloud`` and ``oriented``,
#: a mesh with vertex normals both ``mesh`` and ``oriented``
KINDS: dict[str, str] = {
    "cloud": "a point cloud",
    "oriented": "points with normals",
    "mesh": "a triangle mesh",
    "grid": "a grid (.npz)",
    "tileset": "a 3D Tiles tileset (a folder)",
}


def kinds_of(obj: Any) -> frozenset[str]:
    """The kinds of a loaded object: ``{"cloud", "oriented"}`` for a cloud with normals, etc."""
    from recon_cli.geometry import PointCloud, TriangleMesh
    from recon_cli.grid import Grid
    from recon_cli.io.tiles import Tileset

    if isinstance(obj, Grid):
        return frozenset({"grid"})
    if isinstance(obj, Tileset):
        return frozenset({"tileset"})
    if isinstance(obj, TriangleMesh):
        return frozenset({"mesh", "oriented"} if obj.normals is not None else {"mesh"})
    if isinstance(obj, PointCloud):
        return frozenset({"cloud", "oriented"} if obj.normals is not None else {"cloud"})
    return frozenset()


def describe_kinds(kinds: Sequence[str]) -> str:
    """``("cloud", "mesh")`` -> ``"a point cloud or a triangle mesh"``."""
    names = [KINDS.get(k, k) for k in kinds]
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " or " + names[-1]


# ---- text forms ----------------------------------------------------------------------------------
_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")
_INT = re.compile(r"[+-]?\d+")


def parse_bool(text: str) -> bool:
    """The one boolean parser: true/yes/on/1 and false/no/off/0 (any case).

    Anything else is an error.
    """
    s = text.strip().lower()
    if s in _TRUE:
        return True
    if s in _FALSE:
        return False
    raise ValueError(f"expected true or false, got {text!r}")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) or _is_numpy_number(x)


def _is_numpy_number(x: Any) -> bool:
    t = type(x)
    return t.__module__ == "numpy" and t.__name__.startswith(("float", "int", "uint"))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (tuple, list)):
        return ",".join(_fmt(x) for x in v)
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


# ---- one parameter -------------------------------------------------------------------------------
TYPES = ("int", "float", "bool", "choice", "vector", "floats", "any")


@dataclass(frozen=True)
class Param:
    """One declared parameter of a stage.

    Parameters
    ----------
    name : str
        Python name (``point_weight``); the option is ``--point-weight``.
    type : {"int", "float", "bool", "choice", "vector", "floats"}
        ``vector``: three numbers (``"x,y,z"`` or a list); ``floats``: one or more numbers.
    default
        Value when not given; ``None`` means "not set" (the stage decides, e.g. automatic).
    help : str
        One sentence for ``--help`` and the stage's page.
    unit : str
        What the number is measured in ("input units", "fraction of the diagonal", "voxels", ...).
    min, max : float, optional
        Range, inclusive unless ``min_open`` / ``max_open``.
    choices : tuple of str
        For ``choice``.
    words : mapping
        Words accepted in place of a value, and the value each stands for
        (``{"auto": "auto"}``, ``{"exact": None}``); matched case-insensitively.
    special : mapping
        Values with a meaning of their own, for the help text (``{0: "radius only"}``).
    metavar : str, optional
        Shown in ``--help`` (``X,Y,Z``).
    also : tuple
        Values allowed outside the range (``knn``: ``0`` = radius only, else ``>= 3``).
    validate : callable, optional
        Run on the value once its type is checked (not on None): returns it, maybe converted,
        or raises ValueError with the expected values (``six numbers ... with x0 <= x1``), so
        a rule between the numbers of one value is checked wherever the type is.
    allowed : str
        The allowed values in words, for ``--help`` and the stage's page, where a range cannot
        say them (a ``validate`` rule: ``x0 <= x1, y0 <= y1, z0 <= z1``).
    """

    name: str
    type: str
    default: Any
    help: str
    unit: str = ""
    min: float | None = None
    max: float | None = None
    min_open: bool = False
    max_open: bool = False
    choices: tuple[str, ...] = ()
    words: Mapping[str, Any] = field(default_factory=dict)
    special: Mapping[Any, str] = field(default_factory=dict)
    metavar: str | None = None
    also: tuple = ()
    validate: Callable[[Any], Any] | None = field(default=None, compare=False, repr=False)
    allowed: str = ""

    def __post_init__(self) -> None:
        if self.type not in TYPES:
            raise ValueError(f"parameter {self.name!r}: unknown type {self.type!r}")
        if self.type == "choice" and not self.choices:
            raise ValueError(f"parameter {self.name!r}: a choice needs choices")

    # -- names
    @property
    def option(self) -> str:
        """The command-line option: ``--point-weight``."""
        return "--" + self.name.replace("_", "-")

    @property
    def dashed(self) -> str:
        """The name with dashes: ``point-weight``."""
        return self.name.replace("_", "-")

    # -- description
    def range_text(self) -> str:
        """``"0 <= x <= 1"``-like text of the allowed values ("" when unrestricted)."""
        if self.type == "choice":
            return " | ".join(self.choices)
        if self.allowed:
            return self.allowed
        lo = None if self.min is None else f"{_fmt(self.min)} {'<' if self.min_open else '<='} "
        hi = None if self.max is None else f" {'<' if self.max_open else '<='} {_fmt(self.max)}"
        if lo is None and hi is None:
            return ""
        extra = "".join(f"{_fmt(a)} or " for a in self.also)
        return f"{extra}{lo or ''}x{hi or ''}"

    def default_text(self) -> str:
        """The default as the help and the tables write it ("not set" or the word for None)."""
        if self.default is None:
            word = next((w for w, v in self.words.items() if v is None), None)
            return word or "not set"
        return _fmt(self.default)

    # -- checking
    def coerce(self, value: Any, text_ok: bool = True) -> Any:
        """``value`` checked and converted to the declared type.

        Parameters
        ----------
        value
            A typed value (from TOML or Python) or, with ``text_ok``, its text form.
        text_ok : bool
            Accept strings for numbers and booleans (command line, ``--set``, library
            calls). Pipeline files pass False: there ``depth = "8"`` is a type error.

        Raises
        ------
        ParameterError
            One line naming the option, the expected values and what was given.
        """
        v = self._coerce(value, text_ok)
        if v is None or self.validate is None or v in self.words.values():
            return v
        try:
            return self.validate(v)
        except ValueError as exc:
            raise self._error(str(exc), value) from None

    def _coerce(self, value: Any, text_ok: bool) -> Any:
        """``value`` as the declared type: a word, None, or by type (range checked)."""
        if isinstance(value, str) and value.strip().lower() in self.words:
            return self.words[value.strip().lower()]
        if value is None:
            return self._missing(value)
        t = self.type
        if t == "any":
            return value
        if t == "bool":
            return self._as_bool(value, text_ok)
        if t == "choice":
            if isinstance(value, str) and value.strip().lower() in self.choices:
                return value.strip().lower()
            raise self._error("one of " + ", ".join(self.choices), value)
        if t == "int":
            return self._in_range(self._as_int(value, text_ok), value, "an integer")
        if t == "float":
            v = self._number(value, text_ok)
            return self._in_range(v, value, "a number")
        return self._as_numbers(value)

    def _missing(self, value: None) -> None:
        """None where the parameter may be unset; else the error saying what it takes."""
        if self.default is None or None in self.words.values():
            return None
        word = {"int": "an integer", "float": "a number", "bool": "true or false"}.get(
            self.type, "a value"
        )
        raise self._error(self._expect(word) if self.type in ("int", "float") else word, value)

    def _as_bool(self, value: Any, text_ok: bool) -> bool:
        if isinstance(value, bool) or (
            type(value).__module__ == "numpy" and "bool" in type(value).__name__
        ):
            return bool(value)
        if isinstance(value, str) and text_ok:
            try:
                return parse_bool(value)
            except ValueError:
                pass
        raise self._error("true or false", value, typed=not text_ok)

    def _as_int(self, value: Any, text_ok: bool) -> int:
        if isinstance(value, str) and text_ok and _INT.fullmatch(value.strip()):
            return int(value.strip())
        if (
            _is_number(value)
            and not isinstance(value, float)
            and "float" not in type(value).__name__
        ):
            return int(value)
        raise self._error(self._expect("an integer"), value, typed=not text_ok)

    def _as_numbers(self, value: Any) -> tuple[float, ...]:
        """A vector or floats parameter: a list or its comma-separated text."""
        t = self.type
        if isinstance(value, str):
            parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
        elif isinstance(value, (list, tuple)) or type(value).__name__ == "ndarray":
            parts = list(value)
        elif t == "floats" and _is_number(value):
            parts = [value]
        else:
            parts = None
        what = "three numbers X,Y,Z" if t == "vector" else self._expect("numbers a,b,...")
        if parts is None or (t == "vector" and len(parts) != 3) or not parts:
            raise self._error(what, value)
        try:
            nums = tuple(self._number(p, True) for p in parts)
        except ParameterError:
            raise self._error(what, value) from None
        for x in nums:
            self._in_range(x, value, "numbers")
        return nums

    def _number(self, value: Any, text_ok: bool) -> float:
        if isinstance(value, str) and text_ok:
            try:
                v = float(value.strip())
            except ValueError:
                raise self._error(self._expect("a number"), value) from None
        elif _is_number(value):
            v = float(value)
        else:
            raise self._error(self._expect("a number"), value, typed=not text_ok)
        if not math.isfinite(v):
            raise self._error(self._expect("a finite number"), value)
        return v

    def _in_range(self, v: float, given: Any, what: str) -> Any:
        if v in self.also:
            return v
        bad = (self.min is not None and (v < self.min or (self.min_open and v == self.min))) or (
            self.max is not None and (v > self.max or (self.max_open and v == self.max))
        )
        if bad:
            raise self._error(self._expect(what), given)
        return v

    def _expect(self, what: str) -> str:
        r = self.range_text()
        return f"{what} with {r}" if r else what

    def _error(self, expected: str, value: Any, typed: bool = False) -> ParameterError:
        words = "".join(f" or '{w}'" for w in self.words)
        if isinstance(value, bool):
            got = f"{str(value).lower()} (a boolean)"
        elif typed and isinstance(value, str):
            got = f"{value!r} (a string)"
        else:
            got = repr(value)
        return ParameterError(f"{self.option} must be {expected}{words}, got {got}")


# ---- one stage -----------------------------------------------------------------------------------
@dataclass
class StageSpec:
    """The declaration of a stage: what it takes, gives, and every parameter.

    Parameters
    ----------
    name : str
        Stage and command name (``poisson``).
    summary : str
        One line for ``recon --help``.
    description : str
        The command's help text (first line = summary if empty).
    takes : tuple of str
        Kinds of input accepted (:data:`KINDS`); the input must have at least one of them.
    gives : tuple of str
        Kinds of the output.
    params : tuple of Param
        The user parameters, in the order of ``--help``.
    backends : tuple of str
        ``native`` first; a ``backend`` choice parameter is added when there are others.
    takes_when : callable, optional
        ``f(params) -> kinds`` when the accepted input depends on a parameter
        (``poisson --estimate-normals`` takes clouds without normals).
    output_suffix : str
        What OUT is, for ``--help`` (``.ply``, ``.npz``).
    declared : bool
        False for a bare function registered as a stage (its kinds are unknown).
    keeps : tuple of str
        Kinds the output has when the input has them (``filter`` keeps normals: an oriented
        cloud in, an oriented cloud out); pipelines check the next stage with them.
    keeps_partial : bool
        The stage catches Ctrl-C itself and returns its best result so far (``fit-sdf``): the
        command then lets the interrupt reach it instead of ending the process at once.
    from_files : str, optional
        ``"module:function"`` that runs the command from IN's path, never loading it in the
        command's process, when the parameters call for it (``poisson --workers``):
        ``f(input, output, params, *, save_kw, ascii, progress)`` writes OUT and returns the
        report, or returns None (the command then loads IN and runs the stage).
    execution : tuple of str
        The options of :class:`recon_cli.execution.Execution` the stage honours (``workers``,
        ``scheduler``, ``partitions``, ``memory``, ``temp_dir``): its command takes them
        (declared once in :data:`recon_cli.execution.PARAMS`) and runs the stage in
        :func:`recon_cli.execution.run_on` them.
    read_hint : str, optional
        ``"module:function"`` giving, from the checked parameters, the part of its input
        file the stage keeps (``f(params) -> ReadHint | None``, :mod:`recon_cli.io.hint`):
        the command, a pipeline that starts with the stage and the library function given a
        file name read only that where the format can (``filter --crop`` of a COPC file).
    """

    name: str
    summary: str
    takes: tuple[str, ...]
    gives: tuple[str, ...]
    params: tuple[Param, ...] = ()
    description: str = ""
    backends: tuple[str, ...] = ("native",)
    takes_when: Callable[[dict], tuple[str, ...]] | None = None
    output_suffix: str = ".ply"
    declared: bool = True
    keeps: tuple[str, ...] = ()
    keeps_partial: bool = False
    from_files: str | None = None
    execution: tuple[str, ...] = ()
    read_hint: str | None = None
    run: Callable[..., Any] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        for k in (*self.takes, *self.gives, *self.keeps):
            if k not in KINDS:
                raise ValueError(f"stage {self.name!r}: unknown kind {k!r}")
        if len(self.backends) > 1 and "backend" not in {p.name for p in self.params}:
            self.params = (
                *self.params,
                Param(
                    "backend",
                    "choice",
                    "native",
                    "Implementation: ours (native) or a reference library "
                    "(needs recon[reference]).",
                    choices=self.backends,
                ),
            )
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError(f"stage {self.name!r}: a parameter is declared twice")
        self._by_name = {p.name: p for p in self.params}

    # -- parameters
    def param(self, name: str) -> Param:
        """The parameter ``name`` (``point_weight`` or ``point-weight``)."""
        key = name.replace("-", "_")
        if key not in self._by_name:
            known = ", ".join(p.dashed for p in self.params) or "none"
            raise ParameterError(
                f"stage {self.name!r} has no parameter {name.replace('_', '-')!r} "
                f"(parameters: {known})"
            )
        return self._by_name[key]

    def defaults(self) -> dict[str, Any]:
        """Every parameter's default, by name."""
        return {p.name: p.default for p in self.params}

    def check(
        self, values: Mapping[str, Any], text_ok: bool = True, complete: bool = True
    ) -> dict[str, Any]:
        """``values`` checked (names, types, ranges) and, with ``complete``, the defaults added."""
        out = self.defaults() if complete else {}
        for k, v in values.items():
            p = self.param(k)
            out[p.name] = p.coerce(v, text_ok=text_ok)
        return out

    def input_kinds(self, values: Mapping[str, Any] | None = None) -> tuple[str, ...]:
        """The kinds of input the stage takes with these parameter ``values``."""
        if self.takes_when is not None:
            return tuple(self.takes_when({**self.defaults(), **dict(values or {})}))
        return self.takes

    def output_kinds(self, given: frozenset[str] | None) -> frozenset[str]:
        """Kinds of the output for an input of kinds ``given``.

        ``given`` None means not known: every kept kind is then possible, and the next stage
        is checked when it runs.
        """
        kept = set(self.keeps) if given is None else given & set(self.keeps)
        return frozenset(self.gives) | kept

    def check_input(self, data: Any, values: Mapping[str, Any] | None = None) -> None:
        """Raise :class:`~recon_cli.errors.InputError` unless this stage takes ``data``'s kind."""
        from recon_cli.errors import InputError

        want = self.input_kinds(values)
        have = kinds_of(data)
        if not have & set(want):
            hint = ""
            if "oriented" in want and "oriented" not in have and have & {"cloud", "mesh"}:
                alt = ", or pass --estimate-normals" if "estimate_normals" in self._by_name else ""
                hint = f" (run 'recon normals' first{alt})"
            raise InputError(
                f"{self.name} needs {describe_kinds(want)}, got {describe_data(have)}{hint}"
            )

    # -- the implementation
    def runner(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """Decorate ``run_stage(data, *, <every parameter>, progress=None)``.

        The returned function takes every parameter as an optional keyword with the
        declared default, checks the given ones (:meth:`check`) and the input's kind, and
        calls ``fn`` with all of them. ``fn`` declares no defaults of its own; its keyword
        names must be exactly the declared ones, or some of them and ``**rest`` that takes the
        others (a stage that hands a group of them on to a library function; checked here).
        """
        sig = inspect.signature(fn)
        declared = [p.name for p in self.params]
        own = [
            k
            for k, p in sig.parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY and k != "progress"
        ]
        rest = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values())
        named_ok = set(own) <= set(declared) if rest else sorted(own) == sorted(declared)
        if not named_ok:
            raise TypeError(
                f"{fn.__qualname__}: keywords {own} differ from the declaration of "
                f"{self.name!r}: {declared}"
            )

        @functools.wraps(fn)
        def run(data: Any, *, progress: Any = None, **values: Any) -> Any:
            checked = self.check(values)
            self.check_input(data, checked)
            return fn(data, progress=progress, **checked)

        data_param = next(iter(sig.parameters.values()))
        run.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
            [data_param]
            + [
                inspect.Parameter(p.name, inspect.Parameter.KEYWORD_ONLY, default=p.default)
                for p in self.params
            ]
            + [inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY, default=None)],
            return_annotation=sig.return_annotation,
        )
        run.spec = self  # type: ignore[attr-defined]
        self.run = run
        return run

    # -- documentation
    #: the columns of :meth:`table_rows`
    TABLE_COLUMNS = ("option", "type", "default", "allowed", "unit", "meaning")

    def table_rows(self, code: Callable[[str], str] = str) -> list[tuple[str, ...]]:
        """The parameter table of this stage: a row of :data:`TABLE_COLUMNS` per parameter.

        Parameters
        ----------
        code : callable
            Marks up a literal (an option, a value, a word), e.g. as inline code.

        Returns
        -------
        list of tuple of str
            Option, type, default, allowed values ("any" when unrestricted), unit ("–" when
            none) and meaning (the help, then the values with a meaning of their own).
        """
        rows: list[tuple[str, ...]] = []
        for p in self.params:
            allowed = f"{p.option} / --no-{p.dashed}" if p.type == "bool" else p.range_text()
            extra = [f"{code(_fmt(k))}: {v}" for k, v in p.special.items()]
            extra += [code(w) for w in p.words if p.words[w] is not None or p.default is not None]
            meaning = p.help + ("" if not extra else " (" + "; ".join(extra) + ")")
            rows.append(
                (
                    code(p.option),
                    p.type,
                    code(p.default_text()),
                    allowed or "any",
                    p.unit or "–",
                    meaning,
                )
            )
        return rows


def describe_data(have: frozenset[str] | set[str]) -> str:
    """What data of these kinds is, in words: ``{"cloud", "oriented"}`` -> a cloud with normals."""
    if "grid" in have:
        return "a grid"
    if "tileset" in have:
        return "a 3D Tiles tileset (a folder: no stage takes it)"
    if "mesh" in have:
        return "a triangle mesh"
    if "cloud" in have:
        return (
            "a point cloud with normals" if "oriented" in have else "a point cloud without normals"
        )
    return "nothing usable"
