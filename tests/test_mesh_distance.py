"""Exact closest points on triangle meshes, and the winding number."""

from __future__ import annotations

import numpy as np
import pytest

from recon_cli.errors import InputError, ParameterError
from recon_cli.mesh.distance import build_bvh, closest_points, distance_grid
from recon_cli.mesh.winding import winding_number

from shapes import box_distance, box_mesh
from shared_data import load_shared


def test_box_exact(rng):
    """Closest points on a box: the exact box distance, points on their face, winding 1 inside."""
    v, f = box_mesh()
    # outward winding check of the helper itself
    t = v[f]
    assert np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6 == pytest.approx(
        6.0
    )
    q = rng.uniform(-2, 4, size=(20000, 3))
    d, face, c = closest_points(v, f, q)
    assert np.allclose(d, box_distance(q, (0, 0, 0), (1, 2, 3)), atol=1e-12)
    assert np.allclose(np.linalg.norm(q - c, axis=1), d, atol=1e-12)
    # the closest point lies on the returned face (inside its plane and triangle)
    tri = v[f[face]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.abs(np.einsum("ij,ij->i", c - tri[:, 0], n)).max() < 1e-9
    w = winding_number(v, f, q, method="exact")
    inside = (q > 0).all(axis=1) & (q < [1, 2, 3]).all(axis=1)
    assert np.allclose(w, inside.astype(float), atol=1e-9)


def test_against_open3d_on_real_meshes(rng):
    """Distances to real meshes within 1e-5 of the diagonal of Open3D's (float32).

    Random queries around and near the kitten and the bunny; the closest points lie at the distance
    reported, on valid faces.
    """
    from recon_cli.backends.open3d_backend import unsigned_distance

    for name in ("kitten", "bunny_zipper"):
        m = load_shared(name)
        lo, hi = m.vertices.min(0), m.vertices.max(0)
        diag = np.linalg.norm(hi - lo)
        q = np.concatenate(
            [
                rng.uniform(lo - 0.2 * diag, hi + 0.2 * diag, size=(20000, 3)),
                m.vertices[rng.integers(0, len(m.vertices), 5000)]
                + rng.normal(scale=1e-3 * diag, size=(5000, 3)),
            ]
        )
        d, face, c = closest_points(m.vertices, m.faces, q)
        ref = unsigned_distance(m, q)
        # Open3D works in float32
        assert np.abs(d - ref).max() < 1e-5 * diag
        assert np.allclose(np.linalg.norm(q - c, axis=1), d, atol=1e-12 * diag)
        assert (face >= 0).all() and (face < len(m.faces)).all()


def test_brute_force_small_mesh(rng):
    """BVH answers equal a brute-force minimum over every triangle."""
    m = load_shared("mug")
    keep = rng.choice(len(m.faces), 300, replace=False)
    v, f = m.vertices, m.faces[keep]
    q = rng.uniform(v.min(0), v.max(0), size=(500, 3))
    d, face, _ = closest_points(v, f, q)
    brute = np.array([closest_points(v, f[i : i + 1], q)[0] for i in range(len(f))]).min(axis=0)
    assert np.allclose(d, brute, rtol=0, atol=1e-12)


def test_upper_bound_and_degenerate():
    """``upper`` leaves farther queries unanswered; zero-area triangles act as segments, points."""
    v, f = box_mesh()
    q = np.array([[0.5, 1.0, 10.0], [0.5, 1.0, 3.5]])
    d, face, c = closest_points(v, f, q, upper=1.0)
    assert d[0] == np.inf and face[0] == -1 and np.isnan(c[0]).all()
    assert d[1] == pytest.approx(0.5) and face[1] >= 0
    # zero-area triangles (collinear and coincident corners) act as segments / points
    vd = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 5, 5]], float)
    fd = np.array([[0, 1, 2], [3, 3, 3]])
    d, face, c = closest_points(vd, fd, np.array([[1.5, 1.0, 0.0], [3.0, 0, 0], [5, 5, 6]]))
    assert np.allclose(d, [1.0, 1.0, 1.0])
    assert np.allclose(c[0], [1.5, 0, 0]) and np.allclose(c[1], [2, 0, 0])
    assert face.tolist() == [0, 0, 1]


def test_validation():
    """Bad queries, faces, meshes and bounds are refused; no queries give empty results."""
    v, f = box_mesh()
    with pytest.raises(InputError):
        closest_points(v, f, np.zeros((3, 2)))
    with pytest.raises(InputError):
        closest_points(v, f + 100, np.zeros((3, 3)))
    with pytest.raises(InputError):
        closest_points(v, np.zeros((0, 3), np.int64), np.zeros((3, 3)))
    with pytest.raises(InputError):
        closest_points(v, f, np.full((1, 3), np.nan))
    with pytest.raises(ParameterError):
        closest_points(v, f, np.zeros((1, 3)), upper=-1.0)
    d, face, c = closest_points(v, f, np.zeros((0, 3)))
    assert d.shape == (0,) and c.shape == (0, 3)
    with pytest.raises(ParameterError):
        winding_number(v, f, np.zeros((1, 3)), method="nope")


