"""recon fit-sdf: a neural signed distance field fitted to small analytic clouds (seconds each).

Sphere and torus, 5k points, offset and scaled: the zero level within 1 % of the radius, the
eikonal property on grid samples near the surface, a fixed seed giving the same field, the
IGR form without normals, the occupancy form, autodiff normals, the model file, Ctrl-C,
the missing extra, and `recon compare` with fit-sdf as a method.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("torch")

from recon_cli.errors import BackendError, InputError, ParameterError  # noqa: E402
from recon_cli.geometry import PointCloud, TriangleMesh  # noqa: E402
from recon_cli.grid import Grid  # noqa: E402
from recon_cli.io import read_ply, write_ply  # noqa: E402
from recon_cli.io.npz import read_grid  # noqa: E402
from recon_cli.stages import apply_stage  # noqa: E402
from recon_cli.stages.learned import (  # noqa: E402
    extract_mesh,
    fit_sdf,
    load_model,
    sample_grid,
    save_model,
)
from recon_cli.stages.sdf import eikonal_check, grid_frame  # noqa: E402

from shapes import sphere_cloud, torus_cloud, torus_distance  # noqa: E402

FAST = {"iterations": 250, "width": 48, "depth": 3, "batch": 512, "threads": 1}
RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def _grid(fit, pts, res=48):
    o, h, s = grid_frame(pts.min(0), pts.max(0), res)
    return Grid(sample_grid(fit.model, o, h, s), o, h)


@pytest.fixture(scope="module")
def sphere_fit():
    """A sphere of radius 0.3 far from the origin, fitted with normals."""
    centre = np.array([1e3, -250.0, 40.0])
    p, n = sphere_cloud(5000, 0.3, centre, seed=1)
    return centre, p, n, fit_sdf(p, n, seed=3, **FAST)


def test_sphere_zero_level_within_one_percent(sphere_fit):
    """A fitted sphere's zero level and mesh lie within 1 % of r; normals radial; signs right."""
    centre, p, n, fit = sphere_fit
    r = 0.3
    # the field on the true sphere, and the surface the grid meshes to
    d = np.random.default_rng(0).normal(size=(2000, 3))
    on = centre + r * d / np.linalg.norm(d, axis=1, keepdims=True)
    assert np.abs(fit.model.values(on)).max() <= 0.01 * r
    g = _grid(fit, p)
    v, f, nv = extract_mesh(fit.model, g)
    radii = np.linalg.norm(v - centre, axis=1)
    assert len(f) > 1000 and np.abs(radii - r).max() <= 0.01 * r
    # autodiff normals: outward and radial
    assert np.einsum("ij,ij->i", nv, (v - centre) / radii[:, None]).min() > 0.99
    # inside negative, outside positive, both well away from 0
    assert fit.model.values(centre[None])[0] < -0.3 * r
    assert fit.model.values(centre[None] + (2 * r, 0, 0))[0] > 0.5 * r


def test_sphere_eikonal(sphere_fit):
    """The fitted sphere's field has unit gradient within 0.1 on 90 % of cells and samples."""
    _, p, _, fit = sphere_fit
    g = _grid(fit, p)
    eik = eikonal_check(g)["near"]
    assert eik["cells"] > 1000 and eik["fraction_within_0.1"] >= 0.9
    # the exact gradient too, at random points near the surface
    rng = np.random.default_rng(5)
    q = p[rng.integers(0, len(p), 2000)] + rng.normal(scale=0.02, size=(2000, 3))
    _, grad = fit.model.gradients(q)
    assert np.mean(np.abs(np.linalg.norm(grad, axis=1) - 1) <= 0.1) >= 0.9


def test_sphere_without_normals_igr():
    """IGR's form (zero level + eikonal) grows the initial sphere onto the points."""
    centre = np.array([-40.0, 0.5, 1e4])
    p, _ = sphere_cloud(5000, 2.0, centre, seed=11)
    fit = fit_sdf(p, None, seed=1, **dict(FAST, iterations=500))
    assert fit.eikonal_weight == 0.1
    v, f, nv = extract_mesh(fit.model, _grid(fit, p))
    radii = np.linalg.norm(v - centre, axis=1)
    assert np.abs(radii - 2.0).max() <= 0.01 * 2.0
    assert np.einsum("ij,ij->i", nv, (v - centre) / radii[:, None]).min() > 0.97


