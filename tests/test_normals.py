"""Tests of recon_cli.stages.normals: estimation, orientation, the stage and the command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon_cli.backends import open3d_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.mesh.sampling import face_normals
from recon_cli.stages import apply_stage
from recon_cli.stages.normals import estimate_normals, orient_normals, run_stage

from shared_data import ALL_MESHES, CLOSED_MESHES, load_shared, sampled_cloud

NOISE = 0.0025  # 0.25 % of the bbox diagonal


def _abs_cos(a, b):
    return np.abs(np.einsum("ij,ij->i", a, b))


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(_abs_cos(a, b), 0.0, 1.0)))


def _same_way(a, b):
    return float((np.einsum("ij,ij->i", a, b) > 0).mean())


def _sphere(n, rng, center=(0.0, 0.0, 0.0), r=1.0):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(center) + r * v, v


# ----------------------------------------------------------------------------- estimation


@pytest.mark.parametrize("name", ALL_MESHES)
def test_unoriented_accuracy_vs_open3d(name):
    """Unoriented normals of noisy samples: median error within 0.5 degree of Open3D's, same lines.

    Unit normals, none degenerate, |cos| > 0.99 to Open3D's for 99 % of the points, curvature in [0,
    1/3].
    """
    cloud = sampled_cloud(name, 100_000, NOISE)
    ours, curv, deg = estimate_normals(cloud.points, knn=30)
    ref = open3d_backend.estimate_normals(cloud, knn=30)
    assert np.isfinite(ours).all() and not deg.any()
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-9)
    med_ours = np.median(_angle_deg(ours, cloud.normals))
    med_ref = np.median(_angle_deg(ref, cloud.normals))
    assert med_ours <= med_ref + 0.5
    # the normal lines agree with Open3D's (same PCA): |cos| > 0.99 for >= 99 % of points
    assert (_abs_cos(ours, ref) > 0.99).mean() >= 0.99
    assert ((curv >= 0) & (curv <= 1 / 3 + 1e-12)).all()


def test_pca_matches_dense_eigh(rng):
    """Closed-form 3x3 PCA gives LAPACK's smallest eigenvector and curvature, also 1e5 away."""
    # closed-form 3x3 eigenvectors against LAPACK on the same neighbourhoods, far from the origin
    # too
    pts = rng.normal(size=(3000, 3)) * [1.0, 1.0, 0.05]
    for offset in (0.0, 1e5):
        p = pts + offset
        nrm, curv, deg = estimate_normals(p, knn=12)
        _, idx = cKDTree(p).query(p, 12)
        nb = p[idx] - p[idx].mean(axis=1, keepdims=True)
        w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        ok = w[:, 1] > 1e-6 * w[:, 2]
        assert ok.mean() > 0.99 and not deg.any()
        assert _abs_cos(nrm[ok], v[ok, :, 0]).min() > 1 - 1e-6
        np.testing.assert_allclose(curv, w[:, 0] / w.sum(axis=1), atol=1e-6)


def test_single_plane_normals_and_curvature(rng):
    """A plane: normals along z, zero curvature, one side; ``direction`` turns them down."""
    pts = np.c_[rng.random((5000, 2)), np.zeros(5000)]
    nrm, curv, deg = estimate_normals(pts)
    assert np.abs(nrm[:, 2]).min() > 1 - 1e-12
    assert curv.max() < 1e-12 and not deg.any()
    res = run_stage(PointCloud(pts), orient="mst", curvature=True)
    nz = res.output.normals[:, 2]
    assert (np.sign(nz) == np.sign(nz[0])).all()  # one consistent side
    assert res.report["components"] == 1
    assert res.output.attributes["curvature"].max() < 1e-12
    down = run_stage(PointCloud(pts), orient="direction", direction="0,0,-5")
    assert (down.output.normals[:, 2] < -0.999).all()


def test_sphere_curvature_larger_than_plane(rng):
    """A sphere's surface variation is about a cap's a^2 / 8 (within a factor 3)."""
    pts, _ = _sphere(20_000, rng)
    _, curv, _ = estimate_normals(pts, knn=30)
    # surface variation of a spherical cap of angular radius a is about a^2 / 8 (a from K/n)
    a = 2 * np.sqrt(30 / 20_000)
    assert 0.3 * a * a / 8 < np.median(curv) < 3 * a * a / 8


