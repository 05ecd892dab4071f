"""The library: one function per stage, made from its declaration, and ``read``/``write``.

``recon_cli.normals(cloud, knn=30, ...)``, ``recon_cli.poisson(...)``, ... exist for every
registered stage (built-in or from a plugin; ``fit-sdf`` is ``fit_sdf``): each is made here
from the stage's :class:`~recon_cli.params.StageSpec` when first used, with the real
signature (the declared parameters as keywords, their defaults and types) and a numpydoc
docstring (each parameter's type, default, range and unit; the References of the stage's
module). A call checks the parameters as the command line does (the same one-line
:class:`~recon_cli.errors.ParameterError`), converts the input, runs the stage through
:func:`recon_cli.stages.apply_stage` (so the result's ``history`` records it) and returns
recon's own object with the stage's report as its ``report`` attribute.

Inputs: recon's :class:`~recon_cli.geometry.PointCloud`, :class:`~recon_cli.geometry.TriangleMesh`
and :class:`~recon_cli.grid.Grid`; an (n, 3) array of points (with ``normals=`` an (n, 3)
array of normals); a ``(vertices, faces)`` pair; a 3-d array of grid values (unit spacing,
origin 0); Open3D and trimesh point clouds and meshes (converted by
:func:`recon_cli.geometry.geometry_from`; Open3D and trimesh are imported only for their own
objects); a file name (read by :func:`~recon_cli.api.read`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import os
import re
import textwrap
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Literal

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, geometry_from
from recon_cli.grid import Grid
from recon_cli.io.tiles import Tileset
from recon_cli.params import Param, StageSpec, describe_kinds
from recon_cli.progress import Progress
from recon_cli.stages import apply_stage, declaring_module, get_spec, read_hint, stage_names

# names the annotations' source text uses (runtime and the generated stub alike)
_NAMESPACE = {
    "Any": Any,
    "Literal": Literal,
    "Sequence": Sequence,
    "np": np,
    "os": os,
    "PointCloud": PointCloud,
    "TriangleMesh": TriangleMesh,
    "Grid": Grid,
    "Tileset": Tileset,
    "Progress": Progress,
}
_RETURNS = {
    "cloud": "PointCloud",
    "oriented": "PointCloud",
    "mesh": "TriangleMesh",
    "grid": "Grid",
    "tileset": "Tileset",
}
_DATA_NAMES = {"cloud": "cloud", "oriented": "cloud", "mesh": "mesh", "grid": "grid"}
_OPTION = re.compile(r"--([a-z][a-z0-9]*(?:-[a-z0-9]+)*)")


# ---- names ---------------------------------------------------------------------------------------
def function_name(stage: str) -> str:
    """The Python name of stage ``stage``'s function: ``fit-sdf`` -> ``fit_sdf``."""
    return stage.replace("-", "_")


def function_names() -> list[str]:
    """The names of every registered stage's function (those :mod:`recon_cli` offers)."""
    taken = _taken_names()
    return [function_name(s) for s in stage_names() if function_name(s) not in taken]


@functools.lru_cache(maxsize=1)
def _taken_names() -> frozenset[str]:
    """Names of recon_cli's modules: a plugin stage called like one gets no top-level function."""
    import pkgutil

    import recon_cli

    return frozenset(m.name for m in pkgutil.iter_modules(recon_cli.__path__))


def function_named(name: str) -> Callable[..., Any] | None:
    """The function of the stage whose Python name is ``name`` (None if there is none)."""
    if name in _taken_names():
        return None
    for stage in stage_names():
        if function_name(stage) == name:
            return stage_function(stage)
    return None


