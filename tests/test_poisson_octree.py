"""Poisson's adaptive octree: samples splatted at the depth their density supports.

The tree is no deeper than the splats, so depth beyond the data costs (almost) nothing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.octree import indices_in_boxes, points_in_boxes, unique_keys
from recon_cli.stages.poisson.splat import make_splats, merge_samples

from shapes import shape_cloud, sphere_sdf  # noqa: F401  (sphere_sdf documents the shape)


def _unit(points: np.ndarray, scale: float = 1.1) -> np.ndarray:
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = float((hi - lo).max()) * scale
    return (points - (0.5 * (lo + hi) - 0.5 * size)) / size


@pytest.mark.parametrize("n", [2_000, 30_000])
def test_tree_depth_is_where_the_density_reaches_samples_per_node(rng, n):
    """The tree stops one level past where the density reaches the samples per node.

    Whatever ``--depth`` is; at most 2 % of the nodes deeper.
    """
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
    """1,000 points at depth 14 give depth 10's tree and surface (tree depth <= 6)."""
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
    """40k points at depths 9, 10 and 11: the same tree, face counts within 1 %."""
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
    """A 16x sparser half is splatted about two levels coarser; the tree stops at its density."""
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


def _cells(level) -> set:
    from recon_cli.stages.poisson.octree import unpack_keys

    return set(map(tuple, unpack_keys(level.cell_keys).tolist()))


def _sibling_block(cells, ring: int, top: int) -> set:
    """The cells within ``ring`` of ``cells`` (coordinates 0..top), completed in siblings."""
    out = set()
    r = range(-ring, ring + 1)
    for x, y, z in cells:
        for dx in r:
            for dy in r:
                for dz in r:
                    X, Y, Z = x + dx, y + dy, z + dz
                    if 0 <= X <= top and 0 <= Y <= top and 0 <= Z <= top:
                        px, py, pz = X >> 1, Y >> 1, Z >> 1
                        out.update(
                            (2 * px + a, 2 * py + b, 2 * pz + c)
                            for a in (0, 1)
                            for b in (0, 1)
                            for c in (0, 1)
                        )
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_own_ring_1_tree_is_poissonrecons(seed):
    """With own_ring 1 each level is PoissonRecon's: the cells near its items, graded.

    Items at two depths; the tree is a subset of own_ring 2's, graded, and holds every cell its
    items' field reaches.
    """
    # items at two depths in one cloud (a dense patch splatted at 6 inside a sparse sphere
    # splatted at 5): with own_ring 1 each level is exactly the cells within 1 of its own
    # items plus those within 2 of its cells over finer items, completed in siblings
    # (PoissonRecon's finest nodes); a subset of own_ring 2's, graded (a cell's parent's
    # neighbours all exist one level up) and containing every cell its items' field reaches
    from recon_cli.stages.poisson.octree import build_levels, unpack_keys

    rng = np.random.default_rng(seed)
    p, _ = shape_cloud("sphere", 400, rng)
    u = _unit(p)
    dense = u[u[:, 2] > u[:, 2].mean() + 0.25 * np.ptp(u[:, 2])]
    pos = np.concatenate([u, dense])
    lvl = np.concatenate([np.full(len(u), 5), np.full(len(dense), 6)])
    depth, full = 6, 2
    one = build_levels(pos, lvl, depth, full, "neumann", own_ring=1)
    two = build_levels(pos, lvl, depth, full, "neumann", own_ring=2)
    for d in range(full + 1, depth + 1):
        top = (1 << d) - 1
        own = {
            tuple(c) for c in np.floor(pos[lvl == d] * (1 << d)).astype(int).clip(0, top).tolist()
        }
        over_finer = {
            tuple(c) for c in np.floor(pos[lvl > d] * (1 << d)).astype(int).clip(0, top).tolist()
        }
        expect = _sibling_block(own, 1, top) | _sibling_block(over_finer, 2, top)
        got = _cells(one[d])
        assert got == expect, (d, len(got), len(expect))
        assert got <= _cells(two[d])
        # graded: the neighbours (within 1) of every cell's parent exist one level up
        up = _cells(one[d - 1])
        for x, y, z in got:
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for dz in (-1, 0, 1):
                        q = ((x >> 1) + dx, (y >> 1) + dy, (z >> 1) + dz)
                        if all(0 <= c <= top >> 1 for c in q):
                            assert q in up, (d, (x, y, z), q)
    assert len(one[depth].cell_keys) < len(two[depth].cell_keys)
    assert unpack_keys(one[depth].cell_keys).max() <= (1 << depth) - 1