def test_radius_and_hybrid(rng):
    """Radius and hybrid neighbourhoods give the kNN normal lines; a tiny radius: degenerate."""
    pts = np.c_[rng.random((4000, 2)), 0.001 * rng.random(4000)]
    knn_n, _, _ = estimate_normals(pts, knn=30)
    hyb_n, _, hyb_deg = estimate_normals(pts, knn=30, radius=0.05)
    rad_n, _, rad_deg = estimate_normals(pts, knn=0, radius=0.05)
    for nrm in (hyb_n, rad_n):
        assert (_abs_cos(nrm, knn_n) > 0.99).mean() > 0.99
    assert not hyb_deg.any() and not rad_deg.any()
    r = run_stage(PointCloud(pts), knn=30, radius=0.05)
    assert r.report["neighbourhood_size"] <= 30
    r2 = run_stage(PointCloud(pts), knn=0, radius="0.05")
    # radius 0.05 over 4000 points on a unit square: about pi * 0.05^2 * 4000 = 31 neighbours
    assert 22 < r2.report["neighbourhood_size"] < 34
    # a radius smaller than the spacing: lonely points are degenerate, still unit normals
    tiny_n, _, tiny_deg = estimate_normals(pts, knn=0, radius=1e-4)
    assert tiny_deg.all()
    np.testing.assert_allclose(np.linalg.norm(tiny_n, axis=1), 1.0)


# ----------------------------------------------------------------------------- degenerate input


def test_two_points_and_one_point():
    """One or two points: degenerate, finite unit normals, zero curvature, a warning."""
    for pts in (np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[1.0, 2, 3]])):
        nrm, curv, deg = estimate_normals(pts)
        assert deg.all() and np.isfinite(nrm).all() and (curv == 0).all()
        np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0)
        assert np.abs(nrm[:, 0]).max() < 1e-12  # orthogonal to the line (or (0, 0, 1))
        res = run_stage(PointCloud(pts))
        assert res.report["degenerate"] == len(pts)
        assert "degenerate" in res.report["warning"]
        assert np.isfinite(res.output.normals).all()


def test_collinear_points_are_degenerate():
    """Collinear points are degenerate, with unit normals orthogonal to their line."""
    t = np.linspace(0, 1, 200)
    pts = np.c_[t, 2 * t, -t]
    nrm, _, deg = estimate_normals(pts, knn=10)
    assert deg.all()
    assert np.abs(nrm @ (np.array([1.0, 2, -1]) / np.sqrt(6))).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0)


def test_nan_rows_rejected():
    """Rows with NaN points or normals are refused, naming the count and the first row."""
    pts = np.zeros((10, 3))
    pts[:, 0] = np.arange(10)
    pts[:, 1] = np.arange(10) ** 2
    pts[7, 1] = np.nan
    with pytest.raises(InputError, match="1 rows with NaN.*row 7"):
        estimate_normals(pts)
    with pytest.raises(InputError, match="NaN"):
        orient_normals(pts, np.ones((10, 3)), "none")
    good = np.nan_to_num(pts)
    with pytest.raises(InputError, match="normals hold NaN"):
        orient_normals(good, np.full((10, 3), np.nan), "none")


def test_duplicates(rng):
    """A duplicated cloud keeps its normals; a pile of coincident points borrows one.

    The 40 coincident points on a plane are degenerate and take a neighbour's normal, zero
    curvature.
    """
    cloud = sampled_cloud("kitten", 20_000)
    once, _, _ = estimate_normals(cloud.points, knn=30)
    twice, _, deg = estimate_normals(np.vstack([cloud.points, cloud.points]), knn=60)
    assert not deg.any()
    # a duplicate sees the same neighbourhood, twice over: same normal line
    assert _abs_cos(twice[:20_000], twice[20_000:]).min() > 1 - 1e-9
    assert _abs_cos(twice[:20_000], once).min() > 1 - 1e-6
    res = run_stage(PointCloud(np.vstack([cloud.points, cloud.points])), knn=60)
    n2 = res.output.normals
    assert (np.einsum("ij,ij->i", n2[:20_000], n2[20_000:]) > 0.999).all()
    assert _same_way(n2[:20_000], cloud.normals) > 0.999
    # a pile of 40 coincident points on a plane: degenerate, borrow a neighbour's normal
    plane = np.c_[rng.random((2000, 2)), np.zeros(2000)]
    pile = np.vstack([plane, np.repeat([[0.5, 0.5, 0.0]], 40, axis=0)])
    nrm, curv, deg = estimate_normals(pile, knn=30)
    assert deg.sum() == 40 and deg[2000:].all()
    assert np.abs(nrm[:, 2]).min() > 1 - 1e-9 and (curv[2000:] == 0).all()


