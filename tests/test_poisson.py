"""Screened Poisson: quality against Open3D, cross-checks, topology, sphere, bad input."""

from __future__ import annotations

import functools
import logging

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon_cli.backends import open3d_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, bbox_diagonal
from recon_cli.mesh.sampling import sample_surface
from recon_cli.mesh.topology import report as topology_report
from recon_cli.stages.poisson import run_stage, screened_poisson

from reference import isolated
from shared_data import CLOSED_MESHES, load_shared, sampled_cloud

N_EVAL = 100_000


def _chamfer_f(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[float, float]:
    """Chamfer-L1 (mean of the two mean distances) and F-score at ``tau``."""
    da = cKDTree(b).query(a)[0]
    db = cKDTree(a).query(b)[0]
    p, r = float((da < tau).mean()), float((db < tau).mean())
    return 0.5 * (da.mean() + db.mean()), (2 * p * r / (p + r) if p + r > 0 else 0.0)


@functools.cache
def _ours(name: str, noise: float, depth: int):
    c = sampled_cloud(name, 100_000, noise=noise)
    return screened_poisson(c.points, c.normals, depth=depth)


@functools.cache
def _open3d(name: str, noise: float, depth: int):
    c = sampled_cloud(name, 100_000, noise=noise)
    return isolated(open3d_backend.poisson, c, depth=depth)[
        0
    ]  # its own process: see tests/reference.py


@functools.cache
def _truth_samples(name: str) -> np.ndarray:
    return sample_surface(load_shared(name), N_EVAL, seed=1).points


def _samples(mesh) -> np.ndarray:
    return sample_surface(mesh, N_EVAL, seed=2).points


def _quality_case(name: str, noise: float, depth: int, cross_check: bool = False) -> None:
    """Assert ours fits the true surface no worse than Open3D's (and, cross-checking, lies near it).

    ``cross_check``: also our surface within half a finest cell of Open3D's (Chamfer; in practice a
    third of a cell).
    """
    truth = load_shared(name)
    tau = 0.005 * bbox_diagonal(truth.vertices)
    ours = _ours(name, noise, depth)
    ref = _open3d(name, noise, depth)
    ours_samples, ref_samples = _samples(ours.mesh), _samples(ref)
    ch_o, f_o = _chamfer_f(ours_samples, _truth_samples(name), tau)
    ch_r, f_r = _chamfer_f(ref_samples, _truth_samples(name), tau)
    assert ch_o <= 1.05 * ch_r, (ch_o, ch_r)
    assert f_o >= f_r - 0.01, (f_o, f_r)
    if cross_check:
        cell = ours.report["finest_cell"]
        ch, _ = _chamfer_f(ours_samples, ref_samples, cell)
        assert ch < 0.5 * cell, (ch, cell)


@pytest.mark.slow
@pytest.mark.parametrize("name", CLOSED_MESHES + ["bunny_zipper"])
def test_quality_clean_depth8(name):
    """Clean samples at depth 8: ours fits each mesh no worse than Open3D."""
    # the same two meshes cross-check ours against Open3D on the shapes without thin parts
    _quality_case(name, 0.0, 8, cross_check=name in ("kitten", "armadillo"))


@pytest.mark.slow
@pytest.mark.parametrize("name", CLOSED_MESHES + ["bunny_zipper"])
def test_quality_noisy_depth8(name):
    """Noisy samples (0.25 %) at depth 8: ours fits each mesh no worse than Open3D."""
    _quality_case(name, 0.0025, 8)


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 0.0025])
def test_quality_depth9_kitten(noise):
    """The kitten at depth 9, clean and noisy: ours fits it no worse than Open3D."""
    # noisy depth 9 is where too strong a screening weight showed (ratio 1.06 before the
    # weight was calibrated); bench/quality_poisson.py prints every mesh
    _quality_case("kitten", noise, 9)