# ---- the declaration as Python -------------------------------------------------------------------
def annotation_source(p: Param) -> str:
    """The type annotation of parameter ``p``, as source text (``"int"``, ``"float | None"``)."""
    base = {
        "int": "int",
        "float": "float",
        "bool": "bool",
        "vector": "tuple[float, float, float]",
        "floats": "Sequence[float]",
        "any": "Any",
    }.get(p.type)
    if base is None:  # a choice
        base = "Literal[" + ", ".join(f'"{c}"' for c in p.choices) + "]"
    parts = [base]
    words = [w for w in p.words if not (p.type == "choice" and w in p.choices)]
    if words and p.type != "any":
        parts.append("Literal[" + ", ".join(f'"{w}"' for w in words) + "]")
    if p.default is None and p.type != "any":
        parts.append("None")
    return " | ".join(parts)


def _data_kinds(spec: StageSpec) -> tuple[str, ...]:
    return spec.takes if spec.declared and spec.takes else ("cloud", "mesh", "grid")


def data_name(spec: StageSpec) -> str:
    """The name of the function's first argument.

    ``cloud``, ``mesh``, ``grid`` (by the first kind the stage takes) or ``data`` (an undeclared
    stage, or a parameter of that name).
    """
    name = _DATA_NAMES.get(spec.takes[0], "data") if spec.declared and spec.takes else "data"
    return "data" if name in {p.name for p in spec.params} else name


def takes_normals(spec: StageSpec) -> bool:
    """Whether the function has ``normals=``.

    It takes point clouds, and no parameter is so named.
    """
    return bool({"cloud", "oriented"} & set(_data_kinds(spec))) and not any(
        p.name == "normals" for p in spec.params
    )


def return_source(spec: StageSpec) -> str:
    """The return annotation's source text."""
    if not spec.declared or not spec.gives:
        return "PointCloud | TriangleMesh | Grid"
    return _RETURNS[spec.gives[0]]


def signature_parts(spec: StageSpec) -> list[tuple[str, Any, str, Any]]:
    """``(name, kind, annotation source, default)`` of every argument of the stage's function."""
    kw = inspect.Parameter.KEYWORD_ONLY
    parts: list[tuple[str, Any, str, Any]] = [
        (data_name(spec), inspect.Parameter.POSITIONAL_OR_KEYWORD, "Any", inspect.Parameter.empty)
    ]
    if takes_normals(spec):
        parts.append(("normals", kw, "np.ndarray | None", None))
    parts += [(p.name, kw, annotation_source(p), p.default) for p in spec.params]
    parts.append(("progress", kw, "Progress | bool | None", None))
    return parts


def signature(spec: StageSpec) -> inspect.Signature:
    """The real signature of the stage's function (annotations evaluated)."""
    params = [
        inspect.Parameter(name, kind, default=default, annotation=eval(src, _NAMESPACE))
        for name, kind, src, default in signature_parts(spec)
    ]
    return inspect.Signature(params, return_annotation=eval(return_source(spec), _NAMESPACE))


def _python_text(text: str, spec: StageSpec) -> str:
    """``--point-weight`` -> ``point_weight`` where the option is one of the declared parameters."""
    names = {p.dashed for p in spec.params}

    def sub(m: re.Match) -> str:
        return f"``{m.group(1).replace('-', '_')}``" if m.group(1) in names else m.group(0)

    return _OPTION.sub(sub, text)


def _type_text(p: Param) -> str:
    base = {
        "int": "int",
        "float": "float",
        "bool": "bool",
        "vector": "(3,) sequence of float",
        "floats": "sequence of float",
        "any": "object",
    }.get(p.type) or "{" + ", ".join(f'"{c}"' for c in p.choices) + "}"
    words = [f'"{w}"' for w in p.words if not (p.type == "choice" and w in p.choices)]
    extra = words + (["None"] if p.default is None and p.type != "any" else [])
    return " or ".join([base, *extra]) + f", default {p.default!r}"


