"""Pipeline files: everything checked before anything runs, each error with its file and line."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.pipeline import apply_overrides, check_input, parse_pipeline


def _pipe(text: str, overrides=()):
    pipe = parse_pipeline(text, "p.toml", check=False)
    apply_overrides(pipe, overrides)
    from recon_cli.pipeline import check_pipeline

    check_pipeline(pipe)
    return pipe


@pytest.mark.parametrize(
    "text, message",
    [
        (
            '[[stage]]\nname = "normals"\n\n[[stage]]\nname = "poisson"\ndepth = -3\n',
            r"p.toml:6: stage 2 \(poisson\): --depth must be an integer with 1 <= x <= 14, got -3",
        ),
        (
            '[[stage]]\nname = "poisson"\ndepth = true\n',
            r"p.toml:3: .*--depth must be an integer .* got true \(a boolean\)",
        ),
        (
            '[[stage]]\nname = "poisson"\ndepth = "9"\n',
            r"p.toml:3: .*--depth must be an integer .* got '9' \(a string\)",
        ),
        ('[[stage]]\nname = "poisson"\ndepth = 8.0\n', r"p.toml:3: .*--depth must be an integer"),
        (
            '[[stage]]\nname = "normals"\ncurvature = "maybe"\n',
            r"p.toml:3: .*--curvature must be true or false",
        ),
        (
            '[[stage]]\nname = "normals"\ncurvature = 1\n',
            r"p.toml:3: .*--curvature must be true or false",
        ),
        (
            '[[stage]]\nname = "normals"\n\n[[stage]]\nname = "mcubes"\n',
            r"p.toml:4: stage 2 \(mcubes\) needs a grid \(.npz\), but stage 1 \(normals\) "
            r"gives a point cloud with normals",
        ),
        (
            '[[stage]]\nname = "sdf"\n\n[[stage]]\nname = "repair"\n',
            r"p.toml:4: stage 2 \(repair\) needs a triangle mesh, but stage 1 \(sdf\) gives a grid",
        ),
        ('[[stage]]\nname = "frob"\n', r"p.toml:1: unknown stage 'frob'"),
        (
            '[[stage]]\nname = "poisson"\n\ndepht = 9\n',
            r"p.toml:4: stage 1 \(poisson\) has no parameter 'depht'",
        ),
        (
            '[[stage]]\nname = "poisson"\npoint-weight = 2\npoint_weight = 3\n',
            r"p.toml:4: parameter 'point_weight' is given twice",
        ),
        (
            '[[stage]]\nname = "ballpivot"\nradii = [0.1, -1]\n',
            r"p.toml:3: .*--radii must be numbers",
        ),
        (
            '[[stage]]\nname = "normals"\norient = "camera"\ncamera = [0, 1]\n',
            r"p.toml:4: .*--camera must be three numbers",
        ),
    ],
)
def test_pipeline_errors_name_file_and_line(text, message):
    """A bad pipeline value is refused with the file, line, stage and option in the message."""
    with pytest.raises(ParameterError, match=message):
        _pipe(text)


def test_values_are_typed_and_mean_the_same_as_on_the_command_line():
    """Pipeline values are typed and mean what the same option means on the command line."""
    pipe = _pipe(
        '[[stage]]\nname = "normals"\nknn = 0\nradius = 1\ncamera = "0,0,1"\n\n[[stage]]\n'
        'name = "ballpivot"\nradii = [0.5, 1]\n'
    )
    assert pipe.steps[0].params == {
        "knn": 0,
        "radius": 1.0,
        "camera": (0.0, 0.0, 1.0),
    }  # knn 0 = radius only, as on the CLI
    assert pipe.steps[1].params == {"radii": (0.5, 1.0)}
    pipe = _pipe('[[stage]]\nname = "poisson"\nestimate-normals = true\n')
    assert pipe.steps[0].params == {"estimate_normals": True}


def test_set_overrides_by_name_and_index():
    """``--set`` overrides by stage name or index; bad targets and names are refused."""
    text = (
        '[[stage]]\nname = "normals"\n\n[[stage]]\nname = "poisson"\ndepth = 7\n\n[[stage]]\n'
        'name = "repair"\n'
    )
    pipe = _pipe(text, ["poisson.depth=9", "3.fill-holes=20", "1.curvature=yes"])
    assert pipe.steps[1].params["depth"] == 9 and pipe.steps[2].params["fill_holes"] == 20
    assert pipe.steps[0].params["curvature"] is True
    for bad, msg in [
        (
            ["poisson.depth=abc"],
            r"--set poisson.depth=abc: stage 2 \(poisson\): --depth must be an integer",
        ),
        (["4.depth=9"], r"stages 1..3"),
        (["mcubes.iso=0"], r"no stage 'mcubes'"),
        (["poisson-depth=9"], r"expected STAGE.PARAM=VALUE"),
        (["poisson.dept=9"], r"--set poisson.dept=9: stage 2 \(poisson\) has no parameter 'dept'"),
    ]:
        with pytest.raises(ParameterError, match=msg):
            _pipe(text, bad)
    with pytest.raises(ParameterError, match="2 stages are called 'repair'"):
        _pipe(text + '\n[[stage]]\nname = "repair"\n', ["repair.fill_holes=3"])


def test_estimate_normals_changes_what_poisson_takes():
    """``estimate_normals`` lets poisson take points without normals; otherwise they are refused."""
    pipe = _pipe('[[stage]]\nname = "poisson"\n')
    bare = PointCloud(np.random.default_rng(0).normal(size=(20, 3)))
    with pytest.raises(
        InputError,
        match=r"in.ply: poisson needs points with normals, got a point cloud without normals",
    ):
        check_input(pipe, bare, "in.ply")
    check_input(_pipe('[[stage]]\nname = "poisson"\nestimate_normals = true\n'), bare, "in.ply")


def test_run_checks_before_touching_the_output(tmp_path, monkeypatch):
    """``recon run`` checks the whole pipeline before any stage runs or the output is touched.

    ``--validate`` with a ``--set`` fix reports the pipeline valid, still running nothing.
    """
    from recon_cli.cli.main import cli
    from recon_cli.stages import normals

    called = []
    monkeypatch.setattr(normals.SPEC, "run", lambda *a, **k: called.append(1))
    pipe = tmp_path / "p.toml"
    pipe.write_text(
        '[[stage]]\nname = "normals"\n\n[[stage]]\nname = "poisson"\nboundary = "periodic"\n'
    )
    src = tmp_path / "in.ply"
    from recon_cli.io import write_ply

    write_ply(PointCloud(np.ones((3, 3))), src)
    out = tmp_path / "out.ply"
    res = CliRunner().invoke(cli, ["run", str(pipe), str(src), str(out)])
    assert isinstance(res.exception, ParameterError) and "p.toml:6:" in str(res.exception)
    assert "--boundary must be one of neumann, dirichlet" in str(res.exception)
    assert not called and not out.exists()
    res = CliRunner().invoke(
        cli, ["run", str(pipe), "--validate", "--set", "poisson.boundary=dirichlet", "--json"]
    )
    assert res.exit_code == 0 and '"valid": true' in res.output and not called
