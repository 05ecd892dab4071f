"""Poisson's free boundary (--boundary free, PoissonRecon's BOUNDARY_FREE).

The domain tables, open scans that do not bend to the cube's faces, closed shapes as accurate as
Neumann's.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from recon_cli.errors import ParameterError
from recon_cli.mesh.topology import Connectivity
from recon_cli.stages.poisson import run_stage, screened_poisson
from recon_cli.stages.poisson._bspline import b2_factors
from recon_cli.stages.poisson._luts import B2_MASS, B2_STIFFNESS
from recon_cli.stages.poisson.bspline import level_tables
from recon_cli.stages.poisson.free import domain_tables

from shapes import FAR_OFFSETS, random_rotation, shape_cloud, single_view_scan


def test_domain_tables_whole_line_are_the_unrestricted_tables():
    """Over the whole line the domain tables are the unrestricted B-spline tables."""
    n = 12
    m1, k1, fv, fd = domain_tables(n, -3.0, n + 3.0)
    for i in range(n):
        np.testing.assert_allclose(m1[i], B2_MASS, rtol=0, atol=1e-15)
        np.testing.assert_allclose(k1[i], B2_STIFFNESS, rtol=0, atol=1e-14)
        np.testing.assert_allclose(fv[i], m1[i], rtol=0, atol=0)
        for t in range(-2, 3):
            assert fd[i, t + 2] == pytest.approx(b2_factors(float(t), 1.0)[1], abs=1e-14)


@pytest.mark.parametrize("lo,hi", [(4.0, 12.0), (3.5, 7.25), (0.0, 16.0)])
def test_domain_tables_are_integrals_over_the_interval(lo, hi):
    """The domain tables are the B-splines' integrals over the interval (midpoint rule)."""
    n = 16
    m1, k1, _, fd = domain_tables(n, lo, hi)
    # midpoint rule over the interval against the closed forms of the B-splines
    u = np.linspace(lo, hi, 20_001)
    u = 0.5 * (u[1:] + u[:-1])
    du = (hi - lo) / len(u)

    def b(i, x):
        a = np.abs(x - i - 0.5)
        return np.where(a < 0.5, 0.75 - a * a, np.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0))

    def db(i, x):
        y = x - i - 0.5
        a = np.abs(y)
        return np.where(a < 0.5, -2 * y, np.where(a < 1.5, -np.sign(y) * (1.5 - a), 0.0))

    for i in range(n):
        for t in range(-2, 3):
            j = i + t
            if not 0 <= j < n:
                continue
            assert m1[i, t + 2] == pytest.approx((b(i, u) * b(j, u)).sum() * du, abs=2e-6)
            assert k1[i, t + 2] == pytest.approx((db(i, u) * db(j, u)).sum() * du, abs=2e-6)
            assert fd[i, t + 2] == pytest.approx((db(i, u) * b(j, u)).sum() * du, abs=2e-6)
            # symmetric mass and stiffness
            assert m1[i, t + 2] == pytest.approx(m1[j, 2 - t], abs=1e-15)
        # a cell whose support misses the interval has no equation at all
        missing = i + 2 <= lo or i - 1 >= hi
        assert (np.abs(m1[i]).max() == 0) == missing


def test_level_tables_free_partition_of_unity():
    """The free level tables: partition of unity over the domain; level 1 carries nothing."""
    # the free basis spans the constants on the domain: a row of the mass sums to the
    # integral of its function over the domain, a row of the stiffness to 0
    m1, k1, _, _ = level_tables(32, 1.0, True)
    np.testing.assert_allclose(k1.sum(axis=1), 0.0, rtol=0, atol=1e-14)
    assert m1.sum() == pytest.approx(16.0, abs=1e-12)  # the domain is 16 cells long
    inner = m1[9:23].sum(axis=1)  # supports wholly inside [8, 24]
    np.testing.assert_allclose(inner, 1.0, rtol=0, atol=1e-14)
    assert not level_tables(2, 1.0, True)[0].any()  # level 1 carries no function


def _hugging_area(mesh, lo, size, cell, cells=3):
    """Fraction of the area lying along the cube's faces.

    The area within ``cells`` finest cells of a cube face whose normal is within 30 degrees of that
    face's.
    """
    t = mesh.vertices[mesh.faces]
    c = t.mean(axis=1)
    nn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area = 0.5 * np.linalg.norm(nn, axis=1)
    nn /= np.maximum(2 * area, 1e-300)[:, None]
    hug = np.zeros(len(t), bool)
    for a in range(3):
        near = (np.abs(c[:, a] - lo[a]) < cells * cell) | (
            np.abs(c[:, a] - lo[a] - size) < cells * cell
        )
        hug |= near & (np.abs(nn[:, a]) > np.cos(np.radians(30)))
    return float(area[hug].sum() / area.sum())


