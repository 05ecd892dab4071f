"""Poisson's bases: degree 1 (trilinear) and 2 (quadratic B-spline), each meshing a sphere."""

import numpy as np
import pytest

from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.basis import Quadratic, Trilinear, basis_for


def test_basis_for_each_degree():
    """basis_for gives the trilinear or quadratic basis and each basis's tree depth."""
    assert isinstance(basis_for(1), Trilinear) and basis_for(1).degree == 1
    assert isinstance(basis_for(2), Quadratic) and basis_for(2).degree == 2
    # level 0 carries no quadratic function (nor level 1 with the free boundary's cube)
    assert Quadratic().tree_depth(0, False) == 1 and Quadratic().tree_depth(0, True) == 2
    assert Quadratic().tree_depth(7, True) == 7 and Trilinear().tree_depth(0, True) == 0


@pytest.mark.parametrize("degree", [1, 2])
def test_both_bases_reconstruct_a_sphere(degree):
    """Both bases mesh a sphere 1e6 away within half a finest cell, with the full report."""
    rng = np.random.default_rng(4)
    n = rng.normal(size=(6000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    res = screened_poisson(3.0 * n + 1e6, n, depth=6, degree=degree)
    r = np.linalg.norm(res.mesh.vertices - 1e6, axis=1)
    cell = res.report["finest_cell"]
    assert np.abs(r - 3.0).max() < 0.5 * cell, np.abs(r - 3.0).max() / cell
    assert set(res.report["timings"]) >= {"samples", "density", "tree", "solve", "extract"}
    assert res.report["solver_iterations"] > 0 and res.report["residual"] < 1e-3