def test_fixed_seed_reproducible_other_seed_differs():
    """The same seed gives the same field and history; another seed another field."""
    p, n = sphere_cloud(2000, 1.0, seed=2)
    kw = dict(FAST, iterations=40)
    a = fit_sdf(p, n, seed=7, **kw)
    b = fit_sdf(p, n, seed=7, **kw)
    c = fit_sdf(p, n, seed=8, **kw)
    q = p[:500] * 1.1
    assert np.array_equal(a.model.values(q), b.model.values(q))
    assert not np.array_equal(a.model.values(q), c.model.values(q))
    assert a.history == b.history


@pytest.mark.parametrize("with_normals", [True, False], ids=["normals", "igr"])
def test_torus(with_normals):
    """The torus (genus 1) from the sphere init: with normals, and IGR's form without."""
    major, minor = 1.0, 0.35
    centre = np.array([-3.0, 7.0, 2.0])
    p, n = torus_cloud(5000, major, minor, centre, seed=4)
    rot = np.linalg.qr(np.random.default_rng(9).normal(size=(3, 3)))[0]
    pr = (p - centre) @ rot.T + centre
    nr = n @ rot.T
    fit = fit_sdf(
        pr,
        nr if with_normals else None,
        seed=0,
        **dict(FAST, iterations=300 if with_normals else 900),
    )
    g = _grid(fit, pr, res=64)
    v, f, _ = extract_mesh(fit.model, g)
    d = torus_distance((v - centre) @ rot + centre, major, minor, centre)
    tol = 0.01 if with_normals else 0.02
    assert np.abs(d).max() <= tol * major, np.abs(d).max()
    from recon_cli.mesh.topology import report

    topo = report(TriangleMesh(vertices=v, faces=f))
    assert topo["components"] == 1 and topo["watertight"] and topo["genus"] == 1
    if with_normals:
        eik = eikonal_check(g)["near"]
        assert eik["cells"] > 1000 and eik["fraction_within_0.1"] >= 0.9, eik


@pytest.mark.parametrize(
    "shape, iterations",
    [("sphere", 30), ("sphere", 120), ("rounded_box", 60), ("rounded_box", 200)],
)
def test_short_fits_do_not_fold(shape, iterations):
    """A fit stopped early is one closed surface of the input's genus.

    A fit stopped early is still one closed surface of the input's genus: no spurious
    sheets or bubbles in the empty space (SIREN's off-surface term keeps zero levels away).
    """
    from recon_cli.mesh.topology import report

    from shapes import shape_cloud

    rng = np.random.default_rng(12)
    p, n = shape_cloud(shape, 3000, rng, scale=3.0, offset=np.array([50.0, -20.0, 7.0]))
    fit = fit_sdf(p, n, seed=2, **dict(FAST, iterations=iterations))
    v, f, _ = extract_mesh(fit.model, _grid(fit, p, res=40))
    topo = report(TriangleMesh(vertices=v, faces=f))
    assert topo["components"] == 1 and topo["watertight"] and topo["genus"] == 0, topo


def test_thin_plate_keeps_its_inside():
    """A plate 0.08 thick (1.25 % of its 2 x 1.6 sides) keeps a negative inside, meshed closed.

    Without the samples along the normals and the eikonal ramp a short fit lost it: the field
    positive everywhere, a valley touching zero on both faces.
    """
    from recon_cli.mesh.topology import report

    from shapes import shape_cloud, thin_plate_sdf

    offset = np.array([-7.0, 2.0, 30.0])
    p, n = shape_cloud("thin_plate", 5000, np.random.default_rng(21), rotate=False, offset=offset)
    fit = fit_sdf(p, n, seed=1, **dict(FAST, iterations=400))
    g = _grid(fit, p, res=64)
    assert g.sdf.min() < -0.02  # the plate's half-thickness is 0.04
    v, f, _ = extract_mesh(fit.model, g)
    d = np.abs(thin_plate_sdf(v - offset))
    assert d.max() <= 0.03 and d.mean() <= 0.005, (d.max(), d.mean())
    topo = report(TriangleMesh(vertices=v, faces=f))
    assert topo["components"] == 1 and topo["watertight"] and topo["genus"] == 0, topo


