"""recon_cli.eval.report: what a compare report states (units, directions, parameters, setting)."""

from __future__ import annotations

import hashlib
import json
import re

import numpy as np
import pytest

from recon_cli.eval.report import (
    environment,
    file_provenance,
    html_page,
    markdown,
    parameter_lines,
    result_table,
)
from recon_cli.geometry import PointCloud
from recon_cli.io import write_ply


def _row(method="poisson:depth=7", status="ok", seconds=1.5, metrics=True):
    met = None
    if metrics:
        met = {
            "accuracy": 0.001,
            "completeness": 0.002,
            "chamfer_l1": 0.0015,
            "hausdorff": 0.01,
            "hausdorff_p95": 0.004,
            "tau_relative": [0.005, 0.01],
            "tau": [0.01, 0.02],
            "fscore": [0.9, 0.95],
            "normal_consistency": 0.99,
            "reference_diagonal": 2.0,
            "topology": {"candidate": {"watertight": True, "components": 1}},
        }
    return {
        "method": method,
        "stage": "poisson",
        "backend": "open3d",
        "params": {"depth": "7"},
        "status": status,
        "error": None if status == "ok" else "boom",
        "seconds": seconds if status == "ok" else None,
        "process_seconds": seconds + 2 if status == "ok" else None,
        "peak_mb": 12.5 if status == "ok" else None,
        "faces": 100 if status == "ok" else None,
        "vertices": 52,
        "metrics": met,
        "picture": None,
        "output": None,
        "params_resolved": {"depth": 7, "scale": 1.1, "radius": None} if status == "ok" else None,
        "stage_report": {"stage": "poisson", "faces": 100, "iso_value": None}
        if status == "ok"
        else None,
        "library_calls": [
            {"call": "open3d.x.poisson", "arguments": {"depth": 7, "linear_fit": False}}
        ]
        if status == "ok"
        else None,
    }


def _result(rows, unit="mm"):
    return {
        "input": "in.ply",
        "reference": "gt.ply",
        "samples": 1000,
        "seed": 0,
        "unit": unit,
        "reference_diagonal": 2.0,
        "methods": rows,
        "overview": None,
        "plot": None,
        "environment": environment(),
        "provenance": {"input": None, "reference": None},
    }


def test_table_heads_carry_units_and_directions():
    """Every numeric column head has its unit and which way is better; failed rows show dashes."""
    head, body = result_table(_result([_row(), _row("ballpivot", "failed", metrics=False)]))
    assert head[:2] == ["method", "status"]
    assert "accuracy [mm] ↓" in head and "Chamfer-L1 [mm] ↓" in head and "stage time [s] ↓" in head
    assert "process time [s] ↓" in head and "peak memory [MB] ↓" in head
    assert "F-score @0.5% ↑" in head and "F-score @1% ↑" in head and "normal consistency ↑" in head
    # every numeric column says which way is better
    for h in head[2:]:
        assert h.endswith(("↑", "↓")) or h in ("faces", "watertight", "components"), h
    assert body[0][head.index("process time [s] ↓")] == "3.5" and body[1][2:] == ["—"] * (
        len(head) - 2
    )
    head, _ = result_table(_result([_row()], unit=None))
    assert "accuracy [model units] ↓" in head


def test_parameter_lines_resolved_and_library_calls():
    """A row's lines: resolved parameters, the library call, the stage's report; none if failed."""
    lines = parameter_lines(_row())
    assert lines[0].startswith(
        "stage parameters (the backend passes only those in its library call): depth=7, "
        "scale=1.1, radius=none"
    )
    assert lines[1] == (
        "library call: open3d.x.poisson(depth=7, linear_fit=False), the library's defaults for "
        "the rest"
    )
    assert lines[2] == "stage reported: faces 100, iso-value none"
    assert parameter_lines(_row(status="failed")) == []


def test_environment_and_provenance(tmp_path):
    """The environment's date, machine and libraries; a file's hash, size, kind and history."""
    env = environment()
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", env["date"])
    assert env["machine"]["cores"] >= 1 and env["machine"]["memory_gb"] > 0
    assert set(env["libraries"]) >= {"numpy", "scipy", "numba", "open3d", "pymeshlab"}
    cloud = PointCloud(
        points=np.random.default_rng(0).normal(size=(50, 3)), history=["recon 0.1.0 normals knn=30"]
    )
    p = tmp_path / "c.ply"
    write_ply(cloud, p)
    prov = file_provenance(p, cloud)
    assert (
        prov["sha256"] == hashlib.sha256(p.read_bytes()).hexdigest()
        and prov["bytes"] == p.stat().st_size
    )
    assert (
        prov["kind"] == "cloud"
        and prov["points"] == 50
        and prov["faces"] == 0
        and not prov["normals"]
    )
    assert prov["history"] == ["recon 0.1.0 normals knn=30"]
    json.dumps(prov)


def test_markdown_and_html_state_the_setting_and_sort_offline(tmp_path):
    """Markdown and HTML reports state version, machine, units, provenance; HTML sorts offline."""
    res = _result([_row(), _row("ballpivot", seconds=0.5)])
    res["provenance"]["input"] = {
        "path": "in.ply",
        "bytes": 10,
        "sha256": "ab" * 32,
        "modified": "2026-01-01T00:00:00Z",
        "kind": "cloud",
        "points": 5,
        "faces": 0,
        "normals": True,
        "history": ["recon 0.1.0 normals"],
    }
    md = markdown(res, str(tmp_path))
    assert f"recon {res['environment']['recon']}" in md and res["environment"]["date"] in md
    assert (
        "cores" in md and "GB memory" in md and "Distances in mm" in md and "diagonal is 2 mm" in md
    )
    assert "history: recon 0.1.0 normals" in md and "sha256 abababab" in md
    assert "  - library call: open3d.x.poisson(depth=7, linear_fit=False)" in md
    page = html_page(res, str(tmp_path))
    assert (
        "<table class='sortable'>" in page
        and "<script>" in page
        and "addEventListener('click'" in page
    )
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", page)  # nothing to fetch: works offline
    # numeric cells carry their value for sorting; the dash of a missing value does not
    assert "<td data-v='1.5'>1.5</td>" in page and "<td data-v='0.5'>0.5</td>" in page


@pytest.mark.slow
def test_compare_records_the_reference_library_call(tmp_path):
    """``compare_methods`` with Open3D's Poisson records its exact library call and arguments."""
    from recon_cli.eval.compare import compare_methods

    rng = np.random.default_rng(3)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    src = tmp_path / "s.ply"
    write_ply(PointCloud(points=p, normals=p.copy()), src)
    res = compare_methods(
        src, "open3d:poisson:depth=5", None, tmp_path / "out", isolate=False, views=["front"]
    )
    row = res["methods"][0]
    assert row["status"] == "ok", row["error"]
    assert row["library_calls"] == [
        {
            "call": "open3d.geometry.TriangleMesh.create_from_point_cloud_poisson",
            "arguments": {"depth": 5, "scale": 1.1, "linear_fit": False, "n_threads": 1},
        }
    ]
    assert (
        row["params_resolved"]["depth"] == 5 and res["plot"] is None
    )  # no reference: nothing to plot
