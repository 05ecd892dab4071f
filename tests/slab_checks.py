"""Checks the slab tests share (tests/test_poisson_distributed.py, test_poisson_slab_options.py)."""

from __future__ import annotations

import numpy as np

from recon_cli.mesh.topology import report as topology_report


def closed_pieces(mesh, pieces: int = 1) -> None:
    """``mesh`` is closed, manifold, oriented, clean, in ``pieces`` pieces, no vertex twice."""
    rep = topology_report(mesh)
    assert rep["components"] == pieces
    assert rep["watertight"] and rep["edge_manifold"] and rep["vertex_manifold"]
    assert rep["consistently_oriented"]
    assert rep["duplicate_faces"] == 0 and rep["degenerate_faces"] == 0
    assert rep["unreferenced_vertices"] == 0
    # no vertex twice: the two slabs of a seam share theirs
    assert len(np.unique(mesh.vertices, axis=0)) == len(mesh.vertices)
    assert rep["volume"] > 0
