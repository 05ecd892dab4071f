"""Trimming a Poisson surface along a density contour (recon_cli.stages.poisson.trim)."""

from __future__ import annotations

import numpy as np
import pytest

from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.topology import Connectivity
from recon_cli.mesh.topology import report as topology_report
from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.trim import trim_by_density
from recon_cli.tolerances import tol

from shapes import SHAPES, icosphere, random_rotation, single_view_scan


def _manifold_oriented(mesh) -> dict:
    rep = topology_report(mesh)
    assert rep["edge_manifold"] and rep["vertex_manifold"], rep
    assert rep["consistently_oriented"], rep
    assert rep["degenerate_faces"] == 0 and rep["duplicate_faces"] == 0, rep
    return rep


@pytest.mark.parametrize("level", [-0.55, -0.1, 0.0, 0.3, 0.8])
def test_cut_follows_the_contour_exactly(level):
    # density = height on a closed sphere: the cut is the circle z = level, exactly
    s = TriangleMesh(*icosphere(4))
    z = s.vertices[:, 2]
    out = trim_by_density(s, z, level)
    m = out.mesh
    rep = _manifold_oriented(m)
    assert rep["components"] == 1 and rep["boundary_loops"] == 1
    # crossings within tol.contour of an edge's end are moved off it (no slivers): the contour
    # is exact up to that fraction of the longest edge
    ends = s.vertices[s.faces]
    slack = tol.contour * np.linalg.norm(ends - np.roll(ends, 1, axis=1), axis=2).max() + 1e-12
    assert m.vertices[:, 2].min() >= level - slack
    loop = Connectivity(m.faces, len(m.vertices)).boundary_loops[0]
    assert np.allclose(m.vertices[loop, 2], level, atol=slack)  # the boundary is the contour
    assert np.allclose(out.density[loop], level)
    # the kept area is the area of the cap above the contour (up to the facets' chordal error)
    area = Connectivity(m.faces, len(m.vertices), m.vertices).face_areas.sum()
    cap = 2 * np.pi * (1 - level)
    assert abs(area - cap) / cap < 0.01
    # winding unchanged: the kept faces' normals point out of the sphere
    v = m.vertices[m.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (np.einsum("ij,ij->i", n, v.mean(axis=1)) > 0).all()


def test_small_islands_filled_and_dropped():
    s = TriangleMesh(*icosphere(6))
    x, z = s.vertices[:, 0], s.vertices[:, 2]
    d = z.copy()
    # a small low dip inside the kept part (a sparse patch: must not become a hole) and a
    # small high bump inside the removed part (an outlier: must go)
    dip = np.linalg.norm(s.vertices - [0.0, 0.0, 1.0], axis=1) < 0.03
    bump = np.linalg.norm(s.vertices - [1.0, 0.0, 0.0], axis=1) < 0.03
    d[dip] = -1.0
    d[bump] = 1.0
    assert dip.sum() >= 3 and bump.sum() >= 3
    m = trim_by_density(s, d, 0.2).mesh
    rep = _manifold_oriented(m)
    assert rep["components"] == 1 and rep["boundary_loops"] == 1
    assert m.vertices[:, 2].max() > 0.999  # the dip stayed
    assert (
        m.vertices[:, 2].min() >= 0.2 - 1e-4 and not (m.vertices[:, 0] > 0.99).any()
    )  # the bump went
    # with no island rule both stay as they are
    m0 = trim_by_density(s, d, 0.2, island_ratio=0.0).mesh
    assert topology_report(m0)["components"] == 2 and topology_report(m0)["boundary_loops"] == 3
    del x


def test_nothing_to_trim_returns_the_mesh():
    s = TriangleMesh(*icosphere(2))
    out = trim_by_density(s, np.ones(len(s.vertices)), 0.5)
    assert out.mesh is s and out.removed_area == 0.0 and out.untouched_faces == len(s.faces)


@pytest.mark.parametrize("name", sorted(SHAPES))
@pytest.mark.parametrize("seed", [0, 1])
def test_single_view_scans_lose_the_sheet_keep_the_scan(name, seed):
    # a ray-cast partial scan, randomly rotated and offset: untrimmed the surface is closed by a
    # sheet far from the samples; trimmed (0.3) it is manifold, lies on the shape (the Poisson
    # surface bends away from it only along the scan's border) and covers the scan
    rng = np.random.default_rng(seed)
    pts, nrm = single_view_scan(name, 90, rng)
    rot = random_rotation(rng)
    off = rng.uniform(-1e3, 1e3, 3)
    sdf, _ = SHAPES[name]
    res = screened_poisson(pts @ rot.T + off, nrm @ rot.T, depth=7, trim=0.3)
    m = res.mesh
    _manifold_oriented(m)
    assert 0 < res.report["trimmed_faces"] and 0.2 < res.report["trimmed_area"] < 0.95
    cell = res.report["finest_cell"]
    local = (m.vertices - off) @ rot  # back in the shape's frame
    dist = np.abs(sdf(local))
    assert np.quantile(dist, 0.99) < 2.5 * cell and dist.max() < 3 * cell, (
        dist.max(),
        cell,
    )  # no sheet left
    from scipy.spatial import cKDTree

    covered = cKDTree(local).query(pts)[0] < 2 * cell
    assert covered.mean() > 0.97, covered.mean()  # the scanned surface stays
