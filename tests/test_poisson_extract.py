"""Poisson's extraction over the adaptive tree: on generated shapes (random rotations, scales,
offsets of 1e6, thin parts, holes, sparse and dense halves, single-view scans) the untrimmed
surface is closed, edge- and vertex-manifold, one piece, outward, with no duplicate vertices."""

from __future__ import annotations

import numpy as np
import pytest

from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.topology import report as topology_report
from recon_cli.poisson import screened_poisson

from shapes import SHAPES, shape_cloud, single_view_scan


def _assert_closed_manifold_one_piece(mesh: TriangleMesh) -> None:
    rep = topology_report(mesh)
    assert rep["faces"] > 0
    assert rep["watertight"] and rep["boundary_edges"] == 0, rep["boundary_edges"]
    assert rep["edge_manifold"] and rep["vertex_manifold"], (rep["non_manifold_edges"], rep["non_manifold_vertices"])
    assert rep["components"] == 1, rep["components"]
    assert rep["duplicate_faces"] == 0 and rep["degenerate_faces"] == 0
    assert rep["consistently_oriented"] and rep["volume"] > 0
    # welded: no two vertices at one position
    assert len(np.unique(mesh.vertices, axis=0)) == len(mesh.vertices)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_generated_shapes_closed_manifold_one_piece(rng, name):
    scale = 10.0 ** rng.uniform(-2, 2)
    p, n = shape_cloud(name, 12_000, rng, scale=scale, offset=rng.uniform(-1e6, 1e6, 3))
    _assert_closed_manifold_one_piece(screened_poisson(p, n, depth=7).mesh)


@pytest.mark.parametrize("name", ["sphere", "torus", "rounded_box", "plate_with_hole"])
def test_single_view_scans_closed_manifold_one_piece(rng, name):
    # an open surface: the solution runs into the sparse, coarse part of the tree and the
    # cube's faces, and must still close
    d = rng.normal(size=3)
    p, n = single_view_scan(name, 90, rng, direction=d)
    _assert_closed_manifold_one_piece(screened_poisson(p, n, depth=8).mesh)


def test_sparse_and_dense_halves_closed_manifold_one_piece(rng):
    p, n = shape_cloud("torus", 40_000, rng, rotate=False)
    keep = (p[:, 0] > 0) | (rng.random(len(p)) < 1 / 16)
    _assert_closed_manifold_one_piece(screened_poisson(p[keep], n[keep], depth=9).mesh)


def test_sphere_radius_error_falls_with_depth(rng):
    p, n = shape_cloud("sphere", 60_000, rng)
    err = []
    for depth in (5, 6, 7):
        v = screened_poisson(p, n, depth=depth).mesh.vertices
        err.append(float(np.abs(np.linalg.norm(v, axis=1) - 1.0).mean()))
    # the finest cell halves at each depth (2.2 / 2**depth); the error must fall with it
    assert err[1] < 0.7 * err[0] and err[2] < 0.7 * err[1], err
    assert err[2] < 0.1 * 2.2 / 2**7, err
