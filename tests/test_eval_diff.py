"""``recon diff``: rows, JSON/CSV, heatmap and picture outputs, exit codes."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from recon_cli.cli.main import main
from recon_cli.eval.figure import layout
from recon_cli.eval.render import colormap
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import read_ply, write_ply

from picture_checks import ink
from shapes import cut_sphere


def run(capsys, *args) -> tuple[int, str, str]:
    """Run the CLI in this process on ``args``: (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def _plate(z: float, n: int = 4) -> TriangleMesh:
    g = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    return TriangleMesh(
        v,
        np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]),
        point_dtype=np.float64,
    )


@pytest.fixture
def files(tmp_path):
    """gt.ply (plate z=0), a.ply (z=0.01), b.ply (z=0.03), s.ply (a sphere), cloud.ply."""
    paths = {}
    for name, z in (("gt", 0.0), ("a", 0.01), ("b", 0.03)):
        paths[name] = tmp_path / f"{name}.ply"
        write_ply(_plate(z), paths[name])
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    paths["s"] = tmp_path / "s.ply"
    write_ply(
        TriangleMesh(np.asarray(s.vertices) + 0.5, np.asarray(s.faces), point_dtype=np.float64),
        paths["s"],
    )
    paths["cloud"] = tmp_path / "cloud.ply"
    pts = np.random.default_rng(0).uniform(0, 1, size=(3000, 3)) * np.array([1.0, 1.0, 0.0])
    write_ply(PointCloud(points=pts, point_dtype=np.float64), paths["cloud"])
    return paths


def test_two_files_json_is_one_row(capsys, files):
    """Plates 0.01 apart: one JSON row, every distance 0.01, F-score 0 then 1, open topology."""
    code, out, err = run(capsys, "diff", files["a"], files["gt"], "--samples", 3000, "--json")
    assert code == 0, err
    r = json.loads(out)
    assert isinstance(r, dict)
    assert r["candidate"] == str(files["a"]) and r["reference"] == str(files["gt"])
    for key in (
        "accuracy",
        "completeness",
        "chamfer_l1",
        "hausdorff",
        "hausdorff_p95",
        "hausdorff_p99",
    ):
        assert r[key] == pytest.approx(0.01, rel=1e-9)
    assert r["chamfer_l2"] == pytest.approx(1e-4, rel=1e-9)
    # taus 0.5 % and 1 % of the diagonal sqrt(2): 0.00707 < 0.01 < 0.0141
    assert r["fscore"] == [0.0, 1.0]
    assert r["normal_consistency"] == pytest.approx(1.0)
    assert r["topology"]["candidate"]["boundary_loops"] == 1
    assert r["topology"]["reference"]["watertight"] is False


def test_ref_with_several_candidates_table_csv(capsys, files, tmp_path):
    """Two candidates against ``--ref``: a table, CSV rows with their distances, JSON as a list."""
    out_csv = tmp_path / "rows.csv"
    code, out, err = run(
        capsys,
        "diff",
        files["a"],
        files["b"],
        "--ref",
        files["gt"],
        "--samples",
        2000,
        "--tau",
        "0.02",
        "--csv",
        out_csv,
    )
    assert code == 0, err
    assert "a.ply" in out and "b.ply" in out and "F@" in out and "holes 1" in out
    rows = list(csv.DictReader(io.StringIO(out_csv.read_text())))
    assert [r["candidate"] for r in rows] == [str(files["a"]), str(files["b"])]
    assert float(rows[0]["accuracy"]) == pytest.approx(0.01, rel=1e-6)
    assert float(rows[1]["hausdorff"]) == pytest.approx(0.03, rel=1e-6)
    f = [k for k in rows[0] if k.startswith("fscore@")]
    assert len(f) == 1 and float(rows[0][f[0]]) == 1.0 and float(rows[1][f[0]]) == 0.0
    code, out, err = run(
        capsys, "diff", files["a"], "--ref", files["gt"], "--samples", 500, "--json"
    )
    rows = json.loads(out)
    assert isinstance(rows, list) and len(rows) == 1 and rows[0]["candidate"] == str(files["a"])
    code, out, err = run(
        capsys, "diff", files["a"], files["b"], "--ref", files["gt"], "--samples", 500, "--csv", "-"
    )
    assert code == 0 and out.splitlines()[0].startswith("candidate,reference,mode")
    assert len(out.splitlines()) == 3