def _param_doc(p: Param, spec: StageSpec) -> list[str]:
    lines = [f"{p.name} : {_type_text(p)}"]
    text = _python_text(p.help, spec)
    notes = []
    if p.unit:
        notes.append(f"Unit: {p.unit}.")
    rng = p.range_text()
    if rng and p.type != "choice":
        special = "; ".join(f"{k!r}: {v}" for k, v in p.special.items())
        notes.append(f"Allowed: {rng}" + (f" ({_python_text(special, spec)})." if special else "."))
    meaning = [f"``{w!r}`` means {v!r}" for w, v in p.words.items() if w != v]
    if meaning:
        notes.append(", ".join(meaning) + ".")
    return lines + _wrap(" ".join([text, *notes]))


def _wrap(text: str) -> list[str]:
    return textwrap.wrap(text, 88, initial_indent="    ", subsequent_indent="    ")


def _module_references(spec: StageSpec) -> list[str]:
    """The References section of the module that declares the stage (its lines), or []."""
    module = declaring_module(spec)
    doc = inspect.getdoc(module) if module is not None else None
    if not doc:
        return []
    lines = doc.splitlines()
    for i in range(len(lines) - 1):
        if lines[i].strip() == "References" and set(lines[i + 1].strip()) == {"-"}:
            out = []
            for j in range(i + 2, len(lines)):
                nxt = lines[j + 1].strip() if j + 1 < len(lines) else ""
                if lines[j].strip() and nxt and set(nxt) == {"-"}:
                    break  # the next section's title
                out.append(lines[j])
            while out and not out[-1].strip():
                out.pop()
            return out
    return []


def docstring(spec: StageSpec, name: str | None = None) -> str:
    """The numpydoc docstring of the stage's function, made from its declaration."""
    name = name or function_name(spec.name)
    desc = inspect.cleandoc(spec.description or spec.summary)
    head, _, rest = desc.partition("\n")
    out = [spec.summary.strip()]
    if head.strip() != spec.summary.strip():
        out += ["", head.strip()]
    if rest.strip():
        out += ["", _python_text(inspect.cleandoc(rest), spec)]
    kinds = describe_kinds(_data_kinds(spec))
    data = data_name(spec)
    takes = set(_data_kinds(spec))
    types, forms = [], []
    if takes & {"cloud", "oriented"}:
        types.append("PointCloud")
        forms.append("an (n, 3) array holds points")
    if takes & {"cloud", "oriented", "mesh"}:
        types.append("TriangleMesh")
        forms.append("a ``(vertices, faces)`` pair a mesh")
    if "grid" in takes:
        types.append("Grid")
        forms.append("a 3-d array grid values (spacing 1, origin 0)")
    types.append("array_like")
    if takes - {"grid"}:
        types.append("Open3D or trimesh geometry")
        forms.append("Open3D and trimesh clouds and meshes are converted")
    out += [
        "",
        f"The library's ``recon {spec.name}`` (and a pipeline's ``name = \"{spec.name}\"``):",
        "the same parameters, checks and result.",
        "",
        "Parameters",
        "----------",
        f"{data} : {', '.join(types)} or path",
        *_wrap(
            f"The input: {kinds}. "
            + "; ".join(forms)
            + "; a path is read (:func:`~recon_cli.api.read`)."
        ),
    ]
    if takes_normals(spec):
        out += [
            "normals : (n, 3) array_like, optional",
            f"    Normals of the points of ``{data}`` (they replace the input's own).",
        ]
    for p in spec.params:
        out += _param_doc(p, spec)
    result = return_source(spec)
    out += [
        "progress : bool or Progress, optional",
        "    ``True``: progress bars on stderr (when it is a terminal); a",
        "    :class:`~recon_cli.progress.Progress` to draw them on; default silent.",
        "",
        "Returns",
        "-------",
        result,
        *_wrap(
            f"The result ({describe_kinds(spec.gives)})"
            + (
                ", with ``.to_open3d()`` and ``.to_trimesh()``"
                if result not in ("Grid", "Tileset")
                else ""
            )
            + f"; ``report`` holds the stage's report (the keys of ``recon {spec.name} --json``)"
            " and ``history`` ends with this call's provenance line."
        ),
        "",
        "Raises",
        "------",
        "ParameterError",
        "    A parameter outside its declaration (the command line's one-line message).",
        "InputError",
        f"    The input is not {kinds}, or its data cannot be used.",
        "StageFailed",
        "    The stage could not make a result from this input.",
    ]
    refs = _module_references(spec)
    if refs:
        out += ["", "References", "----------", *refs]
    return "\n".join(out) + "\n"