def test_own_ring_is_validated():
    """An own_ring other than 1 or 2 is refused."""
    from recon_cli.stages.poisson.octree import build_levels

    with pytest.raises(ValueError, match="own_ring"):
        build_levels(np.full((1, 3), 0.5), np.array([3]), 3, 1, "neumann", own_ring=3)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-(2**62), 2**62), max_size=300), st.integers(1, 4))
def test_unique_keys_is_numpys_unique(values, repeat):
    """unique_keys is np.unique's sorted distinct values, duplicates and empty input included."""
    # sort-and-compare gives exactly np.unique's sorted distinct values, duplicates and empty
    # input included (dtype kept)
    keys = np.repeat(np.asarray(values, np.int64), repeat)[::-1]
    got = unique_keys(keys)
    assert got.dtype == np.int64 and np.array_equal(got, np.unique(keys))


@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 300),
    k=st.integers(0, 12),
    offset=st.sampled_from([0.0, 1e6]),
)
@settings(max_examples=60, deadline=None)
def test_points_in_boxes_as_a_brute_force(seed, n, k, offset):
    """points_in_boxes and indices_in_boxes agree with a brute force, ties and faces included."""
    # the islands' count and the folds' targets (drop_bubbles): closed boxes, points on a
    # face counted, x ties kept; the indices in any box each once, sorted
    rng = np.random.default_rng(seed)
    pts = np.round(rng.uniform(0, 4, (n, 3)) * 4) / 4 + offset  # on a lattice: many ties
    a = np.round(rng.uniform(0, 4, (k, 3)) * 4) / 4 + offset
    b = a + np.round(rng.uniform(0, 2, (k, 3)) * 4) / 4
    inside = [np.all((pts >= lo) & (pts <= hi), axis=1) for lo, hi in zip(a, b, strict=True)]
    assert points_in_boxes(pts, a, b).tolist() == [int(m.sum()) for m in inside]
    anywhere = np.any(inside, axis=0) if k else np.zeros(n, bool)
    assert indices_in_boxes(pts, a, b).tolist() == np.flatnonzero(anywhere).tolist()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_finer_cells_give_the_levels_the_finer_items_give(seed):
    """Level-dc cells standing for finer items give the levels those items give, bit for bit."""
    # the distributed coarse tree: the level-dc cells holding finer items stand for them, and
    # levels 0..dc are those the finer items (here at dc + 1 and dc + 2) would give, bit for
    # bit, without building the finer levels (the coordinator's largest arrays)
    from recon_cli.stages.poisson.octree import build_levels, pack_keys

    rng = np.random.default_rng(seed)
    dc, full = 6, 3
    p = rng.normal(size=(20_000, 3))
    p = 0.5 + 0.4 * p / np.linalg.norm(p, axis=1)[:, None]  # a sphere's samples
    lvl = rng.integers(full + 1, dc + 3, len(p))
    coarse = lvl <= dc
    whole = build_levels(p, lvl, dc + 2, full, "neumann", False, 1)[: dc + 1]
    cells = pack_keys(np.floor(p[~coarse] * (1 << dc)))
    finer = np.unique(cells)
    part = build_levels(p[coarse], lvl[coarse], dc, full, "neumann", False, 1, finer)
    assert len(part) == dc + 1
    for a, b in zip(whole, part, strict=True):
        assert np.array_equal(a.cell_keys, b.cell_keys)
        assert np.array_equal(a.node_keys, b.node_keys)
        assert (a.cell_parent is None) == (b.cell_parent is None)
        if a.cell_parent is not None:
            assert np.array_equal(a.cell_parent, b.cell_parent)
    assert len(whole[dc].cell_keys) > len(whole[dc - 1].cell_keys) > 0
    # without the finer cells the tree stops where the coarse items stop
    less = build_levels(p[coarse], lvl[coarse], dc, full, "neumann", False, 1)
    assert len(less[dc].cell_keys) < len(whole[dc].cell_keys)
