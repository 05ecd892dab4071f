"""The cascadic solve: level by level, coarse to fine, by preconditioned conjugate gradients.

Each level's correction to the coarser levels' indicator function is solved with Jacobi
preconditioning.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.memory import release_free_heap
from recon_cli.progress import task
from recon_cli.stages.poisson import _octree as O
from recon_cli.stages.poisson import _system as Y
from recon_cli.stages.poisson._luts import UNIT_STIFFNESS
from recon_cli.stages.poisson.octree import Level
from recon_cli.stages.poisson.splat import NormalField, Samples, Splats

log = logging.getLogger("recon")

# the screening pulls chi towards this value at the samples
TARGET = 0.5
# the screening weight where the samples are clean and where they are noisy, relative to
# make_splats' (Splats.screening): the best accuracy against Open3D's (bench/calibration.md)
SCREEN_CLEAN = 1.3
SCREEN_NOISY = 0.5


def solve(
    levels: list[Level],
    smp: Samples,
    splats: Splats,
    full_depth: int,
    cg_tolerance: float,
    progress: Any = None,
) -> tuple[list[np.ndarray], list[dict], int, float]:
    """Solve every level in turn.

    Returns chi per level (at its nodes, the coarser levels' part included), per-level statistics,
    total iterations and the finest relative residual.

    Each level's arrays go as soon as no later step needs them (sets ``face_nodes`` and
    ``leaf`` of every level, drops the rest; ``splats.rhs_fields`` is consumed, set to
    None): at the finest level the peak is the level's cells plus the solver's (n,)
    vectors, tens of MB each.
    """
    depth = len(levels) - 1
    spos = smp.pos
    alpha = splats.alpha
    screen_w = splats.screening(SCREEN_CLEAN, SCREEN_NOISY)
    total_it = 0
    last_res = 0.0
    gvals: list[np.ndarray] = []
    per_level = []
    work = solve_work(levels, full_depth)
    assert splats.rhs_fields is not None  # made by make_splats, consumed here once
    node_keys = [lev.node_keys for lev in levels]
    assert all(k is not None for k in node_keys)  # set with the tree
    field = NormalField(splats.rhs_fields, node_keys)  # type: ignore[arg-type]  # checked above
    del node_keys
    splats.rhs_fields = None  # the field drops each level's share once used
    with task(progress, "poisson: solve", total=sum(work)) as tk:
        for lev in levels:
            tk.expect(work[lev.depth])  # the bar moves on an estimate while the level's kernels run
            release_free_heap()
            tl = time.perf_counter()
            d = lev.depth
            ke = UNIT_STIFFNESS / (1 << d)
            # (n,) vectors are updated in place
            assert lev.node_keys is not None and lev.unknown is not None  # until this level ends
            rhs = field.rhs(d, lev.cell_keys, lev.node_keys, lev.unknown)
            # past the right-hand side only the nodes on the cube's faces are needed (for the
            # extraction's clamp), not the node keys
            lev.face_nodes = O.face_nodes(lev.node_keys, 1 << d)
            lev.node_keys = None
            scr = _level_screening(lev, spos, screen_w * (2.0 ** (d - depth)), alpha, rhs)
            par = levels[d - 1] if d > 0 else None
            if par is not None:
                _subtract_coarse(lev, par, gvals[-1], ke, scr, rhs)
            exact = d <= full_depth
            release_free_heap()  # the set-up's temporaries: not resident while the solver runs
            x, it, rel = Y.level_pcg(
                lev.cell_nodes,
                ke,
                scr.cscr,
                (scr.scell, scr.sloc, scr.sw),
                rhs,
                lev.ncell,
                scr.sd_nodes,
                scr.sd_vals,
                lev.unknown,
                1e-7 if exact else cg_tolerance,
                2000 if exact else 200,
            )
            del rhs, scr
            gvals.append(_level_chi(lev, par, gvals[-1] if gvals else None, x))
            del x
            total_it += it
            last_res = rel
            n_unknown = int(lev.unknown.sum())
            lev.unknown = lev.ncell = None
            per_level.append(
                {
                    "depth": d,
                    "nodes": lev.n_nodes,
                    "unknowns": n_unknown,
                    "iterations": it,
                    "residual": rel,
                    "seconds": time.perf_counter() - tl,
                }
            )
            log.info(
                "poisson: level %2d  nodes %9d  unknowns %9d  cg iterations %4d  residual %.2e "
                " %.2f s",
                d,
                lev.n_nodes,
                n_unknown,
                it,
                rel,
                time.perf_counter() - tl,
            )
            tk.advance(work[d])
    levels[-1].leaf = np.ones(len(levels[-1].cell_keys), bool)
    return gvals, per_level, total_it, last_res


@dataclass
class _Screening:
    """A level's screening samples and the solver's views of them (:func:`_level_screening`)."""

    scell: np.ndarray  # (m,) the samples' cells
    sloc: np.ndarray  # (m, 3) their positions in the cells
    sw: np.ndarray  # (m,) their weights, or none when summed into ``cscr``
    sd_nodes: np.ndarray  # the diagonal's screening part: nodes ...
    sd_vals: np.ndarray  # ... and values
    cscr: np.ndarray  # (c, 8, 8) each cell's screening matrix, or none


def _level_screening(
    lev: Level, spos: np.ndarray, lw: np.ndarray, alpha: float, rhs: np.ndarray
) -> _Screening:
    """The samples screening level ``lev`` (weights ``lw``), their part of ``rhs`` added.

    The tree is adaptive: only the samples inside this level's cells screen it; the weight
    halves with each coarser level (PoissonRecon scales a node's point weight by 2**its depth):
    coarse levels, which the finer ones only correct, are not pulled to the samples harder than
    the finest (measured below, make_splats).
    """
    scell, sloc = Y.sample_cells(spos, lev.depth, lev.cell_keys)
    have = scell >= 0
    if not have.all():
        scell, sloc, lw = scell[have], sloc[have], lw[have]
    del have
    # the diagonal, for the preconditioner: a table by incident-cell count (lev.ncell) plus the
    # sparse screening part, not an (n,) vector
    if alpha > 0:
        sd_nodes, sd_vals = Y.screening_diag_rhs(scell, sloc, lev.cell_nodes, lw, TARGET, rhs)
    else:
        sd_nodes, sd_vals = np.zeros(0, np.int64), np.zeros(0)
    sw = lw if alpha > 0 else np.zeros(0)
    cscr = np.zeros((0, 8, 8))
    if alpha > 0 and 4 * len(lev.cell_keys) <= len(sw) and len(lev.cell_keys) <= 1 << 19:
        # coarse levels: samples outnumber cells, so sum each cell's samples into its own 8x8
        # screening matrix once (exact) and let a CG step cost O(cells); (c, 8, 8) floats, so
        # only up to 2**19 cells (256 MB)
        cscr = Y.cell_screening(scell, sloc, sw, len(lev.cell_keys))
        sw = np.zeros(0)
    return _Screening(scell, sloc, sw, sd_nodes, sd_vals, cscr)


def _subtract_coarse(
    lev: Level, par: Level, gpar: np.ndarray, ke: np.ndarray, scr: _Screening, rhs: np.ndarray
) -> None:
    """``rhs -= A G``: the residual the coarser levels' chi (``gpar`` on ``par``) leaves.

    ``G`` is that chi at this level's nodes; it is prolonged again after the solve rather than
    kept: one (n,) vector fewer during the conjugate gradients.
    """
    G = Y.prolong(lev.cell_nodes, lev.cell_keys, lev.cell_parent, par.cell_nodes, gpar, lev.n_nodes)
    AG = np.empty(lev.n_nodes)
    Y.level_matvec(lev.cell_nodes, ke, scr.cscr, scr.scell, scr.sloc, scr.sw, G, AG)
    del G
    rhs -= AG


def _level_chi(lev: Level, par: Level | None, gpar: np.ndarray | None, x: np.ndarray) -> np.ndarray:
    """Chi at the level's nodes: the coarser levels' prolonged plus the correction ``x``.

    Also flags the coarser level's leaves (its cells without children here).
    """
    if par is not None:
        assert gpar is not None  # the coarser level was solved first
        G = Y.prolong(
            lev.cell_nodes, lev.cell_keys, lev.cell_parent, par.cell_nodes, gpar, lev.n_nodes
        )
        par.leaf = ~O.cell_has_child(lev.cell_parent, len(par.cell_keys))
        lev.cell_parent = None
    else:
        G = np.zeros(lev.n_nodes)
    G += x
    return G


def solve_work(levels: list[Level], full_depth: int) -> list[float]:
    """Estimated work of each level's solve, for the progress bar (arbitrary units).

    Set-up and each CG iteration cost about the same per node; an exact level (depth <=
    ``full_depth``, tolerance 1e-7) takes about ``4.5 * 2**depth`` iterations, a finer one
    about 10 (see ``bench/calibration.md``); each level also costs a fixed
    amount (kernel calls, freeing the heap) worth ~30k nodes.
    """
    out = []
    for lev in levels:
        its = 4.5 * (1 << lev.depth) if lev.depth <= full_depth else 10.0
        out.append(30_000.0 + lev.n_nodes * (1.0 + its / 15.0))
    return out


def chi_at(
    levels: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]], pos: np.ndarray
) -> np.ndarray:
    """Chi at unit-cube positions ``pos`` (n, 3), each in the finest cell of the tree holding it.

    Chi is trilinear in a cell and continuous across cells.

    ``levels`` holds (depth, cell_keys, cell_nodes, chi at the level's nodes) per level,
    coarse to fine (:func:`chi_levels`).
    """
    out = np.full(len(pos), np.nan)
    todo = np.arange(len(pos))
    for depth, cell_keys, cell_nodes, g in levels[::-1]:
        scell, sloc = Y.sample_cells(pos[todo], depth, cell_keys)
        have = scell >= 0
        out[todo[have]] = Y.eval_at_samples(scell[have], sloc[have], cell_nodes, g)
        todo = todo[~have]
        if not len(todo):
            break
    return out


def chi_levels(
    levels: list[Level], gvals: list[np.ndarray]
) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """What :func:`chi_at` needs of the solved levels (references, no copies)."""
    out = []
    for lev, g in zip(levels, gvals, strict=True):
        assert lev.cell_nodes is not None  # set with the tree
        out.append((lev.depth, lev.cell_keys, lev.cell_nodes, g))
    return out


def iso_value(levels: list[Level], gvals: list[np.ndarray], smp: Samples) -> float:
    """The level set's value: the count-weighted mean of chi at the samples."""
    chi_s = chi_at(chi_levels(levels, gvals), smp.pos)
    iso = float((chi_s * smp.count).sum() / smp.count.sum())
    log.info("poisson: iso-value %.6f", iso)
    return iso
