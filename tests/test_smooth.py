"""``recon smooth``: Taubin lambda|mu smoothing removes noise and keeps the volume.

The same filter as MeshLab's on closed meshes; boundaries, attributes and precision kept.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from test_simplify import boundary_segments, terrain, to_segments

from recon_cli.backends import pymeshlab_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, bbox_diagonal
from recon_cli.io import read_ply, write_ply
from recon_cli.mesh.sampling import face_normals
from recon_cli.stages import apply_stage
from recon_cli.stages.smooth import neighbours, smooth, taubin_mu

import shapes as S
from shared_data import load_shared


def noisy_sphere(subdivisions: int = 5, noise: float = 0.005, seed: int = 0):
    """A unit icosphere with radial noise (``noise`` of the radius); its clean radii are 1."""
    rng = np.random.default_rng(seed)
    v, f = S.icosphere(subdivisions)
    v = v * (1.0 + rng.normal(scale=noise, size=(len(v), 1)))
    return TriangleMesh(v, f)


def volume(v, f) -> float:
    """Signed volume of the mesh (positive when it is wound outward)."""
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()) / 6


def test_noise_is_removed_and_the_volume_kept():
    """Taubin smoothing of a noisy sphere removes noise and keeps its volume within 0.2 %.

    Plain Laplacian steps of the same strength shrink it beyond that.
    """
    m = noisy_sphere()
    clean_v, clean_f = S.icosphere(5)
    clean = volume(clean_v, clean_f)
    out, rep = smooth(m, iterations=10)
    before = np.sqrt(np.mean((np.linalg.norm(m.vertices, axis=1) - 1.0) ** 2))
    after = np.sqrt(np.mean((np.linalg.norm(out.vertices, axis=1) - 1.0) ** 2))
    assert after < before / 2.5, (before, after)
    # the volume: within 0.2 % of the clean sphere's and of the input's
    assert abs(volume(out.vertices, out.faces) / clean - 1) < 2e-3
    assert abs(rep["volume_change"]) < 2e-3
    assert rep["volume_in"] == pytest.approx(volume(m.vertices, m.faces), rel=1e-9)
    # plain Laplacian steps (mu = 0) of the same strength shrink it beyond that
    from recon_cli.stages.smooth._kernel import taubin

    ptr, nbr, _, _ = neighbours(m.faces, len(m.vertices))
    lap = np.array(m.vertices)
    taubin(lap, ptr, nbr, np.ones(len(lap), bool), 0.5, 0.0, 10)
    assert volume(lap, m.faces) / clean - 1 < -1e-2


@pytest.mark.parametrize("name", ["sphere", "kitten"])
def test_the_same_filter_as_meshlab_on_closed_meshes(name):
    """On closed meshes our filter is PyMeshLab's Taubin smoothing, within 1e-8 of the diagonal."""
    m = noisy_sphere(4) if name == "sphere" else load_shared(name)
    out, rep = smooth(m, iterations=7, step=0.6, pass_band=0.05)
    ml = pymeshlab_backend.smooth_taubin(m, 7, 0.6, rep["mu"])
    assert np.abs(out.vertices - ml.vertices).max() < 1e-8 * bbox_diagonal(m.vertices)


@pytest.mark.parametrize("seed", range(4))
def test_rotations_scales_and_offsets_change_nothing(seed):
    """Rotating, scaling and moving a mesh moves its smoothed mesh alike, to rounding."""
    rng = np.random.default_rng(seed)
    m = noisy_sphere(3, seed=seed)
    R = S.random_rotation(rng)
    scale = 10.0 ** rng.uniform(-3, 3)
    offset = rng.uniform(-1, 1, 3) * 10.0 ** rng.integers(0, 7)
    moved = TriangleMesh(m.vertices @ R.T * scale + offset, m.faces)
    a, _ = smooth(m, iterations=5)
    b, rep = smooth(moved, iterations=5)
    ulp = np.spacing(np.abs(offset).max() + 2 * scale)
    err = np.abs(b.vertices - (a.vertices @ R.T * scale + offset)).max()
    assert err < 1e-11 * scale + 8 * ulp
    assert rep["volume_change"] == pytest.approx(smooth(m, iterations=5)[1]["volume_change"])


def test_open_meshes_keep_their_boundary():
    """An open mesh's fixed boundary stays put; a free one is smoothed along itself."""
    rng = np.random.default_rng(2)
    v, f = terrain(30)
    v = v + rng.normal(scale=0.005, size=v.shape)
    m = TriangleMesh(v, f)
    _, _, rim, closed = neighbours(f, len(v))
    assert not closed and rim.sum() == 4 * 29
    fixed, rep = smooth(m, iterations=10, fixed_boundary=True)
    assert np.array_equal(fixed.vertices[rim], m.vertices[rim])
    assert rep["boundary_vertices"] == 4 * 29 and rep["volume_change"] is None
    free, _ = smooth(m, iterations=10)
    # the rim is smoothed along itself: it stays on the input's rim (within the noise; the
    # corners are rounded) and does not pull inwards, while the interior moves
    a, b = boundary_segments(m)
    assert to_segments(free.vertices[rim], a, b).max() < 0.025
    span = np.ptp(free.vertices[rim][:, :2], axis=0)
    assert (span > 0.98 * np.ptp(v[rim][:, :2], axis=0)).all()
    assert np.abs(free.vertices[~rim] - v[~rim]).max() > 0.005