def test_distance_grid_matches_points(rng):
    """distance_grid equals closest_points at every grid point, its sign the winding number's.

    With a band, samples beyond it hold the band and no sign.
    """
    m = load_shared("kitten")
    bvh = build_bvh(m.vertices, m.faces)
    origin = m.vertices.min(0) - 0.1
    h = 0.07
    shape = (20, 28, 18)
    dist, sign = distance_grid(m.vertices, m.faces, origin, h, shape, pseudonormal=True, bvh=bvh)
    pts = origin + np.indices(shape).reshape(3, -1).T * h
    d, _, _ = closest_points(m.vertices, m.faces, pts, bvh=bvh)
    assert np.allclose(dist.reshape(-1), d, atol=1e-12)
    w = winding_number(m.vertices, m.faces, pts)
    assert np.array_equal(sign.reshape(-1) < 0, w > 0.5)
    band, bsign = distance_grid(
        m.vertices, m.faces, origin, h, shape, band=2 * h, pseudonormal=True
    )
    near = d <= 2 * h
    assert np.allclose(band.reshape(-1)[near], d[near]) and (band.reshape(-1)[~near] == 2 * h).all()
    assert (bsign.reshape(-1)[~near] == 0).all()


def test_winding_fast_matches_exact(rng):
    """The fast winding number is within 0.05 of the exact one, with its inside off the surface.

    A stricter far-field test (beta 6 against 2) at least halves the error.
    """
    m = load_shared("kitten")
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    q = rng.uniform(lo - 0.2, hi + 0.2, size=(3000, 3))
    exact = winding_number(m.vertices, m.faces, q, method="exact")
    fast = winding_number(m.vertices, m.faces, q, method="fast")
    d, _, _ = closest_points(m.vertices, m.faces, q)
    assert np.abs(exact - fast).max() < 0.05
    off = d > 0.01 * np.linalg.norm(hi - lo)
    assert np.array_equal(exact[off] > 0.5, fast[off] > 0.5)
    assert np.abs(exact[off] - np.round(exact[off])).max() < 1e-6  # closed mesh: 0 or 1
    # beta is a real accuracy knob (Barill et al.): a stricter far-field test, a smaller error
    from recon_cli.mesh.winding import WindingTree

    tree = WindingTree(m.vertices, m.faces)
    err2 = np.abs(tree(q, beta=2.0) - exact).max()
    err6 = np.abs(tree(q, beta=6.0) - exact).max()
    assert err6 < 0.5 * err2 and err6 < 0.01


def test_disk_reject_coplanar_and_slivers(rng):
    """The per-triangle disk reject never drops the nearest triangle, coplanar or sliver.

    The reject is plane distance + in-plane distance to the bounding disk. Cases: a finely
    tessellated plane (many coplanar triangles at almost the same distance), needle slivers and a
    tilted facet, queried from far away, just off the plane and exactly on it; the answer equals a
    brute-force minimum over the triangles, and a grid over it equals the pointwise answers.
    """
    n = 12
    x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(x.size).reshape(n + 1, n + 1)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # needles (a normal too unreliable for the disk: ball reject) and a tilted facet
    extra = np.array(
        [
            [0.3, 0.3, 0.2],
            [0.9, 0.3, 0.2],
            [0.6, 0.3, 0.2 + 1e-9],
            [0.2, 0.8, 0.5],
            [0.4, 0.9, 0.1],
            [0.3, 0.6, 0.4],
        ]
    )
    f = np.concatenate([f, len(v) + np.array([[0, 1, 2], [3, 4, 5]])])
    v = np.concatenate([v, extra])
    q = np.concatenate(
        [
            rng.uniform([-2, -2, -3], [3, 3, 3], size=(1500, 3)),
            np.c_[rng.uniform(-0.2, 1.2, size=(1500, 2)), rng.normal(scale=1e-3, size=1500)],
            np.c_[rng.uniform(0, 1, size=(300, 2)), np.zeros(300)],
        ]
    )
    dist, face, _ = closest_points(v, f, q)
    brute = np.array([closest_points(v, f[i : i + 1], q)[0] for i in range(len(f))]).min(axis=0)
    assert np.allclose(dist, brute, rtol=0, atol=1e-12)
    assert (dist[-300:] < 1e-12).all()
    origin, h, shape = np.array([-0.3, -0.2, -0.45]), 0.05, (30, 29, 21)
    grid, _ = distance_grid(v, f, origin, h, shape)
    pts = origin + np.indices(shape).reshape(3, -1).T * h
    assert np.allclose(grid.reshape(-1), closest_points(v, f, pts)[0], rtol=0, atol=1e-12)