@pytest.mark.slow
@pytest.mark.parametrize("name", CLOSED_MESHES)
def test_untrimmed_output_is_watertight_manifold_and_outward(name):
    """The untrimmed surface of each closed mesh is watertight, manifold, oriented and outward.

    Checked with our topology and Open3D's own edge- and vertex-manifold predicates.
    """
    mesh = _ours(name, 0.0, 8).mesh
    topo = topology_report(mesh)
    assert topo["watertight"] and topo["edge_manifold"] and topo["vertex_manifold"]
    assert topo["consistently_oriented"] and topo["degenerate_faces"] == 0
    assert topo["volume"] is not None and topo["volume"] > 0  # outward
    # Open3D's own predicates (its is_watertight adds a quadratic self-intersection test:
    # checked on a small output below)
    m = open3d_backend.to_o3d_mesh(mesh)
    assert m.is_edge_manifold(allow_boundary_edges=False) and m.is_vertex_manifold()


def _separation(a, b):
    """The largest gap between triangles ``a`` and ``b`` (3, 3) over their separating axes.

    The axes: both normals and the nine edge cross products. > 0 when they are apart, <= 0 when they
    touch or cross.
    """
    ea = [a[1] - a[0], a[2] - a[1], a[0] - a[2]]
    eb = [b[1] - b[0], b[2] - b[1], b[0] - b[2]]
    best = -np.inf
    for ax in [np.cross(ea[0], ea[1]), np.cross(eb[0], eb[1])] + [
        np.cross(u, v) for u in ea for v in eb
    ]:
        norm = np.linalg.norm(ax)
        if norm > 1e-300:
            pa, pb = a @ (ax / norm), b @ (ax / norm)
            best = max(best, pb.min() - pa.max(), pa.min() - pb.max())
    return best


def test_separation_tells_crossing_from_apart():
    """_separation is > 0 for triangles apart and <= 0 for triangles that cross or touch."""
    a = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert _separation(a, np.array([[0.2, 0.2, -1], [0.3, 0.2, 1], [0.2, 0.3, 1]])) < 0  # pierces a
    assert _separation(a, a + [0, 0, 1e-3]) == pytest.approx(1e-3)  # parallel, above
    assert (
        _separation(a, np.array([[0.501, 0.5, 0], [2, 0, 1], [2, 2, -1]])) > 0
    )  # beside a's long edge, tilted
    assert (
        _separation(a, np.array([[0.499, 0.5, 0], [2, 0, 1], [2, 2, -1]])) <= 0
    )  # its corner inside a
    assert _separation(a, np.array([[1.0, 0, 0], [2, 0, 0], [1, 1, 0]])) <= 0  # shares a vertex


@pytest.mark.parametrize(("name", "depth"), [("kitten", 7), ("armadillo", 8)])
def test_open3d_closed_manifold_no_self_intersections(name, depth):
    """Open3D's checks on our mesh: closed and manifold; the triangles it flags do not touch.

    Each flagged pair is apart along one of its separating axes.
    """
    # Open3D's own checks: no boundary edge, edge- and vertex-manifold, orientable. Its
    # is_watertight also asks for no self-intersecting triangles, and its test flags a few
    # pairs here (1 on the kitten at depth 7, 5 on the armadillo at depth 8): triangles
    # around a lattice point where chi is at the iso-value, whose roots are kept a thousandth
    # of an edge from it. None of them touches: each pair is apart along one of its
    # separating axes, by 0.001-0.03 finest cells
    c = sampled_cloud(name, 20_000)
    mesh = screened_poisson(c.points, c.normals, depth=depth).mesh
    checks = open3d_backend.manifold_checks(mesh, self_intersection=False)
    assert (
        checks["watertight"]
        and checks["edge_manifold"]
        and checks["vertex_manifold"]
        and checks["orientable"]
    )
    flagged = np.asarray(open3d_backend.to_o3d_mesh(mesh).get_self_intersecting_triangles())
    assert len(flagged) <= 1e-3 * len(mesh.faces)
    v, f = mesh.vertices, mesh.faces
    gaps = [_separation(v[f[i]], v[f[j]]) for i, j in flagged]
    assert all(g > 0 for g in gaps), gaps


