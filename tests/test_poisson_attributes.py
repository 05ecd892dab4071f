"""Poisson's --attributes: every per-point property of the input on the vertices, in its dtype,
codes by majority, measurements by mean, from the points on the vertex's side only."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from recon_cli.cli.main import cli
from recon_cli.errors import ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.io import read_ply, write_ply
from recon_cli.stages.poisson import run_stage, screened_poisson
from recon_cli.stages.poisson.attributes import (
    _majority,
    _mean,
    is_code,
    select,
    vertex_normals,
)

from shapes import _project, random_rotation, rounded_box_sdf, shape_cloud


def test_mean_and_majority_keep_dtypes_and_values():
    idx = np.array([[0, 1, 2], [2, 2, 1]])
    w = np.array([[0.5, 0.25, 0.25], [0.2, 0.2, 0.6]])
    v8 = np.array([10, 20, 201], np.uint8)
    out = _mean(v8, idx, w)
    assert out.dtype == np.uint8 and out.tolist() == [round(5 + 5 + 50.25), round(80.4 + 12)]
    vf = np.array([1.0, 2.0, 4.0], np.float32)
    assert _mean(vf, idx, w).dtype == np.float32
    codes = np.array([7, 3, 3], np.uint8)
    # row 0: 7 has 0.5, 3 has 0.5 -> tie, the smaller code; row 1: 3 has all the weight
    assert _majority(codes, idx, w).tolist() == [3, 3]
    assert _majority(np.array([True, False, False]), idx, w).dtype == np.bool_


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 6),
    st.integers(1, 8),
    st.integers(0, 2**31 - 1),
)
def test_majority_picks_a_present_value_of_largest_weight(m, k, seed):
    rng = np.random.default_rng(seed)
    values = rng.integers(-3, 4, size=10).astype(np.int16)
    idx = rng.integers(0, 10, size=(m, k))
    w = rng.random((m, k))
    out = _majority(values, idx, w)
    assert out.dtype == np.int16
    for r in range(m):
        row = values[idx[r]]
        assert out[r] in row
        tot = {int(x): w[r][row == x].sum() for x in np.unique(row)}
        best = max(tot.values())
        assert tot[int(out[r])] == pytest.approx(best)
        assert int(out[r]) == min(x for x, s in tot.items() if np.isclose(s, best))


def test_codes_and_measures():
    assert is_code("classification", np.zeros(1, np.uint8))
    assert is_code("return_number", np.zeros(1, np.uint8))
    assert is_code("flag", np.zeros(1, bool))
    assert not is_code("intensity", np.zeros(1, np.uint16))
    assert not is_code("Intensity", np.zeros(1, np.uint16))
    assert not is_code("gps_time", np.zeros(1))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.sampled_from(["a", "b", "c", "colors", "rgb"]), min_size=1, max_size=5))
def test_select_names(words):
    names, colors = select(",".join(words), ["a", "b", "c"], True)
    assert names == [w for i, w in enumerate(words) if w in "abc" and w not in words[:i]]
    assert colors == any(w in ("colors", "rgb") for w in words)


def test_select_all_none_and_unknown():
    assert select("all", ["x"], True) == (["x"], True)
    assert select(None, ["x"], False) == (["x"], False)
    assert select("none", ["x"], True) == ([], False)
    assert select(["x"], ["x"], True) == (["x"], False)
    with pytest.raises(ParameterError, match=r"no property 'y' \(it has: x, colors\)"):
        select("x,y", ["x"], True)
    with pytest.raises(ParameterError, match="no property 'colors'"):
        select("colors", ["x"], False)


def _plate(rng, half_thickness):
    """A rounded plate under a random rotation and an offset of 1e6, red on top, blue below."""

    def sdf(q):
        return rounded_box_sdf(q, half=(1.0, 0.8, half_thickness), radius=0.8 * half_thickness)

    p = rng.uniform(-1.05, 1.05, (300_000, 3))
    p[:, 2] *= 2 * half_thickness
    p = p[np.abs(sdf(p)) < 0.02]
    p, n = _project(sdf, p)
    ok = np.abs(sdf(p)) < 1e-6
    p, n = p[ok][:40_000], n[ok][:40_000]
    col = np.where(p[:, 2:3] > 0, [[255, 0, 0]], [[0, 0, 255]]).astype(np.uint8)
    rot = random_rotation(rng)
    return p @ rot.T + 1e6, n @ rot.T, col, rot


def test_thin_plate_colours_do_not_bleed(rng):
    # 0.016 thick at depth 7: under one finest cell (0.02), the other face's points are nearer
    # than a cell to every vertex
    p, n, col, rot = _plate(rng, 0.008)
    res = screened_poisson(p, n, depth=7, colors=col, properties={"side": (col[:, 0] > 0)})
    local = (res.mesh.vertices - 1e6) @ rot
    vn = vertex_normals(res.mesh.vertices, res.mesh.faces) @ rot
    inner = (np.abs(local[:, 0]) < 0.9) & (np.abs(local[:, 1]) < 0.7)
    top, bottom = inner & (vn[:, 2] > 0.9), inner & (vn[:, 2] < -0.9)
    assert top.sum() > 1000 and bottom.sum() > 1000
    c = res.mesh.colors
    assert c.dtype == np.uint8
    assert (c[top] == [255, 0, 0]).all() and (c[bottom] == [0, 0, 255]).all()
    side = res.mesh.attributes["side"]
    assert side.dtype == np.bool_ and side[top].all() and not side[bottom].any()
    assert res.report["attribute_fallback_vertices"] == 0
    # the same Gaussian over the nearest points of either side bleeds (the test can fail)
    d, i = cKDTree(p).query(res.mesh.vertices, k=8)
    w = np.exp(-0.5 * (d / res.report["finest_cell"]) ** 2)
    w[:, 0] = np.maximum(w[:, 0], 1e-300)
    naive = (col[i, 2] * w).sum(axis=1) / w.sum(axis=1)
    assert np.mean(naive[top] > 0.5) > 0.1


def test_every_attribute_in_its_dtype_and_none(rng):
    p, n = shape_cloud("sphere", 5000, rng, offset=1e6)
    z = (p[:, 2] - 1e6) > 0
    cloud = PointCloud(
        points=p,
        normals=n,
        colors=np.where(z[:, None], 200, 10).astype(np.uint16) * np.ones((1, 3), np.uint16),
        attributes={
            "classification": np.where(z, 2, 6).astype(np.uint8),
            "intensity": np.where(z, 1000, 3000).astype(np.uint16),
            "gps_time": np.where(z, 1.5, 2.5),
            "scan_angle_rank": np.where(z, -10, 10).astype(np.int8),
        },
    )
    res = run_stage(cloud, depth=6)
    mesh = res.output
    up = (mesh.vertices[:, 2] - 1e6) > 0.2
    down = (mesh.vertices[:, 2] - 1e6) < -0.2
    for k, v in cloud.attributes.items():
        assert mesh.attributes[k].dtype == v.dtype, k
    a = mesh.attributes
    assert (a["classification"][up] == 2).all() and (a["classification"][down] == 6).all()
    assert (a["intensity"][up] == 1000).all()
    np.testing.assert_allclose(a["gps_time"][down], 2.5, rtol=1e-6)
    assert mesh.colors.dtype == np.uint16 and (mesh.colors[up] == 200).all()
    assert res.report["attributes"] == [*sorted(cloud.attributes), "colors"]
    bare = run_stage(cloud, depth=6, attributes="none").output
    assert bare.attributes == {} and bare.colors is None
    some = run_stage(cloud, depth=6, attributes="intensity,rgb").output
    assert sorted(some.attributes) == ["intensity"] and some.colors is not None


def test_cli_unknown_attribute_is_refused(tmp_path, rng):
    p, n = shape_cloud("sphere", 2000, rng)
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(PointCloud(points=p, normals=n, attributes={"intensity": np.ones(len(p))}), src)
    r = CliRunner().invoke(cli, ["poisson", str(src), str(out), "--attributes", "label"])
    assert r.exception is not None and r.exception.exit_code == 2
    assert "no property 'label'" in str(r.exception) and not out.exists()


@pytest.mark.slow
def test_lidar_tile_has_intensity_classification_and_colour(tmp_path):
    from shared_data import SHARED

    las = SHARED / "autzen_trim.laz"
    nrm, out = tmp_path / "n.ply", tmp_path / "p.ply"
    r = CliRunner().invoke(cli, ["normals", str(las), str(nrm)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["poisson", str(nrm), str(out), "--depth", "7"])
    assert r.exit_code == 0, r.output
    mesh = read_ply(out)
    src = read_ply(nrm)
    assert mesh.colors is not None and mesh.colors.dtype == src.colors.dtype == np.uint16
    for k in ("intensity", "classification", "return_number", "gps_time"):
        assert mesh.attributes[k].dtype == src.attributes[k].dtype, k
    # the classes on the mesh are classes of the tile, ground among them
    assert set(np.unique(mesh.attributes["classification"])) <= set(
        np.unique(src.attributes["classification"])
    )
    assert (mesh.attributes["classification"] == 2).mean() > 0.1