def test_heatmap_and_png(capsys, files, tmp_path):
    """A sphere against a plate: the heatmap holds each vertex's true distance; the PNG has ink.

    Several candidates get one heatmap each, named after the candidate.
    """
    from PIL import Image

    heat, png = tmp_path / "heat.ply", tmp_path / "pic.png"
    code, out, err = run(
        capsys,
        "diff",
        files["s"],
        files["gt"],
        "--samples",
        2000,
        "--heatmap",
        heat,
        "--png",
        png,
        "--view",
        "front",
        "--view",
        "iso",
    )
    assert code == 0, err
    h = read_ply(heat)
    s = read_ply(files["s"])
    assert isinstance(h, TriangleMesh) and len(h.faces) == len(s.faces)
    # the sphere's vertices against the unit plate z = 0: distance from the plate's square
    d_true = np.hypot(np.abs(s.vertices[:, 2]), 0.0)
    inside = (
        (s.vertices[:, 0] >= 0)
        & (s.vertices[:, 0] <= 1)
        & (s.vertices[:, 1] >= 0)
        & (s.vertices[:, 1] <= 1)
    )
    np.testing.assert_allclose(
        h.attributes["distance"][inside], d_true[inside], rtol=1e-5, atol=1e-6
    )
    assert h.colors.shape == (len(s.vertices), 3)
    # the farthest vertex has the hottest colour
    assert (
        h.colors[np.argmax(h.attributes["distance"])][0]
        > h.colors[np.argmin(h.attributes["distance"])][0]
    )
    img = np.asarray(Image.open(png).convert("RGB"))
    # rows: the candidate's shape, accuracy, completeness, the reference; one column per view; a
    # colour bar
    box = layout(4, 2, 240, title=True, colorbar=True, legend=True)
    assert img.shape == (box["size"][3], box["size"][2], 3)
    for name in [
        "title",
        "column 0",
        "column 1",
        *(f"row {r}" for r in range(4)),
        "colorbar title",
        "colorbar top",
        "colorbar max",
        "legend",
    ]:
        assert ink(img, box[name]) >= 15, name
    x0, y0, x1, y1 = box["colorbar"]
    assert (img[y0, x0 + 5] == colormap(np.array([1.0]), 0.0, 1.0)[0]).all()
    assert (img != 255).any(axis=2).mean() > 0.05
    # several candidates: one heatmap each, named after the candidate
    code, out, err = run(
        capsys,
        "diff",
        files["a"],
        files["b"],
        "--ref",
        files["gt"],
        "--samples",
        500,
        "--heatmap",
        tmp_path / "h.ply",
        "--json",
    )
    rows = json.loads(out)
    assert [r["heatmap"] for r in rows] == [
        str(tmp_path / "h_0_a.ply"),
        str(tmp_path / "h_1_b.ply"),
    ]
    np.testing.assert_allclose(
        read_ply(tmp_path / "h_1_b.ply").attributes["distance"], 0.03, rtol=1e-6
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_png_completeness_is_red_where_the_candidate_misses_a_part(capsys, tmp_path, seed):
    """A sphere missing a cap: completeness is red facing the cap, blue on the other side."""
    from PIL import Image

    from picture_checks import is_blue, is_red, view_towards

    ref, cand, direction, center, radius = cut_sphere(np.random.default_rng(100 + seed))
    write_ply(ref, tmp_path / "sphere.ply")
    write_ply(cand, tmp_path / "cut.ply")
    png = tmp_path / "cut.png"
    az, el = view_towards(direction)
    back = view_towards(-direction)
    code, out, err = run(
        capsys,
        "diff",
        tmp_path / "cut.ply",
        tmp_path / "sphere.ply",
        "--samples",
        3000,
        "--png",
        png,
        "--view",
        f"{az},{el}",
        "--view",
        f"{back[0]},{back[1]}",
        "--unit",
        "mm",
        "--vmax",
        0.5 * radius,
    )
    assert code == 0, err
    img = np.asarray(Image.open(png).convert("RGB"))
    box = layout(4, 2, 240, title=True, colorbar=True, legend=True)
    assert img.shape == (box["size"][3], box["size"][2], 3)

    def centre(name):
        x0, y0, x1, y1 = box[name]
        return img[(y0 + y1) // 2, (x0 + x1) // 2]

    assert is_red(centre("tile 2 0"))  # completeness, facing the missing cap
    assert not is_red(centre("tile 1 0"))  # through the hole: the inside of the far side, exact
    assert is_blue(centre("tile 2 1")) and is_blue(
        centre("tile 1 1")
    )  # the other side is all there
    for name in ("column 0", "column 1", "row 2", "colorbar top", "colorbar title"):
        assert ink(img, box[name]) >= 15, name


def test_point_cloud_reference_is_stated(capsys, files):
    """A cloud as reference: point-to-point accuracy, stated on stderr; completeness exact."""
    code, out, err = run(capsys, "diff", files["a"], files["cloud"], "--samples", 1000, "--json")
    assert code == 0, err
    r = json.loads(out)
    assert r["mode_accuracy"] == "point-to-point" and r["mode_completeness"] == "point-to-surface"
    assert "no faces" in err and "point-to-point" in err
    # the cloud lies in z = 0: its points are 0.01 from the candidate plate
    assert r["completeness"] == pytest.approx(0.01, rel=1e-9)


def test_bad_inputs_exit_2(capsys, files, tmp_path):
    """Missing, empty, garbage files and bad options (tau, samples, view, vmax): exit 2."""
    code, out, err = run(capsys, "diff", tmp_path / "missing.ply", files["gt"])
    assert code == 2 and "missing.ply: no such file" in err
    empty = tmp_path / "empty.ply"
    write_ply(PointCloud(points=np.zeros((0, 3))), empty)
    code, out, err = run(capsys, "diff", files["a"], empty)
    assert code == 2 and "empty" in err
    code, out, err = run(capsys, "diff", files["a"], files["b"], files["gt"])
    assert code == 2 and "--ref" in err
    code, out, err = run(capsys, "diff", files["a"], files["gt"], "--tau", "-1")
    assert code == 2 and "tau" in err
    code, out, err = run(capsys, "diff", files["a"], files["gt"], "--samples", 0)
    assert code == 2 and "samples" in err
    code, out, err = run(
        capsys, "diff", files["a"], files["gt"], "--png", tmp_path / "x.png", "--view", "sideways"
    )
    assert code == 2 and "view" in err and not (tmp_path / "x.png").exists()
    for bad in ("0", "-1", "nan"):
        code, out, err = run(
            capsys, "diff", files["a"], files["gt"], "--png", tmp_path / "x.png", "--vmax", bad
        )
        assert code == 2 and "vmax" in err and not (tmp_path / "x.png").exists(), bad
    code, out, err = run(
        capsys, "diff", files["a"], files["gt"], "--png", tmp_path / "x.png", "--view", "1,2,3"
    )
    assert code == 2 and "AZIMUTH,ELEVATION" in err and not (tmp_path / "x.png").exists()
    code, out, err = run(capsys, "diff", files["a"], files["gt"], "--json", "--csv", "-")
    assert code == 2 and "stdout" in err
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"not a ply file at all\n")
    code, out, err = run(capsys, "diff", garbage, files["gt"])
    assert code == 2


def test_exit_code_through_the_entry_point(files, tmp_path):
    """``recon diff`` with a missing file as a process: exit 2, "no such file"."""
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "recon_cli.cli.main",
            "diff",
            str(tmp_path / "nope.ply"),
            str(files["gt"]),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2 and "nope.ply: no such file" in p.stderr


# ----------------------------------------------------------------------------- recon compare


def _fake_scaled(data, *, factor="1.0", progress=None):
    """A stand-in stage: the kitten, scaled about its centre by ``factor``."""
    from recon_cli.stages import StageResult

    from shared_data import load_shared

    m = load_shared("kitten")
    c = m.vertices.mean(axis=0)
    m.vertices = c + float(factor) * (m.vertices - c)
    return StageResult(m, {"faces": len(m.faces)})


def _fake_failing(data, *, progress=None):
    from recon_cli.errors import StageFailed

    raise StageFailed("nothing to reconstruct")


def test_parse_methods():
    """``parse_methods`` splits stages, backends and parameters, and refuses malformed lists."""
    from recon_cli.errors import ParameterError
    from recon_cli.eval.compare import parse_methods

    ms = parse_methods(
        "poisson:depth=8,scale=1.2, ballpivot,open3d:poisson,pymeshlab:ballpivot:radii=0.1;0.2"
    )
    assert [(m.stage, m.backend, m.params) for m in ms] == [
        ("poisson", None, {"depth": "8", "scale": "1.2"}),
        ("ballpivot", None, {}),
        ("poisson", "open3d", {}),
        ("ballpivot", "pymeshlab", {"radii": "0.1,0.2"}),
    ]
    assert ms[0].label == "poisson:depth=8:scale=1.2" and ms[3].stage_params() == {
        "radii": "0.1,0.2",
        "backend": "pymeshlab",
    }
    assert [m.label for m in parse_methods(["poisson:depth=8", "poisson:depth=9"])] == [
        "poisson:depth=8",
        "poisson:depth=9",
    ]
    for bad in ("depth=8,poisson", "poisson,poisson", "open3d:", "", "poisson:depth"):
        with pytest.raises(ParameterError):
            parse_methods(bad)


def test_compare_methods_statuses_metrics_and_reports(tmp_path, monkeypatch):
    """``compare_methods``: ok, unavailable and failed rows, their metrics, reports and pictures."""
    from recon_cli.eval.compare import compare_methods
    from recon_cli.stages import STAGES

    from shared_data import shared_path

    monkeypatch.setitem(STAGES, "fakescale", "test_eval_diff:_fake_scaled")
    monkeypatch.setitem(STAGES, "fakefail", "test_eval_diff:_fake_failing")
    monkeypatch.setitem(STAGES, "notbuilt", "recon_cli.not_built_yet:run_stage")
    out = tmp_path / "cmp"
    res = compare_methods(
        shared_path("kitten"),
        "fakescale:factor=1.0,fakescale:factor=1.01,notbuilt,fakefail",
        shared_path("kitten"),
        out,
        samples=5000,
        isolate=False,
        vmax=0.002,
        unit="mm",
    )
    rows = {r["method"]: r for r in res["methods"]}
    assert [r["status"] for r in res["methods"]] == ["ok", "ok", "unavailable", "failed"]
    same, scaled = rows["fakescale:factor=1.0"], rows["fakescale:factor=1.01"]
    assert same["metrics"]["chamfer_l1"] <= 1e-12 and same["metrics"]["fscore"] == [1.0, 1.0]
    assert (
        scaled["metrics"]["hausdorff"] > 1e-3
        and scaled["metrics"]["chamfer_l1"] > same["metrics"]["chamfer_l1"]
    )
    assert same["faces"] == 12100 and same["seconds"] > 0 and same["peak_mb"] >= 0
    assert "not available" in rows["notbuilt"]["error"] and rows["notbuilt"]["metrics"] is None
    assert rows["fakefail"]["error"] == "nothing to reconstruct"
    for name in (
        "results.json",
        "report.md",
        "report.html",
        "overview.png",
        "quality_vs_time.png",
        "fakescale_factor_1.0.ply",
        "fakescale_factor_1.01.png",
    ):
        assert (out / name).exists(), name
    saved = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in saved["methods"]] == ["ok", "ok", "unavailable", "failed"]
    # what each ran with: the given factor, resolved with the stage's defaults
    assert same["params_resolved"] == {"factor": "1.0"} and scaled["params_resolved"] == {
        "factor": "1.01"
    }
    assert same["stage_report"]["faces"] == 12100 and same["library_calls"] == []
    env = saved["environment"]
    assert (
        env["recon"]
        and env["machine"]["cores"] >= 1
        and env["date"].endswith("Z")
        and env["libraries"]["numpy"]
    )
    prov = saved["provenance"]["input"]
    assert (
        prov["faces"] == 12100
        and len(prov["sha256"]) == 64
        and prov["bytes"] == shared_path("kitten").stat().st_size
    )
    assert res["unit"] == "mm" and res["vmax"] == pytest.approx(0.002)
    md = (out / "report.md").read_text()
    assert (
        "| fakescale:factor=1.01 | ok |" in md
        and "![overview](overview.png)" in md
        and "nothing to reconstruct" in md
    )
    assert (
        "Chamfer-L1 [mm] ↓" in md
        and "F-score @0.5% ↑" in md
        and "stage time [s] ↓" in md
        and "peak memory [MB] ↓" in md
    )
    assert "  - stage parameters: factor=1.01" in md and "sha256" in md and "cores" in md
    html = (out / "report.html").read_text()
    assert "<img src='overview.png'" in html and "<img src='quality_vs_time.png'" in html
    assert (
        html.count("<tr class=") == 4 and "<script>" in html and "http" not in html
    )  # offline: nothing fetched
    # pictures: the per-method sheet (turntable: 4 columns; shape, accuracy, completeness,
    # reference) and the overview
    from PIL import Image

    img = np.asarray(Image.open(out / "fakescale_factor_1.01.png").convert("RGB"))
    box = layout(4, 4, 240, title=True, colorbar=True, legend=True)
    assert img.shape == (box["size"][3], box["size"][2], 3)
    for name in [
        "title",
        *(f"column {k}" for k in range(4)),
        *(f"row {r}" for r in range(4)),
        "colorbar top",
        "colorbar title",
    ]:
        assert ink(img, box[name]) >= 15, name
    img = np.asarray(Image.open(out / "overview.png").convert("RGB"))
    box = layout(
        3, 3, 240, title=True, colorbar=True, legend=True
    )  # 2 methods + the reference; 3 rows
    assert img.shape == (box["size"][3], box["size"][2], 3)
    for name in ["column 0", "column 1", "column 2", "row 0", "row 1", "row 2", "colorbar top"]:
        assert ink(img, box[name]) >= 15, name
    img = np.asarray(Image.open(out / "quality_vs_time.png").convert("RGB"))
    assert (
        img.shape == (480, 2 * 760, 3)
        and ink(img, (0, 0, 760, 480)) > 200
        and ink(img, (760, 0, 1520, 480)) > 200
    )


