"""Ball pivoting (recon_cli.stages.ballpivot): quality, topology and exactness, against references.

Quality against Open3D, topology by construction, exact triangulations, cross-checks with
Open3D and PyMeshLab, bad input, CLI.
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon_cli.backends import open3d_backend, pymeshlab_backend
from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.geometry import PointCloud, TriangleMesh, bbox_diagonal
from recon_cli.mesh import topology
from recon_cli.mesh.sampling import face_normals, sample_surface
from recon_cli.stages import apply_stage
from recon_cli.stages.ballpivot import auto_radii, ball_pivoting, nn_spacing, run_stage

from shared_data import ALL_MESHES, load_shared, sampled_cloud


# ---------------------------------------------------------------- helpers
def fscore(mesh: TriangleMesh, truth_samples: np.ndarray, tau: float) -> float:
    """F-score at ``tau`` between dense area-uniform samples of ``mesh`` and of the true mesh."""
    a = sample_surface(mesh, len(truth_samples), seed=1).points
    da, _ = cKDTree(truth_samples).query(a, workers=-1)
    db, _ = cKDTree(a).query(truth_samples, workers=-1)
    p, r = float((da < tau).mean()), float((db < tau).mean())
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


def chamfer(m1: TriangleMesh, m2: TriangleMesh, n: int = 20_000) -> float:
    """Symmetric mean point-to-surface distance between samples of each mesh and the other."""
    a = sample_surface(m1, n, seed=3).points
    b = sample_surface(m2, n, seed=4).points
    dist = open3d_backend.unsigned_distance
    return 0.5 * (dist(m2, a).mean() + dist(m1, b).mean())


def agreement(points: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> float:
    """Fraction of faces whose normal points the way of the mean of their vertex normals."""
    fn, _ = face_normals(points, faces)
    return float((np.einsum("ij,ij->i", fn, normals[faces].sum(axis=1)) > 0).mean())


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """The number of faces at each distinct edge of ``faces``."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    return cnt


def assert_clean_topology(mesh: TriangleMesh) -> dict:
    """Assert a manifold, consistently oriented mesh (ours and Open3D's checks); its report."""
    rep = topology.report(mesh)
    assert rep["non_manifold_edges"] == 0
    assert rep["non_manifold_vertices"] == 0
    assert rep["duplicate_faces"] == 0
    assert rep["degenerate_faces"] == 0
    assert rep["consistently_oriented"]
    assert edge_face_counts(mesh.faces).max() <= 2
    # Open3D's own predicates (not manifold_checks: its is_watertight tests self-intersection,
    # slowly)
    m = open3d_backend.to_o3d_mesh(mesh)
    assert m.is_edge_manifold(allow_boundary_edges=True) and m.is_vertex_manifold()
    assert len(m.get_non_manifold_edges(allow_boundary_edges=True)) == 0
    assert len(m.get_non_manifold_vertices()) == 0
    return rep