@pytest.mark.slow
@pytest.mark.parametrize("name", ["kitten", "armadillo"])
def test_cross_check_pymeshlab_within_one_cell(name):
    """Our surface and PyMeshLab's lie within half a finest cell of each other (Chamfer).

    Degree 2 (the default), depth 7 on 50k points, PyMeshLab being slow on a busy machine. Against
    Open3D: ``test_quality_clean_depth8``.
    """
    from recon_cli.backends import pymeshlab_backend

    c = sampled_cloud(name, 50_000)
    ours7 = screened_poisson(c.points, c.normals, depth=7)
    cell7 = ours7.report["finest_cell"]
    ch, _ = _chamfer_f(_samples(ours7.mesh), _samples(pymeshlab_backend.poisson(c, depth=7)), cell7)
    assert ch < 0.5 * cell7, (ch, cell7)


@pytest.mark.parametrize("degree", [1, 2])
def test_report_keys_and_solver_log(caplog, degree):
    """The report's keys and values (iso value near 1/2, small residual) and the solver's log."""
    c = sampled_cloud("kitten", 20_000)
    with caplog.at_level(logging.INFO, logger="recon"):
        res = run_stage(c, depth=6, degree=degree)
    rep = res.report
    for key in (
        "vertices",
        "faces",
        "depth",
        "iso_value",
        "solver_iterations",
        "residual",
        "trimmed_faces",
    ):
        assert key in rep
    assert rep["depth"] == 6 and rep["faces"] == len(res.output.faces) and rep["trimmed_faces"] == 0
    assert rep["solver_iterations"] > 0 and 0 <= rep["residual"] < 1e-3
    assert 0.3 < rep["iso_value"] < 0.7  # chi is about 1 inside, 0 outside, 1/2 at the samples
    assert any("cg iterations" in r.getMessage() for r in caplog.records)


def _sphere_cloud(n: int, r: float, rng) -> PointCloud:
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return PointCloud(points=r * v + np.array([1.0, -2.0, 0.5]), normals=v)


@pytest.mark.parametrize("degree", [1, 2])
@pytest.mark.parametrize("boundary", ["neumann", "dirichlet"])
def test_sphere_radius_within_half_a_cell(rng, boundary, degree):
    """A sphere, both boundaries and degrees: within half a finest cell of it, watertight."""
    r = 2.0
    c = _sphere_cloud(60_000, r, rng)
    res = screened_poisson(c.points, c.normals, depth=7, boundary=boundary, degree=degree)
    cell = res.report["finest_cell"]
    dist = np.linalg.norm(res.mesh.vertices - np.array([1.0, -2.0, 0.5]), axis=1)
    assert np.abs(dist - r).max() < 0.5 * cell, (np.abs(dist - r).max(), cell)
    assert topology_report(res.mesh)["watertight"]


@pytest.mark.parametrize("degree", [1, 2])
def test_unscreened_sphere_is_closed_and_close(rng, degree):
    """Without screening (point weight 0) a sphere is still closed and within a finest cell."""
    c = _sphere_cloud(30_000, 1.0, rng)
    res = screened_poisson(c.points, c.normals, depth=6, point_weight=0, degree=degree)
    dist = np.linalg.norm(res.mesh.vertices - np.array([1.0, -2.0, 0.5]), axis=1)
    assert np.abs(dist - 1.0).max() < res.report["finest_cell"]
    assert topology_report(res.mesh)["watertight"]


@pytest.mark.parametrize("degree", [1, 2])
def test_density_trim_and_colors(rng, degree):
    """An open half sphere: density marks the closing cap, trim removes it, colours follow."""
    # an open half sphere: Poisson closes it with a low-density cap that trimming removes
    c = _sphere_cloud(20_000, 1.0, rng)
    keep = c.normals[:, 2] > -0.2
    half = c.subset(keep)
    half.colors = np.clip((half.normals * 0.5 + 0.5) * 255, 0, 255).astype(np.uint8)
    full = run_stage(half, depth=6, density=True, degree=degree)
    mesh = full.output
    assert "density" in mesh.attributes and len(mesh.attributes["density"]) == len(mesh.vertices)
    assert topology_report(mesh)["watertight"]
    low = mesh.vertices[:, 2] < 0.5 - 0.4  # the cap, below every sample (z >= 0.3)
    high = mesh.vertices[:, 2] > 0.5 + 0.5
    assert low.sum() > 100 and high.sum() > 100
    assert mesh.attributes["density"][low].max() < mesh.attributes["density"][high].min()
    assert mesh.colors is not None and mesh.colors.dtype == np.uint8
    # colours follow the normals: red grows with x on the sphere
    xs = mesh.vertices[high, 0] - 1.0
    assert np.corrcoef(xs, mesh.colors[high, 0].astype(float))[0, 1] > 0.9
    # about 35 % of the vertices lie on the unsupported extension (density near 0)
    trimmed = run_stage(half, depth=6, trim=0.4, degree=degree).output
    t = topology_report(trimmed)
    assert t["edge_manifold"] and t["vertex_manifold"] and not t["watertight"]
    assert trimmed.vertices[:, 2].min() > 0.5 - 0.4
    assert len(trimmed.faces) < len(mesh.faces)