# ----------------------------------------------------------------------------- orientation


@pytest.mark.parametrize("name", CLOSED_MESHES)
def test_mst_orientation_clean(name):
    """MST orientation of 100k clean samples: one component, >= 99.9 % facing the true way."""
    cloud = sampled_cloud(name, 100_000)
    res = run_stage(PointCloud(cloud.points), knn=30, orient="mst")
    assert res.report["components"] == 1
    # the issue asks >= 99.5 %; we measure >= 99.99 % on all three
    assert _same_way(res.output.normals, cloud.normals) >= 0.999


@pytest.mark.slow
@pytest.mark.parametrize("name", CLOSED_MESHES)
def test_mst_orientation_noisy_vs_open3d(name):
    """MST orientation of 50k noisy samples: at least Open3D's fraction right, >= 99.5 %."""
    cloud = sampled_cloud(name, 50_000, NOISE)
    ours = run_stage(PointCloud(cloud.points), knn=30, orient="mst").output.normals
    ref = open3d_backend.estimate_normals(cloud, knn=30, orient_tangent_plane=30)
    f_ours = _same_way(ours, cloud.normals)
    f_ref = _same_way(ref, cloud.normals)
    # measured at 50k: armadillo 0.9954 vs 0.9949, kitten 0.99968 both, mug 0.9965 vs 0.58
    assert f_ours >= f_ref
    assert f_ours >= 0.995


@pytest.mark.slow
def test_mst_orientation_noisy_100k():
    """MST orientation of 100k noisy samples: at least the measured fraction right, per mesh."""
    # absolute figures at 100k (Open3D measured: armadillo 0.9967, kitten 0.9998, mug 0.58)
    want = {"armadillo": 0.997, "kitten": 0.9997, "mug": 0.998}
    for name, f in want.items():
        cloud = sampled_cloud(name, 100_000, NOISE)
        ours = run_stage(PointCloud(cloud.points), knn=30).output.normals
        assert _same_way(ours, cloud.normals) >= f, name


def _scan_truth():
    scan = load_shared("bunny_scan_000")
    z = load_shared("bunny_zipper")
    fn, _ = face_normals(z.vertices, z.faces)
    _, fi = cKDTree(z.vertices[z.faces].mean(axis=1)).query(scan.points)
    return scan, fn[fi]


def test_raw_scan_camera_and_mst():
    """A raw scan oriented towards the camera, or by MST: >= 99.5 % facing as the true normals."""
    scan, truth = _scan_truth()
    cam = run_stage(scan, orient="camera", camera="0,0,1")
    assert _same_way(cam.output.normals, truth) >= 0.995
    mst = run_stage(scan, orient="mst")
    assert _same_way(mst.output.normals, truth) >= 0.995
    assert mst.report["components"] >= 1 and mst.report["degenerate"] == 0


def test_two_disconnected_spheres_outward(rng):
    """Two disconnected spheres: two components, each oriented outward entirely."""
    a, na = _sphere(8000, rng, (0, 0, 0), 1.0)
    b, nb = _sphere(3000, rng, (5, 0, 0), 0.5)
    res = run_stage(PointCloud(np.vstack([a, b])), knn=20)
    assert res.report["components"] == 2
    out = res.output.normals
    assert _same_way(out[:8000], na) == 1.0
    assert _same_way(out[8000:], nb) == 1.0


