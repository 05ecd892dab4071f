"""Stage declarations (recon_cli.params, recon_cli.stages): one declaration, all derived from it."""

from __future__ import annotations

import inspect
import subprocess
import sys
from importlib.metadata import EntryPoint

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from recon_cli import stages
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.params import Param, StageSpec, parse_bool
from recon_cli.stages import (
    BUILTIN,
    StageResult,
    declaring_module,
    get_spec,
    register_stage,
    stage_summary,
    unregister_stage,
)

from shared_data import ROOT

# ---- Param.coerce: one checker -------------------------------------------------------------------


def test_bool_words_are_exactly_the_documented_ones():
    """parse_bool takes exactly the documented words, any case and padding, and refuses the rest."""
    for w in ("true", "YES", " on ", "1"):
        assert parse_bool(w) is True
    for w in ("false", "No", "off", "0"):
        assert parse_bool(w) is False
    for w in ("maybe", "", "2", "truthy", "y"):
        with pytest.raises(ValueError):
            parse_bool(w)


def test_typed_values_must_have_the_declared_type():
    """Integer and bool parameters take their type (or its text on the command line), in range.

    Floats, other types, out-of-range values and text in TOML are refused with the option's message.
    """
    depth = Param("depth", "int", 8, "d", min=1, max=14)
    assert depth.coerce(9) == 9 and depth.coerce("9") == 9 and depth.coerce(np.int64(3)) == 3
    for bad in (True, False, 8.0, 8.5, "8.0", "x", [8], None):
        with pytest.raises(ParameterError, match="--depth must be an integer"):
            depth.coerce(bad)
    with pytest.raises(ParameterError, match="string"):
        depth.coerce("8", text_ok=False)  # TOML: depth = "8" is a type error
    for bad in (0, 15, "-3"):
        with pytest.raises(ParameterError, match=r"1 <= x <= 14"):
            depth.coerce(bad)
    flag = Param("density", "bool", False, "d")
    assert (
        flag.coerce(True) is True
        and flag.coerce("off") is False
        and flag.coerce(np.bool_(True)) is True
    )
    for bad in (1, 0, "maybe", 1.0):
        with pytest.raises(ParameterError, match="true or false"):
            flag.coerce(bad)
    with pytest.raises(ParameterError):
        flag.coerce("true", text_ok=False)


def test_floats_vectors_words_and_extra_values():
    """float, vector, floats-with-words and extra values are coerced and checked as declared."""
    w = Param("trim", "float", 0.0, "t", min=0.0, max=1.0, max_open=True)
    assert w.coerce(0) == 0.0 and w.coerce("0.25") == 0.25
    for bad in (1.0, -0.1, float("nan"), float("inf"), "nan", True):
        with pytest.raises(ParameterError, match="--trim"):
            w.coerce(bad)
    v = Param("camera", "vector", None, "c")
    assert (
        v.coerce("0,0,1") == (0.0, 0.0, 1.0)
        and v.coerce([1, 2, 3]) == (1.0, 2.0, 3.0)
        and v.coerce(None) is None
    )
    for bad in ("0,1", [1, 2, 3, 4], "a,b,c", 5):
        with pytest.raises(ParameterError, match="three numbers"):
            v.coerce(bad)
    r = Param("radii", "floats", "auto", "r", min=0.0, min_open=True, words={"auto": "auto"})
    assert (
        r.coerce("AUTO") == "auto"
        and r.coerce("0.1, 0.2") == (0.1, 0.2)
        and r.coerce(0.5) == (0.5,)
    )
    with pytest.raises(ParameterError, match="'auto'"):
        r.coerce("0.1,-2")
    knn = Param("knn", "int", 30, "k", min=3, also=(0,))
    assert knn.coerce(0) == 0 and knn.coerce("3") == 3
    with pytest.raises(ParameterError, match="0 or 3 <= x"):
        knn.coerce(2)
    tol = Param("merge_tolerance", "float", None, "m", min=0.0, words={"exact": None})
    assert tol.coerce("Exact") is None and tol.coerce(None) is None and tol.coerce("1e-3") == 1e-3


