"""docs/adding-a-stage.md: a new stage is its package, its registry line and its tests.

A toy stage is written as a package on disk and given its line in the registry, nothing else;
the command, its help, the pipeline stage, the library function, the documentation's page
(with the package's guide), the command-line reference and the warm-up all follow.
"""

from __future__ import annotations

import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import recon_cli
from recon_cli import stages
from recon_cli.cli._warmup import all_phases
from recon_cli.cli.main import cli
from recon_cli.cli.reference import reference_page
from recon_cli.errors import ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.io.ply import read_ply, write_ply
from recon_cli.pipeline import load_pipeline, run_pipeline
from recon_cli.tools import docs

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "adding-a-stage.md"

PACKAGE = '''
"""Shift a cloud along z: the toy stage of tests/test_adding_a_stage.py.

References
----------
None: a test's toy.
"""

from recon_cli.params import Param, StageSpec
from recon_cli.stages import StageResult

SPEC = StageSpec(
    name="toy-shift",
    summary="Shift a cloud along z.",
    takes=("cloud",),
    gives=("cloud",),
    params=(Param("dz", "float", 1.0, "How far.", unit="input units", min=0),),
)

WARMUP = (("c64", "--dz", "0.5"),)
AOT = True


@SPEC.runner
def run_stage(data, *, dz, progress=None):
    from recon_cli.geometry import PointCloud

    pts = data.points + [0.0, 0.0, dz]
    return StageResult(PointCloud(points=pts), {"dz": dz})
'''

GUIDE = "Moves every point of the cloud up by `--dz`, in the cloud's units. " * 4


def test_the_page_lists_three_places():
    """The page's "three places" are numbered 1 to 3: the package, ``STAGES``, the tests."""
    text = PAGE.read_text(encoding="utf-8")
    section = text[text.index("## The three places") :].split("\n## ")[0]
    places = re.findall(r"^\d+\. \*\*(.+?)\*\*", section, re.M)
    assert len(places) == 3, places
    assert "`recon_cli/stages/<stage>/`" in places[0]
    assert "`STAGES`" in section and "tests/test_<stage>" in section


@pytest.fixture
def toy_stage(tmp_path, monkeypatch):
    """The toy stage's package and guide on ``sys.path``, its line in ``STAGES``; undone after."""
    pkg = tmp_path / "toy_shift_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent(PACKAGE), encoding="utf-8")
    (pkg / docs.GUIDE).write_text(GUIDE, encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    # the registry line, and nothing else
    monkeypatch.setitem(stages.STAGES, "toy-shift", "toy_shift_pkg:SPEC")
    yield tmp_path
    all_phases().pop("stage-toy-shift", None)
    sys.modules.pop("toy_shift_pkg", None)


def test_a_stage_is_its_package_and_its_registry_line(toy_stage):
    """The toy stage's package and registry line alone give it every surface the page promises.

    Its command (help, parameter checks, its line in ``recon --help``), pipeline stage, library
    function, documentation page with its guide, command-line reference entry, warm-up step and
    ahead-of-time kernel module.
    """
    src, out = toy_stage / "in.ply", toy_stage / "out.ply"
    pts = np.random.default_rng(0).normal(size=(50, 3))
    write_ply(PointCloud(points=pts), str(src))
    runner = CliRunner()
    # the command, its help and its line in recon --help
    listing = runner.invoke(cli, ["--help"], prog_name="recon")
    assert re.search(r"^\s+toy-shift\s+Shift a cloud along z\.$", listing.output, re.M)
    helped = runner.invoke(cli, ["toy-shift", "--help"], prog_name="recon")
    assert "--dz" in helped.output and "How far." in helped.output
    ran = runner.invoke(cli, ["-q", "toy-shift", str(src), str(out), "--dz", "2"])
    assert ran.exit_code == 0, ran.output
    assert np.array_equal(read_ply(str(out)).points, pts + [0, 0, 2])
    refused = runner.invoke(cli, ["toy-shift", str(src), str(out), "--dz", "-1"])
    assert isinstance(refused.exception, ParameterError)  # recon's main: exit 2, one line
    assert str(refused.exception) == "--dz must be a number with 0 <= x, got '-1'"
    # the pipeline stage and the library function
    toml = toy_stage / "p.toml"
    toml.write_text('[[stage]]\nname = "toy-shift"\ndz = 3.0\n', encoding="utf-8")
    pipe = load_pipeline(str(toml))
    out_data, reports = run_pipeline(pipe, PointCloud(points=pts))
    assert np.array_equal(out_data.points, pts + [0, 0, 3]) and reports[0]["dz"] == 3.0
    assert np.array_equal(recon_cli.toy_shift(pts, dz=0.5).points, pts + [0, 0, 0.5])
    # the documentation: its page with the guide, the command-line reference
    page = docs.stage_page("toy-shift", str(toy_stage / "docs"))
    assert docs.param_table(stages.get_spec("toy-shift")) in page
    assert ".. include:: ../toy_shift_pkg/guide.md" in page
    assert "\n``recon toy-shift``\n" in reference_page()
    # the warm-up runs it
    steps = all_phases()["stage-toy-shift"].steps
    from recon_cli.cli._warmup_inputs import Files

    assert [name for name, _ in steps(Files(str(toy_stage), str(toy_stage)))] == [
        "recon toy-shift cloud_float64.ply out.ply --dz 0.5"
    ]
    # AOT = True: the warm-up builds its kernel module ahead of time
    from recon_cli.aot.build import modules_to_build

    assert "toy_shift_pkg._kernel" in modules_to_build()