def test_occupancy_field():
    """An occupancy fit of a far sphere: values near -0.5/+0.5, mesh within 3 %; needs normals."""
    p, n = sphere_cloud(5000, 0.5, (2.0, 0.0, 0.0), seed=6)
    fit = fit_sdf(p, n, field="occupancy", seed=0, **dict(FAST, iterations=400))
    g = _grid(fit, p)
    assert (
        g.sdf.min() < -0.4 and g.sdf.max() > 0.4
    )  # 0.5 - p(inside): inside -> -0.5, outside -> +0.5
    v, f, nv = extract_mesh(fit.model, g)
    r = np.linalg.norm(v - (2.0, 0.0, 0.0), axis=1)
    assert np.abs(r - 0.5).max() <= 0.03 * 0.5
    assert np.einsum("ij,ij->i", nv, (v - (2.0, 0, 0)) / r[:, None]).min() > 0.9
    with pytest.raises(ParameterError, match="normals"):
        fit_sdf(p, None, field="occupancy", iterations=1)


def test_interrupt_restores_best_and_says_so(monkeypatch):
    """A KeyboardInterrupt mid-fit keeps the best field so far, marked as interrupted."""
    from recon_cli.stages.learned import _torch_net

    p, n = sphere_cloud(1000, 1.0, seed=3)
    real = _torch_net.train

    def stopping(*args, **kwargs):
        on_step = args[-1]

        def stop(it, loss, t):
            on_step(it, loss, t)
            if it == 55:
                raise KeyboardInterrupt

        return real(*args[:-1], stop, **kwargs)

    monkeypatch.setattr(_torch_net, "train", stopping)
    fit = fit_sdf(p, n, iterations=1000, width=32, depth=2, threads=1)
    assert fit.interrupted and fit.iterations == 55
    assert np.isfinite(fit.loss)


@pytest.mark.parametrize(
    "kw, err",
    [
        ({"width": 0}, ParameterError),
        ({"iterations": 0}, ParameterError),
        ({"field": "udf"}, ParameterError),
        ({"eikonal_weight": -1}, ParameterError),
        ({"max_seconds": "soon"}, ParameterError),
    ],
)
def test_bad_parameters(kw, err):
    """Zero width or iterations, an unknown field, negative weights, bad times: ParameterError."""
    p, n = sphere_cloud(100, 1.0)
    with pytest.raises(err):
        fit_sdf(p, n, **kw)