def test_flux_check_flips_inside_out_seed(rng, monkeypatch):
    """The flux check turns components seeded inward outward; without it they stay inside out."""
    # force every component seed to point inward: the flux check must turn the spheres out
    import recon_cli.stages.normals as mod

    a, na = _sphere(5000, rng, (0, 0, 0), 1.0)
    b, nb = _sphere(2000, rng, (4, 0, 0), 0.5)
    true = np.vstack([na, nb])
    real = mod._seed_signs
    monkeypatch.setattr(mod, "_seed_signs", lambda n, r: -real(n, r))
    out, info = mod.orient_normals(np.vstack([a, b]), true, "mst", knn=20)
    assert info["components"] == 2
    assert _same_way(out, true) == 1.0
    # without the check they would stay inside-out
    monkeypatch.setattr(mod, "_FLUX_MIN", np.inf)
    out, _ = mod.orient_normals(np.vstack([a, b]), true, "mst", knn=20)
    assert _same_way(out, true) == 0.0


def test_input_normals_replaced_or_kept():
    """Input normals are replaced, or their signs kept with ``keep`` (zero rows follow neighbours).

    ``keep`` without input normals is refused.
    """
    cloud = sampled_cloud("kitten", 20_000)
    garbage = np.tile([1.0, 0.0, 0.0], (20_000, 1))
    res = run_stage(PointCloud(cloud.points, normals=garbage), orient="mst")
    assert res.report["input_normals"] == "replaced"
    assert _same_way(res.output.normals, cloud.normals) > 0.999
    # keep: the input's signs, also where the input is inward
    flipped_in = cloud.normals * np.where(np.arange(20_000) % 2, 1.0, -1.0)[:, None]
    kept = run_stage(PointCloud(cloud.points, normals=flipped_in), orient="keep")
    assert kept.report["input_normals"] == "sign kept"
    assert (np.einsum("ij,ij->i", kept.output.normals, flipped_in) > 0).all()
    # zero rows have no sign: they follow their neighbours by propagation
    partial = cloud.normals.copy()
    partial[5000:15000] = 0.0
    k2 = run_stage(PointCloud(cloud.points, normals=partial), orient="keep")
    assert _same_way(k2.output.normals, cloud.normals) > 0.999
    with pytest.raises(InputError, match="needs input normals"):
        run_stage(PointCloud(cloud.points), orient="keep")


def test_orient_normals_direct_methods(rng):
    """orient_normals by camera, direction and MST: every normal on its side, flips counted."""
    pts, true = _sphere(2000, rng)
    out, info = orient_normals(pts, -true, "camera", camera=(0, 0, 10))
    assert (np.einsum("ij,ij->i", out, [0, 0, 10] - pts) >= 0).all()
    assert info["components"] is None and info["flipped"] > 0
    out, info = orient_normals(pts, true, "direction", direction="1,0,0")
    assert (out[:, 0] >= 0).all() and info["flipped"] == int((true[:, 0] < 0).sum())
    out, info = orient_normals(pts, -true, "mst", knn=20)
    assert _same_way(out, true) == 1.0 and info["flipped"] == 2000 and info["components"] == 1


# ----------------------------------------------------------------------------- stage and CLI


def test_parameter_errors():
    """Each bad parameter is refused with its message; camera orientation without a scanner too."""
    c = PointCloud(np.random.default_rng(0).random((50, 3)))
    for kwargs, msg in [
        ({"knn": 2}, "knn must be"),
        ({"knn": "abc"}, "knn must be"),
        ({"radius": -1.0}, "radius must be"),
        ({"knn": 0}, "needs --radius"),
        ({"orient": "up"}, "orient must be"),
        ({"orient": "camera", "camera": "1,2"}, "three"),
        ({"orient": "direction", "direction": "0,0,0"}, "zero vector"),
        ({"orient": "mst", "camera": "0,0,1"}, "only used with"),
        ({"backend": "pcl"}, "backend"),
        ({"backend": "open3d", "curvature": True}, "curvature"),
    ]:
        with pytest.raises(ParameterError, match=msg):
            run_stage(c, **kwargs)
    with pytest.raises(InputError, match="shape"):
        estimate_normals(np.zeros((5, 2)))
    # no --camera and no scanner position in the data: the input's problem (exit 2, file named)
    with pytest.raises(InputError, match="needs --camera X,Y,Z: the input gives no scanner"):
        run_stage(c, orient="camera")


