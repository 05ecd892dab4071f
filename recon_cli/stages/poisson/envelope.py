"""A constraint envelope (``--envelope MESH``, as PoissonRecon's ``--envelope``).

A closed mesh known to contain the surface; the space outside it is empty.

PoissonRecon fixes the coefficients of the tree's nodes outside the envelope to 0 (Dirichlet
constraints) and solves. With no data between an open scan and the envelope, chi then falls
smoothly from the scan's inside value to 0 at the envelope and the iso-surface closes the scan
halfway, far inside the envelope. Here the envelope decides what the data do not:

- The solve's cube is doubled until it holds the envelope (:func:`covering_cube`, one level
  deeper each time: the finest lattice, so the scan's cells, stay where they were).
- Chi is solved as without an envelope, then clipped wherever it is read after the solve
  (the leaves' corners, the vertices' roots, ``--grid``, so mesh and grid agree) by
  :class:`FieldClip`: space no sample sees (:class:`Carving`: rays from the samples along
  their normals cross free space) is solid away from the samples, and
  ``iso + min(chi - iso, (s - offset) / slope)``, ``s`` the signed distance to the envelope,
  puts everything outside it (and within :data:`SHEET_OFFSET` finest cells of it) outside. So
  an open scan's closing sheet runs on the envelope behind the scan, and from the scan's
  silhouette to the envelope along the free space seen in front of it; the scan's own
  neighbourhood (:data:`DATA_NEAR`) keeps chi as solved.
- The tree is refined along the envelope and the carving's sheet to :data:`REFINE_OFFSET`
  levels above its finest, so that the sheet is made of cells that small.

Samples outside the envelope neither screen nor make the iso-value (counted in the report). As
a last guard, vertices the extraction places outside (a root on a leaf edge that crosses the
envelope) are moved inside it and counted.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M. PoissonRecon 18 (``--envelope``: Dirichlet constraints outside the envelope).
Barill, G. et al. (2018). Fast winding numbers for soups and clouds. ACM TOG 37(4)
(the inside test).
"""

from __future__ import annotations

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh

# the closing sheet lies this many finest cells inside the envelope (its vertices stay inside)
SHEET_OFFSET = 0.5
# beyond the sheet the clipped chi falls by 1 over this many finest cells (about chi's own rate)
CLIP_CELLS = 2.0
# the carving grid (free space in front of the samples) is this many levels above the finest,
# and no finer than CARVE_MAX_LEVEL (128^3 cells)
CARVE_OFFSET = 1
CARVE_MAX_LEVEL = 7
# the carved mask's smoothing (Gaussian sigma, carving cells): one stray ray does not carve
CARVE_SIGMA = 1.0
# within DATA_NEAR carving cells of a sample chi alone decides (the scan part is kept); the
# carving's say ramps in up to DATA_FAR
DATA_NEAR, DATA_FAR = 2.0, 3.0
# the cells where the smoothed solid mask is within this of 1/2 hold the carving's sheet
BOUNDARY_BAND = 0.25
# near the samples the solid term drops by this much: below chi - iso wherever chi is (>= -1)
NEAR_DROP = 2.0
# the solve's cube holds the envelope with this many finest cells to spare
COVER_MARGIN = 4.0
# the tree is refined along the envelope down to this many levels above its finest
REFINE_OFFSET = 2
# points per envelope triangle side at the refinement level (its items cover the surface)
REFINE_SPACING = 0.5
# winding number above which a point is inside
INSIDE = 0.5