@given(st.integers(min_value=-(10**12), max_value=10**12))
def test_int_text_round_trip(n):
    """Any integer's text coerces to the integer itself."""
    p = Param("n", "int", 0, "n")
    assert p.coerce(str(n)) == n == p.coerce(n)


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_float_text_round_trip(x):
    """Any finite float's repr coerces to the float itself."""
    p = Param("x", "float", 0.0, "x")
    assert p.coerce(repr(x)) == x == p.coerce(x)


@given(st.text(max_size=12))
def test_bool_parser_never_guesses(s):
    """A bool parameter takes only the eight words (any case, padded) and refuses other text."""
    p = Param("f", "bool", False, "f")
    word = s.strip().lower()
    if word in ("true", "yes", "on", "1", "false", "no", "off", "0"):
        assert p.coerce(s) is (word in ("true", "yes", "on", "1"))
    else:
        with pytest.raises(ParameterError):
            p.coerce(s)


# ---- every built-in stage: declaration, library, command, docs -----------------------------------
@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_stage_is_registered_and_derived_from_its_declaration(name):
    """A built-in stage is registered, its function and command derived from its declaration.

    The keyword defaults are the declaration's; the command has no module of its own and an option
    per parameter.
    """
    from recon_cli.cli.main import COMMANDS, cli
    from recon_cli.cli.options import stage_command

    spec = get_spec(name)
    assert spec.name == name and spec.declared and spec.run is not None
    # the library function's keyword defaults are the declaration's
    sig = inspect.signature(spec.run)
    kw = {
        k: p.default
        for k, p in sig.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and k != "progress"
    }
    assert kw == spec.defaults()
    # the command: made from the declaration (no module of its own, no summary repeated)
    assert name not in COMMANDS and stage_summary(name) == spec.summary
    assert not (ROOT / "recon_cli" / "cli" / f"{name.replace('-', '_')}.py").exists()
    assert cli.get_command(None, name).name == name
    cmd = stage_command(name)
    opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
    for p in spec.params:
        assert p.option in opts
        if p.type != "bool":
            help_text = next(q.help for q in cmd.params if p.option in getattr(q, "opts", []))
            assert f"default: {p.default_text()}" in help_text and (
                not p.unit or p.unit in help_text
            )
    res = CliRunner().invoke(cmd, ["--help"])
    assert res.exit_code == 0 and inspect.cleandoc(spec.description).split()[0] in res.output


def _bad_values(p: Param) -> list:
    """Values the declaration of ``p`` refuses (one per kind of mistake)."""
    bad: list = {
        "int": [1.5, "x"],
        "float": ["x", float("nan")],
        "bool": ["maybe"],
        "choice": ["no-such-choice"],
        "vector": ["1,2"],
        "floats": ["a"],
        "any": [],
    }[p.type]
    if p.type in ("int", "float"):
        if p.min is not None and p.min - 1 not in p.also:
            bad.append(p.min - 1)
        if p.max is not None:
            bad.append(p.max + 1)
    return bad


def _public_functions(spec: StageSpec):
    mod = declaring_module(spec)  # its runner may live in another module (poisson's stage.py)
    for name, fn in vars(mod).items():
        if (
            inspect.isfunction(fn)
            and fn.__module__ == mod.__name__
            and not name.startswith("_")
            and name != "run_stage"
        ):
            yield fn


@pytest.mark.parametrize("name", BUILTIN)
def test_public_functions_take_defaults_and_checks_from_the_declaration(name):
    """A stage's public functions take their defaults and checks from the declaration.

    A keyword named like a declared parameter defaults to the declared value and is refused with the
    command line's message, before any data is looked at.
    """
    # a keyword of a stage's public function named like a declared parameter defaults to the
    # declared value and is checked by the declaration (same message as the command line),
    # before any data is looked at
    spec = get_spec(name)
    covered = 0
    for fn in _public_functions(spec):
        sig = inspect.signature(fn)
        required = [
            k
            for k, q in sig.parameters.items()
            if q.default is inspect.Parameter.empty
            and q.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
        ]
        for k, q in sig.parameters.items():
            if k not in spec.defaults() or q.default is inspect.Parameter.empty:
                continue
            p = spec.param(k)
            assert q.default == p.default, f"{fn.__name__}({k}=...) repeats another default"
            for bad in _bad_values(p):
                with pytest.raises(ParameterError) as want:
                    p.coerce(bad)
                with pytest.raises(ParameterError) as got:
                    fn(**{r: None for r in required if r != k}, **{k: bad})
                assert str(got.value) == str(want.value), (fn.__name__, k, bad)
                covered += 1
    # every built-in stage so far has such a function; a new one may have none
    assert covered or name not in ("normals", "poisson", "ballpivot", "repair", "sdf", "mcubes")


