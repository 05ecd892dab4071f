"""Poisson's --attributes: every per-point property of the input on the vertices, in its dtype.

Codes by majority, measurements by mean, from the points on the vertex's side only.
"""

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
from recon_cli.stages.poisson import attributes as attributes_module
from recon_cli.stages.poisson import run_stage, screened_poisson
from recon_cli.stages.poisson.attributes import (
    _Grid,
    _majority,
    _mean,
    is_code,
    select,
    transfer,
    vertex_normal_sums,
    vertex_normals,
)

from shapes import _project, random_rotation, rounded_box_sdf, shape_cloud


def test_mean_and_majority_keep_dtypes_and_values():
    """Mean and majority keep the values' dtypes and values; a tie goes to the smaller code."""
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
    """The majority is a present value of the largest total weight, on random rows."""
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
    """Classification, return numbers and flags are codes; intensity and times are measurements."""
    assert is_code("classification", np.zeros(1, np.uint8))
    assert is_code("return_number", np.zeros(1, np.uint8))
    assert is_code("flag", np.zeros(1, bool))
    assert not is_code("intensity", np.zeros(1, np.uint16))
    assert not is_code("Intensity", np.zeros(1, np.uint16))
    assert not is_code("gps_time", np.zeros(1))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.sampled_from(["a", "b", "c", "colors", "rgb"]), min_size=1, max_size=5))
def test_select_names(words):
    """select() keeps the named properties once, in order, and colours when asked."""
    names, colors = select(",".join(words), ["a", "b", "c"], True)
    assert names == [w for i, w in enumerate(words) if w in "abc" and w not in words[:i]]
    assert colors == any(w in ("colors", "rgb") for w in words)


def test_select_all_none_and_unknown():
    """select() of all, none, a list or nothing; an unknown property refused."""
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
    """A plate thinner than a cell: each face's vertices take their own side's colour, no bleeding.

    A Gaussian over the nearest points of either side does bleed here, so the test can fail.
    """
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
    """Colours and every attribute in their dtype, with the values of their side of a sphere."""
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
    """``--attributes`` naming a property the input lacks exits 2 and writes nothing."""
    p, n = shape_cloud("sphere", 2000, rng)
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(PointCloud(points=p, normals=n, attributes={"intensity": np.ones(len(p))}), src)
    r = CliRunner().invoke(cli, ["poisson", str(src), str(out), "--attributes", "label"])
    assert r.exception is not None and r.exception.exit_code == 2
    assert "no property 'label'" in str(r.exception) and not out.exists()


@pytest.mark.slow
def test_lidar_tile_has_intensity_classification_and_colour(tmp_path):
    """A lidar tile through normals and poisson: colour and LAS attributes in their dtypes.

    The mesh's classes are classes of the tile, ground among them.
    """
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


def _kd_tree_transfer(points, normals, values, verts, vn, cell):
    """The transfer as it was made with a k-d tree: the reference the grid must match bit for bit.

    Every vertex's 16 nearest points, a block's rows widened to the 64 of its fallback rows.
    """
    tree = cKDTree(points)
    n = len(points)

    def side(d, i, nv):
        agree = np.einsum("mkj,mj->mk", normals[i], nv) > 0.0
        w = np.exp(-0.5 * (d / cell) ** 2) * agree
        first = np.argmax(agree, axis=1)
        rows = np.arange(len(nv))
        has = agree[rows, first]
        w[rows[has], first[has]] = np.maximum(w[rows[has], first[has]], 1e-300)
        s = w.sum(axis=1)
        w[has] /= s[has, None]
        return w, ~has

    k, k2 = min(16, n), min(64, n)
    d, i = (a.reshape(len(verts), k) for a in tree.query(verts, k=k))
    w, none = side(d, i, vn)
    reach = d[:, -1].copy()
    fallback = 0
    if none.any():
        rows = np.flatnonzero(none)
        d2, i2 = (a.reshape(len(rows), k2) for a in tree.query(verts[rows], k=k2))
        w2, none2 = side(d2, i2, vn[rows])
        w2[none2] = 0.0
        w2[none2, 0] = 1.0
        fallback = int(none2.sum())
        reach[rows] = d2[:, -1]
        wide_i, wide_w = np.zeros((len(verts), k2), np.int64), np.zeros((len(verts), k2))
        wide_i[:, :k], wide_w[:, :k] = i, w
        wide_i[rows], wide_w[rows] = i2, w2
        i, w = wide_i, wide_w
    out = {name: (_majority if is_code(name, v) else _mean)(v, i, w) for name, v in values.items()}
    return out, fallback, reach