class Envelope:
    """A closed triangle mesh bounding the surface (world units).

    Parameters
    ----------
    mesh : TriangleMesh
        The envelope: closed (every edge shared by exactly two faces) and orientable; its
        windings are made to agree (either way out: the inside test takes |winding number|).
    name : str
        For the errors (the file's name).

    Raises
    ------
    InputError
        Not a mesh, no faces, or not closed.
    """

    def __init__(self, mesh, name: str = "the envelope"):
        from recon_cli.mesh.topology import Connectivity

        if not isinstance(mesh, TriangleMesh) or not len(mesh.faces):
            what = "a point cloud" if hasattr(mesh, "points") else type(mesh).__name__
            raise InputError(f"--envelope needs a closed triangle mesh, got {what}", name)
        v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        if not np.isfinite(v[np.unique(f)]).all():
            raise InputError("--envelope has non-finite vertices", name)
        c = Connectivity(f, len(v))
        open_edges = int(np.count_nonzero(c.edge_face_count != 2))
        if open_edges:
            raise InputError(
                f"--envelope must be a closed mesh: {open_edges} edges are not shared by "
                "exactly two faces",
                name,
            )
        flip, _, conflict = c.orientation()
        if len(conflict):
            raise InputError("--envelope is not orientable (a closed mesh must be)", name)
        if flip.any():  # windings made to agree (the inside test needs it), either way out
            f = f.copy()
            f[flip] = f[flip][:, ::-1]
        self._index(v, f)

    def _index(self, v: np.ndarray, f: np.ndarray) -> None:
        """Keep the checked mesh (``v`` (n, 3), ``f`` (m, 3)) and its search trees."""
        from recon_cli.mesh.distance import build_bvh
        from recon_cli.mesh.winding import WindingTree

        self.vertices, self.faces = v, f
        self.bvh = build_bvh(v, f)
        self.winding = WindingTree(v, f, bvh=self.bvh)

    def turned(self, perm: tuple[int, int, int]) -> Envelope:
        """The envelope with its axes turned: column ``perm[a]`` becomes axis ``a``.

        A run in slabs works in axes turned so that its slabs' axis is ``x``
        (:func:`.distributed.frame_of`); the mesh is the checked one, its windings kept (a
        cyclic turn keeps a mesh's orientation).
        """
        out = Envelope.__new__(Envelope)
        out._index(np.ascontiguousarray(self.vertices[:, list(perm)]), self.faces)
        return out

    def inside(self, pts: np.ndarray) -> np.ndarray:
        """(m,) bool: the points strictly inside (|winding number| above 1/2)."""
        return np.abs(self.winding(pts)) > INSIDE

    def distance(self, pts: np.ndarray, upper: float = np.inf) -> np.ndarray:
        """(m,) distance to the envelope's surface (``inf`` beyond ``upper``)."""
        from recon_cli.mesh.distance import closest_points

        return closest_points(self.vertices, self.faces, pts, bvh=self.bvh, upper=upper)[0]

    def surface_items(self, origin: np.ndarray, size: float, level: int) -> np.ndarray:
        """Points on the envelope's surface, about :data:`REFINE_SPACING` cells of ``level`` apart.

        In unit-cube coordinates of the solve's cube ``origin + [0, size]^3``:
        the tree is refined along them.
        """
        v = (self.vertices - origin) / size
        t = v[self.faces]
        h = 1.0 / (1 << level)
        edge = np.max(np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2), axis=1)
        k = np.maximum(1, np.ceil(edge / (REFINE_SPACING * h)).astype(np.int64))
        out = [v]
        for kk in np.unique(k):
            if kk < 2:
                continue
            tri = t[k == kk]
            i, j = np.meshgrid(np.arange(kk + 1), np.arange(kk + 1), indexing="ij")
            ok = i + j <= kk
            a = (i[ok] / kk)[None, :, None]
            b = (j[ok] / kk)[None, :, None]
            p = tri[:, None, 0] + a * (tri[:, None, 1] - tri[:, None, 0])
            p = p + b * (tri[:, None, 2] - tri[:, None, 0])
            out.append(p.reshape(-1, 3))
        p = np.concatenate(out)
        return p[np.all((p >= 0.0) & (p < 1.0), axis=1)]

    def pull_inside(self, verts: np.ndarray, cell: float = 0.0) -> tuple[np.ndarray, int]:
        """The vertices outside the envelope moved to the sheet's depth inside it.

        :data:`SHEET_OFFSET` times ``cell`` (the finest cell) past their closest point on the
        envelope. Returns the vertices and how many moved.
        """
        depth = SHEET_OFFSET * cell
        out = np.flatnonzero(~self.inside(verts))
        if len(out):
            from recon_cli.mesh.distance import closest_points

            verts = verts.copy()
            cp = closest_points(self.vertices, self.faces, verts[out], bvh=self.bvh)[2]
            step = cp - verts[out]
            length = np.linalg.norm(step, axis=1)[:, None]
            verts[out] = cp + depth * step / np.where(length > 0, length, 1.0)
        return verts, len(out)