# ---- inputs --------------------------------------------------------------------------------------
def as_input(
    data: Any, spec: StageSpec, normals: Any = None, hint: Any = None
) -> PointCloud | TriangleMesh | Grid:
    """``data`` as recon's own object for stage ``spec`` (see the module docstring).

    ``hint``: for a file name, what the stage keeps of the file (a
    :class:`~recon_cli.io.hint.ReadHint`: a COPC file then decodes only that).

    Raises
    ------
    InputError
        Nothing recon can read as a cloud, a mesh or a grid.
    """
    if isinstance(data, (str, os.PathLike)):
        from recon_cli.io.load import load

        obj: Any = read(data) if hint is None else load(data, hint=hint)
    elif isinstance(data, (PointCloud, TriangleMesh, Grid)):
        obj = data
    elif type(data).__module__.split(".")[0] in ("open3d", "trimesh"):
        obj = geometry_from(data)
    elif isinstance(data, tuple) and len(data) == 2 and np.ndim(data[0]) == 2:
        obj = TriangleMesh(vertices=_numbers(data[0], "vertices"), faces=_faces(data[1]))
    else:
        arr = _numbers(data, "the input")
        if arr.ndim == 3 and "grid" in _data_kinds(spec):
            obj = Grid(sdf=arr, origin=np.zeros(3), voxel_size=1.0)
        elif arr.ndim == 2 and arr.shape[1] == 3:
            obj = PointCloud(points=arr)
        else:
            want = describe_kinds(_data_kinds(spec))
            raise InputError(
                f"{spec.name} needs {want}; an array of shape {arr.shape} is none "
                "(points are (n, 3))"
            )
    if normals is not None:
        if not isinstance(obj, (PointCloud, TriangleMesh)):
            raise InputError(f"normals= is for points, not for {type(obj).__name__}")
        obj = dataclasses.replace(obj, normals=_numbers(normals, "normals"))
    return obj


def _numbers(a: Any, what: str) -> np.ndarray:
    """``a`` as a numeric array; float32 and float64 keep their type (double in, double out)."""
    try:
        arr = np.asarray(a)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what} is not an array of numbers ({exc})") from None
    if arr.dtype.kind not in "fiub":
        raise InputError(f"{what} is not an array of numbers (dtype {arr.dtype})")
    return arr if arr.dtype in (np.float32, np.float64) else arr.astype(np.float64)


def _faces(a: Any) -> np.ndarray:
    f = np.asarray(a)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
        raise InputError(f"faces must be an (m, 3) integer array, got {f.dtype} {f.shape}")
    return f


@contextlib.contextmanager
def _progress(progress: Any) -> Iterator[Progress | None]:
    if progress is True:
        p = Progress()
        try:
            yield p
        finally:
            p.close()
    elif progress is None or progress is False:
        yield None
    elif isinstance(progress, Progress):
        yield progress
    else:
        raise ParameterError(f"progress must be true, false or a Progress, got {progress!r}")


# ---- the functions -------------------------------------------------------------------------------
_FUNCTIONS: dict[str, tuple[StageSpec, Callable[..., Any]]] = {}


def stage_function(stage: str) -> Callable[..., Any]:
    """The library function of stage ``stage`` (made once per declaration).

    Raises
    ------
    ParameterError
        Unknown stage.
    """
    spec = get_spec(stage)
    cached = _FUNCTIONS.get(stage)
    if cached is not None and cached[0] is spec:
        return cached[1]
    fn = _make(stage, spec)
    _FUNCTIONS[stage] = (spec, fn)
    return fn


