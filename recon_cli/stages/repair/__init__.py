"""``recon repair``: make a mesh manifold, clean and consistently oriented.

Seven steps, in order, each counted in the report:

1. merge duplicate vertices (exact by default; ``merge_tolerance`` relative to the diagonal);
2. remove degenerate faces (repeated index or zero area), duplicate faces (same vertex set,
   either winding; the first one is kept) and unreferenced vertices;
3. non-manifold edges: keep two faces per edge (the two with most manifold neighbours,
   ties to the first faces); the others are dropped when nothing else holds them
   (fins glued on), otherwise detached (their corners are not joined across the edge, so
   step 4 gives them their own vertices); edges that cannot be detached lose their extra faces;
4. non-manifold vertices: one vertex per fan of faces (the fan holding the vertex's first
   corner keeps the index, the others get copies appended);
5. orientation: windings made consistent by a breadth-first walk over manifold edges; closed
   components outward (positive signed volume); open components agree with vertex normals
   when present, else keep the winding of the larger area; non-orientable parts are cut along
   the conflicting edges (or lose a face per conflict when cutting cannot separate them);
6. ``fill_holes=N``: boundary loops of at most N edges get a minimum-area triangulation
   that uses no existing edge as a chord (so the result stays manifold);
7. ``min_component`` / ``keep_largest``: drop small pieces.

A mesh that is already clean passes through unchanged: the same vertex and face arrays in
the same order. Report keys (stable): ``vertices_in``, ``faces_in``, ``vertices_merged``,
``merge_distance``, ``degenerate_faces_removed``, ``duplicate_faces_removed``,
``unreferenced_vertices_removed``, ``non_manifold_edges``, ``non_manifold_faces_dropped``,
``non_manifold_faces_detached``, ``non_manifold_vertices_split``, ``vertices_added``,
``faces_flipped``, ``components_reversed``, ``non_orientable_edges_cut``,
``non_orientable_faces_dropped``, ``holes``, ``holes_filled``, ``holes_skipped``,
``fill_faces_added``, ``components_removed``, ``component_faces_removed``, ``vertices_out``,
``faces_out``, ``components``, ``boundary_loops``, ``watertight``, ``genus``, ``volume``.

References
----------
Guéziec, A., Taubin, G., Lazarus, F. & Horn, B. (2001). Cutting and stitching: converting sets
of polygons to manifold surfaces. IEEE TVCG 7(2) (non-manifold edges and vertices, step 3-4).
Liepa, P. (2003). Filling holes in meshes. SGP (minimum-area triangulation of a loop, step 6).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import TriangleMesh, bbox_diagonal, float64, local_origin
from recon_cli.mesh.topology import CHUNK, Connectivity, index_dtype, stable_argsort
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult
from recon_cli.tolerances import tol

# ---- the declaration -------------------------------------------------------------------------
SPEC = StageSpec(
    name="repair",
    summary="Make a mesh manifold, clean and consistently oriented.",
    description="""Make a mesh manifold, clean and consistently oriented.

    Steps, in order: merge duplicate vertices; remove degenerate and duplicate faces and
    unreferenced vertices; keep two faces per edge; split pinched vertices; orient
    consistently (closed parts outward); fill holes up to N edges; drop small components.
    A clean mesh passes through unchanged.""",
    takes=("mesh",),
    gives=("mesh",),
    backends=("native", "pymeshlab"),
    params=(
        Param(
            "merge_tolerance",
            "float",
            None,
            "Merge vertices closer than this (default: exact duplicates only).",
            unit="fraction of the bbox diagonal",
            min=0.0,
            words={"exact": None, "none": None},
            metavar="F|exact",
        ),
        Param(
            "fill_holes",
            "int",
            0,
            "Close boundary loops of at most N edges (0: no filling).",
            unit="edges",
            min=0,
            metavar="N",
        ),
        Param(
            "min_component",
            "float",
            0.0,
            "Drop components with fewer than this fraction of the faces.",
            unit="fraction of the faces",
            min=0.0,
            max=1.0,
            metavar="F",
        ),
        Param("keep_largest", "bool", False, "Keep only the component with most faces."),
    ),
)


# ---- the working state -------------------------------------------------------------------------
class _State:
    """Vertices and faces being repaired, with the source row of each (to carry attributes).

    Faces and source rows are kept in :func:`~recon_cli.mesh.topology.index_dtype` (int32 below
    2^31 entries) once changed: the output mesh converts back to int64.
    """

    def __init__(self, mesh: TriangleMesh):
        self.vertices = mesh.vertices
        self.faces = mesh.faces
        self.vsrc: np.ndarray | None = None  # None: identity (nothing changed yet)
        self.fsrc: np.ndarray | None = None
        # room for the vertices and faces that steps 4 and 6 may add
        self.it = index_dtype(
            4 * len(mesh.vertices) + 3 * len(mesh.faces) + 3, 3 * len(mesh.faces) + 3
        )

    @property
    def faces(self) -> np.ndarray:
        return self._faces

    @faces.setter
    def faces(self, f: np.ndarray) -> None:
        self._faces = f
        # the connectivity is rebuilt only after the faces changed
        self._conn: Connectivity | None = None

    def _vs(self):
        return np.arange(len(self.vertices), dtype=self.it) if self.vsrc is None else self.vsrc

    def _fs(self):
        return np.arange(len(self.faces), dtype=self.it) if self.fsrc is None else self.fsrc

    def keep_faces(self, keep: np.ndarray) -> None:
        if keep.all():
            return
        self.fsrc = self._fs()[keep]
        self.faces = self.faces[keep]

    def add_faces(self, faces: np.ndarray) -> None:
        if len(faces) == 0:
            return
        self.fsrc = np.concatenate([self._fs(), np.full(len(faces), -1, dtype=self.it)])
        self.faces = np.concatenate([self.faces, faces])

    def add_vertices(self, rows: np.ndarray) -> np.ndarray:
        """Copies of vertices ``rows``; returns their new indices."""
        n = len(self.vertices)
        self.vsrc = np.concatenate([self._vs(), self._vs()[rows]])
        self.vertices = np.concatenate([self.vertices, self.vertices[rows]])
        return n + np.arange(len(rows), dtype=self.it)

    def compact(self) -> int:
        """Drop unreferenced vertices (order kept); returns how many."""
        used = np.zeros(len(self.vertices), dtype=bool)
        used[self.faces.ravel()] = True
        n_drop = int(len(used) - used.sum())
        if n_drop:
            new: np.ndarray = np.cumsum(used, dtype=self.it)
            new -= 1
            self.faces = new[self.faces]
            self.vsrc = self._vs()[used]
            self.vertices = self.vertices[used]
        return n_drop

    def drop_conn(self) -> None:
        """Free the cached connectivity (the caller holds no reference to it either)."""
        self._conn = None

    def conn(self) -> Connectivity:
        if self._conn is None or self._conn.n_vertices != len(self.vertices):
            self._conn = Connectivity(self.faces, len(self.vertices), self.vertices)
        return self._conn


# ---- steps --------------------------------------------------------------------------------------
def _merge_vertices(st: _State, tolerance: float | None) -> tuple[int, float]:
    v = st.vertices
    n = len(v)
    if n < 2:
        return 0, 0.0
    if tolerance is None:
        order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
        sv = v[order]
        new = np.ones(n, dtype=bool)
        new[1:] = np.any(sv[1:] != sv[:-1], axis=1)
        if new.all():
            return 0, 0.0
        gid = np.cumsum(new) - 1
        # representative: the smallest index of each group (order is stable, so the group's first)
        rep_of_group = order[np.flatnonzero(new)]
        rep = np.empty(n, dtype=st.it)
        rep[order] = rep_of_group[gid]
        del order, sv, new, gid, rep_of_group
        dist = 0.0
    else:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        finite = np.flatnonzero(np.isfinite(v).all(axis=1))  # unreferenced rows may hold nan
        dist = tolerance * bbox_diagonal(v[finite])
        pairs = cKDTree(v[finite]).query_pairs(dist, output_type="ndarray")
        if len(pairs) == 0:
            return 0, dist
        pairs = finite[pairs]
        g = coo_matrix(
            (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n)
        )
        _, labels = connected_components(g, directed=False)
        first = np.full(labels.max() + 1, n, dtype=st.it)
        np.minimum.at(first, labels, np.arange(n))
        rep = first[labels]
    merged = int((rep != np.arange(n)).sum())
    if merged:
        st.faces = rep[st.faces]
    return merged, dist


def _split_fans(
    st: _State, conn: Connectivity, link_a: np.ndarray, link_b: np.ndarray
) -> tuple[int, int]:
    """Give every fan but one of each vertex its own vertex.

    Returns (vertices split, vertices added).
    """
    labels = conn.corner_fans(link_a, link_b)
    if len(labels) == 0:
        return 0, 0
    n_fans = int(labels.max()) + 1
    if n_fans == int(conn.referenced.sum()):
        return 0, 0
    fan_vertex = np.empty(n_fans, dtype=st.it)
    fan_vertex[labels] = st.faces.ravel()
    # fans are numbered in order of first corner, so a stable sort by vertex puts each
    # vertex's fan with the first corner first: that one keeps the index
    order = stable_argsort(fan_vertex, len(st.vertices))
    fv = fan_vertex[order]
    primary = np.ones(n_fans, dtype=bool)
    primary[1:] = fv[1:] != fv[:-1]
    extra = order[~primary]
    fan_index = np.empty(n_fans, dtype=st.it)
    fan_index[order[primary]] = fv[primary]
    del order, fv, primary
    fan_index[extra] = st.add_vertices(fan_vertex[extra])
    st.faces = fan_index[labels].reshape(-1, 3)
    return int(len(np.unique(fan_vertex[extra]))), int(len(extra))


def _face_support(conn: Connectivity) -> np.ndarray:
    """Number of manifold (two-face) edges of each face."""
    e = conn.half_edge_edge
    two = np.zeros(len(e), dtype=bool)
    ok = e >= 0
    two[ok] = conn.edge_face_count[e[ok]] == 2
    return two.reshape(-1, 3).sum(axis=1).astype(np.int64)


def _edge_slots(conn: Connectivity, edges: np.ndarray) -> np.ndarray:
    """Positions in ``conn.edge_half_edges`` of the half-edges of ``edges``."""
    counts = conn.edge_face_count[edges]
    starts = np.repeat(conn.edge_ptr[edges], counts)
    return starts + (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))


def _choose(conn: Connectivity, nm: np.ndarray):
    """Keep flags per half-edge slot (two per non-manifold edge), slots of ``nm``, face support."""
    from recon_cli.stages.repair._kernel import choose_edge_pairs

    support = _face_support(conn)
    keep_slot = choose_edge_pairs(nm, conn.edge_ptr, conn.edge_half_edges, support)
    return keep_slot, _edge_slots(conn, nm), support


def _non_manifold(st: _State, rep: dict) -> None:
    """Steps 3 and 4: two faces per edge, then one vertex per fan."""
    conn = st.conn()
    nm = conn.non_manifold_edges
    rep["non_manifold_edges"] = int(len(nm))
    dropped = detached = 0
    if len(nm):
        # a face held by nothing but non-manifold or boundary edges is a fin: drop it
        keep_slot, slots, support = _choose(conn, nm)
        extra = np.unique(conn.edge_half_edges[slots[~keep_slot[slots]]] // 3)
        keep = np.ones(conn.n_faces, dtype=bool)
        keep[extra[support[extra] == 0]] = False
        dropped = int((~keep).sum())
        del conn, keep_slot, slots, support, extra
        st.keep_faces(keep)
        del keep
        conn = st.conn()
        nm = conn.non_manifold_edges
    a, b, _ = conn._manifold_pairs
    if len(nm):
        # the others are detached: their corners are not joined across the edge
        keep_slot, slots, _ = _choose(conn, nm)
        kept = slots[keep_slot[slots]].reshape(-1, 2)
        detached = int(len(np.unique(conn.edge_half_edges[slots[~keep_slot[slots]]] // 3)))
        hs = conn.edge_half_edges
        a = np.concatenate([a, hs[kept[:, 0]]])
        b = np.concatenate([b, hs[kept[:, 1]]])
    split, added = _split_fans(st, conn, a, b)
    del a, b, conn
    # edges whose stars stay connected cannot be detached: they lose their extra faces
    while True:
        conn = st.conn()
        nm = conn.non_manifold_edges
        if len(nm) == 0:
            break
        keep_slot, slots, _ = _choose(conn, nm)
        drop = np.unique(conn.edge_half_edges[slots[~keep_slot[slots]]] // 3)
        keep = np.ones(conn.n_faces, dtype=bool)
        keep[drop] = False
        del conn
        st.keep_faces(keep)
        dropped += int(len(drop))
        detached = max(0, detached - int(len(drop)))
        conn = st.conn()
        a, b, _ = conn._manifold_pairs
        s2, a2 = _split_fans(st, conn, a, b)
        del a, b, conn
        split += s2
        added += a2
    rep["non_manifold_faces_dropped"] = dropped
    rep["non_manifold_faces_detached"] = detached
    rep["non_manifold_vertices_split"] = split
    rep["vertices_added"] = added


def _orient(st: _State, normals: np.ndarray | None, rep: dict) -> None:
    """Step 5."""
    flip, comp, conn = _consistent_winding(st, rep)
    m = len(st.faces)
    if m == 0:
        rep["faces_flipped"] = 0
        rep["components_reversed"] = 0
        return
    n_comp = int(comp.max()) + 1
    # closed components: outward by signed volume (centred per component for accuracy)
    open_comp = np.zeros(n_comp, dtype=bool)
    open_comp[comp[conn.edge_half_edges[conn.edge_ptr[conn.boundary_edges]] // 3]] = True
    del conn
    vol, agree = _component_sides(st, normals, comp, flip, n_comp)
    reverse = np.where(open_comp, agree < 0, vol < 0)
    flip = flip ^ reverse[comp]  # not in place: the connectivity's cached array
    rep["faces_flipped"] = int(flip.sum())
    rep["components_reversed"] = int(reverse.sum())
    if flip.any():
        st.drop_conn()  # stale once the faces flip: free it before copying them
        f = st.faces.copy()
        f[flip] = f[flip][:, [0, 2, 1]]
        st.faces = f


def _consistent_winding(st: _State, rep: dict) -> tuple[np.ndarray, np.ndarray, Any]:
    """Make the windings consistent: cut, then drop, the faces along conflicting edges.

    Returns the faces to flip for a consistent winding, their components and the connectivity.
    """
    cut = dropped = 0
    for rnd in range(len(st.faces) + 2):
        conn = st.conn()
        flip, comp, conflict = conn.orientation()
        if len(conflict) == 0:
            break
        if rnd < 2:
            # cut along the conflicting edges: do not join fans across them
            a, b, e = conn._manifold_pairs
            cut_edge = np.zeros(conn.n_edges, dtype=bool)
            cut_edge[conflict] = True
            ok = ~cut_edge[e]
            split, _ = _split_fans(st, conn, a[ok], b[ok])
            cut += int(len(conflict))
            if split:
                continue
        # cutting could not separate them: drop one face per conflicting edge
        h = conn.edge_half_edges[conn.edge_ptr[conflict] + 1]
        keep = np.ones(conn.n_faces, dtype=bool)
        keep[np.unique(h // 3)] = False
        st.keep_faces(keep)
        dropped += int((~keep).sum())
        conn = st.conn()
        a, b, _ = conn._manifold_pairs
        _split_fans(st, conn, a, b)
    rep["non_orientable_edges_cut"] = cut
    rep["non_orientable_faces_dropped"] = dropped
    return flip, comp, conn


def _component_sides(
    st: _State, normals: np.ndarray | None, comp: np.ndarray, flip: np.ndarray, n_comp: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per component: its signed volume, and its agreement with the vertex normals (or area).

    With the faces flipped as ``flip`` says.
    """
    m = len(st.faces)
    f = st.faces
    v = st.vertices
    # signed volume about a point of each component (its mean first corner): fewer lost digits
    centre = np.zeros((n_comp, 3))
    for k in range(3):
        for s in range(0, m, CHUNK):
            centre[:, k] += np.bincount(
                comp[s : s + CHUNK], weights=v[f[s : s + CHUNK, 0], k], minlength=n_comp
            )
    centre /= np.bincount(comp, minlength=n_comp)[:, None]
    vs = None if normals is None else st._vs()
    # per-face terms in chunks, (chunk, 3) float64 temporaries instead of (m, 3) ones: six
    # times the signed volume of the face's tetrahedron, and the area (or the agreement
    # with the vertex normals), both sign-flipped with the face
    sums = []
    for kind in ("volume", "side"):
        term = np.empty(m, dtype=np.float64)
        for s in range(0, m, CHUNK):
            fk = f[s : s + CHUNK]
            p0 = v[fk[:, 0]]
            cross = np.cross(v[fk[:, 1]] - p0, v[fk[:, 2]] - p0)  # twice the area vector
            if kind == "volume":
                p0 -= centre[comp[s : s + CHUNK]]
                term[s : s + len(fk)] = np.einsum("ij,ij->i", p0, cross)
            elif normals is not None and vs is not None:
                term[s : s + len(fk)] = np.einsum("ij,ij->i", normals[vs[fk]].sum(axis=1), cross)
            else:
                term[s : s + len(fk)] = 0.5 * np.linalg.norm(cross, axis=1)
        term[flip] *= -1.0
        sums.append(np.bincount(comp, weights=term, minlength=n_comp))
        del term
    return sums[0], sums[1]