def test_documentation_parameter_tables_match_the_declarations():
    """Each stage page holds its declaration's parameter table once, its options in order.

    No hand copy of a table is left in the README.
    """
    # the tables live on the stage pages of the user guide, written from the declarations by
    # recon_cli.tools.docs at every build (tests/test_tools_docs.py reads them cell by cell)
    from recon_cli.tools import docs

    for name in BUILTIN:
        spec = get_spec(name)
        page = docs.stage_page(name)
        assert page.count(docs.param_table(spec)) == 1, name
        options = [
            line.split("``")[1] for line in page.splitlines() if line.startswith("   * - ``")
        ]
        assert options == [p.option for p in spec.params], name
    # no hand copy left in the README
    assert "| option | type | default" not in (ROOT / "README.md").read_text(encoding="utf-8")


def test_runner_refuses_a_function_that_differs_from_its_declaration():
    """A runner whose keywords differ from the declaration is refused."""
    spec = StageSpec(
        "toy2", "t", takes=("cloud",), gives=("cloud",), params=(Param("a", "int", 1, "a"),)
    )
    with pytest.raises(TypeError, match="differ"):

        @spec.runner
        def run_stage(data, *, a, b, progress=None):  # b is not declared
            return StageResult(data)

    with pytest.raises(TypeError, match="differ"):

        @spec.runner
        def run_stage_rest(data, *, b, progress=None, **rest):  # b is not declared
            return StageResult(data)


def test_runner_hands_the_undeclared_keywords_to_rest():
    """A runner's ``**rest`` gets the undeclared keywords with their defaults, checked."""
    # a stage may name some of its parameters and hand the others on together (fit-sdf's fit)
    spec = StageSpec(
        "toy3",
        "t",
        takes=("cloud",),
        gives=("cloud",),
        params=(Param("a", "int", 1, "a"), Param("b", "int", 2, "b"), Param("c", "int", 3, "c")),
    )

    @spec.runner
    def run_stage(data, *, a, progress=None, **rest):
        return StageResult(data, {"a": a, **rest})

    cloud = PointCloud(np.zeros((3, 3)))
    assert run_stage(cloud, c=5).report == {"a": 1, "b": 2, "c": 5}
    with pytest.raises(ParameterError, match="--b must be an integer"):
        run_stage(cloud, b=1.5)


def test_library_call_checks_values_and_input_kind():
    """A library call refuses a badly typed value and an input of the wrong kind."""
    from recon_cli.stages.poisson import run_stage

    pts = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(ParameterError, match="--depth must be an integer"):
        run_stage(PointCloud(pts, normals=pts), depth=True)
    with pytest.raises(
        InputError, match="poisson needs points with normals, got a point cloud without normals"
    ):
        run_stage(PointCloud(pts))


# ---- a toy stage through the public registration API ---------------------------------------------
TOY = StageSpec(
    "toy-scale",
    "Scale a cloud (toy).",
    takes=("cloud",),
    gives=("cloud",),
    params=(Param("factor", "float", 2.0, "Scale factor.", min=0.0, min_open=True),),
)


@TOY.runner
def _toy_run(data, *, factor, progress=None):
    out = data.copy()
    out.points = np.asarray(out.points, dtype=np.float64) * factor
    return StageResult(out, {"factor": factor})


@pytest.fixture
def toy():
    """The toy stage registered for one test, unregistered after."""
    register_stage(TOY)
    yield TOY
    unregister_stage(TOY.name)