@pytest.mark.parametrize(
    "cloud, match",
    [
        (
            PointCloud(points=np.random.default_rng(0).random((100, 3))),
            "without normals .*--estimate-normals",
        ),
        (
            PointCloud(
                points=np.random.default_rng(0).random((100, 3)), normals=np.zeros((100, 3))
            ),
            "zero length",
        ),
        (
            PointCloud(points=np.ones((50, 3)), normals=np.tile([0.0, 0.0, 1.0], (50, 1))),
            "coincide",
        ),
        (PointCloud(points=np.eye(3), normals=np.eye(3)), "at least 4"),
    ],
)
def test_bad_input(cloud, match):
    """Inputs without usable normals, with coincident points or too few points are refused."""
    with pytest.raises(InputError, match=match):
        run_stage(cloud)


@pytest.mark.parametrize(
    "params",
    [
        {"depth": 0},
        {"depth": 20},
        {"depth": "x"},
        {"scale": 0.5},
        {"point_weight": -1},
        {"samples_per_node": 0},
        {"boundary": "periodic"},
        {"trim": 1.0},
        {"backend": "cgal"},
    ],
)
def test_bad_parameters(params):
    """Each out-of-range or unknown parameter value is refused."""
    c = sampled_cloud("kitten", 1000)
    with pytest.raises(ParameterError):
        run_stage(c, **params)


def test_zero_normals_are_ignored_and_strings_accepted():
    """Zero normals are ignored and counted; parameters given as text are accepted."""
    c = sampled_cloud("kitten", 20_000)
    c.normals[::10] = 0.0
    res = run_stage(c, depth="6", point_weight="4", boundary="Dirichlet", density="true")
    assert res.report["ignored_points"] == 2000
    assert topology_report(res.output)["watertight"]


@pytest.mark.slow
def test_reference_backends_report():
    """The Open3D and PyMeshLab backends report their backend and faces, no iso value."""
    c = sampled_cloud("kitten", 20_000)
    for backend in ("open3d", "pymeshlab"):
        res = run_stage(c, depth=6, backend=backend)
        assert (
            res.report["backend"] == backend and res.report["faces"] == len(res.output.faces) > 1000
        )
        assert res.report["iso_value"] is None


def test_cli_poisson(tmp_path):
    """``recon poisson`` writes a mesh with density; no normals: exit 2 naming the fix."""
    from click.testing import CliRunner

    from recon_cli.cli.main import cli
    from recon_cli.io import read_ply, write_ply

    src = tmp_path / "in.ply"
    write_ply(sampled_cloud("kitten", 20_000), src)
    out = tmp_path / "out.ply"
    r = CliRunner().invoke(
        cli, ["poisson", str(src), str(out), "--depth", "6", "--density", "--json"]
    )
    assert r.exit_code == 0, r.output
    mesh = read_ply(out)
    assert len(mesh.faces) > 1000 and "density" in mesh.attributes
    bare = tmp_path / "bare.ply"
    write_ply(PointCloud(points=sampled_cloud("kitten", 1000).points), bare)
    r = CliRunner().invoke(cli, ["poisson", str(bare), str(out)])
    assert isinstance(r.exception, InputError) and r.exception.exit_code == 2
    assert "recon normals" in str(r.exception)
