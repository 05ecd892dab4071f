"""The degree-2 B-spline system: the stage's default basis, as PoissonRecon's ``--degree 2``.

Open3D uses degree 1. This module holds the cascadic solve, the iso-value, and chi at the levels'
nodes for the extraction.

At level ``d`` every cell of the tree carries the tensor-product quadratic B-spline centred on it
(support 3 cells per axis), reflected at the cube's faces (even for Neumann, odd for Dirichlet, so
``chi = 0`` there). A function of level ``d - 1`` is exactly a combination of level-``d`` functions
(refinement mask ``(1, 3, 3, 1) / 4`` per axis), so, as for the trilinear basis, each level holds
the whole ``chi`` of the coarser levels (prolonged) plus its own correction, solved on the residual
they leave by conjugate gradients preconditioned by the inverse of each block of 8 siblings. The
coefficients live on ``E``: the level's cells and a ring of two cells around them (the children of
the parents within one of a parent of the level's cells, in blocks of siblings), enough for the
prolongation to be exact on the stencil (5 cells per axis) of every cell of the level: the set grows
by a parent ring per level, and the levels' parents are within one of the tree's parents, so the
coarser ``E`` always holds what the prolongation reads.

The right-hand side is that of the normals' field of :func:`.splat.spread_fields` (each sample's
share at its level(s) unmerged: merging per cell moves the items of a curved surface inwards, a bias
this basis resolves), its B-splines :data:`KERNEL_WIDTH` cells of the splat level wide; for a width
of 1 (the levels' own B-splines) it is made in time linear in the cells by :class:`NormalRHS`
(refinement, a fixed stencil, restriction). The screening at level ``d`` uses the samples merged per
cell of that level (summed weights, weighted mean position), as PoissonRecon merges its
interpolation points per node.

The rest of the stage reads chi through one function, :meth:`ChiField.at` (chi at any
point of the cube: from the finest level whose cells are within one cell of the point, all
finer levels' functions vanishing there): the iso-value at the samples, chi at every
level's nodes for the extraction (the leaves' corners; at a lattice point the B-spline is
1/2 at its cell's faces, so the value is the mean of the 8 cells' coefficients around it),
and :meth:`ChiField.refine_vertices`, which moves each extracted vertex along its lattice
edge to chi's root there. Inside a leaf chi is piecewise quadratic, not trilinear: an
extraction that refines leaves must read the finer lattice points through
:meth:`ChiField.at` too (the current one interpolates them trilinearly from the leaf's
corners, exact only at the corners).

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M., Bolitho, M. & Hoppe, H. (2006). Poisson surface reconstruction. SGP.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.memory import release_free_heap
from recon_cli.progress import task
from recon_cli.stages.poisson import _bspline as B
from recon_cli.stages.poisson import _bspline_eval as BE
from recon_cli.stages.poisson import _bspline_operator as BO
from recon_cli.stages.poisson import _bspline_rhs as BR
from recon_cli.stages.poisson import _octree as O
from recon_cli.stages.poisson._luts import B2_MASS, B2_STIFFNESS
from recon_cli.stages.poisson.free import FREE_DOMAIN, domain_tables
from recon_cli.stages.poisson.octree import (
    Level,
    dilate,
    pack_keys,
    set_corners,
    unique_keys,
    unpack_keys,
)
from recon_cli.stages.poisson.splat import Samples, Splats, fields_as_items

log = logging.getLogger("recon")

TARGET = 0.5
# the normals' kernel is this many times the splat level's cell wide (a quadratic B-spline):
# wider is better on smooth shapes and worse on detailed ones (bench/calibration.md)
KERNEL_WIDTH = 1.0
# the screening weight relative to make_splats' where the samples are clean and where they are
# noisy (Splats.screening, splat.noise_fraction): the quadratic B-splines are smaller at a sample
# (at most 0.42 against a hat's 1) and smoother, so clean samples want a stronger pull than
# degree 1's, noisy ones a weaker (bench/calibration.md)
SCREEN_CLEAN = 5.0
SCREEN_NOISY = 0.5


def folded_tables(n: int, s: float) -> tuple[np.ndarray, np.ndarray]:
    """(n, 5) mass and stiffness between cells ``i`` and ``i + t`` of the reflected basis.

    Column ``t + 2`` holds offset ``t``, on ``n`` cells: the sum over the images of cell ``i + t``
    (``j + 2kn`` with sign 1, ``-1 - j + 2kn`` with sign ``s``) within 2 of ``i``.
    """
    m1 = np.zeros((n, 5))
    k1 = np.zeros((n, 5))
    i = np.arange(n)
    for t in range(-2, 3):
        j = i + t
        ok = (j >= 0) & (j < n)
        for kk in range(-3, 4):
            for img, sg in ((j + 2 * kk * n, 1.0), (-1 - j + 2 * kk * n, s)):
                off = i - img
                hit = ok & (np.abs(off) <= 2)
                m1[hit, t + 2] += sg * B2_MASS[off[hit] + 2]
                k1[hit, t + 2] += sg * B2_STIFFNESS[off[hit] + 2]
    return m1, k1


@functools.lru_cache(maxsize=32)
def level_tables(n: int, s: float, free: bool) -> tuple[np.ndarray, ...]:
    """The 1D tables of a level of ``n`` cells.

    ``m1``, ``k1`` (:func:`folded_tables`, or over :data:`FREE_DOMAIN` only with ``free``) and the
    right-hand side's ``fv``, ``fd`` (n, 5) (:func:`._bspline_rhs.field_rhs`; ``fd`` per cell). With
    ``free``, the level of 2 cells, whose domain is not made of whole cells, carries no function
    (its rows are 0): the finer levels, solved exactly up to the full depth, hold everything it
    would.
    """
    if free:
        if n < 4:
            z = np.zeros((n, 5))
            return z, z, z, z
        return domain_tables(n, FREE_DOMAIN[0] * n, FREE_DOMAIN[1] * n)
    m1, k1 = folded_tables(n, s)
    fv = np.empty(5)
    fd = np.empty(5)
    for t in range(-2, 3):
        fv[t + 2], fd[t + 2] = B.b2_factors(float(t), 1.0)
    return m1, k1, np.tile(fv, (n, 1)), np.tile(fd, (n, 1))


def boundary_sign(boundary: str) -> float:
    """The reflection's sign at the solve's cube faces.

    -1 Dirichlet, 1 otherwise (the free boundary's cube faces lie outside its domain).
    """
    return -1.0 if boundary == "dirichlet" else 1.0


@dataclass
class LevelField:
    """chi on one level in the degree-2 basis: coefficients on ``E`` and the lookups.

    ``E`` is the children of the sorted parent keys ``q_keys`` in block order (cell
    ``8 i + o``, :mod:`._bspline`); :class:`ChiField` reads chi from the levels' fields.
    """

    depth: int
    s: float  # 1 Neumann, -1 Dirichlet
    q_keys: np.ndarray  # (q,) sorted parent keys (level depth - 1)
    inp: np.ndarray  # (q,) bool: parents of the level's cells (the others are the ring)
    nb: np.ndarray  # (q, 27) int32
    coef: np.ndarray | None = None  # (8q,)

    def locate(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell index in E and local coordinates of unit-cube positions (m, 3).

        The index is -1 when the position is not in a cell of the level.
        """
        return B.locate(pos, self.depth, self.q_keys, self.inp)


def _level_parents(lev: Level) -> tuple[np.ndarray, np.ndarray]:
    """The parents ``Q`` of level ``lev``'s E (depth >= 1) and which are the level's cells'."""
    half = 1 << (lev.depth - 1)
    P = unique_keys(O.halve(lev.cell_keys))
    Q = P
    for axis in range(3):
        Q = dilate(Q, axis, -1, 1, half - 1)
    inp = np.zeros(len(Q), bool)
    inp[O.merge_lookup(P, Q)] = True
    return Q, inp


def level_field(lev: Level, boundary: str) -> LevelField:
    """The coefficient set E of level ``lev`` (depth >= 1) and its lookups."""
    Q, inp = _level_parents(lev)
    nb = np.empty((len(Q), 27), np.int32)
    B.neighbour_table_into(Q, (1 << (lev.depth - 1)) - 1, nb)
    return LevelField(lev.depth, boundary_sign(boundary), Q, inp, nb)


def level_fields(levels: list[Level], boundary: str) -> tuple[list[LevelField | None], tuple]:
    """Every level's E (:func:`level_field`; None for level 0), and the arrays holding them.

    The levels' E are views of arrays holding all the levels (parents, flags, neighbour tables,
    coefficients: :class:`ChiField`'s layout, filled level by level, so the field is made without a
    copy); and those arrays ``(q_all, q_off, inp_all, nb_all, coef_all)``.
    """
    parts = [_level_parents(lev) for lev in levels[1:]]
    top = len(levels) - 1
    sizes = np.zeros(top + 2, np.int64)
    for lev, (Q, _) in zip(levels[1:], parts, strict=True):
        sizes[lev.depth + 1] = len(Q)
    q_off = np.cumsum(sizes)
    q_all = np.concatenate([Q for Q, _ in parts]) if parts else np.zeros(0, np.int64)
    inp_all = np.concatenate([inp for _, inp in parts]) if parts else np.zeros(0, bool)
    del parts
    nb_all = neighbour_tables(q_all, q_off)
    arrays = (q_all, q_off, inp_all, nb_all, np.zeros(8 * len(q_all)))
    return field_views(arrays, boundary, top), arrays


def field_views(arrays: tuple, boundary: str, top: int) -> list[LevelField | None]:
    """Levels 1..``top``'s E as views of the arrays :func:`level_fields` made (None: level 0)."""
    q_all, q_off, inp_all, nb_all, _ = arrays
    s = boundary_sign(boundary)
    out: list[LevelField | None] = [None]
    for d in range(1, top + 1):
        lo, hi = q_off[d], q_off[d + 1]
        out.append(LevelField(d, s, q_all[lo:hi], inp_all[lo:hi], nb_all[lo:hi]))
    return out


def neighbour_tables(q_all: np.ndarray, q_off: np.ndarray) -> np.ndarray:
    """(q, 27) int32: every level's neighbour table, the levels' parents concatenated.

    Made by :func:`._bspline.neighbour_table_into`; level ``L`` is at ``q_off[L]:q_off[L + 1]``.
    """
    nb = np.empty((len(q_all), 27), np.int32)
    for lv in range(1, len(q_off) - 1):
        lo, hi = q_off[lv], q_off[lv + 1]
        B.neighbour_table_into(q_all[lo:hi], (1 << (lv - 1)) - 1, nb[lo:hi])
    return nb


class ChiField:
    """chi of the degree-2 solve, everywhere in the cube.

    Every level's coefficients and lookups, concatenated (level ``L`` at ``q_off[L]:q_off[L + 1]``).

    :meth:`at` is the one way the rest of the stage reads chi (the iso-value at the
    samples, the leaves' corners for the extraction, the roots along the edges).
    """

    def __init__(self, fields: list[LevelField], boundary: str, arrays: tuple | None = None):
        # ``f(pos, chi) -> chi`` applied to every value read (an envelope's, .envelope.FieldClip)
        self.clip: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
        if arrays is not None:
            # the levels' arrays as :func:`level_fields` made them (the fields are views)
            self.q_all, self.q_off, self.inp_all, self.nb_all, self.coef_all = arrays
            self.top = len(self.q_off) - 2
            self.s = boundary_sign(boundary)
            return
        top = max((f.depth for f in fields), default=0)
        sizes = np.zeros(top + 2, np.int64)
        for f in fields:
            sizes[f.depth + 1] = len(f.q_keys)
        self.q_off = np.cumsum(sizes)
        self.top = top
        self.s = boundary_sign(boundary)
        order = sorted(fields, key=lambda f: f.depth)
        self.q_all = np.concatenate([f.q_keys for f in order]) if order else np.zeros(0, np.int64)
        self.inp_all = np.concatenate([f.inp for f in order]) if order else np.zeros(0, bool)
        self.nb_all = (
            np.concatenate([f.nb for f in order]) if order else np.zeros((0, 27), np.int32)
        )
        self.coef_all = np.concatenate([f.coef for f in order]) if order else np.zeros(0)

    def at(self, pos: np.ndarray) -> np.ndarray:
        """Chi at unit-cube positions (m, 3) (:func:`._bspline_eval.chi_at`), clipped."""
        pos = np.ascontiguousarray(pos, dtype=np.float64)
        chi = BE.chi_at(
            pos,
            self.top,
            self.q_all,
            self.q_off,
            self.inp_all,
            self._neighbours(),
            self.coef_all,
            self.s,
        )
        return chi if self.clip is None else self.clip(pos, chi)

    def drop_neighbours(self) -> None:
        """Free the levels' neighbour tables while chi is not read.

        They are 27 int32 a parent, the field's largest arrays (1.7x its coefficients); :meth:`at`
        makes them again (in time linear in the parents: 0.1 s at depth 9) when next called. The
        extraction runs between the leaves' corner values and the vertices' roots without them.
        """
        self.nb_all = None

    def _neighbours(self) -> np.ndarray:
        if self.nb_all is None:
            self.nb_all = neighbour_tables(self.q_all, self.q_off)
        return self.nb_all

    def at_nodes(self, lev: Level, node_keys: np.ndarray) -> np.ndarray:
        """Chi at the nodes ``node_keys`` of ``lev``.

        The leaves' corners for the extraction (their positions made a chunk at a time: at once they
        were the largest arrays after the solve).
        """
        out = np.empty(len(node_keys))
        step = 1 << 16
        for a in range(0, len(node_keys), step):
            out[a : a + step] = self.at(
                unpack_keys(node_keys[a : a + step]) / float(1 << lev.depth)
            )
        return out

    def refine_vertices(
        self, verts: np.ndarray, iso: float, origin: np.ndarray, size: float, depth: int
    ) -> np.ndarray:
        """Move each vertex to where chi crosses ``iso`` along its lattice edge.

        Marching cubes put the vertex on an edge of the ``2**depth`` lattice by linear
        interpolation; chi is one
        quadratic along a finest edge (it lies in one cell of every level), so its values at
        the two ends and the middle give the root exactly. Vertices stay on their edges, so
        the mesh's connectivity is unchanged. Vertices not on an edge (marching cubes' cell
        centres of ambiguous cases) stay where they are.
        """
        verts = verts.copy()
        # a chunk at a time: on all 2M vertices of a depth-10 mesh at once the temporaries
        # (three points per vertex, their lattice coordinates) were the process's peak
        step = 1 << 16
        for a in range(0, len(verts), step):
            self._refine_chunk(verts[a : a + step], iso, origin, size, depth)
        return verts

    def _refine_chunk(
        self, verts: np.ndarray, iso: float, origin: np.ndarray, size: float, depth: int
    ) -> None:
        """:meth:`refine_vertices` on ``verts`` (a view, moved in place)."""
        from recon_cli.stages.mcubes import DEGENERATE_CLAMP

        res = float(1 << depth)
        u = (verts - origin) / size * res
        frac = np.abs(u - np.round(u))
        axis = np.argmax(frac, axis=1)
        on_edge = np.sort(frac, axis=1)[:, 1] < 1e-6
        keep_idx = np.flatnonzero(on_edge)
        u, axis = u[keep_idx], axis[keep_idx]
        rows = np.arange(len(u))
        lo = np.round(u)
        lo[rows, axis] = np.floor(u[rows, axis])
        lat = np.clip(u[rows, axis] - lo[rows, axis], 0.0, 1.0)
        pts = np.empty((3, len(u), 3))
        for k, t in enumerate((0.0, 0.5, 1.0)):
            q = lo.copy()
            q[rows, axis] += t
            pts[k] = q / res
        v0, vm, v1 = (self.at(pts[k]) for k in range(3))
        t = BE.edge_roots(lat, iso, v0, vm, v1, DEGENERATE_CLAMP)
        out = lo
        out[rows, axis] += t
        verts[keep_idx] = out / res * size + origin


_NO_FIELD = np.zeros((0, 3))
_NO_ROWS = np.zeros(0, np.int32)


class NormalRHS:
    """The right-hand side ``b_i = int grad(B_i) . W`` level by level, coarse to fine.

    ``W`` is the field of :func:`.splat.spread_fields` (a sum of unit-integral cell-centred
    quadratic B-splines over the splat levels), in time linear in the cells: the degree-2
    counterpart of :class:`.splat.NormalField`.

    - Level ``d``'s own share of ``W`` and the coarser levels' (written exactly on level
      ``d``'s E by B-spline refinement, :func:`._bspline_rhs.prolong_field`, carried from level
      to level) give a fixed 5 x 5 x 5 stencil per cell (:func:`._bspline_rhs.field_rhs`).
    - The finer levels' shares are their stencils at their own level (on the whole E: a
      share reaches three cells beyond its items), taken to coarser cells by the quadratic
      B-splines' restriction (a coarse B-spline is the finer ones with weights
      (1, 3, 3, 1) / 4 per axis, :func:`._bspline_rhs.restrict_rhs`), computed once from the
      finest level up when the field is made.

    The field is kept folded at the cube's faces (its images beyond them added onto the
    cells they mirror) and the test functions are reflected: this is, to rounding, what
    splatting every share at every level with its kernel (:func:`._bspline_rhs.splat_rhs`)
    gives, faces included (tested). Only for :data:`KERNEL_WIDTH` 1, where the kernels are
    the level's own B-splines.
    """

    def __init__(
        self,
        fields: dict[int, tuple[np.ndarray, np.ndarray]],
        level_fields: list[LevelField | None],
        free: bool = False,
        finer: np.ndarray | None = None,
        lowest: int = 1,
    ):
        # ``finer``: the shares of levels beyond these, restricted onto the finest of them (the
        # distributed solve's coarse levels); added where the single solve adds them, so both
        # round alike. ``lowest``: the finer shares are restricted down to this level only (a
        # slab sends its level's and solves none coarser)
        # a level's own share is dropped once its right-hand side is made (the dict is
        # copied: the caller's is left whole; drop it there to free the arrays)
        self.fields = dict(fields)
        self.free = free  # integrals over the free boundary's domain only (level_tables)
        self.lf = list(level_fields)
        depth = len(level_fields) - 1
        self.depth = depth
        self.carry: np.ndarray | None = None  # the field on the previous level's E, (8q, 3)
        self.finer: list[np.ndarray | None] = [None] * (depth + 1)
        self.finer[depth] = finer
        up = finer
        for lv in range(depth, max(lowest, 1), -1):
            f = level_fields[lv]
            assert f is not None  # levels 1.. have a field
            own = self._own(lv)
            t = None
            if own is not None:
                t = np.zeros(8 * len(f.q_keys))
                fv, fd = self._factors(lv)
                BR.field_rhs(
                    f.q_keys,
                    f.nb,
                    np.ones(len(f.q_keys), bool),
                    1 << lv,
                    f.s,
                    fv,
                    fd,
                    _NO_FIELD,
                    *own,
                    t,
                )
                del own
            if up is not None:
                t = up if t is None else t + up
            if t is None:
                up = None
                continue
            c = level_fields[lv - 1]
            assert c is not None  # lv - 1 >= 1
            blocks = BR.finer_blocks(c.q_keys, f.q_keys)
            up = BR.restrict_rhs(c.q_keys, c.nb, c.inp, blocks, t, 1 << (lv - 1), c.s)
            self.finer[lv - 1] = up
            del t, blocks

    def _factors(self, lv: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, 5) value and derivative factors of a field's cell at offset -2..2, per axis.

        Relative to a level-``lv`` test function's cell, derivatives per unit length
        (:func:`level_tables`).
        """
        f = self.lf[lv]
        assert f is not None  # a level's field lives until the next finer one is done
        fv, fd = level_tables(1 << lv, f.s, self.free)[2:]
        return fv, fd * float(1 << lv)

    def _own(self, lv: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Level ``lv``'s own share of the field.

        The row of each cell of its E (-1 none) and the rows (:func:`._bspline_rhs.field_rows`);
        None if it has none.
        """
        own = self.fields.get(lv)
        if own is None or not len(own[0]):
            return None
        lf = self.lf[lv]
        assert lf is not None  # a level's field lives until the next finer one is done
        idx, missing = BR.field_rows(lf.q_keys, own[0])
        if missing:
            raise RuntimeError(
                f"poisson: {missing} cells of level {lv}'s normal field lie outside its E"
            )
        return idx, own[1]

    def rhs(self, d: int) -> np.ndarray:
        """(8q,) right-hand side on level ``d``'s E (0 but at the children of the flagged parents).

        Call once per level, 1 to the finest, in order.
        """
        f = self.lf[d]
        assert f is not None  # levels 1.., in order
        carry, self.carry = self.carry, None
        if d == 1:
            root = self.fields.get(0)
            if root is not None and len(root[0]):
                # the one cell of level 0, refined onto level 1's 8 cells (each a mirror of the
                # other across every face: weight (3 + sign) / 8 per axis, sign -s along the
                # component's axis and s across it)
                vec = np.zeros((8 * len(f.q_keys), 3))
                across = (3.0 + f.s) / 8.0
                along = (3.0 - f.s) / 8.0
                for a in range(3):
                    vec[:, a] = root[1][0, a] * along * across * across
                carry = vec
        else:
            p = self.lf[d - 1]
            assert p is not None  # freed only after level d
            if carry is not None and d < self.depth:
                carry = BR.prolong_field(f.q_keys, p.q_keys, p.nb, carry, 1 << (d - 1), f.s)
        own = self._own(d)
        self.fields.pop(d, None)
        if d == 1:
            self.fields.pop(0, None)
        b = np.zeros(8 * len(f.q_keys))
        fv, fd = self._factors(d)
        if d < self.depth:
            # the field on E, carried to the next level
            if carry is None:
                carry = np.zeros((8 * len(f.q_keys), 3))
            if own is not None:
                BR.add_rows(carry, *own)
            BR.field_rhs(f.q_keys, f.nb, f.inp, 1 << d, f.s, fv, fd, carry, _NO_ROWS, _NO_FIELD, b)
            self.carry = carry
        elif carry is not None and d > 1:
            # the finest level: the coarser field refined and its own share read where they
            # are (no copy of either on E)
            p = self.lf[d - 1]
            assert p is not None  # freed only after level d
            BR.field_rhs_prolonged(
                f.q_keys,
                f.nb,
                f.inp,
                1 << d,
                f.s,
                fv,
                fd,
                (p.q_keys, p.nb, carry),
                *(own if own is not None else (_NO_ROWS, _NO_FIELD)),
                b,
            )
        elif carry is not None or own is not None:
            BR.field_rhs(
                f.q_keys,
                f.nb,
                f.inp,
                1 << d,
                f.s,
                fv,
                fd,
                _NO_FIELD if carry is None else carry,
                *(own if own is not None else (_NO_ROWS, _NO_FIELD)),
                b,
            )
        self.lf[d - 1] = None
        del carry, own
        finer = self.finer[d]
        if finer is not None:
            b += finer
            self.finer[d] = None
        return b


def _merge_per_cell(pos: np.ndarray, w: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples merged per cell of ``level``: weighted mean position, summed weight."""
    res = 1 << level
    keys = pack_keys(np.clip(np.floor(pos * res), 0, res - 1))
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    sw = np.bincount(inv, weights=w, minlength=len(uk))
    safe = np.where(sw > 0, sw, 1.0)
    mp = np.stack(
        [np.bincount(inv, weights=pos[:, a] * w, minlength=len(uk)) / safe for a in range(3)],
        axis=1,
    )
    return mp, sw


def solve(
    levels: list[Level],
    smp: Samples,
    splats: Splats,
    boundary: str,
    full_depth: int,
    cg_tolerance: float,
    progress: Any = None,
    sample_ok: np.ndarray | None = None,
    clip: Any = None,
) -> tuple[list[np.ndarray], list[dict], int, float, float, ChiField]:
    """Solve every level in turn (level 0, a single cell, carries no function).

    Returns chi at each level's nodes (for the extraction), per-level statistics, total iterations,
    the finest relative residual, the iso-value (count-weighted mean of chi at the samples) and the
    field (:class:`ChiField`).

    ``sample_ok`` (s,) bool says which samples screen the solve and make the iso-value (the
    others lie outside the envelope). With ``clip`` (``clip(iso)`` ->
    ``f(pos, chi) -> chi``, :class:`.envelope.FieldClip`) every value read after the iso-value
    (the nodes' values, the returned field) is clipped.
    """
    spos, count = smp.pos, smp.count
    screen_w = splats.screening(SCREEN_CLEAN, SCREEN_NOISY)
    if sample_ok is not None:
        screen_w = screen_w * sample_ok
        count = count * sample_ok
    total_it = 0
    last_res = 0.0
    per_level = []
    fields: list[LevelField] = []
    node_keys: list[np.ndarray] = []
    prev: LevelField | None = None
    # every level's E first: the finer levels' right-hand sides are restricted from the finest up
    lfs, arrays = level_fields(levels, boundary)
    coef_all = arrays[4]
    rhs_fields = splats.rhs_fields
    assert rhs_fields is not None  # made by make_splats, consumed here once
    if KERNEL_WIDTH == 1.0:
        normal_rhs = NormalRHS(rhs_fields, lfs, free=boundary == "free")
        splats.rhs_fields = None  # NormalRHS drops each level's share once used
        del rhs_fields
    else:  # kernels other than the levels' own B-splines: splat every share at every level
        items = fields_as_items(rhs_fields)

    def merged(d: int) -> tuple[np.ndarray, np.ndarray] | None:
        return _merge_per_cell(spos, screen_w, d) if splats.alpha > 0 else None

    with task(progress, "poisson: solve", total=len(levels)) as tk:
        for lev in levels:
            release_free_heap()
            tl = time.perf_counter()
            _prepare_level(levels, lev, node_keys)
            d = lev.depth
            if d == 0:
                tk.advance(1)
                continue
            f = lfs[d]
            assert f is not None  # levels 1.. have a field
            lfs[d] = None
            if KERNEL_WIDTH == 1.0:
                make_rhs = functools.partial(normal_rhs.rhs, d)
            else:
                make_rhs = functools.partial(
                    BR.splat_rhs, *items, d, f.q_keys, f.inp, f.s, KERNEL_WIDTH
                )
            stats, solved = solve_level(
                f,
                prev,
                make_rhs,
                coef_all[8 * arrays[1][d] : 8 * arrays[1][d + 1]],
                merged,
                boundary,
                1e-7 if d <= full_depth else cg_tolerance,
                2000 if d <= full_depth else 200,
            )
            del make_rhs
            fields.append(f)
            prev = f
            stats["seconds"] = time.perf_counter() - tl
            per_level.append(stats)
            if solved:
                total_it += stats["iterations"]
                last_res = stats["residual"]
                log.info(
                    "poisson: level %2d  cells %9d  unknowns %9d  cg iterations %4d  residual "
                    "%.2e  %.2f s",
                    d,
                    stats["nodes"],
                    stats["unknowns"],
                    stats["iterations"],
                    stats["residual"],
                    time.perf_counter() - tl,
                )
            tk.advance(1)
    del prev
    chi, gvals, iso = _level_values(levels, node_keys, fields, boundary, arrays, spos, count, clip)
    del arrays, coef_all, fields
    log.info("poisson: iso-value %.6f", iso)
    return gvals, per_level, total_it, last_res, iso, chi


# public name for the distributed solve (.distributed)
level_parents = _level_parents


def _prepare_level(levels: list[Level], lev: Level, node_keys: list[np.ndarray]) -> None:
    """The tree's bookkeeping before level ``lev``'s solve.

    Its face nodes are made, its node keys moved to ``node_keys`` (the corners need them after the
    solve) and the coarser level's leaves flagged.
    """
    d = lev.depth
    lev.face_nodes = O.face_nodes(lev.node_keys, 1 << d)
    assert lev.node_keys is not None  # dropped only after the solve
    node_keys.append(lev.node_keys)
    lev.node_keys = lev.unknown = lev.ncell = None
    if d > 0:
        levels[d - 1].leaf = ~O.cell_has_child(lev.cell_parent, len(levels[d - 1].cell_keys))
        lev.cell_parent = None


def solve_level(
    f: LevelField,
    prev: LevelField | None,
    make_rhs: Callable[[], np.ndarray],
    coef: np.ndarray,
    merged: Callable[[int], tuple[np.ndarray, np.ndarray] | None],
    boundary: str,
    tolerance: float,
    max_iter: int,
) -> tuple[dict, bool]:
    """Solve one level's correction to the coarser levels' field ``prev``; set ``f.coef``.

    ``make_rhs()`` gives the level's right-hand side (8q,) on E (made here, so that only the
    unknowns' part outlives the screening), ``coef`` (8q,) the view of the solve's coefficients that
    becomes ``f.coef``: the level's whole chi, the coarser field prolonged plus the correction.
    ``merged(d)`` gives the screening samples merged per cell of level ``d`` (weighted mean
    positions, summed weights) or None without screening: the single-process solve merges its
    samples, a slab of the distributed one (:mod:`.slab`) its own and its pad's.
    Returns the level's statistics (depth, nodes, unknowns, iterations, residual) and whether
    it was solved (the free boundary's level 1 carries no function).
    """
    d = f.depth
    n = 1 << d
    h = 1.0 / n
    m1, k1 = level_tables(n, f.s, boundary == "free")[:2]
    unknown = np.repeat(f.inp, 8)
    ne = len(unknown)
    if not m1.any():
        # the free boundary's level 1 carries no function (level_tables): chi is 0 on it
        f.coef = coef
        return {"depth": d, "nodes": ne, "unknowns": 0, "iterations": 0, "residual": 0.0}, False
    rhs = make_rhs()
    samples = _screening_samples(f, merged(d), rhs)
    stiffness = (m1, k1, h)
    # the solve's vectors on the unknowns only (the children of the flagged parents), made before
    # the coarser levels' field is prolonged: on the finest level of a large solve the right-hand
    # side, the prolonged field and its product on all of E were alive at once
    cmap = np.cumsum(f.inp) - 1
    cmap[~f.inp] = -1
    rhs = rhs[unknown]
    if prev is not None:
        _subtract_coarse(f, prev, cmap, stiffness, samples, rhs)
    release_free_heap()
    # made after the prolonged field is gone: 64 doubles a parent, the largest of the solve's arrays
    inv = _sibling_block_inverses(f, cmap, stiffness, samples)
    x, it, rel = BO.level_pcg(
        f.q_keys, f.nb, f.inp, cmap, stiffness, n, f.s, samples, rhs, inv, tolerance, max_iter
    )
    del rhs, inv, samples, cmap
    # the level's chi: the coarser field prolonged again (cheaper than keeping it on all of E
    # through the conjugate gradients) plus the correction
    f.coef = coef
    if prev is not None:
        B.prolong_into(f.q_keys, prev.q_keys, prev.nb, prev.coef, n >> 1, f.s, f.coef)
    f.coef[unknown] += x
    stats = {
        "depth": d,
        "nodes": ne,
        "unknowns": int(unknown.sum()),
        "iterations": it,
        "residual": rel,
    }
    return stats, True


def _screening_samples(
    f: LevelField,
    merged: tuple[np.ndarray, np.ndarray] | None,
    rhs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The level's screening samples ``(scell, sloc, sw)``, their term added to ``rhs``.

    Each sample's child cell ``8 i + o`` (k,), its position in that cell (k, 3) and its weight
    (k,), as :func:`._bspline_operator.screening_matvec` takes them.

    ``merged``: the samples merged per cell of the level (positions, weights); their screening
    is added to ``rhs`` (8q,) in place. None (empty arrays) without screening.
    """
    if merged is None or not len(merged[0]):
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    mp, mw = merged
    del merged
    scell, sloc = f.locate(mp)
    have = scell >= 0
    samples = (scell[have], sloc[have], mw[have])
    del mp, mw, have, scell, sloc
    BO.screening_rhs(f.q_keys, f.nb, 1 << f.depth, f.s, samples, TARGET, rhs)
    return samples


def _sibling_block_inverses(
    f: LevelField,
    cmap: np.ndarray,
    stiffness: tuple,
    samples: tuple,
) -> np.ndarray:
    """The conjugate gradients' block-Jacobi preconditioner: (u, 36), u flagged parents.

    For flagged parent ``i`` (at ``cmap[i]``), the inverse of the operator (stiffness and
    screening) between its 8 children; 0 on the rows and columns of children with no positive
    diagonal (fixed: the free boundary's cells outside its domain). In double precision: the
    single-process and distributed solves go through here with the same arrays in the same order
    and must give the same mesh to rounding, which float32 factors broke. A block that is not
    positive definite (the pure Neumann level 1 without screening, the whole operator with the
    constant in its kernel) gets its diagonal's inverse, plain Jacobi, and a debug line.
    The inverses are symmetric to the bit: kept packed (their lower triangles,
    :func:`._bspline_operator.pack_blocks`, 288 bytes a parent, not 512), the conjugate
    gradients' largest array at the finest level.
    """
    n = 1 << f.depth
    u = int(np.count_nonzero(f.inp))
    flat = np.empty(64 * u)
    blocks = flat.reshape(u, 8, 8)
    BO.stiffness_blocks(f.q_keys, f.inp, cmap, *stiffness, blocks)
    if len(samples[2]):
        BO.screening_blocks(f.q_keys, f.nb, cmap, n, f.s, samples, blocks)
    singular = BO.factor_blocks(blocks)
    if singular:
        log.debug(
            "poisson: level %d  %d sibling blocks not positive definite: Jacobi", f.depth, singular
        )
    del blocks
    BO.pack_blocks(flat, u)
    # the buffer shrunk in place (realloc): the tail goes back before the solve's vectors come
    flat.resize(BO.PACKED * u, refcheck=False)
    return flat.reshape(u, BO.PACKED)


def _subtract_coarse(
    f: LevelField,
    prev: LevelField,
    cmap: np.ndarray,
    stiffness: tuple,
    samples: tuple,
    rhs: np.ndarray,
) -> None:
    """``rhs -= A G`` at the unknowns: the residual the coarser levels' field ``G`` leaves.

    ``G`` is ``prev``'s field prolonged onto all of the level's E.
    """
    n = 1 << f.depth
    G = B.prolong(f.q_keys, prev.q_keys, prev.nb, prev.coef, n >> 1, f.s)
    AG = np.empty(len(rhs))
    xmap = np.arange(len(f.q_keys))
    BO.level_matvec(f.q_keys, f.nb, f.inp, xmap, cmap, stiffness, n, f.s, samples, G, AG)
    rhs -= AG


def _level_values(
    levels: list[Level],
    node_keys: list[np.ndarray],
    fields: list[LevelField],
    boundary: str,
    arrays: tuple,
    spos: np.ndarray,
    count: np.ndarray,
    clip: Any = None,
) -> tuple[ChiField, list[np.ndarray], float]:
    """The solved field, chi at each level's nodes as the extraction reads them, the iso-value.

    The extraction interpolates each leaf trilinearly from its corners: the finer side of a
    leaf's faces takes those values (chi's own everywhere else). The iso-value is the
    ``count``-weighted mean of chi at the samples ``spos``; ``clip(iso)`` then clips the field.
    """
    levels[-1].leaf = np.ones(len(levels[-1].cell_keys), bool)
    for lev, keys in zip(levels, node_keys, strict=True):
        set_corners(lev, keys)
    chi = ChiField(fields, boundary, arrays)
    iso = float((chi.at(spos) * count).sum() / count.sum())
    if clip is not None:
        chi.clip = clip(iso)
    gvals = [chi.at_nodes(lev, keys) for lev, keys in zip(levels, node_keys, strict=True)]
    for d in range(1, len(levels)):
        up = levels[d - 1]
        BE.constrain_to_coarse_leaves(
            node_keys[d], gvals[d], up.cell_keys, up.cell_nodes, up.leaf, gvals[d - 1]
        )
    return chi, gvals, iso