def covering_cube(
    vertices: np.ndarray, origin: np.ndarray, size: float, depth: int, max_depth: int
) -> tuple[np.ndarray, float, int]:
    """The solve's cube doubled about its centre until it holds ``vertices`` (the envelope).

    Each doubling adds a level, so the finest lattice is the same (the scan's cells do not
    move); at most up to ``max_depth``. Returns (origin, size, depth).
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    while depth < max_depth:
        margin = COVER_MARGIN * size / (1 << depth)
        if np.all(lo - margin >= origin) and np.all(hi + margin <= origin + size):
            break
        origin, size, depth = origin - 0.5 * size, 2.0 * size, depth + 1
    return origin, size, depth


def carve_level(tree_depth: int) -> int:
    """The carving grid's level for a tree of ``tree_depth`` levels."""
    return max(1, min(CARVE_MAX_LEVEL, tree_depth - CARVE_OFFSET))


def refine_level(tree_depth: int, full_depth: int) -> int:
    """The level the tree is refined to along the envelope and the carving's sheet."""
    return min(tree_depth, max(full_depth, tree_depth - REFINE_OFFSET))


def carving_masks(pos: np.ndarray, normal: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """The cells of :class:`Carving`'s grid a sample's ray crosses, and those holding a sample.

    Parameters
    ----------
    pos, normal : (s, 3) float
        Samples in unit-cube coordinates and their normals (any length).
    level : int
        The grid's level (``r = 2**level`` cells a side).

    Returns
    -------
    free, held : (r**3,) bool
        x-major cell flags. Each is an OR over the samples: the masks of a run's slabs, each
        from its own samples, OR-ed are the whole cloud's.
    """
    r = 1 << level
    nrm = normal / np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
    free = np.zeros(r**3, bool)
    step = 0.5 / r  # half a cell: a ray skips no cell it crosses
    chunk = max(1, (1 << 22) // (2 * r))
    for a in range(0, len(pos), chunk):
        p, n = pos[a : a + chunk], nrm[a : a + chunk]
        for k in range(1, int(np.ceil(np.sqrt(3.0) / step)) + 1):
            q = p + (k * step) * n
            ok = np.all((q >= 0.0) & (q < 1.0), axis=1)
            if not ok.any():
                break
            c = (q[ok] * r).astype(np.int64)
            free[(c[:, 0] * r + c[:, 1]) * r + c[:, 2]] = True
    held = np.zeros(r**3, bool)
    c = np.clip((pos * r).astype(np.int64), 0, r - 1)
    held[(c[:, 0] * r + c[:, 1]) * r + c[:, 2]] = True
    return free, held


class Carving:
    """Free space seen in front of the samples, on a grid over the solve's unit cube.

    A ray from every sample along its normal (outward: toward whatever saw it) crosses free
    space up to the cube's faces; the cells no ray crosses are unobserved, taken as solid
    (the envelope bounds them). The solid mask is smoothed (:data:`CARVE_SIGMA`) and read
    trilinearly: :meth:`solid` is its value minus 1/2 (positive: solid), and :meth:`near`
    says how much the samples' own field should decide instead (1 within :data:`DATA_NEAR`
    cells of a sample, 0 beyond :data:`DATA_FAR`).

    Parameters
    ----------
    pos, normal : (s, 3) float
        The samples in unit-cube coordinates and their normals (any length).
    level : int
        The grid's level (``2**level`` cells a side).
    """

    def __init__(self, pos: np.ndarray, normal: np.ndarray, level: int):
        self._set_masks(*carving_masks(pos, normal, level), level)

    @classmethod
    def of_masks(cls, free: np.ndarray, held: np.ndarray, level: int) -> Carving:
        """The carving of :func:`carving_masks`' masks (OR-ed over a run's slabs)."""
        out = cls.__new__(cls)
        out._set_masks(free, held, level)
        return out

    def _set_masks(self, free: np.ndarray, held: np.ndarray, level: int) -> None:
        from scipy import ndimage

        r = 1 << level
        self.r = r
        solid = ndimage.gaussian_filter((~free).reshape(r, r, r).astype(np.float32), CARVE_SIGMA)
        self.solid_grid = solid - np.float32(0.5)
        self.dist_grid = ndimage.distance_transform_edt(~held.reshape(r, r, r)).astype(np.float32)

    def boundary_items(self) -> np.ndarray:
        """Unit-cube centres of the cells where the solid mask changes, away from the samples.

        The closing sheet runs there (the tree is refined along them, as along the envelope).
        """
        r = self.r
        edge = (np.abs(self.solid_grid) < BOUNDARY_BAND) & (self.dist_grid > DATA_NEAR)
        return (np.argwhere(edge) + 0.5) / r

    def _read(self, grid: np.ndarray, pos: np.ndarray) -> np.ndarray:
        from scipy import ndimage

        return ndimage.map_coordinates(grid, (pos * self.r - 0.5).T, order=1, mode="nearest")

    def solid(self, pos: np.ndarray) -> np.ndarray:
        """(m,) the smoothed solid mask minus 1/2 at unit-cube positions (m, 3)."""
        return self._read(self.solid_grid, pos).astype(np.float64)

    def near(self, pos: np.ndarray) -> np.ndarray:
        """(m,) 1 near the samples, 0 far from them, a linear ramp between."""
        d = self._read(self.dist_grid, pos).astype(np.float64)
        return np.clip((DATA_FAR - d) / (DATA_FAR - DATA_NEAR), 0.0, 1.0)


class FieldClip:
    """Chi clipped by the envelope: ``iso + min(chi - iso, (s - offset) / slope)``.

    ``s`` is the signed distance to the envelope's surface (positive inside, world units),
    ``offset`` :data:`SHEET_OFFSET` and ``slope`` :data:`CLIP_CELLS` finest cells. Outside the
    envelope (and within ``offset`` of it) the clipped chi is below the iso-value, so no part
    of the surface is there; inside, where chi says inside (above the iso-value), it stays
    inside up to the envelope, whose surface closes it. Only points above the iso-value are
    measured (the clip cannot raise chi). :meth:`__call__` takes unit-cube positions of the
    solve's cube ``origin + [0, size]^3``, as :class:`.bspline.ChiField` reads chi.
    """

    def __init__(
        self,
        env: Envelope,
        carving: Carving,
        origin: np.ndarray,
        size: float,
        cell: float,
        iso: float,
    ):
        self.env, self.carving, self.origin, self.size, self.iso = env, carving, origin, size, iso
        self.offset, self.slope = SHEET_OFFSET * cell, CLIP_CELLS * cell

    def __call__(self, pos: np.ndarray, chi: np.ndarray) -> np.ndarray:
        """(m,) chi at unit-cube positions ``pos`` (m, 3), clipped."""
        # unobserved space is solid: max(chi - iso, solid), the samples' field near them
        solid = self.carving.solid(pos) - NEAR_DROP * self.carving.near(pos)
        out = np.maximum(chi, self.iso + solid)
        idx = np.flatnonzero(out > self.iso)
        if not len(idx):
            return out
        w = self.origin + self.size * pos[idx]
        above = out[idx] - self.iso
        # beyond this distance inside, the clip leaves chi as it is
        reach = self.offset + self.slope * float(above.max())
        d = self.env.distance(w, upper=reach)
        inside = self.env.inside(w)
        far_out = np.flatnonzero(np.isinf(d) & ~inside)
        if len(far_out):  # outside, far: the exact distance keeps the field linear there
            d[far_out] = self.env.distance(w[far_out])
        s = np.where(inside, d, -d)
        out[idx] = self.iso + np.minimum(above, (s - self.offset) / self.slope)
        return out


def load_envelope(path) -> Envelope:
    """The envelope in the mesh file ``path`` (any format recon reads).

    Raises
    ------
    InputError
        Missing or unreadable file, not a mesh, not closed (one line naming the file).
    """
    import os

    from recon_cli.io.load import load

    name = os.fspath(path)
    if name == "-":
        raise InputError("--envelope needs a file name ('-' is the input's standard input)")
    return Envelope(load(name), name)