def _fill_holes(st: _State, max_edges: int, rep: dict) -> None:
    """Step 6."""
    from recon_cli.stages.repair._kernel import fill_loops

    conn = st.conn()
    loops = conn.boundary_loops
    rep.update(holes=len(loops), holes_filled=0, holes_skipped=0, fill_faces_added=0)
    small = [lp for lp in loops if len(lp) <= max_edges]
    if small:
        n = max(len(st.vertices), 1)
        edges = conn.edges  # int64: the keys below need it
        keys = np.sort(edges[:, 0] * n + edges[:, 1])
        del edges
        ptr = np.zeros(len(small) + 1, dtype=np.int64)
        np.cumsum([len(lp) for lp in small], out=ptr[1:])
        diag = bbox_diagonal(st.vertices)
        new, filled = fill_loops(
            np.concatenate(small), ptr, st.vertices, keys, n, tol.area * diag * diag
        )
        # a 3-loop that bounds a lone triangle would be closed by its own duplicate: skip such fills
        if len(new):
            c = Connectivity(np.concatenate([st.faces, new]), len(st.vertices))
            dup = c.duplicate_faces
            dup = dup[dup >= len(st.faces)] - len(st.faces)
            if len(dup):
                bad = np.zeros(len(new), dtype=bool)
                bad[dup] = True
                owner = np.repeat(np.flatnonzero(filled), ptr[1:][filled] - ptr[:-1][filled] - 2)
                bad_loops = np.unique(owner[bad])
                filled[bad_loops] = False
                new = new[~np.isin(owner, bad_loops)]
        st.add_faces(new)
        if len(new):
            _outward_closed(st, rep)
        rep["holes_filled"] = int(filled.sum())
        rep["fill_faces_added"] = int(len(new))
    rep["holes_skipped"] = rep["holes"] - rep["holes_filled"]