def unit_sphere(n: int, seed: int = 0) -> np.ndarray:
    """``n`` random points on the unit sphere (they are also its normals)."""
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def flat_grid(nx: int = 30, ny: int = 20, h: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """An ``nx`` by ``ny`` grid of points ``h`` apart on a plane at an offset, normals +z."""
    x, y = np.meshgrid(np.arange(nx) * h, np.arange(ny) * h, indexing="ij")
    pts = np.c_[x.ravel(), y.ravel(), np.zeros(nx * ny)] + np.array([3.0, -2.0, 1.5])
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


# ---------------------------------------------------------------- shared meshes, 100k samples
@functools.cache
def _both(name: str):
    cloud = sampled_cloud(name, 100_000)
    radii = auto_radii(cloud.points)
    ours = TriangleMesh(cloud.points, ball_pivoting(cloud.points, cloud.normals, radii))
    ref = open3d_backend.ball_pivoting(cloud, radii)
    return cloud, radii, ours, ref


@pytest.mark.slow
@pytest.mark.parametrize("name", ALL_MESHES)
def test_shared_mesh_quality_vs_open3d(name):
    """100k samples of each shared mesh: F-score over 0.99 and Open3D's, clean and nearly closed.

    The mesh is manifold, oriented as the normals, with no more boundary edges than Open3D's
    (under 3 % of edges) and nearly every input point used.
    """
    cloud, radii, ours, ref = _both(name)
    truth = load_shared(name)
    tau = 0.005 * bbox_diagonal(truth.vertices)
    truth_samples = sample_surface(truth, 200_000, seed=2).points
    f_ours, f_ref = fscore(ours, truth_samples, tau), fscore(ref, truth_samples, tau)
    assert f_ours >= f_ref - 0.01
    assert f_ours > 0.99
    rep = assert_clean_topology(ours)
    ref_boundary = int((edge_face_counts(ref.faces) == 1).sum())
    assert rep["boundary_edges"] <= ref_boundary
    # holes are rare: under 3 % of the edges are boundary edges (Open3D: 2 to 6.5 %)
    assert rep["boundary_edges"] < 0.03 * rep["edges"]
    assert agreement(cloud.points, cloud.normals, ours.faces) >= 0.999
    # the mesh interpolates: vertices are the input points, nearly all of them used
    assert rep["unreferenced_vertices"] < 0.005 * len(cloud.points)


# ---------------------------------------------------------------- exact cases
@pytest.mark.parametrize("radii", ["auto", [0.075], [0.1, 0.2]])
def test_flat_grid_two_triangles_per_square(radii):
    """A flat grid meshes as exactly two triangles a square, facing +z, one boundary loop."""
    nx, ny, h = 30, 20, 0.1
    pts, nrm = flat_grid(nx, ny, h)
    faces = ball_pivoting(pts, nrm, radii)
    assert len(faces) == 2 * (nx - 1) * (ny - 1)
    mesh = TriangleMesh(pts, faces)
    rep = assert_clean_topology(mesh)
    assert rep["boundary_edges"] == 2 * (nx - 1 + ny - 1)
    assert rep["boundary_loops"] == 1
    assert rep["unreferenced_vertices"] == 0
    fn, area = face_normals(pts, faces)
    np.testing.assert_allclose(area, 0.5 * h * h, rtol=1e-9)  # each is half a square
    np.testing.assert_allclose(fn, np.tile([0.0, 0.0, 1.0], (len(faces), 1)), atol=1e-12)
    # every face lies within one grid square
    ij = np.floor((pts[faces] - pts.min(axis=0))[:, :, :2] / h + 1e-9).astype(int)
    span = ij.max(axis=1) - ij.min(axis=1)
    assert np.all(span == 1)


def test_flat_grid_flipped_normals_wind_the_other_way():
    """Flipped normals on a flat grid give as many faces, all facing -z."""
    pts, nrm = flat_grid(12, 9)
    up = ball_pivoting(pts, nrm, [0.1])
    down = ball_pivoting(pts, -nrm, [0.1])
    assert len(up) == len(down) == 2 * 11 * 8
    assert np.all(face_normals(pts, down)[0][:, 2] < -0.999)


def test_dense_random_sphere_is_closed():
    """20k random points on a sphere: a closed one-piece genus-0 mesh with the sphere's volume."""
    pts = unit_sphere(20_000)
    s = nn_spacing(pts)
    faces = ball_pivoting(pts, pts, [2 * s, 4 * s, 8 * s])
    rep = assert_clean_topology(TriangleMesh(pts, faces))
    assert rep["watertight"]
    assert rep["boundary_edges"] == 0
    assert rep["euler_characteristic"] == 2 and rep["components"] == 1
    assert rep["unreferenced_vertices"] == 0
    assert agreement(pts, pts, faces) == 1.0
    assert abs(rep["volume"] - 4 / 3 * np.pi) < 0.01 * 4 / 3 * np.pi


def test_auto_radii_rule():
    """Automatic radii are 2 and 4 times the point spacing, duplicates not counted."""
    pts, _ = flat_grid(10, 10, 0.1)
    np.testing.assert_allclose(auto_radii(pts), [0.2, 0.4], rtol=1e-9)
    # exact duplicates do not shrink the spacing
    np.testing.assert_allclose(auto_radii(np.r_[pts, pts]), [0.2, 0.4], rtol=1e-9)


@pytest.mark.parametrize("seed", range(16))
def test_nn_spacing_is_the_exact_median_nearest_positive_distance(seed):
    """``nn_spacing`` equals the brute-force median of nearest positive distances, on any cloud.

    ``nn_spacing`` (our grid, no k-d tree) equals the brute-force median distance to the nearest
    point at a positive distance, on blobs, flat and thin sheets, lines, clouds with many exact
    duplicates, far from the origin and at any scale.
    """
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 1500))
    kind = seed % 5
    if kind == 0:
        pts = rng.normal(size=(n, 3))
    elif kind == 1:  # a sheet, very thin along one axis
        pts = np.c_[rng.uniform(size=(n, 2)), rng.uniform(size=n) * 1e-6]
    elif kind == 2:  # a line
        pts = np.outer(rng.uniform(size=n), rng.normal(size=3))
    elif kind == 3:  # half the points one repeated point
        pts = rng.normal(size=(n, 3))
        pts[: n // 2] = pts[0]
    else:  # a cluster far from the origin
        pts = rng.normal(size=(n, 3)) * 1e-3 + 1e6
    pts = pts * 10.0 ** rng.uniform(-4, 4) @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    gap = np.sqrt(((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
    gap[gap == 0] = np.inf
    nearest = gap.min(axis=1)
    want = float(np.median(nearest[np.isfinite(nearest)])) if np.isfinite(nearest).any() else 0.0
    assert nn_spacing(pts) == pytest.approx(want, rel=1e-12, abs=0)
    # one point far from all others: its distance is in the median, or the point is left out
    # (no other point within SPACING_RINGS cells of it)
    far = np.r_[pts, [pts.min(axis=0) + 1e3 * (np.ptp(pts, axis=0).max() + 1e-9)]]
    gap = np.sqrt(((far[:, None, :] - far[None, :, :]) ** 2).sum(-1))
    gap[gap == 0] = np.inf
    nearest = gap.min(axis=1)
    with_far = float(np.median(nearest[np.isfinite(nearest)]))
    assert nn_spacing(far) in (
        pytest.approx(with_far, rel=1e-12, abs=0),
        pytest.approx(want, rel=1e-12, abs=0),
    )


# ---------------------------------------------------------------- cross-checks
@pytest.mark.slow
def test_cross_check_open3d_pymeshlab_chamfer():
    """Ours, Open3D's and PyMeshLab's meshes of a cloud agree in Chamfer distance within 2e-4.

    Ours also covers at least each reference's area, with no more boundary edges.
    """
    cloud = sampled_cloud("kitten", 20_000)
    diag = bbox_diagonal(cloud.points)
    radii = auto_radii(cloud.points)
    ours = TriangleMesh(cloud.points, ball_pivoting(cloud.points, cloud.normals, radii))
    o3d = open3d_backend.ball_pivoting(cloud, radii)
    pml = pymeshlab_backend.ball_pivoting_radii(cloud, radii)
    assert chamfer(ours, o3d) < 2e-4 * diag
    assert chamfer(ours, pml) < 2e-4 * diag
    assert chamfer(o3d, pml) < 2e-4 * diag
    # at least as complete as each reference with the same radii, and as PyMeshLab's own radius
    pml_auto = pymeshlab_backend.ball_pivoting(cloud)
    area = topology.report(ours)["area"]
    for ref in (o3d, pml, pml_auto):
        assert area >= topology.report(ref)["area"]
        assert (edge_face_counts(ours.faces) == 1).sum() <= (edge_face_counts(ref.faces) == 1).sum()


def test_backends_through_run_stage():
    """The native and Open3D backends report the same radii and keep the points; meshes close."""
    cloud = sampled_cloud("mug", 5_000)
    radii = auto_radii(cloud.points)
    res = {b: run_stage(cloud, radii=radii, backend=b) for b in ("native", "open3d")}
    assert res["open3d"].report["radii"] == res["native"].report["radii"]
    a, b = res["native"].output, res["open3d"].output
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert chamfer(a, b, 5_000) < 1e-3 * bbox_diagonal(cloud.points)


# ---------------------------------------------------------------- stage, report, provenance
def test_stage_report_and_provenance():
    """The stage's report, provenance and history; the radii as a CLI string give the same faces."""
    cloud = sampled_cloud("kitten", 5_000)
    cloud.history = ["made by a test"]
    res = apply_stage("ballpivot", cloud, {"radii": "auto"})
    rep = res.report
    for key in (
        "faces",
        "boundary_edges",
        "boundary_loops",
        "radii",
        "non_manifold_edges",
        "non_manifold_vertices",
    ):
        assert key in rep
    assert rep["radii"] == pytest.approx(auto_radii(cloud.points))
    assert rep["provenance"] == {"radii": rep["radii"]}
    assert rep["non_manifold_edges"] == 0 and rep["non_manifold_vertices"] == 0
    assert rep["faces"] == len(res.output.faces)
    out = res.output
    assert out.history[0] == "made by a test"
    assert (
        "ballpivot" in out.history[-1]
        and "radii=" + ",".join(str(r) for r in rep["radii"]) in out.history[-1]
    )
    np.testing.assert_array_equal(out.vertices, cloud.points)
    np.testing.assert_array_equal(out.normals, cloud.normals)
    # the CLI string form gives the same mesh
    text = ",".join(repr(r) for r in rep["radii"])
    np.testing.assert_array_equal(run_stage(cloud, radii=text).output.faces, out.faces)
    json.dumps(rep)


def test_cli_json(tmp_path):
    """``recon ballpivot --json`` as a process: its report matches the mesh written."""
    from recon_cli.io.ply import read_ply, write_ply

    src = tmp_path / "in.ply"
    dst = tmp_path / "out.ply"
    cloud = sampled_cloud("mug", 3_000)
    write_ply(cloud, src)
    r = subprocess.run(
        [sys.executable, "-m", "recon_cli.cli.main", "ballpivot", str(src), str(dst), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["faces"] > 5_000 and rep["non_manifold_vertices"] == 0
    assert len(rep["provenance"]["radii"]) == 2
    mesh = read_ply(dst)
    assert len(mesh.faces) == rep["faces"]
    assert any("ballpivot" in h and "radii=" in h for h in mesh.history)


# ---------------------------------------------------------------- bad input
def test_no_normals_names_recon_normals():
    """A cloud without normals is refused with a message naming ``recon normals``."""
    cloud = PointCloud(points=sampled_cloud("kitten", 500).points)
    with pytest.raises(InputError, match="recon normals"):
        run_stage(cloud)
    with pytest.raises(InputError, match="recon normals"):
        ball_pivoting(cloud.points, None, "auto")


@pytest.mark.parametrize("radii", [[0.0], [-0.1], [0.1, -0.2], [float("nan")], "0.1,abc", [], "0"])
def test_bad_radii(radii):
    """Zero, negative, NaN, non-numeric or empty radii raise ParameterError."""
    pts, nrm = flat_grid(5, 5)
    with pytest.raises(ParameterError):
        ball_pivoting(pts, nrm, radii)


def test_radius_larger_than_cloud():
    """A radius over the cloud's diagonal is refused as "larger than the cloud"."""
    pts, nrm = flat_grid(5, 5)
    diag = bbox_diagonal(pts)
    with pytest.raises(ParameterError, match="larger than the cloud"):
        ball_pivoting(pts, nrm, [0.1, 3 * diag])
    with pytest.raises(ParameterError, match="larger than the cloud"):
        run_stage(PointCloud(points=pts, normals=nrm), radii=f"{10 * diag}")


def test_radius_far_below_spacing_makes_no_face():
    """A radius far below the spacing gives no face, and the stage fails as "too small"."""
    pts, nrm = flat_grid(5, 5)
    assert ball_pivoting(pts, nrm, [0.01]).shape == (0, 3)
    with pytest.raises(StageFailed, match="too small"):
        run_stage(PointCloud(points=pts, normals=nrm), radii=[0.01])


def test_too_few_points():
    """Two points are refused; three points give their one triangle."""
    with pytest.raises(InputError, match="at least 3"):
        ball_pivoting(np.zeros((2, 3)), np.tile([0.0, 0, 1], (2, 1)), [1.0])
    one_triangle = ball_pivoting(np.eye(3), np.ones((3, 3)), [1.0])
    np.testing.assert_array_equal(one_triangle, [[0, 1, 2]])


def test_nan_rows_are_ignored():
    """Rows with NaN or zero normals are skipped: no face uses them, the other squares meshed."""
    nx, ny = 12, 10
    pts, nrm = flat_grid(nx, ny)
    bad = np.array([3, 40, 77])  # two on the border (2 squares each), one inside (4 squares)
    p2, n2 = pts.copy(), nrm.copy()
    p2[bad[0], 1] = np.nan
    n2[bad[1]] = np.nan
    n2[bad[2]] = 0.0
    # rho below the point spacing: only the half-squares fit a ball
    faces, info = ball_pivoting(p2, n2, [0.09], return_info=True)
    assert info["skipped_points"] == 3
    assert not np.isin(faces, bad).any()
    assert faces.max() < len(pts)
    # a square with a missing corner keeps the one triangle of its other three corners
    idx = np.arange(nx * ny).reshape(nx, ny)
    corners = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]], axis=-1).reshape(
        -1, 4
    )
    missing = np.isin(corners, bad).sum(axis=1)
    assert missing.max() == 1
    assert len(faces) == 2 * (missing == 0).sum() + (missing == 1).sum()
    rep = assert_clean_topology(TriangleMesh(pts, faces))
    assert (
        rep["boundary_loops"] == 2
    )  # the outer border (through two holes' notches) and the inner hole
    assert rep["unreferenced_vertices"] == 3


def test_duplicate_points_are_used_once():
    """A grid given twice: one copy of each point used, two triangles a square, clean topology."""
    nx, ny = 15, 11
    pts, nrm = flat_grid(nx, ny)
    faces, info = ball_pivoting(np.r_[pts, pts], np.r_[nrm, nrm], [0.1], return_info=True)
    assert info["duplicate_points"] == len(pts)
    assert len(faces) == 2 * (nx - 1) * (ny - 1)
    assert len(np.unique(faces)) == len(pts)  # one copy of each point is used
    assert_clean_topology(TriangleMesh(np.r_[pts, pts], faces))


def test_shape_errors():
    """Points or normals of the wrong shape, and an unknown backend, are refused."""
    with pytest.raises(InputError, match="shape"):
        ball_pivoting(np.zeros((5, 2)), np.zeros((5, 2)), [1.0])
    with pytest.raises(InputError, match="shape"):
        ball_pivoting(np.zeros((5, 3)), np.zeros((4, 3)), [1.0])
    with pytest.raises(ParameterError, match="backend"):
        run_stage(PointCloud(points=np.eye(3), normals=np.ones((3, 3))), backend="cgal")