def test_attributes_types_and_normals():
    """Attributes keep their types, far float32 coordinates stay float32, normals recomputed."""
    rng = np.random.default_rng(4)
    m0 = noisy_sphere(3)
    n = len(m0.vertices)
    m = TriangleMesh(
        vertices=(m0.vertices + 1e6).astype(np.float32),
        faces=m0.faces,
        normals=np.zeros((n, 3), np.float32),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        attributes={"quality": rng.random(n).astype(np.float32), "label": np.arange(n) % 5},
        face_attributes={"region": (np.arange(len(m0.faces)) % 3).astype(np.uint8)},
        history=["h"],
        point_dtype=np.float32,
    )
    out, rep = smooth(m, iterations=3)
    assert out.point_dtype == np.float32 and out.history == ["h"]
    assert np.array_equal(out.colors, m.colors) and out.colors.dtype == np.uint8
    for k in m.attributes:
        assert np.array_equal(out.attributes[k], m.attributes[k])
        assert out.attributes[k].dtype == m.attributes[k].dtype
    assert np.array_equal(out.face_attributes["region"], m.face_attributes["region"])
    # normals computed again from the smoothed faces: unit, outward, in their type
    assert out.normals.dtype == np.float32
    assert np.allclose(np.linalg.norm(out.normals, axis=1), 1.0, atol=1e-6)
    radial = out.vertices - 1e6
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", out.normals, radial).min() > 0.95
    fn, _ = face_normals(out.vertices - 1e6, out.faces)
    assert np.einsum("ij,ij->i", out.normals[out.faces[:, 0]], fn).min() > 0.8


def test_parameters_and_inputs_are_checked():
    """Bad step, pass band and iterations are refused; clouds and meshes without faces too."""
    m = noisy_sphere(2)
    assert taubin_mu(0.5, 0.1) == pytest.approx(-0.526315789, rel=1e-8)
    for kwargs, message in (
        ({"step": 1.0}, "--step must be a number with 0 < x < 1"),
        ({"pass_band": 0.0}, "--pass-band must be a number with 0 < x < 1"),
        ({"iterations": 0}, "--iterations must be an integer with 1 <= x"),
    ):
        with pytest.raises(ParameterError, match=message):
            smooth(m, **kwargs)
    with pytest.raises(InputError, match="smooth needs a triangle mesh, got a point cloud"):
        apply_stage("smooth", PointCloud(m.vertices), {})
    with pytest.raises(InputError, match="no faces"):
        smooth(TriangleMesh(m.vertices, np.zeros((0, 3), np.int64)))
    res = apply_stage("smooth", TriangleMesh(m.vertices, m.faces, history=["x"]), {})
    assert res.output.history[-1].startswith("recon") and "mu=-0.526316" in res.output.history[-1]


def test_cloud_on_the_command_line_is_one_line_exit_2(tmp_path):
    """A cloud given to ``recon smooth``: exit 2, one line naming the file, nothing written."""
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(PointCloud(noisy_sphere(2).vertices), src)
    r = subprocess.run(
        [sys.executable, "-m", "recon_cli.cli.main", "smooth", src, out],
        capture_output=True,
        timeout=300,
    )
    err = r.stderr.decode().strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1, err
    assert "smooth needs a triangle mesh, got a point cloud" in err and str(src) in err
    assert not out.exists() and os.listdir(tmp_path) == ["in.ply"]


def test_simplify_then_smooth_as_a_pipeline(tmp_path):
    """A ``recon run`` pipeline of simplify then smooth writes the smoothed quarter mesh."""
    src, out, pipe = tmp_path / "in.ply", tmp_path / "out.ply", tmp_path / "p.toml"
    write_ply(noisy_sphere(4), src)
    pipe.write_text(
        '[[stage]]\nname = "simplify"\nratio = 0.25\n\n'
        '[[stage]]\nname = "smooth"\niterations = 5\nfixed-boundary = true\n'
    )
    r = subprocess.run(
        [sys.executable, "-m", "recon_cli.cli.main", "-q", "run", pipe, src, out],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr.decode()
    mesh = read_ply(out)
    assert len(mesh.faces) == 1280
    assert any("simplify" in h for h in mesh.history) and "smooth" in mesh.history[-1]