@pytest.mark.parametrize("n", [5, 40, 3000])
@pytest.mark.parametrize("seed", [0, 1])
def test_transfer_is_the_k_d_tree_transfer_bit_for_bit(n, seed):
    """The grid-search transfer is the k-d tree transfer bit for bit.

    The grid search finds the k-d tree's neighbours, in its order, at its distances: every
    attribute, the fallback count and the reach are the same bits, for a sheet of points 1e6 from
    the origin with vertices on it, off it, flipped (no agreeing point: the 64), outside the points'
    box and far from every point (past the grid's shells: the k-d tree), and for fewer points than
    16 and 64.
    """
    rng = np.random.default_rng(seed)
    rot = random_rotation(rng)
    uv = rng.random((n, 2)) * [3.0, 2.0]
    flat = np.c_[uv, 0.02 * rng.standard_normal(n)]
    centre = np.array([1e6, -2e5, 3e5])
    points = flat @ rot.T + centre
    up = np.tile([0.0, 0.0, 1.0], (n, 1)) + 0.3 * rng.standard_normal((n, 3))
    normals = up @ rot.T
    m = 4000
    vflat = np.c_[rng.random((m, 2)) * [3.4, 2.4] - 0.2, 0.05 * rng.standard_normal(m)]
    vflat[:200, 2] += rng.uniform(0.5, 40.0, 200)  # off the sheet, some far past the shells
    vflat[200:260] -= [10.0, 0.0, 0.0]  # outside the points' box
    verts = vflat @ rot.T + centre
    vn = np.tile([0.0, 0.0, 1.0], (m, 1))
    vn[::7] *= -1.0  # the other side: their fallback
    vn = (vn + 0.2 * rng.standard_normal((m, 3))) @ rot.T
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    values = {
        "classification": rng.integers(0, 4, n).astype(np.uint8),
        "intensity": rng.integers(0, 60000, n).astype(np.uint16),
        "gps_time": rng.random(n) * 1e5,
        "height": rng.random(n).astype(np.float32),
        "flag": rng.random(n) < 0.5,
    }
    colors = rng.integers(0, 65535, (n, 3)).astype(np.uint16)
    cell = 0.05
    got = transfer(points, normals, values, colors, verts, None, cell, vn)
    want, fallback, reach = _kd_tree_transfer(points, normals, values, verts, vn, cell)
    for name, v in want.items():
        assert got.values[name].dtype == v.dtype
        np.testing.assert_array_equal(got.values[name], v, err_msg=name)
    rgb = ("red", "green", "blue")  # measurements: the mean, as the colours
    cols = _kd_tree_transfer(
        points, normals, dict(zip(rgb, colors.T, strict=True)), verts, vn, cell
    )[0]
    np.testing.assert_array_equal(got.colors, np.stack([cols[c] for c in rgb], 1))
    assert got.fallback == fallback > 0
    np.testing.assert_array_equal(got.reach, reach)


def test_grid_search_reads_past_its_shells_and_is_exact():
    """The grid search's neighbours are the k-d tree's, bit for bit, on clustered points.

    Clustered points (dense blobs, lone points between them) and queries at every distance: the same
    bits, also for the queries past its shells (answered by the k-d tree) and those outside the
    points' box.
    """
    rng = np.random.default_rng(7)
    blobs = rng.normal(size=(6, 3)) * 50.0
    pts = np.concatenate(
        [b + rng.normal(scale=0.5, size=(2000, 3)) for b in blobs] + [rng.uniform(-80, 80, (50, 3))]
    )
    grid = _Grid(pts)
    q = np.concatenate([pts[::37] + 0.01, rng.uniform(-200, 200, (3000, 3))])
    tree = cKDTree(pts)
    for k in (1, 16, 64):
        d, i = grid.query(q, k)
        d0, i0 = tree.query(q, k=k)
        np.testing.assert_array_equal(d, d0.reshape(len(q), k))
        np.testing.assert_array_equal(i, i0.reshape(len(q), k))
    assert grid._tree is not None  # some queries were past the shells


def test_vertex_normal_sums_are_np_add_at_bits():
    """vertex_normal_sums is np.add.at's sum of face normals, to the bit."""
    rng = np.random.default_rng(3)
    v = rng.normal(size=(500, 3)) * 1e3 + 1e5
    f = rng.integers(0, 500, (3000, 3))
    t = v[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    want = np.zeros_like(v)
    for c in range(3):
        np.add.at(want, f[:, c], fn)
    np.testing.assert_array_equal(vertex_normal_sums(v, f), want)
    assert attributes_module.FALLBACK_NEIGHBOURS == 64 and attributes_module.NEIGHBOURS == 16
