"""Poisson's adaptive octree: samples splatted at the depth their density supports, the tree
no deeper than the splats, so depth beyond the data costs (almost) nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from recon_cli.poisson import screened_poisson
from recon_cli.poisson.splat import make_splats, merge_samples

from shapes import shape_cloud, sphere_sdf  # noqa: F401  (sphere_sdf documents the shape)


def _unit(points: np.ndarray, scale: float = 1.1) -> np.ndarray:
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = float((hi - lo).max()) * scale
    return (points - (0.5 * (lo + hi) - 0.5 * size)) / size


@pytest.mark.parametrize("n", [2_000, 30_000])
def test_tree_depth_is_where_the_density_reaches_samples_per_node(rng, n):
    # n points on a unit sphere in a cube of side 2.2: at level L a node's area is 4**-L of
    # the unit cube's faces, the sphere's area there 4 pi / 2.2**2, so samples-per-node 1.5
    # is reached at L* = log4(n / (1.5 * area)); the tree goes one level past L* (a
    # fractional depth is shared with the next level) and no further, whatever --depth is
    # (a few locally dense samples may reach one level more: a sliver of nodes)
    p, nrm = shape_cloud("sphere", n, rng)
    area = 4 * math.pi / 2.2**2
    expect = math.ceil(0.5 * math.log2(n / (1.5 * area)))
    for depth in (9, 12):
        rep = screened_poisson(p, nrm, depth=depth).report
        assert expect <= rep["tree_depth"] <= expect + 1, (n, depth, rep["tree_depth"], expect)
        # per level solved (degree 2 has no function on level 0: its list starts at 1)
        nodes = {lv["depth"]: lv["nodes"] for lv in rep["levels"]}
        finer = sum(v for d, v in nodes.items() if d > expect)
        assert finer <= 0.02 * nodes[expect], nodes


def test_depth_beyond_the_data_adds_nothing(rng):
    # 1,000 points: --depth 14 builds the same tree and the same surface as --depth 10 (it
    # used to pass 11 GB at depth 12 and never finish at 14); only the merging of points
    # sharing a finest cell could differ
    p, nrm = shape_cloud("torus", 1_000, rng)
    a = screened_poisson(p, nrm, depth=10)
    b = screened_poisson(p, nrm, depth=14)
    assert [lv["nodes"] for lv in a.report["levels"]] == [lv["nodes"] for lv in b.report["levels"]]
    assert a.report["tree_depth"] == b.report["tree_depth"] <= 6
    assert len(a.mesh.faces) == len(b.mesh.faces)
    np.testing.assert_allclose(a.mesh.vertices, b.mesh.vertices, rtol=0, atol=1e-6 * np.ptp(p))


def test_faces_barely_change_past_the_datas_depth(rng):
    # 40k points on a rounded box are exhausted near depth 7: depths 9, 10 and 11 give the
    # same tree and nearly the same surface (only the merging of points per finest cell
    # differs)
    p, nrm = shape_cloud("rounded_box", 40_000, rng)
    faces = {}
    for depth in (9, 10, 11):
        res = screened_poisson(p, nrm, depth=depth)
        assert res.report["tree_depth"] <= 8
        faces[depth] = len(res.mesh.faces)
    assert abs(faces[11] - faces[10]) <= 0.01 * faces[10], faces
    assert abs(faces[10] - faces[9]) <= 0.01 * faces[9], faces


def test_sparse_half_is_splatted_coarser(rng):
    # one cloud, a dense and a sparse half: the sparse half's samples go to coarser levels
    # (16x fewer samples per area: two levels coarser)
    p, nrm = shape_cloud("sphere", 64_000, rng, rotate=False)
    keep = (p[:, 2] > 0) | (rng.random(len(p)) < 1 / 16)
    p, nrm = p[keep], nrm[keep]
    unit = _unit(p)
    smp = merge_samples(unit, nrm, 12)
    sp = make_splats(smp, 12, 1.5, 4.0, False)
    # the sphere's centre is the cube's (its bounding box is symmetric)
    upper = sp.pos[:, 2] > 0.6
    lower = sp.pos[:, 2] < 0.4
    lu = np.average(sp.level[upper])
    ll = np.average(sp.level[lower])
    assert 1.5 <= lu - ll <= 2.5, (lu, ll)
    # the tree stops where the samples stop: no splat deeper than the dense half supports
    assert sp.tree_depth == int(sp.level[upper].max())
