"""Command line: exit codes, one-line errors, stdin/stdout, atomic output, info, run, start-up."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.io.ply import read_ply

from shared_data import ROOT, shared_path

RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def recon(*args, input: bytes | None = None, cwd=None) -> subprocess.CompletedProcess:
    """Run ``recon`` with ``args`` as a process (no COLUMNS), its output captured."""
    env = dict(os.environ)
    env.pop("COLUMNS", None)
    return subprocess.run(
        [*RECON, *map(str, args)], input=input, capture_output=True, cwd=cwd, env=env, timeout=300
    )


def test_help_is_instant_and_imports_no_numpy():
    """``recon --help`` imports no numpy and lists every stage with its declaration's summary."""
    code = (
        "import sys, recon_cli.cli.main as m; m.cli.main(['--help'], standalone_mode=False); "
        "print('numpy' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"
    # every stage is listed with its declaration's summary, read without importing the stage
    from recon_cli.stages import BUILTIN, get_spec

    listed = " ".join(out.stdout.split())
    for name in BUILTIN:
        assert f"{name} {' '.join(get_spec(name).summary.split())}" in listed, name


def test_version():
    """``recon --version`` exits 0 and prints the package's version."""
    from recon_cli import __version__

    r = recon("--version")
    assert r.returncode == 0
    assert __version__ in r.stdout.decode()


def test_info_json_keys_are_stable():
    """``recon info --json`` of the kitten: a one-entry list, every key, the counts and box."""
    r = recon("info", "--json", shared_path("kitten"))
    assert r.returncode == 0, r.stderr
    [rep] = json.loads(r.stdout)  # always a list, one entry per file
    for key in (
        "file",
        "kind",
        "format",
        "vertices",
        "faces",
        "elements",
        "properties",
        "bbox",
        "history",
        "has_normals",
    ):
        assert key in rep
    assert rep["kind"] == "mesh" and rep["vertices"] == 6050 and rep["faces"] == 12100
    assert rep["bbox"]["diagonal"] == pytest.approx(2.23, abs=0.01)
    assert rep["history"] == ["Created by Open3D"]


def test_info_reads_stdin_and_several_files():
    """``recon info`` reads a cloud from stdin, and several files in the order given."""
    data = shared_path("stereo_fragment").read_bytes()
    r = recon("info", "--json", "-", input=data)
    assert r.returncode == 0, r.stderr
    [rep] = json.loads(r.stdout)
    assert rep["kind"] == "point_cloud" and rep["vertices"] == 3748 and rep["has_colors"]
    r = recon("info", "--json", shared_path("mug"), shared_path("kitten"))
    assert [x["vertices"] for x in json.loads(r.stdout)] == [5084, 6050]


@pytest.mark.parametrize(
    "content,needle",
    [
        (b"", "empty file"),
        (b"hello, not a ply\n", "not a PLY file"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
            b"property double x\nproperty double y\nproperty double z\nend_header\n\0\0",
            "truncated",
        ),
    ],
)
def test_bad_input_one_line_exit_2_no_output(tmp_path, content, needle):
    """An empty, non-PLY or truncated input: exit 2, one line naming it, no traceback, no output."""
    bad = tmp_path / "bad.ply"
    bad.write_bytes(content)
    out = tmp_path / "out.ply"
    r = recon("convert", bad, out)
    assert r.returncode == 2
    err = r.stderr.decode().strip()
    assert len(err.splitlines()) == 1, err
    assert str(bad) in err and needle in err
    assert "Traceback" not in err
    assert not out.exists()
    assert os.listdir(tmp_path) == ["bad.ply"]


def test_missing_file_exit_2(tmp_path):
    """A missing input: exit 2 with "no such file"."""
    r = recon("info", tmp_path / "nope.ply")
    assert r.returncode == 2
    assert "no such file" in r.stderr.decode()


def test_usage_error_exit_2():
    """A command missing its arguments: exit 2."""
    r = recon("convert")
    assert r.returncode == 2


def test_convert_pipes_through_stdin_stdout(tmp_path):
    """ASCII then binary through two pipes: the mesh written at the end equals the source."""
    src = shared_path("kitten")
    p1 = subprocess.Popen([*RECON, "convert", "--ascii", str(src), "-"], stdout=subprocess.PIPE)
    p2 = subprocess.Popen([*RECON, "convert", "-", "-"], stdin=p1.stdout, stdout=subprocess.PIPE)
    p1.stdout.close()
    p3 = subprocess.run(
        [*RECON, "convert", "-", str(tmp_path / "k.ply")], stdin=p2.stdout, capture_output=True
    )
    p2.stdout.close()
    assert p1.wait() == 0 and p2.wait() == 0 and p3.returncode == 0, p3.stderr
    a, b = read_ply(src), read_ply(tmp_path / "k.ply")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_existing_output_not_clobbered_on_error(tmp_path):
    """A failed convert leaves an existing output's bytes as they were."""
    out = tmp_path / "out.ply"
    out.write_bytes(b"precious")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
    r = recon("convert", bad, out)
    assert r.returncode == 2
    assert out.read_bytes() == b"precious"


def test_run_rejects_unknown_stage_naming_line(tmp_path):
    """``recon run`` with an unknown stage: exit 2 naming the file and line, no output."""
    pipe = tmp_path / "p.toml"
    pipe.write_text('description = "x"\n\n[[stage]]\nname = "frobnicate"\n')
    r = recon("run", pipe, shared_path("kitten"), tmp_path / "o.ply")
    assert r.returncode == 2
    err = r.stderr.decode()
    assert f"{pipe}:3:" in err and "unknown stage 'frobnicate'" in err
    assert not (tmp_path / "o.ply").exists()


def test_run_rejects_bad_toml(tmp_path):
    """``recon run`` with broken TOML: exit 2, "not valid TOML"."""
    pipe = tmp_path / "p.toml"
    pipe.write_text("[[stage]\nname=")
    r = recon("run", pipe, shared_path("kitten"), tmp_path / "o.ply")
    assert r.returncode == 2
    assert "not valid TOML" in r.stderr.decode()


def test_pipeline_parameter_errors_name_the_line(monkeypatch):
    """A misspelt parameter names file, line and stage; fixed, the pipeline runs, with history."""
    from recon_cli import stages
    from recon_cli.errors import ParameterError
    from recon_cli.pipeline import parse_pipeline

    monkeypatch.setitem(stages.STAGES, "scale", "test_cli:_scale_stage")
    text = (
        '[[stage]]\nname = "scale"\nfactor = 2.0\n\n[[stage]]\nname = "scale"\nfactor = 3\n'
        "factr = 1\n"
    )
    with pytest.raises(
        ParameterError, match=r"p.toml:8: stage 2 \(scale\) has no parameter 'factr'"
    ):
        parse_pipeline(text, "p.toml")
    pipe = parse_pipeline(text.replace("factr = 1\n", ""), "p.toml")
    from recon_cli.geometry import PointCloud
    from recon_cli.pipeline import run_pipeline

    out, reports = run_pipeline(pipe, PointCloud(points=np.ones((4, 3))))
    np.testing.assert_array_equal(out.points, 6 * np.ones((4, 3)))
    assert [r["stage"] for r in reports] == ["scale", "scale"]
    # provenance: one line per stage, with its parameters
    assert out.history[-2:] == ["recon 0.1.0 scale factor=2.0", "recon 0.1.0 scale factor=3.0"]


def _scale_stage(data, *, factor=1.0, progress=None):
    from recon_cli.stages import StageResult

    out = data.copy()
    out.points[:] = out.points * factor
    return StageResult(out, {"factor": factor})


def test_pipeline_files_shipped_parse():
    """Every pipeline shipped in pipelines/ (demo.toml among them) loads and checks."""
    # every shipped pipeline is fully checked: stages, parameter types and ranges, kinds of data
    # between stages
    from recon_cli.pipeline import load_pipeline

    files = sorted((ROOT / "pipelines").glob("*.toml"))
    assert {f.name for f in files} >= {"demo.toml"}
    for f in files:
        pipe = load_pipeline(f)
        assert pipe.steps
