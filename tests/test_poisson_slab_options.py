"""Poisson's options in slabs (recon_cli.stages.poisson.distributed) against the single process.

One slab, to the bit; colours, density, the input's attributes, confidence, trimming (a fraction
or auto), the free boundary and the grid, each against the single-process run.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from slab_checks import closed_pieces

from recon_cli.geometry import PointCloud
from recon_cli.mesh.topology import report as topology_report
from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.distributed import distributed_poisson

from shapes import random_rotation, shape_cloud, single_view_scan, sphere_cloud


@pytest.mark.parametrize("n", [8000, 40_000])
def test_one_slab_is_the_single_process_mesh(n):
    """With one slab, the slab pipeline gives the single-process mesh, in both extractions.

    The coarse and fine solves split and the whole pipeline give the single-process solve's mesh, to
    rounding (the same vertices).
    """
    pts, nrm = sphere_cloud(n, seed=3)
    pts = pts * np.array([1.0, 0.8, 0.7])  # x the longest axis: the same frame
    res = distributed_poisson(pts, nrm, depth=7, partitions=1)
    single = screened_poisson(pts, nrm, depth=7)
    assert len(res.mesh.vertices) == len(single.mesh.vertices)
    assert len(res.mesh.faces) == len(single.mesh.faces)
    d, i = cKDTree(single.mesh.vertices).query(res.mesh.vertices)
    assert d.max() < 1e-12
    assert len(np.unique(i)) == len(i)
    assert abs(res.report["iso_value"] - single.report["iso_value"]) < 1e-12


@pytest.mark.parametrize("longest", [0, 1, 2])
def test_one_slab_is_the_single_process_mesh_to_the_bit_whatever_the_longest_axis(longest):
    """One slab gives the single process's mesh to the bit, whichever axis is the longest.

    The same vertices and faces in the same order and the same iso-value: one slab keeps the
    input's axes (only a cut into slabs turns them: the engine's rounding depends on the axes'
    order). At depth 6 the kernel density's level is coarser than the coordinator's levels:
    the samples are placed from it down, as in one process.
    """
    pts, nrm = sphere_cloud(8000, seed=3)
    stretch = np.array([0.8, 0.7, 0.75])
    stretch[longest] = 1.0
    pts = pts * stretch + np.array([0.1, -0.2, 0.3])
    res = distributed_poisson(pts, nrm, depth=6, partitions=1)
    single = screened_poisson(pts, nrm, depth=6)
    assert res.report["iso_value"] == single.report["iso_value"]
    assert np.array_equal(res.mesh.faces, single.mesh.faces)
    assert np.array_equal(res.mesh.vertices, single.mesh.vertices)


def test_colours_and_density_per_vertex():
    """Colours and density in 3 slabs match the single-process vertex nearest."""
    pts, nrm = sphere_cloud(8000, seed=9)
    colors = (np.clip(pts * 0.5 + 0.5, 0, 1) * 255).astype(np.uint8)
    res = distributed_poisson(pts, nrm, depth=7, partitions=3, colors=colors, density=True)
    single = screened_poisson(pts, nrm, depth=7, colors=colors, density=True)
    m = res.mesh
    assert m.colors.dtype == np.uint8 and len(m.colors) == len(m.vertices)
    d, i = cKDTree(single.mesh.vertices).query(m.vertices)
    assert np.abs(m.colors.astype(int) - single.mesh.colors[i].astype(int)).max() <= 2
    dens = m.attributes["density"]
    ref = single.mesh.attributes["density"][i]
    assert np.allclose(dens, ref, rtol=1e-3)


def test_attributes_carried_as_single():
    """Every input property is carried in slabs as in the single-process run, in its dtype.

    Each comes from the points on the vertex's side: codes (a classification by a plane the seams
    cross) only take codes the points have and match the single-process vertex nearest; measurements
    (intensity, colours) within a unit of it; no vertex's neighbours reach past its slab's pad.
    """
    rng = np.random.default_rng(21)
    p, n = sphere_cloud(20_000, seed=21)
    r = random_rotation(rng)
    pts, nrm = p @ r.T * 3.0 + 1e5, n @ r.T
    props = {
        "classification": np.where(p[:, 0] + 0.3 * p[:, 1] > 0.1, 6, 2).astype(np.uint8),
        "intensity": (1000 + 500 * p[:, 2]).astype(np.uint16),
        "gps_time": 1e9 + p[:, 1],
    }
    colors = (np.clip(p * 0.5 + 0.5, 0, 1) * 255).astype(np.uint8)
    res = distributed_poisson(
        pts, nrm, depth=7, partitions=3, properties=props, colors=colors, density=True
    )
    single = screened_poisson(pts, nrm, depth=7, properties=props, colors=colors, density=True)
    m, s = res.mesh, single.mesh
    assert list(m.attributes) == list(s.attributes) == [*props, "density"]
    for k, v in props.items():
        assert m.attributes[k].dtype == v.dtype and len(m.attributes[k]) == len(m.vertices)
    assert res.report["attributes"] == single.report["attributes"]
    assert res.report["distributed"]["attribute_inexact_vertices"] == 0
    _, i = cKDTree(s.vertices).query(m.vertices)
    cls = m.attributes["classification"]
    assert set(np.unique(cls)) == {2, 6}
    assert (cls != s.attributes["classification"][i]).mean() < 0.001
    di = np.abs(m.attributes["intensity"].astype(int) - s.attributes["intensity"][i].astype(int))
    assert di.max() <= 2
    assert np.abs(m.colors.astype(int) - s.colors[i].astype(int)).max() <= 2
    assert np.abs(m.attributes["gps_time"] - s.attributes["gps_time"][i]).max() < 1e-3
    closed_pieces(m)


def test_one_slab_with_confidence_is_the_single_process_mesh():
    """--confidence with one slab gives the single-process mesh, to the bit.

    --confidence weighs each point by its normal's length over the mean of all of them.
    """
    rng = np.random.default_rng(22)
    pts, nrm = sphere_cloud(12_000, seed=22)
    pts = pts * np.array([1.0, 0.8, 0.7])
    nrm = nrm * rng.uniform(0.2, 3.0, size=(len(nrm), 1))
    res = distributed_poisson(pts, nrm, depth=7, partitions=1, confidence=True)
    single = screened_poisson(pts, nrm, depth=7, confidence=True)
    plain = screened_poisson(pts, nrm, depth=7)
    assert np.array_equal(res.mesh.vertices, single.mesh.vertices)
    assert np.array_equal(res.mesh.faces, single.mesh.faces)
    # and the weights did something
    d2, _ = cKDTree(plain.mesh.vertices).query(res.mesh.vertices)
    assert d2.max() > 1e-6


def test_trim_of_an_open_scan_as_single():
    """A single-view scan's closing sheet trimmed over three slabs: the single-process mesh.

    The holes and islands the trim decides are joined across seams, the cut vertices on seams
    shared; the mesh is the single-process one (faces, area removed, boundary loops), manifold, no
    vertex twice.
    """
    rng = np.random.default_rng(0)
    pts, nrm = single_view_scan("torus", 160, rng, direction=(0.3, 0.2, -1.0))
    single = screened_poisson(pts, nrm, depth=7, trim=0.2)
    res = distributed_poisson(pts, nrm, depth=7, partitions=3, trim=0.2, density=True)
    _same_trim(single, res, res.report["finest_cell"], 0.5)
    assert len(res.mesh.attributes["density"]) == len(res.mesh.vertices)


def _same_trim(single, res, cell: float, hausdorff_cells: float) -> None:
    """``res`` (slabs) trimmed as ``single`` (one process): faces, pieces, holes, area."""
    from recon_cli.mesh.distance import closest_points

    a, b = topology_report(single.mesh), topology_report(res.mesh)
    assert abs(b["faces"] - a["faces"]) <= 0.001 * a["faces"]
    assert abs(res.report["trimmed_area"] - single.report["trimmed_area"]) < 1e-3
    assert b["boundary_loops"] == a["boundary_loops"] > 0
    assert b["components"] == a["components"]
    assert b["edge_manifold"] and b["vertex_manifold"] and b["consistently_oriented"]
    assert abs(b["area"] - a["area"]) < 1e-3 * a["area"]
    assert len(np.unique(res.mesh.vertices, axis=0)) == len(res.mesh.vertices)
    ma, mb = single.mesh, res.mesh
    dab = closest_points(mb.vertices, mb.faces, ma.vertices)[0].max()
    dba = closest_points(ma.vertices, ma.faces, mb.vertices)[0].max()
    assert max(dab, dba) <= hausdorff_cells * cell, max(dab, dba) / cell


def test_trim_auto_of_an_open_scan_as_single():
    """``--trim auto`` over three slabs gives the single process's mesh.

    The samples' spacing capped at the global median, the vertices' support ratio, holes and islands
    joined across seams; the mesh is the single process's (within a finest cell where the cut
    crosses a seam's neighbourhood).
    """
    rng = np.random.default_rng(0)
    pts, nrm = single_view_scan("torus", 160, rng, direction=(0.3, 0.2, -1.0))
    single = screened_poisson(pts, nrm, depth=7, trim="auto")
    res = distributed_poisson(pts, nrm, depth=7, partitions=3, trim="auto", density=True)
    _same_trim(single, res, res.report["finest_cell"], 0.5)
    assert res.report["distributed"]["trim_inexact_samples"] == 0
    assert len(res.mesh.attributes["density"]) == len(res.mesh.vertices)


@pytest.mark.slow
def test_trim_auto_of_a_cluttered_scene_as_single():
    """``--trim auto`` of a cluttered office in slabs: the single process's pieces, holes, area.

    A cluttered depth-camera office (near objects, far walls, flying pixels), turned and 1e6 away.
    """
    from recon_cli.stages import normals

    from sensors import cluttered_cloud

    p, eye = cluttered_cloud("office", 0)
    c = normals.run_stage(PointCloud(points=p), orient="camera", camera=tuple(eye)).output
    single = screened_poisson(c.points, c.normals, depth=8, trim="auto")
    res = distributed_poisson(c.points, c.normals, depth=8, partitions=3, trim="auto")
    # the cut runs where the support ratio crosses 1, along edges whose ends moved by at most
    # half a cell near a seam: the cut point moves by up to about a cell
    _same_trim(single, res, res.report["finest_cell"], 1.25)


def _open_along_the_domain(mesh, report) -> None:
    """Assert every boundary vertex of a free-boundary mesh lies on a face of its domain.

    The domain: the points' cube, the solve's middle half.
    """
    from recon_cli.mesh.topology import Connectivity

    c = Connectivity(mesh.faces, len(mesh.vertices))
    bv = mesh.vertices[np.unique(c.edges[c.boundary_edges])]
    assert len(bv)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    on = np.zeros(len(bv), bool)
    for a in range(3):
        on |= np.isclose(bv[:, a], lo[a], rtol=0, atol=1e-9 * report["finest_cell"] * 1e6)
        on |= np.isclose(bv[:, a], hi[a], rtol=0, atol=1e-9 * report["finest_cell"] * 1e6)
    assert on.all()


@pytest.mark.parametrize("parts", [1, 2, 4])
def test_grid_as_single(parts):
    """``--grid`` in slabs gives the one-process grid, whose zero level is the slabs' mesh.

    Same lattice, values within 0.02 finest cell; on a cloud whose longest axis is not x (the slabs'
    axes are turned and the grid turned back).
    """
    from recon_cli.mesh.distance import closest_points
    from recon_cli.stages.mcubes import marching_cubes

    pts, nrm = shape_cloud("torus", 30_000, np.random.default_rng(4), offset=1e5)
    pts, nrm = pts[:, [2, 0, 1]], nrm[:, [2, 0, 1]]
    ref = screened_poisson(pts, nrm, depth=7, with_grid=True).grid
    res = distributed_poisson(pts, nrm, depth=7, partitions=parts, with_grid=True)
    g = res.grid
    assert g.sdf.shape == ref.sdf.shape and res.report["grid_shape"] == list(g.sdf.shape)
    assert g.voxel_size == ref.voxel_size and np.allclose(g.origin, ref.origin, rtol=1e-15)
    assert np.abs(g.sdf - ref.sdf).max() < 0.02 * g.voxel_size
    v, f, _ = marching_cubes(g.sdf, 0.0, spacing=g.voxel_size, origin=g.origin)
    d = closest_points(res.mesh.vertices, res.mesh.faces, v)[0] / g.voxel_size
    assert d.mean() < 0.05 and d.max() < 0.5, (d.mean(), d.max())


@pytest.mark.parametrize("parts", [1, 2, 4])
def test_free_boundary_terrain_as_single(parts):
    """A tilted plane at UTM-like offsets, free boundary, in 1, 2 and 4 slabs: the single mesh.

    The plane covers the whole footprint; ``boundary="free"``: the single process's surface (flat to
    the domain's faces, open only there), within a hundredth of a finest cell.
    """
    from recon_cli.mesh.distance import closest_points

    from shapes import FAR_OFFSETS

    rng = np.random.default_rng(7)
    m = 20_000
    xy = rng.uniform(-1, 1, (m, 2))
    g = np.array([0.3, -0.2])
    p = np.column_stack([xy, xy @ g]) + np.asarray(FAR_OFFSETS["utm"])
    nrm = np.tile(np.array([-g[0], -g[1], 1.0]) / np.sqrt(1 + g @ g), (m, 1))
    single = screened_poisson(p, nrm, depth=7, boundary="free")
    res = distributed_poisson(p, nrm, depth=7, partitions=parts, boundary="free")
    assert len(res.mesh.faces) == len(single.mesh.faces)
    cell = res.report["finest_cell"]
    assert cell == single.report["finest_cell"]
    assert res.report["depth"] == 7 == res.report["tree_depth"]
    d = closest_points(single.mesh.vertices, single.mesh.faces, res.mesh.vertices)[0]
    assert d.max() < 0.05 * cell, d.max() / cell
    assert topology_report(res.mesh)["boundary_loops"] == 1
    assert len(np.unique(res.mesh.vertices, axis=0)) == len(res.mesh.vertices)


def test_free_boundary_open_scan_as_single():
    """A single-view scan, free boundary, in 3 slabs: the single process's open surface.

    Turned and 1e6 away, ``boundary="free"``: open only along the domain's faces, the single
    process's pieces and loops, the same surface near the data; the unsupported sheet (chi flat
    there) within half a cell.
    """
    from recon_cli.mesh.distance import closest_points

    rng = np.random.default_rng(1)
    p, n = single_view_scan("torus", 120, rng, direction=rng.normal(size=3))
    rot = random_rotation(rng)
    p, n = p @ rot.T + 1e6, n @ rot.T
    single = screened_poisson(p, n, depth=7, boundary="free")
    res = distributed_poisson(p, n, depth=7, partitions=3, boundary="free")
    a, b = topology_report(single.mesh), topology_report(res.mesh)
    assert abs(b["faces"] - a["faces"]) <= 0.001 * a["faces"]
    assert (b["components"], b["boundary_loops"]) == (a["components"], a["boundary_loops"])
    assert b["edge_manifold"] and b["vertex_manifold"] and b["consistently_oriented"]
    assert len(np.unique(res.mesh.vertices, axis=0)) == len(res.mesh.vertices)
    _open_along_the_domain(res.mesh, res.report)
    cell = res.report["finest_cell"]
    d = closest_points(single.mesh.vertices, single.mesh.faces, res.mesh.vertices)[0] / cell
    near = cKDTree(p).query(res.mesh.vertices)[0] < 2 * cell
    assert d[near].max() < 0.01 and d.max() < 0.5, (d[near].max(), d.max())


def test_free_boundary_from_files_as_in_memory(tmp_path):
    """The free boundary from a file in 3 slabs gives the in-memory slabs' mesh, to rounding.

    The free boundary's cube is the points' doubled: the rows are sorted into sub-slabs on the
    job's cube, as in memory (sorted on the undoubled one, the slabs' points and seams moved and
    the mesh with them, 0.005 of the torus's radius here).
    """
    from recon_cli.geometry import PointCloud as Cloud
    from recon_cli.io.load import save
    from recon_cli.stages.poisson.files import reconstruct_files

    p, n = single_view_scan("torus", 120, np.random.default_rng(0))
    save(Cloud(p, normals=n), str(tmp_path / "scan.ply"))
    ref = distributed_poisson(p, n, depth=7, partitions=3, boundary="free")
    res = reconstruct_files(
        str(tmp_path / "scan.ply"), client=None, depth=7, partitions=3, boundary="free"
    )
    assert len(res.mesh.faces) == len(ref.mesh.faces)
    d = cKDTree(ref.mesh.vertices).query(res.mesh.vertices)[0]
    assert d.max() < 1e-6 * res.report["finest_cell"], d.max() / res.report["finest_cell"]
