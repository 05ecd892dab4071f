"""Poisson's --envelope: a closed mesh bounding the surface (chi fixed to 0 outside it), refused
in one line when it is not a closed mesh; and --confidence (weights from the normals' lengths)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from click.testing import CliRunner

from recon_cli.cli.main import cli
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import read_ply, write_ply
from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.envelope import CellClassifier, Envelope
from recon_cli.stages.poisson.octree import pack_keys

from shapes import FAR_OFFSETS, icosphere, random_rotation, shape_cloud, single_view_scan
from shared_data import load_shared


def _sphere_around(p: np.ndarray, factor: float) -> TriangleMesh:
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    radius = factor * np.linalg.norm(p - centre, axis=1).max()
    v, f = icosphere(4, radius, centre)
    return TriangleMesh(vertices=v, faces=f)


@functools.cache
def _bunny():
    from recon_cli.stages.normals import run_stage as normals

    scan = load_shared("bunny_scan_000")
    return normals(PointCloud(points=scan.points)).output


def test_bunny_scan_inside_a_sphere():
    # the shared raw scan: its closing sheet runs outside a sphere just around it; with the
    # sphere as the envelope no vertex is outside
    c = _bunny()
    env = _sphere_around(c.points, 1.03)
    e = Envelope(env)
    free = screened_poisson(c.points, c.normals, depth=7)
    assert np.count_nonzero(~e.inside(free.mesh.vertices)) > 100
    res = screened_poisson(c.points, c.normals, depth=7, envelope=env)
    assert res.report["envelope_outside_points"] == 0
    assert np.count_nonzero(~e.inside(res.mesh.vertices)) == 0
    assert res.report["envelope_pulled_vertices"] == 0
    # the scan itself is kept: its points are on the surface
    from recon_cli.mesh.distance import closest_points

    d = closest_points(res.mesh.vertices, res.mesh.faces, c.points)[0]
    assert np.quantile(d, 0.95) < res.report["finest_cell"]


@pytest.mark.parametrize("seed", [0, 1])
def test_open_scans_stay_in_a_box_envelope(seed):
    # single-view scans by ray casting, randomly rotated and far from the origin; the envelope a
    # box (rotated with them) 1.3x their extent
    rng = np.random.default_rng(seed)
    p, n = single_view_scan(["torus", "rounded_box"][seed], 70, rng, direction=rng.normal(size=3))
    lo, hi = p.min(axis=0), p.max(axis=0)
    c, h = 0.5 * (lo + hi), 0.65 * (hi - lo) + 0.3
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    from scipy.spatial import ConvexHull

    bv = c + corners * h
    bf = ConvexHull(bv).simplices
    rot = random_rotation(rng)
    off = np.asarray(FAR_OFFSETS["1e6"])
    p, n, bv = p @ rot.T + off, n @ rot.T, bv @ rot.T + off
    env = TriangleMesh(vertices=bv, faces=bf)
    res = screened_poisson(p, n, depth=6, envelope=env)
    assert not (~Envelope(env).inside(res.mesh.vertices)).any()
    # the last guard moves at most a few vertices of coarse leaves onto the envelope
    assert res.report["envelope_pulled_vertices"] <= 1e-3 * len(res.mesh.vertices)
    assert len(res.mesh.faces) > 1000


def test_classifier_inherits_from_parents(rng):
    # a cell's answer from its parent's equals measuring it
    env = Envelope(TriangleMesh(*icosphere(3, 0.3, (0.5, 0.5, 0.5))))
    cls = CellClassifier(env, np.zeros(3), 1.0)
    for level in range(2, 7):
        n = 1 << level
        xyz = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
        got = cls(level, pack_keys(xyz))
        want = env.free_cells((xyz + 0.5) / n, 1.0 / n)
        assert np.array_equal(got, want), level
    assert got.sum() > 1000


def test_refused_envelopes(tmp_path, rng):
    p, n = shape_cloud("sphere", 2000, rng)
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    v, f = icosphere(2, 2.0)
    write_ply(TriangleMesh(vertices=v, faces=f[:-1]), tmp_path / "open.ply")
    write_ply(PointCloud(points=v), tmp_path / "cloud.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a mesh")
    write_ply(TriangleMesh(vertices=0.2 * v, faces=f), tmp_path / "small.ply")
    for name, match in (
        ("open.ply", "must be a closed mesh: 3 edges"),
        ("cloud.ply", "needs a closed triangle mesh, got a point cloud"),
        ("missing.ply", "no such file"),
        ("junk.ply", ""),
        ("small.ply", "every point lies outside the envelope"),
    ):
        r = CliRunner().invoke(
            cli, ["poisson", str(src), str(out), "--depth", "5", "--envelope", str(tmp_path / name)]
        )
        assert isinstance(r.exception, InputError) and r.exception.exit_code == 2, (name, r.output)
        assert match in str(r.exception) and "\n" not in str(r.exception)
        assert not out.exists()
    with pytest.raises(ParameterError, match="degree 2"):
        screened_poisson(p, n, depth=5, degree=1, envelope=TriangleMesh(vertices=v, faces=f))
    r = CliRunner().invoke(
        cli,
        [
            "poisson",
            str(src),
            str(out),
            "--envelope",
            str(tmp_path / "small.ply"),
            "--backend",
            "open3d",
        ],
    )
    assert isinstance(r.exception, ParameterError) and "native" in str(r.exception)


def test_cli_envelope(tmp_path, rng):
    p, n = shape_cloud("torus", 5000, rng, offset=1e6)
    src, out, env = tmp_path / "in.ply", tmp_path / "out.ply", tmp_path / "env.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    write_ply(_sphere_around(p, 1.2), env)
    r = CliRunner().invoke(
        cli, ["poisson", str(src), str(out), "--depth", "6", "--envelope", str(env), "--json"]
    )
    assert r.exit_code == 0, r.output
    assert '"envelope_outside_points": 0' in r.output
    mesh = read_ply(out)
    assert not (~Envelope(read_ply(env)).inside(mesh.vertices)).any()


def test_confidence_weights_the_points(rng):
    # the same lengths everywhere change nothing; short normals on a cluster of wrong points
    # (a second, offset sphere's cap) let the surface ignore it
    p, n = shape_cloud("sphere", 20_000, rng)
    a = screened_poisson(p, n, depth=6)
    b = screened_poisson(p, 7.0 * n, depth=6, confidence=True)
    np.testing.assert_allclose(a.mesh.vertices, b.mesh.vertices, rtol=0, atol=1e-12)
    q, m = shape_cloud("sphere", 4000, rng)
    cap = q[:, 2] > 0.5
    bad_p, bad_n = 0.9 * q[cap] + [0.0, 0.0, 0.25], m[cap]
    P = np.concatenate([p, bad_p])
    N = np.concatenate([n, bad_n])
    weights = np.concatenate([np.ones(len(p)), np.full(len(bad_p), 0.02)])
    plain = screened_poisson(P, N, depth=6)
    conf = screened_poisson(P, N * weights[:, None], depth=6, confidence=True)
    err = {
        k: np.abs(np.linalg.norm(r.mesh.vertices, axis=1) - 1).mean()
        for k, r in (("plain", plain), ("confidence", conf))
    }
    assert err["confidence"] < 0.5 * err["plain"], err