def test_compare_cli_runs_a_real_stage_in_a_child(tmp_path, capsys):
    """``recon compare`` runs ball pivoting in a child: accurate, its radii and time reported."""
    from shared_data import sampled_cloud, shared_path

    cloud = sampled_cloud("kitten", 4000, seed=2)
    cloud.attributes = {}
    src = tmp_path / "kc.ply"
    write_ply(cloud, src)
    out = tmp_path / "cmp"
    code, stdout, err = run(
        capsys,
        "compare",
        src,
        "--methods",
        "ballpivot",
        "--ref",
        shared_path("kitten"),
        "--out",
        out,
        "--samples",
        5000,
        "--json",
    )
    assert code == 0, err
    res = json.loads(stdout)
    r = res["methods"][0]
    assert r["status"] == "ok", r["error"]
    assert r["seconds"] > 0 and r["peak_mb"] > 0 and r["faces"] > 4000
    # ball pivoting interpolates exact samples: accurate to well under 1 % of the diagonal
    assert r["metrics"]["accuracy"] < 1e-3 * r["metrics"]["reference_diagonal"]
    assert (out / "report.md").exists() and (out / "ballpivot.png").exists()
    # the automatic radii are reported as what it ran with, and the peak memory and process time are
    # there
    radii = r["stage_report"]["radii"]
    assert r["params_resolved"]["radii"] == radii and len(radii) >= 1 and r["params"] == {}
    assert r["process_seconds"] >= r["seconds"]
    assert "radii=" + ",".join(f"{x:.6g}" for x in radii) in (out / "report.md").read_text()
    code, stdout, err = run(capsys, "compare", src, "--methods", "nosuchstage", "--out", out)
    assert code == 2 and "unknown stage" in err
