"""The two bases of the solve (degree 1 and 2): what differs between them, in one object each.

:func:`~recon_cli.stages.poisson.screened_poisson` runs the same phases for both bases; the
tree's shape, the solve, the iso-value and the extraction's vertex refinement differ. A
:class:`Basis` holds those differences: trilinear hat functions on the nodes (degree 1,
:mod:`.system`) or quadratic B-splines centred on the cells (degree 2, :mod:`.bspline`).

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.stages.poisson.octree import Level
from recon_cli.stages.poisson.splat import Samples, Splats


@dataclass
class Solution:
    """A solved field: the levels' coefficients and what the extraction needs of it.

    Attributes
    ----------
    levels : list of Level
        The tree (consumed by the extraction).
    gvals : list of ndarray
        Each level's coefficients (consumed by the extraction).
    per_level : list of dict
        Per-level solver statistics (``report["levels"]``).
    iterations : int
        Conjugate-gradient iterations over all levels.
    residual : float
        The finest level's relative residual.
    iso : float
        The level set's value.
    chi : Any
        Degree 2: the :class:`.bspline.ChiField` the vertices are refined on; degree 1: None.
    """

    levels: list[Level]
    gvals: list[np.ndarray]
    per_level: list[dict]
    iterations: int
    residual: float
    iso: float
    chi: Any = None


class Basis:
    """What differs between the bases: the tree's shape, the solve and the extraction.

    Attributes
    ----------
    degree : int
        1 (trilinear hat functions on the nodes) or 2 (quadratic B-splines on the cells).
    corners : bool
        The tree holds its cells' corner nodes (degree 1's unknowns).
    own_ring : int
        Cells around each splat's own cell kept at its level (:func:`.octree.build_levels`).
    merge_splats : bool
        Splats of a cell merged into one (:func:`.splat.make_splats`' ``merge``).
    """

    degree = 0
    corners = False
    own_ring = 1
    merge_splats = False

    def tree_depth(self, tree_depth: int, free: bool) -> int:
        """The tree's depth given the splats' deepest level ``tree_depth`` (``free`` boundary)."""
        return tree_depth

    def build_tree(
        self,
        item_pos: np.ndarray,
        item_level: np.ndarray,
        tree_depth: int,
        full_depth: int,
        boundary: str,
    ) -> list[Level]:
        """The tree over the splat items (positions (m, 3) in the unit cube, levels (m,))."""
        from recon_cli.stages.poisson.octree import build_levels

        return build_levels(
            item_pos,
            item_level,
            tree_depth,
            full_depth,
            boundary,
            corners=self.corners,
            own_ring=self.own_ring,
        )

    def solve(
        self,
        levels: list[Level],
        smp: Samples,
        splats: Splats,
        boundary: str,
        full_depth: int,
        cg_tolerance: float,
        progress: Any,
        sample_ok: np.ndarray | None,
        clip: Any = None,
    ) -> Solution:
        """Solve every level, coarse to fine, and find the iso-value.

        ``sample_ok`` as :func:`.bspline.solve`'s; ``clip(iso)`` gives the
        clip of the field read after the solve (an envelope's, :class:`.envelope.FieldClip`;
        degree 2 only).
        """
        raise NotImplementedError

    def extract(
        self,
        sol: Solution,
        origin: np.ndarray,
        size: float,
        tree_depth: int,
        with_grid: bool,
    ) -> tuple[np.ndarray, np.ndarray, Any]:
        """(vertices in world units, faces, chi for the grid or None); consumes ``sol``."""
        raise NotImplementedError


class Trilinear(Basis):
    """Degree 1: trilinear hat functions on the nodes (:mod:`.system`), as Open3D's Poisson."""

    degree = 1
    corners = True
    own_ring = 2
    merge_splats = True

    def solve(
        self,
        levels,
        smp,
        splats,
        boundary,
        full_depth,
        cg_tolerance,
        progress,
        sample_ok,
        clip=None,
    ):
        """Solve every level, coarse to fine; the iso-value: chi's mean at the samples."""
        from recon_cli.stages.poisson.system import iso_value, solve

        gvals, per_level, total_it, last_res = solve(
            levels, smp, splats, full_depth, cg_tolerance, progress
        )
        iso = iso_value(levels, gvals, smp)
        return Solution(levels, gvals, per_level, total_it, last_res, iso)

    def extract(self, sol, origin, size, tree_depth, with_grid):
        """Extract in finest-lattice units, each vertex to the root of chi's quadratic fit."""
        from recon_cli.stages.poisson.extract import extract, refine_roots
        from recon_cli.stages.poisson.system import chi_at, chi_levels

        res = 1 << tree_depth
        chi_lv = chi_levels(sol.levels, sol.gvals)
        verts, faces = extract(sol.levels, sol.gvals, sol.iso, np.zeros(3), float(res))
        sol.levels = sol.gvals = []
        refine_roots(verts, chi_lv, sol.iso, tree_depth)
        verts *= size / res
        verts += origin
        chi_fn = functools.partial(chi_at, chi_lv) if with_grid else None
        return verts, faces, chi_fn


class Quadratic(Basis):
    """Degree 2: quadratic B-splines centred on the cells (:mod:`.bspline`), as PoissonRecon."""

    degree = 2

    def tree_depth(self, tree_depth, free):
        """Level 0 carries no degree-2 function (nor level 1 with the free boundary)."""
        return max(tree_depth, 2 if free else 1)

    def solve(
        self,
        levels,
        smp,
        splats,
        boundary,
        full_depth,
        cg_tolerance,
        progress,
        sample_ok,
        clip=None,
    ):
        """Solve every level, coarse to fine (:func:`.bspline.solve`)."""
        from recon_cli.stages.poisson import bspline

        gvals, per_level, total_it, last_res, iso, chi = bspline.solve(
            levels,
            smp,
            splats,
            boundary,
            full_depth,
            cg_tolerance,
            progress,
            sample_ok=sample_ok,
            clip=clip,
        )
        return Solution(levels, gvals, per_level, total_it, last_res, iso, chi)

    def extract(self, sol, origin, size, tree_depth, with_grid):
        """Extract on the leaves' corners, then each vertex to chi's exact root on its edge."""
        from recon_cli.memory import release_free_heap
        from recon_cli.stages.poisson.extract import extract
        from recon_cli.stages.poisson.system import chi_at, chi_levels

        chi = sol.chi
        # memory: chi is not read again until the vertices' roots, and the heap the solve and
        # then the extraction freed is given back
        chi.drop_neighbours()
        release_free_heap()
        # the grid reads chi as the extraction does: trilinear in each leaf from its corners
        chi_fn = functools.partial(chi_at, chi_levels(sol.levels, sol.gvals)) if with_grid else None
        verts, faces = extract(sol.levels, sol.gvals, sol.iso, origin, size)
        sol.levels = sol.gvals = []
        sol.chi = None
        release_free_heap()
        # chi is not trilinear between the lattice's points: each vertex to chi's root on its edge
        verts = chi.refine_vertices(verts, sol.iso, origin, size, tree_depth)
        return verts, faces, chi_fn


def basis_for(degree: int) -> Basis:
    """The :class:`Basis` of B-spline ``degree`` (1 or 2)."""
    return Quadratic() if degree == 2 else Trilinear()