def test_stage_report_history_and_open3d_backend():
    """The stage's report keys, history and curvature attribute, and the Open3D backend's output."""
    cloud = sampled_cloud("mug", 20_000)
    res = apply_stage(
        "normals", PointCloud(cloud.points, history=["source"]), {"knn": 20, "curvature": True}
    )
    rep = res.report
    for key in (
        "points",
        "knn",
        "radius",
        "neighbourhood_size",
        "degenerate",
        "components",
        "flipped",
        "orient",
    ):
        assert key in rep
    assert rep["points"] == 20_000 and rep["knn"] == 20 and rep["neighbourhood_size"] == 20.0
    assert res.output.history[0] == "source" and "normals" in res.output.history[1]
    assert res.output.attributes["curvature"].shape == (20_000,)
    o3d = run_stage(
        PointCloud(cloud.points), knn=20, orient="camera", camera="0,0,1000", backend="open3d"
    )
    assert o3d.report["backend"] == "open3d"
    assert (_abs_cos(o3d.output.normals, res.output.normals) > 0.99).mean() > 0.99
    assert (np.einsum("ij,ij->i", o3d.output.normals, [0, 0, 1000] - cloud.points) >= 0).all()


def test_cli_normals(tmp_path, capsys):
    """``recon normals`` writes oriented normals, curvature; ``--orient camera`` alone exits 2."""
    from recon_cli.cli.main import main
    from recon_cli.io import read_ply, write_ply

    cloud = sampled_cloud("kitten", 5000)
    src = tmp_path / "in.ply"
    write_ply(PointCloud(cloud.points), src)
    out = tmp_path / "out.ply"
    with pytest.raises(SystemExit) as e:
        main(["normals", str(src), str(out), "--knn", "20", "--curvature", "--json"])
    assert e.value.code == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["points"] == 5000 and rep["orient"] == "mst"
    got = read_ply(out)
    assert _same_way(got.normals, cloud.normals) > 0.999 and "curvature" in got.attributes
    with pytest.raises(SystemExit) as e:
        main(["normals", str(src), str(out), "--orient", "camera"])
    assert e.value.code == 2
    assert "needs --camera" in capsys.readouterr().err


def test_rotation_and_translation_equivariance(rng):
    """Normals of a rotated, moved cloud are the rotated normals, orientation included."""
    from scipy.spatial.transform import Rotation

    cloud = sampled_cloud("kitten", 10_000, NOISE)
    rot = Rotation.random(random_state=7).as_matrix()
    moved = cloud.points @ rot.T + [1e4, -2e4, 3e4]
    a = run_stage(PointCloud(cloud.points), knn=20).output.normals
    b = run_stage(PointCloud(moved), knn=20).output.normals
    # same lines, and the same orientation, up to rounding of the far-away coordinates
    assert (np.einsum("ij,ij->i", a @ rot.T, b) > 1 - 1e-6).mean() > 0.999


def test_open_pieces_follow_the_anchor_with_a_bounded_vote(rng, monkeypatch):
    """The smaller of two open pieces turns to agree with the larger, by a bounded vote.

    Two flat open pieces seeded opposite ways: the smaller (9000 points) turns to agree with the
    largest, voting with at most ``_ALIGN_SAMPLES`` of its points (a nearest-anchor query from far
    away is slow: all 9000 took seconds per 10^5 in a slab).
    """
    import scipy.spatial

    import recon_cli.stages.normals as mod

    a = np.column_stack([rng.uniform(0, 1, 12_000), rng.uniform(0, 1, 12_000), np.zeros(12_000)])
    b = np.column_stack([rng.uniform(1.3, 2, 9000), rng.uniform(0, 1, 9000), np.zeros(9000)])
    real = mod._seed_signs
    monkeypatch.setattr(mod, "_seed_signs", lambda n, r: real(n, r) * np.resize([1, -1], len(n)))
    queried = []

    class Tree(scipy.spatial.cKDTree):
        def query(self, x, *args, **kw):
            queried.append(len(x))
            return super().query(x, *args, **kw)

    monkeypatch.setattr(scipy.spatial, "cKDTree", Tree)
    nrm = np.tile([0.0, 0.0, 1.0], (21_000, 1))
    out, info = mod.orient_normals(np.vstack([a, b]), nrm, "mst", knn=20)
    assert info["components"] == 2
    z = np.sign(out[:, 2])
    assert (z == z[0]).all()
    assert queried[-1] == 3000  # every third point of the 9000: at most _ALIGN_SAMPLES (4096)