@functools.cache
def _scan(seed: int, name: str):
    rng = np.random.default_rng(seed)
    p, n = single_view_scan(name, 90, rng, direction=rng.normal(size=3))
    rot = random_rotation(rng)
    off = np.asarray(list(FAR_OFFSETS.values())[seed % 3])
    return p @ rot.T + off, n @ rot.T


@pytest.mark.parametrize("seed,name", [(1, "sphere"), (2, "torus"), (3, "rounded_box")])
def test_open_scans_do_not_bend_to_the_cube_faces(seed, name):
    """Open scans with the free boundary do not hug the cube's faces, open only along them.

    Neumann's surface hugs the faces more; the free one's boundary vertices all lie on a face.
    """
    p, n = _scan(seed, name)
    lo, hi = p.min(axis=0), p.max(axis=0)
    size = float((hi - lo).max()) * 1.1
    origin = 0.5 * (lo + hi) - 0.5 * size
    out = {}
    for boundary in ("neumann", "free"):
        r = screened_poisson(p, n, depth=6, boundary=boundary)
        out[boundary] = _hugging_area(r.mesh, origin, size, r.report["finest_cell"])
        if boundary == "free":
            # open only along the cube's faces: every boundary vertex lies on one
            c = Connectivity(r.mesh.faces, len(r.mesh.vertices))
            bv = np.unique(c.edges[c.boundary_edges])
            assert len(bv) > 0
            u = (r.mesh.vertices[bv] - origin) / size
            on_face = np.min(np.minimum(np.abs(u), np.abs(1 - u)), axis=1) < 1e-6
            assert on_face.all()
            # the samples are on the surface
            from recon_cli.mesh.distance import closest_points

            d = closest_points(r.mesh.vertices, r.mesh.faces, p)[0]
            assert np.quantile(d, 0.99) < r.report["finest_cell"]
    # Neumann's closing surface lies along the faces; the free one crosses them
    assert out["neumann"] > 0.2, out
    assert out["free"] < 0.02, out


def test_terrain_stays_flat_to_the_faces(rng):
    """A tilted plane at UTM offsets stays flat to the faces when free; Neumann's bends.

    Free: within 2 finest cells of the plane; Neumann: more than 10.
    """
    # a tilted plane over the whole footprint (an airborne tile's ground): the free surface is
    # the plane up to the cube's faces; Neumann's bends to meet them and hugs them
    m = 20_000
    xy = rng.uniform(-1, 1, (m, 2))
    g = np.array([0.3, -0.2])
    p = np.column_stack([xy, xy @ g]) + np.asarray(FAR_OFFSETS["utm"])
    nrm = np.tile(np.array([-g[0], -g[1], 1.0]) / np.sqrt(1 + g @ g), (m, 1))
    dev = {}
    for boundary in ("neumann", "free"):
        r = screened_poisson(p, nrm, depth=6, boundary=boundary)
        h = (r.mesh.vertices - p.mean(axis=0)) @ nrm[0]
        dev[boundary] = np.abs(h).max() / r.report["finest_cell"]
    assert dev["free"] < 2.0, dev
    assert dev["neumann"] > 10.0, dev


def test_closed_shapes_as_accurate_as_neumann(rng):
    """A closed sphere 1e6 away: the free boundary as accurate as Neumann's, closed, full depth."""
    p, n = shape_cloud("sphere", 20_000, rng, offset=1e6)
    r = {b: screened_poisson(p, n, depth=7, boundary=b) for b in ("neumann", "free")}
    for b, res in r.items():
        rad = np.linalg.norm(res.mesh.vertices - 1e6, axis=1)
        cell = res.report["finest_cell"]
        assert np.abs(rad - 1).max() < 0.1 * cell, b
        assert Connectivity(res.mesh.faces, len(res.mesh.vertices)).boundary_edges.size == 0
    err = {
        b: np.abs(np.linalg.norm(res.mesh.vertices - 1e6, axis=1) - 1).mean()
        for b, res in r.items()
    }
    assert err["free"] < 1.1 * err["neumann"], err
    assert r["free"].report["depth"] == 7 and r["free"].report["tree_depth"] == 7


def test_free_needs_degree_2_and_the_native_backend(rng):
    """The free boundary with degree 1 or a reference backend is refused."""
    p, n = shape_cloud("sphere", 500, rng)
    with pytest.raises(ParameterError, match="degree 2"):
        screened_poisson(p, n, depth=5, boundary="free", degree=1)
    from recon_cli.geometry import PointCloud

    with pytest.raises(ParameterError, match="native"):
        run_stage(PointCloud(points=p, normals=n), boundary="free", backend="open3d")
