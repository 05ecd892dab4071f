"""Poisson's ``--envelope`` in slabs against the single-process run.

An open scan, turned and far from the origin, closed along a box envelope in one and three
slabs (recon_cli.stages.poisson.slab_envelope), in memory and from the file by the command.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from scipy.spatial import ConvexHull, cKDTree
from slab_checks import closed_pieces

from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import read_ply, write_ply
from recon_cli.mesh.distance import closest_points
from recon_cli.mesh.topology import report as topology_report
from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.distributed import distributed_poisson, frame_of
from recon_cli.stages.poisson.envelope import Envelope

from shapes import FAR_OFFSETS, random_rotation, single_view_scan

DEPTH = 6


@functools.cache
def _scan(swap: tuple = (1, 2, 0)) -> tuple[np.ndarray, np.ndarray, TriangleMesh]:
    """A single-view torus scan and a box 1.3 times its extent around it, turned and far away.

    Their axes swapped (by default so that the slabs' axis is not the input's x: the slabs
    turn theirs).
    """
    rng = np.random.default_rng(0)
    p, n = single_view_scan("torus", 120, rng, direction=rng.normal(size=3))
    lo, hi = p.min(axis=0), p.max(axis=0)
    c, h = 0.5 * (lo + hi), 0.65 * (hi - lo) + 0.3
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    bv = c + corners * h
    bf = ConvexHull(bv).simplices
    rot = random_rotation(rng)
    off = np.asarray(FAR_OFFSETS["1e6"])
    p, n, bv = p @ rot.T + off, n @ rot.T, bv @ rot.T + off
    s = list(swap)
    return p[:, s], n[:, s], TriangleMesh(vertices=bv[:, s], faces=bf)


@functools.cache
def _single(swap: tuple = (1, 2, 0)):
    p, n, env = _scan(swap)
    return screened_poisson(p, n, depth=DEPTH, envelope=env)


def test_the_slabs_axes_are_turned():
    """The slabs turn the input's and the envelope's axes when x is not the longest.

    One slab is not cut: it keeps them.
    """
    # the scan's longest axis is x as made, not once swapped: the slabs turn theirs, and the
    # envelope's, in the swapped scan
    for swap, turned in (((0, 1, 2), False), ((1, 2, 0), True)):
        p, _, _ = _scan(swap)
        assert (frame_of(p.min(axis=0), p.max(axis=0), 1.1, 3)[2] != (0, 1, 2)) == turned
        assert frame_of(p.min(axis=0), p.max(axis=0), 1.1, 1)[2] == (0, 1, 2)


@pytest.mark.parametrize("swap", [(0, 1, 2), (1, 2, 0)])
def test_one_slab_is_the_single_process_mesh(swap):
    """One slab gives the single process's mesh to the bit, whichever axis is the longest.

    One slab keeps the input's axes; the report's envelope counts, depths and iso-value agree.
    """
    p, n, env = _scan(swap)
    single = _single(swap)
    res = distributed_poisson(p, n, depth=DEPTH, partitions=1, envelope=env)
    assert res.report["finest_cell"] == single.report["finest_cell"]
    assert np.array_equal(res.mesh.faces, single.mesh.faces)
    assert np.array_equal(res.mesh.vertices, single.mesh.vertices)
    for key in ("depth", "tree_depth", "envelope_outside_points", "envelope_pulled_vertices"):
        assert res.report[key] == single.report[key], key
    # the cube grew for the box (the finest lattice kept): the depths are the asked one
    assert res.report["tree_depth"] == DEPTH
    assert res.report["iso_value"] == single.report["iso_value"]
    assert res.report["envelope_pulled_vertices"] > 0  # the last guard did something
    for key in ("depth", "tree_depth", "envelope_outside_points", "envelope_pulled_vertices"):
        assert res.report[key] == single.report[key], key
    # the cube grew for the box (the finest lattice kept): the depths are the asked one
    assert single.report["tree_depth"] == DEPTH
    assert abs(res.report["iso_value"] - single.report["iso_value"]) < 1e-12


def _as_single(mesh: TriangleMesh, rep: dict, p: np.ndarray, env: TriangleMesh) -> None:
    """``mesh`` and its report ``rep`` (slabs) close the scan as the single process does.

    The same faces (to 0.1 %), pieces and topology, no vertex outside the envelope, the same
    points outside it; within a twentieth of a finest cell for 99 % of the vertices and near
    the data, and within half a cell everywhere (issue 44's bound).
    """
    single = _single()
    a, b = single.mesh, mesh
    cell = single.report["finest_cell"]
    assert abs(len(b.faces) - len(a.faces)) <= 0.001 * len(a.faces)
    ta, tb = topology_report(a), topology_report(b)
    assert (tb["components"], tb["boundary_loops"]) == (ta["components"], ta["boundary_loops"])
    closed_pieces(b, ta["components"])
    assert not (~Envelope(env).inside(b.vertices)).any()
    assert rep["envelope_outside_points"] == single.report["envelope_outside_points"]
    pulled = single.report["envelope_pulled_vertices"]
    assert abs(rep["envelope_pulled_vertices"] - pulled) <= max(2, 0.1 * pulled)
    d = closest_points(a.vertices, a.faces, b.vertices)[0] / cell
    back = closest_points(b.vertices, b.faces, a.vertices)[0] / cell
    near = cKDTree(p).query(b.vertices)[0] < 2 * cell
    assert d[near].max() < 0.05 and np.quantile(d, 0.99) < 0.05, (d[near].max(), d.max())
    assert max(d.max(), back.max()) < 0.5, (d.max(), back.max())


def test_three_slabs_close_the_scan_as_single():
    """Three slabs close the scan as the single process does.

    Each slab tests its samples against the envelope and makes its part of the carving (OR-ed on
    the coordinator); the tree is refined along both, chi clipped, vertices pulled inside.
    """
    p, n, env = _scan()
    res = distributed_poisson(p, n, depth=DEPTH, partitions=3, envelope=env)
    assert len(res.report["distributed"]["slabs"]) == 3
    assert res.report["finest_cell"] == _single().report["finest_cell"]
    _as_single(res.mesh, res.report, p, env)


def test_command_closes_the_scan_in_slabs_from_the_file(tmp_path, monkeypatch, capsys):
    """``recon poisson IN OUT --partitions 3 --envelope E`` gives the single process's mesh.

    The slabs read IN by chunks (the command never loads it, only E); the report counts the
    points outside and the vertices pulled.
    """
    import recon_cli.io.load as L
    from recon_cli.cli.main import main

    p, n, env = _scan()
    src, out, env_path = tmp_path / "scan.ply", tmp_path / "mesh.ply", tmp_path / "box.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    write_ply(env, env_path)
    load = L.load

    def only_the_envelope(path, *a, **k):
        assert str(path) == str(env_path), "the command loaded IN"
        return load(path, *a, **k)

    monkeypatch.setattr(L, "load", only_the_envelope)
    args = ["poisson", str(src), str(out), "--depth", str(DEPTH), "--partitions", "3"]
    with pytest.raises(SystemExit) as exc:
        main([*args, "--envelope", str(env_path), "--json"])
    captured = capsys.readouterr()
    assert exc.value.code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)
    assert len(rep["distributed"]["slabs"]) == 3
    _as_single(read_ply(out), rep, p, env)
