"""A constraint envelope (``--envelope MESH``, as PoissonRecon's ``--envelope``).

A closed mesh known to contain the surface; the space outside it is empty.

PoissonRecon marks the tree's nodes outside the envelope and solves with Dirichlet
constraints there (their coefficients fixed to 0: chi is the outside's value). Here, at every
level of the cascade, a cell is *fixed* (its coefficient 0 in the level's whole chi, not an
unknown of its solve) unless the support of its B-spline (the 3 x 3 x 3 cells around it)
lies inside the envelope: its centre inside (generalised winding number above 1/2, so either
orientation) and farther from the envelope's surface than the support's half diagonal. At a
point outside the envelope every function that reaches it is fixed, so chi is exactly 0
there and the surface (chi at the iso-value, about 1/2) stays inside; the closing sheet of
an open scan, which Neumann's faces or Dirichlet's cube would place, follows the envelope
instead, a support's half diagonal (2.6 cells) inside it at the level of the tree there. The
tree is refined along the envelope to :data:`REFINE_OFFSET` levels above its finest, so that
sheet is made of cells that small. Samples outside the envelope, or too close to it, cannot
be reached (counted in the report). As a last guard, the vertices the extraction places
outside (a coarse leaf's interpolated root on an edge crossing the envelope) are pulled to
the envelope's surface and counted.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M. PoissonRecon 18 (``--envelope``: Dirichlet constraints outside the envelope).
"""

from __future__ import annotations

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh

# the support of a cell's quadratic B-spline: 3 cells a side, its half diagonal in cells
SUPPORT_RADIUS = 1.5 * np.sqrt(3.0)
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
        from recon_cli.mesh.distance import build_bvh
        from recon_cli.mesh.topology import Connectivity
        from recon_cli.mesh.winding import WindingTree

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
        self.vertices, self.faces = v, f
        self.bvh = build_bvh(v, f)
        self.winding = WindingTree(v, f, bvh=self.bvh)

    def inside(self, pts: np.ndarray) -> np.ndarray:
        """(m,) bool: the points strictly inside (|winding number| above 1/2)."""
        return np.abs(self.winding(pts)) > INSIDE

    def distance(self, pts: np.ndarray, upper: float = np.inf) -> np.ndarray:
        """(m,) distance to the envelope's surface (``inf`` beyond ``upper``)."""
        from recon_cli.mesh.distance import closest_points

        return closest_points(self.vertices, self.faces, pts, bvh=self.bvh, upper=upper)[0]

    def free_cells(self, centres: np.ndarray, h: float) -> np.ndarray:
        """(m,) bool: the cells whose B-spline's support lies inside the envelope.

        The cells have side ``h`` (world) and centres ``centres``; the others are fixed to 0.
        """
        r = SUPPORT_RADIUS * h
        far = np.isinf(self.distance(centres, upper=r))
        out = np.zeros(len(centres), bool)
        idx = np.flatnonzero(far)
        out[idx] = self.inside(centres[idx])
        return out

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

    def pull_inside(self, verts: np.ndarray) -> tuple[np.ndarray, int]:
        """The vertices outside the envelope moved to their closest point on it; and how many."""
        out = ~self.inside(verts)
        n = int(out.sum())
        if n:
            from recon_cli.mesh.distance import closest_points

            verts = verts.copy()
            verts[out] = closest_points(self.vertices, self.faces, verts[out], bvh=self.bvh)[2]
        return verts, n


class CellClassifier:
    """Which cells of each level are free (:meth:`Envelope.free_cells`), coarse to fine.

    For the solve's cube ``origin + [0, size]^3``: a cell whose parent's
    support ball was wholly inside (or outside) inherits that (its ball lies in its
    parent's), so only the children of the cells near the envelope's surface are measured.
    """

    NEAR, INSIDE_FAR, OUTSIDE_FAR = 0, 1, 2

    def __init__(self, env: Envelope, origin: np.ndarray, size: float):
        self.env, self.origin, self.size = env, origin, size
        self.prev: tuple[int, np.ndarray, np.ndarray] | None = None

    def __call__(self, level: int, keys: np.ndarray) -> np.ndarray:
        """(m,) bool: the cells (lattice keys of ``level``) whose support is inside."""
        from recon_cli.stages.poisson.octree import pack_keys, unpack_keys

        xyz = unpack_keys(keys)
        code = np.full(len(keys), -1, np.int8)
        if self.prev is not None and self.prev[0] == level - 1 and len(self.prev[1]):
            pk, pc = self.prev[1], self.prev[2]
            par = pack_keys(xyz >> 1)
            at = np.minimum(np.searchsorted(pk, par), len(pk) - 1)
            hit = (pk[at] == par) & (pc[at] != self.NEAR)
            code[hit] = pc[at[hit]]
        todo = np.flatnonzero(code < 0)
        if len(todo):
            h = self.size / (1 << level)
            centres = self.origin + (xyz[todo] + 0.5) * h
            far = np.isinf(self.env.distance(centres, upper=SUPPORT_RADIUS * h))
            sub = np.full(len(todo), self.NEAR, np.int8)
            fi = np.flatnonzero(far)
            inside = self.env.inside(centres[fi])
            sub[fi] = np.where(inside, self.INSIDE_FAR, self.OUTSIDE_FAR)
            code[todo] = sub
        order = np.argsort(keys, kind="stable")
        self.prev = (level, keys[order], code[order])
        return code == self.INSIDE_FAR


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