def _outward_closed(st: _State, rep: dict) -> None:
    """Reverse closed components of negative volume (a filled hole can close an open one)."""
    conn = st.conn()
    comp = conn.face_components
    c = conn.n_components
    closed = np.ones(c, dtype=bool)
    closed[comp[conn.edge_half_edges[conn.edge_ptr[conn.boundary_edges]] // 3]] = False
    vol = conn.signed_volume(per_component=True)
    reverse = closed & (vol < 0)
    if reverse.any():
        flip = reverse[comp]
        f = st.faces.copy()
        f[flip] = f[flip][:, [0, 2, 1]]
        st.faces = f
        rep["components_reversed"] += int(reverse.sum())
        rep["faces_flipped"] += int(flip.sum())


def _components(st: _State, min_component: float, keep_largest: bool, rep: dict) -> None:
    """Step 7."""
    rep["components_removed"] = 0
    rep["component_faces_removed"] = 0
    if not (keep_largest or min_component > 0) or len(st.faces) == 0:
        return
    conn = st.conn()
    comp = conn.face_components
    sizes = np.bincount(comp)
    keep_comp = sizes >= min_component * len(st.faces)
    if keep_largest:
        keep_comp[1:] = False
    keep_comp[0] = keep_comp[0] or not keep_comp.any()  # never drop everything
    keep = keep_comp[comp]
    rep["components_removed"] = int((~keep_comp).sum())
    rep["component_faces_removed"] = int((~keep).sum())
    st.keep_faces(keep)


# ---- public ------------------------------------------------------------------------------------
def repair(
    mesh: TriangleMesh,
    merge_tolerance: float | str | None = SPEC.param("merge_tolerance").default,
    fill_holes: int | str = SPEC.param("fill_holes").default,
    min_component: float | str = SPEC.param("min_component").default,
    keep_largest: bool | str = SPEC.param("keep_largest").default,
    progress=None,
) -> tuple[TriangleMesh, dict]:
    """Make ``mesh`` edge- and vertex-manifold, clean and consistently oriented.

    Parameters
    ----------
    mesh : TriangleMesh
        Vertices (n, 3) and faces (m, 3), any defects.
    merge_tolerance : float, str or None
        None (or "exact"): merge vertices with identical coordinates; a float: merge
        vertices closer than this fraction of the bounding-box diagonal (transitively).
    fill_holes : int
        Fill boundary loops of at most this many edges (0: no filling).
    min_component : float
        Drop components with fewer than this fraction of the faces (0: keep all).
    keep_largest : bool
        Keep only the component with most faces.
    progress : Progress, optional

    Returns
    -------
    mesh : TriangleMesh
        The repaired mesh; per-vertex normals/colours/attributes and per-face attributes
        follow their rows (split vertices copy theirs, filled faces get zeros).
    report : dict
        Counts of every step (see the module docstring).
    """
    v = SPEC.check(
        dict(
            merge_tolerance=merge_tolerance,
            fill_holes=fill_holes,
            min_component=min_component,
            keep_largest=keep_largest,
        ),
        complete=False,
    )
    if not isinstance(mesh, TriangleMesh):
        raise InputError(f"repair needs a triangle mesh, got {type(mesh).__name__}")
    mesh = float64(mesh)
    tolerance = v["merge_tolerance"] or None  # 0: exact
    fill, min_comp, largest = v["fill_holes"], v["min_component"], v["keep_largest"]
    f = mesh.faces
    if len(f) and (f.min() < 0 or f.max() >= len(mesh.vertices)):
        raise InputError(f"faces reference vertices outside 0..{len(mesh.vertices) - 1}")
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[f.ravel()] = True
    if not np.isfinite(mesh.vertices[used]).all():
        raise InputError("mesh has non-finite vertex coordinates")

    rep: dict[str, Any] = {"vertices_in": int(len(mesh.vertices)), "faces_in": int(len(f))}
    st = _State(mesh)
    with task(progress, "repair", total=7) as t:
        merged, dist = _merge_vertices(st, tolerance)
        rep["vertices_merged"] = merged
        rep["merge_distance"] = dist
        t.advance()
        conn = st.conn()
        degenerate = conn.degenerate_faces
        keep = np.ones(len(st.faces), dtype=bool)
        keep[degenerate] = False
        dup = conn.duplicate_faces
        # a duplicate of a degenerate face is counted as degenerate
        dup = dup[keep[dup]]
        keep[dup] = False
        rep["degenerate_faces_removed"] = int(len(degenerate))
        rep["duplicate_faces_removed"] = int(len(dup))
        del conn, degenerate, dup
        st.keep_faces(keep)
        rep["unreferenced_vertices_removed"] = st.compact() - merged
        t.advance()
        _non_manifold(st, rep)
        t.advance(2)
        _orient(st, mesh.normals, rep)
        t.advance()
        if fill > 0:
            _fill_holes(st, fill, rep)
        else:
            rep.update(holes=None, holes_filled=0, holes_skipped=0, fill_faces_added=0)
        t.advance()
        _components(st, min_comp, largest, rep)
        st.compact()
        t.advance()

    conn = st.conn()
    # the output is manifold and oriented by construction, so chi gives the genus directly
    watertight = conn.n_faces > 0 and bool(np.all(conn.edge_face_count == 2))
    rep.update(
        vertices_out=int(len(st.vertices)),
        faces_out=int(len(st.faces)),
        components=int(conn.n_components),
        boundary_loops=int(len(conn.boundary_loops)),
        watertight=watertight,
        genus=int(sum((2 - conn.component_euler) // 2)) if watertight else None,
        volume=conn.signed_volume() if watertight else None,
    )
    # the connectivity is freed before the output's int64 faces are made
    del conn
    st.drop_conn()
    return _output(mesh, st), rep


def _output(mesh: TriangleMesh, st: _State) -> TriangleMesh:
    if st.vsrc is None and st.fsrc is None and st.faces is mesh.faces:
        out = mesh.copy()
        return out
    vs = st._vs()
    fs = st._fs()
    fattr = {}
    for k, v in mesh.face_attributes.items():
        a = np.zeros(len(fs), dtype=v.dtype)
        ok = fs >= 0
        a[ok] = v[fs[ok]]
        fattr[k] = a
    return TriangleMesh(
        vertices=st.vertices,
        faces=st.faces,
        normals=None if mesh.normals is None else mesh.normals[vs],
        colors=None if mesh.colors is None else mesh.colors[vs],
        attributes={k: v[vs] for k, v in mesh.attributes.items()},
        face_attributes=fattr,
        history=list(mesh.history),
        point_dtype=mesh.point_dtype,
        extra_elements=list(mesh.extra_elements),
        obj_info=list(mesh.obj_info),
    )


@SPEC.runner
def run_stage(
    data: TriangleMesh,
    *,
    merge_tolerance: float | None,
    fill_holes: int,
    min_component: float,
    keep_largest: bool,
    backend: str,
    progress=None,
) -> StageResult:
    """Stage ``repair``: see :func:`repair`.

    ``backend="pymeshlab"`` runs PyMeshLab's equivalent filter chain instead
    (:func:`recon_cli.backends.pymeshlab_backend.repair`; exact merging, no component
    filtering, its own hole closing).
    """
    if backend == "pymeshlab":
        fill = fill_holes
        if merge_tolerance or min_component > 0 or keep_largest:
            raise ParameterError("--backend pymeshlab supports only --fill-holes")
        from recon_cli.backends import pymeshlab_backend

        # about a local origin (MeshLab's meshes may be float32), its output moved back
        centre = local_origin(data.vertices[np.isfinite(data.vertices).all(axis=1)])
        out = pymeshlab_backend.repair(
            TriangleMesh(data.vertices - centre, data.faces), fill_holes=fill
        )
        out.vertices = out.vertices + centre
        out.history, out.point_dtype = list(data.history), data.point_dtype
        rep = {
            "backend": "pymeshlab",
            "vertices_in": int(len(data.vertices)),
            "faces_in": int(len(data.faces)),
            "vertices_out": int(len(out.vertices)),
            "faces_out": int(len(out.faces)),
        }
        return StageResult(output=out, report=rep)
    out, rep = repair(
        data,
        merge_tolerance=merge_tolerance,
        fill_holes=fill_holes,
        min_component=min_component,
        keep_largest=keep_largest,
        progress=progress,
    )
    if rep["merge_distance"]:
        rep["provenance"] = {"merge_distance": rep["merge_distance"]}
    return StageResult(output=out, report=rep)