def test_toy_stage_runs_in_a_pipeline_and_as_a_command(toy, tmp_path):
    """A registered toy stage runs in a pipeline (with ``--set``) and as a command."""
    from recon_cli.cli.main import cli
    from recon_cli.io import read_ply, write_ply

    src = tmp_path / "in.ply"
    write_ply(PointCloud(np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]])), src)
    pipe = tmp_path / "p.toml"
    pipe.write_text('[[stage]]\nname = "toy-scale"\nfactor = 3\n\n[[stage]]\nname = "toy-scale"\n')
    out = tmp_path / "out.ply"
    res = CliRunner().invoke(
        cli, ["run", str(pipe), str(src), str(out), "-q", "--set", "2.factor=0.5"]
    )
    assert res.exit_code == 0, res.output
    np.testing.assert_allclose(read_ply(out).points, [[1.5, 3.0, 4.5], [0.0, 0.0, 1.5]])
    assert "toy-scale factor=3.0" in read_ply(out).history[-2]
    # the stage is a command too, its option generated from the declaration
    res = CliRunner().invoke(cli, ["toy-scale", str(src), str(out), "--factor", "-1"])
    assert isinstance(
        res.exception, ParameterError
    ) and "--factor must be a number with 0 < x" in str(res.exception)
    res = CliRunner().invoke(cli, ["--help"])
    assert "toy-scale" in res.output
    with pytest.raises(ParameterError, match="built in"):
        register_stage(StageSpec("poisson", "x", takes=("cloud",), gives=("mesh",)))


def test_entry_points_group_registers_stages(monkeypatch):
    """A stage declared by an entry point is registered and runs."""
    import importlib.metadata as md

    ep = EntryPoint(name="toy-ep", value="test_params:TOY", group=stages.ENTRY_POINT_GROUP)
    monkeypatch.setattr(
        md, "entry_points", lambda group=None: [ep] if group == stages.ENTRY_POINT_GROUP else []
    )
    monkeypatch.setattr(stages, "_entry_points_read", False)
    monkeypatch.setattr(stages, "STAGES", dict(stages.STAGES))
    assert "toy-ep" in stages.stage_names()
    spec = get_spec("toy-ep")
    assert spec is TOY
    res = stages.apply_stage("toy-ep", PointCloud(np.ones((2, 3))), {"factor": "4"})
    np.testing.assert_allclose(res.output.points, 4.0)


# ---- global options after the subcommand ---------------------------------------------------------
def test_global_options_before_and_after_the_subcommand(tmp_path):
    """Global options work before and after the subcommand (-q silent, -v reports, --json)."""
    from recon_cli.cli.main import cli
    from recon_cli.io import write_ply

    rng = np.random.default_rng(1)
    p = rng.normal(size=(300, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    src = tmp_path / "s.ply"
    write_ply(PointCloud(p), src)
    for argv in (
        ["-q", "normals", str(src), str(tmp_path / "a.ply")],
        ["normals", str(src), str(tmp_path / "b.ply"), "-q"],
    ):
        res = CliRunner().invoke(cli, argv)
        assert res.exit_code == 0 and res.output == "", (argv, res.output)
    res = CliRunner().invoke(
        cli, ["normals", str(src), str(tmp_path / "c.ply"), "-v", "--knn", "10"]
    )
    assert res.exit_code == 0 and "points" in res.output
    res = CliRunner().invoke(cli, ["--json", "info", str(src)])
    assert res.exit_code == 0 and res.output.lstrip().startswith("[")


def test_validate_answers_fast_in_a_fresh_process(tmp_path):
    """``recon run --validate`` of a bad stage 2 answers fast in a fresh process."""
    # the check runs before any stage (and without compiling anything): a bad value in stage 2
    pipe = tmp_path / "p.toml"
    pipe.write_text(
        '[[stage]]\nname = "normals"\nknn = 20\n\n[[stage]]\nname = "poisson"\ndepth = -3\n'
    )
    out = tmp_path / "out.ply"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "recon_cli.cli.main",
            "run",
            str(pipe),
            str(ROOT / "sample_data" / "bunny_scan_000.ply"),
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and not out.exists()
    assert r.stderr.strip() == (
        f"recon: error: {pipe}:7: stage 2 (poisson): --depth must be an integer with 1 <= x <= "
        "14, got -3"
    )
    # checking a pipeline loads the declarations, never a kernel (so nothing compiles)
    code = (
        "import sys; from recon_cli.pipeline import load_pipeline; load_pipeline(sys.argv[1], "
        "['2.depth=9']); "
        "print(sorted(m for m in sys.modules if m == 'numba' or m.endswith('_kernel')))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, str(pipe)], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