def _make(stage: str, spec: StageSpec) -> Callable[..., Any]:
    name = function_name(stage)
    first = data_name(spec)
    own = {"progress", *(("normals",) if takes_normals(spec) else ())}

    def run(*args: Any, **kwargs: Any) -> Any:
        if len(args) > 1:
            raise TypeError(
                f"{name}() takes the {first} as its one positional argument; "
                "parameters are keywords"
            )
        if args and first in kwargs:
            raise TypeError(f"{name}() got the {first} twice")
        if not args and first not in kwargs:
            raise TypeError(f"{name}() needs the {first}")
        data = args[0] if args else kwargs.pop(first)
        extra = {k: kwargs.pop(k) for k in own if k in kwargs}
        spec.check(kwargs, complete=False)  # parameters before any data
        # a file name: read only what the stage keeps of it (filter's crop of a COPC file)
        hint = read_hint(stage, kwargs) if isinstance(data, (str, os.PathLike)) else None
        obj = as_input(data, spec, extra.get("normals"), hint=hint)
        with _progress(extra.get("progress")) as progress:
            result = apply_stage(stage, obj, kwargs, progress=progress)
        out = result.output
        out.report = result.report
        return out

    run.__name__ = run.__qualname__ = name
    run.__module__ = "recon_cli"
    run.__doc__ = docstring(spec, name)
    run.__signature__ = signature(spec)  # type: ignore[attr-defined]
    run.spec = spec  # type: ignore[attr-defined]
    return run


# ---- files ---------------------------------------------------------------------------------------
def read(
    path: str | os.PathLike[str], format: str | None = None
) -> PointCloud | TriangleMesh | Grid:
    """Read a point cloud, mesh or grid in any format recon reads (``-``: standard input).

    Parameters
    ----------
    path : str or path-like
        The file; its suffix names the format (PLY, OBJ, OFF, STL, XYZ/CSV, PCD, LAS/LAZ, E57,
        ``.npz`` grids), and a name without one is read by its content.
    format : str, optional
        The format, whatever the name says (``"ply"``, ``"xyz"``, ...).

    Returns
    -------
    PointCloud, TriangleMesh or Grid
        In the precision of the file (float32 columns stay float32), with every property.

    Raises
    ------
    InputError
        A malformed file (the message names the file and the line or byte).
    ParameterError
        An unknown suffix or format, or a missing optional extra (LAS, E57).
    """
    from recon_cli.io.load import load

    return load(path, format)


def write(
    obj: Any,
    path: str | os.PathLike[str],
    *,
    format: str | None = None,
    ascii: bool = False,
    points_only: bool = False,
) -> None:
    """Write a cloud, mesh or grid atomically in the format the suffix of ``path`` names.

    Parameters
    ----------
    obj : PointCloud, TriangleMesh, Grid, or Open3D or trimesh geometry
        What to write (Open3D and trimesh objects are converted first).
    path : str or path-like
        The file (``-``: standard output); a name without a suffix is written as PLY (a grid
        as ``.npz``).
    format : str, optional
        The format, whatever the name says.
    ascii : bool
        Text PLY / STL / PCD instead of binary.
    points_only : bool
        Allow writing a mesh's vertices to a format that holds points only (its faces are
        dropped, and a warning says so).

    Raises
    ------
    ParameterError
        A format that cannot hold ``obj`` (a cloud as STL, a mesh as XYZ without
        ``points_only``), an unknown format.
    OutputError
        The path cannot be written (the message names it and the system's reason).
    """
    from recon_cli.io.load import save

    if not isinstance(obj, Grid):
        obj = geometry_from(obj)
    save(obj, path, ascii=ascii, format=format, points_only=points_only)