def test_fit_options_are_the_declarations():
    """``fit_sdf``'s options are checked by the stage's declaration, with its messages.

    fit_sdf's options named like the stage's parameters are checked by the declaration (the
    command line's message) before any data is looked at; a keyword it has not is refused.
    """
    from recon_cli.stages.learned import FIT_PARAMS, SPEC

    assert set(SPEC.defaults()) - set(FIT_PARAMS) == {"resolution", "padding", "model", "mesh"}
    for k in FIT_PARAMS:
        with pytest.raises(ParameterError) as want:
            SPEC.param(k).coerce("nonsense")
        with pytest.raises(ParameterError) as got:
            fit_sdf(None, **{k: "nonsense"})
        assert str(got.value) == str(want.value)
    with pytest.raises(ParameterError, match="learning_rate must be in"):
        fit_sdf(None, learning_rate=2.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'resolution'"):
        fit_sdf(None, resolution=32)


def test_bad_points():
    """NaN points, too few points, or normals of another length are refused."""
    p, n = sphere_cloud(100, 1.0)
    p[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        fit_sdf(p, n, iterations=1)
    with pytest.raises(InputError, match="at least"):
        fit_sdf(p[:5], None, iterations=1)
    with pytest.raises(InputError, match="normals"):
        fit_sdf(sphere_cloud(100)[0], n[:50], iterations=1)


def test_missing_torch_is_one_line(monkeypatch):
    """Without torch, ``fit_sdf`` is one BackendError naming ``pip install recon[learned]``."""
    import recon_cli.stages.learned

    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.delitem(sys.modules, "recon_cli.stages.learned._torch_net", raising=False)
    monkeypatch.delattr(recon_cli.stages.learned, "_torch_net", raising=False)
    p, n = sphere_cloud(100, 1.0)
    with pytest.raises(BackendError, match=r"pip install recon\[learned\]"):
        fit_sdf(p, n, iterations=1)


def test_model_file_round_trip(tmp_path, sphere_fit):
    """A saved model loads back giving the same values; a file that is no model is refused."""
    _, p, _, fit = sphere_fit
    save_model(fit.model, tmp_path / "m.npz")
    back = load_model(tmp_path / "m.npz")
    q = p[:300] * 1.001
    assert np.array_equal(back.values(q), fit.model.values(q))
    (tmp_path / "bad.npz").write_bytes(b"not a zip at all")
    with pytest.raises(InputError):
        load_model(tmp_path / "bad.npz")


def test_cli_grid_mcubes_info_mesh(tmp_path):
    """``recon fit-sdf`` writes a grid, mesh and model; mcubes and info agree with its report."""
    p, n = sphere_cloud(3000, 1.0, (0.5, 0.5, 0.5), seed=8)
    src = tmp_path / "s.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    out, mesh, model = tmp_path / "s.npz", tmp_path / "s_mesh.ply", tmp_path / "m.npz"
    r = subprocess.run(
        [
            *RECON,
            "fit-sdf",
            src,
            out,
            "--iterations",
            "200",
            "--batch",
            "2048",
            "--width",
            "48",
            "--depth",
            "3",
            "--resolution",
            "40",
            "--mesh",
            mesh,
            "--model",
            model,
            "--threads",
            "1",
            "--json",
        ],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr.decode()
    import json

    rep = json.loads(r.stdout)
    assert rep["iterations"] == 200 and rep["normals_used"] and rep["eikonal"]["cells"] > 0
    g = read_grid(out)
    assert any("fit-sdf" in h for h in g.history)
    # the written grid meshes (as `recon mcubes` does) to the mesh written with --mesh
    from recon_cli.info import describe
    from recon_cli.stages.mcubes import marching_cubes

    mv, mf, _ = marching_cubes(g.sdf, iso=0.0, spacing=g.voxel_size, origin=g.origin)
    m = read_ply(mesh)
    assert np.allclose(mv, m.vertices) and np.array_equal(mf, m.faces)
    radial = (m.vertices - 0.5) / np.linalg.norm(m.vertices - 0.5, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", m.normals, radial).min() > 0.98
    # `recon info` measures the written grid as the stage's report does
    assert describe(out)["eikonal"] == rep["eikonal"] and rep["eikonal_near"]["cells"] > 0
    assert load_model(model).field == "sdf"


def test_cli_bad_input_is_one_line(tmp_path):
    """``recon fit-sdf`` of a broken file: exit 2, one line, no output."""
    (tmp_path / "x.ply").write_bytes(b"ply\nformat nonsense\n")
    r = subprocess.run(
        [*RECON, "fit-sdf", tmp_path / "x.ply", tmp_path / "o.npz"],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 2 and len(r.stderr.decode().strip().splitlines()) == 1
    assert not (tmp_path / "o.npz").exists()


def test_cli_ctrl_c_writes_best_field(tmp_path):
    """Ctrl-C during ``recon fit-sdf`` writes the best field so far and says so."""
    p, n = sphere_cloud(2000, 1.0, seed=8)
    src = tmp_path / "s.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    out = tmp_path / "s.npz"
    # act as a terminal even when the test runner ignores SIGINT (nohup, CI)
    code = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler);"
        "from recon_cli.cli.main import main; main(sys.argv[1:])"
    )
    with subprocess.Popen(
        [
            sys.executable,
            "-c",
            code,
            "-v",
            "fit-sdf",
            str(src),
            str(out),
            "--iterations",
            "10000000",
            "--width",
            "32",
            "--depth",
            "2",
            "--resolution",
            "24",
            "--threads",
            "1",
        ],
        stderr=subprocess.PIPE,
        text=True,
    ) as proc:
        try:
            for line in proc.stderr:
                if "fit-sdf: step 1 done" in line:
                    break
            time.sleep(1.0)
            proc.send_signal(signal.SIGINT)
            rest = proc.stderr.read()
            assert proc.wait(timeout=120) == 130, rest
        finally:
            if proc.poll() is None:
                proc.kill()
    assert "best field so far" in rest
    g = read_grid(out)
    assert g.sdf.min() < 0 < g.sdf.max()


def test_compare_takes_fit_sdf(tmp_path):
    """``compare_methods`` runs fit-sdf with its parameters: a mesh close to the sphere."""
    from recon_cli.eval.compare import compare_methods

    p, n = sphere_cloud(3000, 1.0, seed=9)
    src = tmp_path / "s.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    res = compare_methods(
        src,
        "fit-sdf:iterations=150:width=32:depth=2:resolution=32:threads=1",
        src,
        tmp_path / "cmp",
        samples=2000,
        isolate=False,
    )
    row = res["methods"][0]
    assert row["status"] == "ok", row["error"]
    assert row["faces"] > 0 and row["seconds"] > 0 and row["metrics"]["chamfer_l1"] < 0.02


def test_stage_report_and_provenance():
    """The stage gives a Grid, reports its iterations and records them in the history."""
    p, n = sphere_cloud(2000, 1.0, seed=10)
    res = apply_stage(
        "fit-sdf",
        PointCloud(points=p, normals=n),
        {"iterations": 50, "width": 32, "depth": 2, "resolution": 24, "threads": 1},
    )
    assert isinstance(res.output, Grid) and res.report["iterations"] == 50
    assert "fit-sdf" in res.output.history[-1] and "iterations-done=50" in res.output.history[-1]


@pytest.mark.slow
def test_defaults_meet_the_eikonal_target(tmp_path):
    """At the defaults, 90 % of the grid near the zero level has unit gradient within 0.1.

    At the defaults the written grid, as `recon info` measures it near the zero level,
    has |grad s| within 0.1 of 1 on >= 90 % of the samples (a rounded box, its medial axis
    reaching the band, rotated, scaled and 1e6 off); the stage reports the same figure.
    """
    from recon_cli.info import describe
    from recon_cli.io.npz import write_grid

    from shapes import shape_cloud

    rng = np.random.default_rng(21)
    p, n = shape_cloud(
        "rounded_box", 20_000, rng, scale=rng.uniform(0.2, 30), offset=np.full(3, 1e6)
    )
    res = apply_stage("fit-sdf", PointCloud(points=p, normals=n), {"threads": 1})
    write_grid(res.output, tmp_path / "f.npz")
    near = describe(tmp_path / "f.npz")["eikonal"]["near"]
    assert near == res.report["eikonal_near"]
    assert near["fraction_within_0.1"] >= 0.9 and near["cells"] > 100_000, near
    # the whole grid too (issue 45's figure): beyond the band the exact distance to the surface
    whole = res.report["eikonal"]
    assert whole["fraction_within_0.1"] >= 0.9, whole
    assert res.report["far_field"]["exact"] and res.report["far_field"]["redistanced"] > 0


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_field_of_one_sign_is_refused(monkeypatch, sign):
    """A fitted grid of one sign everywhere fails the stage instead of being written."""
    # a fit with no zero level (thin parts beyond the network) is a failure, not a grid
    import recon_cli.stages.learned as learned
    from recon_cli.errors import StageFailed

    made = learned._written_grid

    def one_sign(*args, **kwargs):
        g, far = made(*args, **kwargs)
        g.sdf = (sign * (np.abs(g.sdf) + 0.01)).astype(g.sdf.dtype)
        return g, far

    monkeypatch.setattr(learned, "_written_grid", one_sign)
    p, n = sphere_cloud(2000, 1.0, seed=10)
    params = {"iterations": 20, "width": 16, "depth": 2, "resolution": 16, "threads": 1}
    with pytest.raises(StageFailed, match="everywhere on the grid"):
        apply_stage("fit-sdf", PointCloud(points=p, normals=n), params)


def test_distance_targets_signed_by_the_nearest_normal():
    """The band samples' distance targets are signed by the nearest point's normal.

    The band samples' distance targets: |x - p| signed by p's normal, none near the points
    (closer than p's spacing) or beside an edge (the side ambiguous).
    """
    from scipy.spatial import cKDTree

    from recon_cli.stages.learned.training import distance_targets

    # a sphere of radius 1 (outward normals) and a square patch of z = 3 facing +z
    p, n = sphere_cloud(20_000, 1.0, seed=4)
    g = np.linspace(-0.5, 0.5, 101)
    patch = np.stack([*np.meshgrid(g, g), np.full((101, 101), 3.0)], -1).reshape(-1, 3)
    q = np.concatenate([p, patch]).astype(np.float32)
    nrm = np.concatenate([n, np.tile([0.0, 0.0, 1.0], (len(patch), 1))])
    tree = cKDTree(q)
    gap = tree.query(q, k=9)[0][:, -1].astype(np.float32)
    fn = distance_targets(tree, q, nrm, gap)
    rng = np.random.default_rng(6)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.concatenate([rng.uniform(0.2, 0.9, 250), rng.uniform(1.1, 1.8, 250)])
    x = (d * r[:, None]).astype(np.float32)
    t, keep = fn(x)
    assert t.dtype == np.float32 and keep.dtype == bool and keep.all()
    assert np.abs(t - (r - 1.0)).max() < 0.02  # the sphere's samples are ~0.03 apart
    t, keep = fn(np.array([[0, 0, 3.4], [0.1, 0, 2.7], [1.5, 0, 3.05], [0, 0, 1.001]], np.float32))
    assert keep.tolist() == [True, True, False, False]  # beside the patch's edge; on a point
    assert t[:2] == pytest.approx([0.4, -0.3], abs=1e-4)
    # the search stops at reach: no target beyond it, both sides of the sphere
    fn = distance_targets(tree, q, nrm, gap, reach=0.5)
    t, keep = fn(np.array([[0, 0, -1.3], [0, 0, -1.7], [0, 0.6, 0], [0, 0.4, 0]], np.float32))
    assert keep.tolist() == [True, False, True, False]
    assert t[[0, 2]] == pytest.approx([0.3, -0.4], abs=0.02)


def test_distance_weight_needs_normals_and_sdf():
    """The distance term is on only with normals and an SDF; asked otherwise it is refused."""
    p, n = sphere_cloud(500, 1.0, seed=2)
    kw = {"iterations": 2, "width": 8, "depth": 1, "threads": 1}
    assert fit_sdf(p, n, **kw).distance_weight == 1.0
    assert fit_sdf(p, None, **kw).distance_weight == 0.0
    assert fit_sdf(p, n, field="occupancy", **kw).distance_weight == 0.0
    assert fit_sdf(p, n, distance_weight=0.0, **kw).distance_weight == 0.0
    for bad in [{"normals": None}, {"field": "occupancy"}]:
        args = dict({"normals": n}, **bad)
        with pytest.raises(ParameterError, match="distance_weight needs"):
            fit_sdf(p, args.pop("normals"), distance_weight=1.0, **args, **kw)
    with pytest.raises(ParameterError, match="distance_weight"):
        fit_sdf(p, n, distance_weight=-1.0, **kw)


def test_offset_targets_through_a_thin_wall():
    """Samples off the points along their normals: the distance signed by the offset's side.

    The target is the smaller of the offset and the distance to the nearest point (both bound
    the distance to the surface from above); a sample that went through a wall thinner than its
    offset (now on the other side of the nearest point) has none.
    """
    from scipy.spatial import cKDTree

    from recon_cli.stages.learned.training import offset_targets

    # a wall 0.06 thick: z = 0 facing -z and z = 0.06 facing +z, points 0.005 apart
    g = np.linspace(-0.5, 0.5, 201)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    lower = np.column_stack([xy, np.zeros(len(xy))])
    upper = np.column_stack([xy, np.full(len(xy), 0.06)])
    q = np.concatenate([lower, upper]).astype(np.float32)
    nrm = np.concatenate([np.tile([0.0, 0, -1], (len(xy), 1)), np.tile([0.0, 0, 1], (len(xy), 1))])
    fn = offset_targets(cKDTree(q), q, nrm)
    # offsets from the upper face's point at the origin: out, in, in past the middle, through
    t = np.array([0.03, -0.02, -0.05, -0.08], np.float32)
    x = (np.array([0.0, 0.0, 0.06]) + t[:, None] * np.array([0.0, 0, 1])).astype(np.float32)
    d, keep = fn(x, t)
    assert d.dtype == np.float32 and keep.tolist() == [True, True, True, False]
    assert d[:3] == pytest.approx([0.03, -0.02, -0.01], abs=1e-6)
