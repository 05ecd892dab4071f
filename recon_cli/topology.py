"""Mesh connectivity: one vectorised structure every stage that needs adjacency uses.

Adjacency is kept as arrays, never as objects. The faces' directed edges are the
half-edges: half-edge ``h = 3 f + k`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``
and starts at corner ``h`` (corner ``3 f + k`` is vertex ``faces[f, k]`` seen from face
``f``). Sorting the undirected keys of the half-edges groups the twins: an edge used by one
half-edge is a boundary edge, by two a manifold edge, by more a non-manifold edge.
Half-edges of repeated-index faces that start and end at one vertex belong to no edge.

Definitions used throughout (they match Open3D / PyMeshLab / trimesh where those agree):

- *components*: faces connected through shared edges (any number of faces per edge);
- *fan* of a vertex: its corners connected through the edges around it; a referenced vertex
  with more than one fan is *non-manifold* (two cones joined at a tip, a pinched sheet);
- *consistently oriented*: no directed edge is used twice (so every manifold edge is used in
  opposite directions by its two faces);
- *orientable*: faces can be flipped so that every manifold edge is used in opposite directions;
- *watertight*: every edge is shared by exactly two faces;
- *genus*: for a closed, edge- and vertex-manifold, orientable component, ``(2 - chi) / 2``
  with ``chi = V - E + F``; the mesh's genus is the sum over its components.
"""

from __future__ import annotations

from functools import cached_property
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.tolerances import tol

# at most this many per-component genera are listed in the report (largest components first)
MAX_LISTED_COMPONENTS = 64


def _check_faces(faces: Any, n_vertices: int | None = None) -> tuple[np.ndarray, int]:
    f = np.asarray(faces)
    if f.size == 0:
        f = f.reshape(0, 3)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces must have shape (m, 3), got {f.shape}")
    if f.dtype.kind not in "iu":
        if f.dtype.kind == "f" and np.all(np.isfinite(f)) and np.all(f == np.round(f)):
            f = f.astype(np.int64)
        else:
            raise InputError(f"faces must be integer vertex indices, got dtype {f.dtype}")
    f = np.ascontiguousarray(f, dtype=np.int64)
    if len(f) and f.min() < 0:
        raise InputError("faces hold negative vertex indices")
    top = int(f.max()) + 1 if len(f) else 0
    if n_vertices is None:
        n_vertices = top
    elif top > n_vertices:
        raise InputError(f"faces reference vertex {top - 1} but the mesh has {n_vertices} vertices")
    return f, int(n_vertices)


def faces_to_edges(faces: np.ndarray, return_index: bool = False):
    """The directed half-edges of ``faces``.

    Parameters
    ----------
    faces : (m, 3) int
        Vertex indices of each triangle.
    return_index : bool
        Also return the face of each half-edge.

    Returns
    -------
    edges : (3 m, 2) int64
        Row ``3 f + k`` is ``(faces[f, k], faces[f, (k + 1) % 3])``.
    face_index : (3 m,) int64
        ``f`` for row ``3 f + k`` (only with ``return_index``).
    """
    f, _ = _check_faces(faces)
    edges = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    if return_index:
        return edges, np.repeat(np.arange(len(f), dtype=np.int64), 3)
    return edges


def stable_argsort(keys: np.ndarray, max_key: int | None = None) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` for non-negative int keys, usually faster.

    When ``max_key * len(keys)`` fits in int64 the index is packed into the key and a plain
    sort (several times faster than an argsort) does the work.
    """
    n = len(keys)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if max_key is None:
        max_key = int(keys.max())
    if (int(max_key) + 1) * n < 2**62:
        packed = keys.astype(np.int64) * n
        packed += np.arange(n, dtype=np.int64)
        packed.sort()
        packed %= n
        return packed
    return np.argsort(keys, kind="stable")


def _group_keys(keys: np.ndarray, max_key: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sort ``keys``: (order, group id of each sorted entry, group start offsets with the end)."""
    order = stable_argsort(keys, max_key)
    sk = keys[order]
    new = np.empty(len(sk), dtype=bool)
    if len(sk):
        new[0] = True
        np.not_equal(sk[1:], sk[:-1], out=new[1:])
    del sk
    gid = np.cumsum(new)
    gid -= 1
    ptr = np.append(np.flatnonzero(new), len(new)).astype(np.int64)
    return order, gid, ptr


class Connectivity:
    """Edges, adjacency, fans and components of a triangle mesh, built from its faces.

    Everything is computed lazily (cached on first access) with sorts and ``np.unique``-like
    grouping; only boundary-loop walking and orientation propagation use numba kernels.

    Parameters
    ----------
    faces : (m, 3) int
        Triangles (any winding, any defects).
    n_vertices : int, optional
        Number of vertices (default: largest index + 1).
    vertices : (n, 3) float, optional
        Coordinates; needed for ``area``, ``volume``, ``face_areas`` and the degenerate test.

    Attributes (all arrays, computed on first use)
    ----------------------------------------------
    half_edges : (3m, 2) int64
        Directed edges, see :func:`faces_to_edges`.
    edges : (E, 2) int64
        Unique undirected edges ``(lo, hi)``, sorted.
    half_edge_edge : (3m,) int64
        Edge of each half-edge (-1 for the zero-length half-edges of repeated-index faces).
    edge_ptr, edge_half_edges : (E+1,), (H,) int64
        CSR: half-edges of edge ``e`` are ``edge_half_edges[edge_ptr[e]:edge_ptr[e+1]]``
        (their faces are ``// 3``).
    edge_face_count : (E,) int64
    boundary_edges, non_manifold_edges : int64 edge indices (count 1, count > 2)
    face_adjacency : (k, 2) int64
        Face pairs sharing a manifold edge; ``face_adjacency_edge`` (k,) the edge,
        ``face_adjacency_same`` (k,) bool whether both traverse it the same way.
    vertex_ptr, vertex_faces : CSR vertex -> faces (a face twice if it repeats the vertex).
    """

    def __init__(self, faces: Any, n_vertices: int | None = None, vertices: np.ndarray | None = None):
        f, n = _check_faces(faces, n_vertices if n_vertices is not None else (None if vertices is None else len(vertices)))
        self.faces = f
        self.n_vertices = n
        self.n_faces = len(f)
        self.vertices = None if vertices is None else np.asarray(vertices, dtype=np.float64).reshape(-1, 3)

    # ---- edges -------------------------------------------------------------------------
    @cached_property
    def half_edges(self) -> np.ndarray:
        return self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)

    @cached_property
    def _edge_groups(self):
        he = self.half_edges
        a, b = he[:, 0], he[:, 1]
        nv = max(self.n_vertices, 1)
        # key of the undirected edge, built in place to keep the peak memory down
        keys = np.minimum(a, b)
        keys *= nv
        keys += np.maximum(a, b)
        valid = a != b
        idx = None if valid.all() else np.flatnonzero(valid)
        order, gid, ptr = _group_keys(keys if idx is None else keys[idx], nv * nv)
        he_sorted = order if idx is None else idx[order]
        del order
        he_edge = np.full(len(he), -1, dtype=np.int64)
        he_edge[he_sorted] = gid
        del gid
        ukeys = keys[he_sorted[ptr[:-1]]]
        del keys
        edges = np.stack([ukeys // nv, ukeys % nv], axis=1)
        return edges.reshape(-1, 2), he_edge, ptr, he_sorted

    @property
    def edges(self) -> np.ndarray:
        return self._edge_groups[0]

    @property
    def half_edge_edge(self) -> np.ndarray:
        return self._edge_groups[1]

    @property
    def edge_ptr(self) -> np.ndarray:
        return self._edge_groups[2]

    @property
    def edge_half_edges(self) -> np.ndarray:
        return self._edge_groups[3]

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    @cached_property
    def edge_face_count(self) -> np.ndarray:
        return np.diff(self.edge_ptr)

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        return np.flatnonzero(self.edge_face_count == 1)

    @cached_property
    def non_manifold_edges(self) -> np.ndarray:
        return np.flatnonzero(self.edge_face_count > 2)

    @cached_property
    def _consecutive_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Half-edge pairs (a, b) consecutive within one edge's group: links every face of an edge."""
        hs = self.edge_half_edges
        if len(hs) < 2:
            e = np.empty(0, np.int64)
            return e, e
        same_edge = np.ones(len(hs) - 1, dtype=bool)
        same_edge[self.edge_ptr[1:-1] - 1] = False
        i = np.flatnonzero(same_edge)
        return hs[i], hs[i + 1]

    @cached_property
    def _manifold_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e = np.flatnonzero(self.edge_face_count == 2)
        a = self.edge_half_edges[self.edge_ptr[e]]
        b = self.edge_half_edges[self.edge_ptr[e] + 1]
        return a, b, e

    @property
    def face_adjacency(self) -> np.ndarray:
        a, b, _ = self._manifold_pairs
        return np.stack([a // 3, b // 3], axis=1)

    @property
    def face_adjacency_edge(self) -> np.ndarray:
        return self._manifold_pairs[2]

    @cached_property
    def face_adjacency_same(self) -> np.ndarray:
        a, b, _ = self._manifold_pairs
        he = self.half_edges
        return he[a, 0] == he[b, 0]

    # ---- vertices ----------------------------------------------------------------------
    @cached_property
    def _vertex_csr(self):
        flat = self.faces.ravel()
        order = stable_argsort(flat, self.n_vertices)
        ptr = np.zeros(self.n_vertices + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat, minlength=self.n_vertices), out=ptr[1:])
        return ptr, order // 3

    @property
    def vertex_ptr(self) -> np.ndarray:
        return self._vertex_csr[0]

    @property
    def vertex_faces(self) -> np.ndarray:
        return self._vertex_csr[1]

    @cached_property
    def referenced(self) -> np.ndarray:
        """(n,) bool: vertex used by some face."""
        r = np.zeros(self.n_vertices, dtype=bool)
        r[self.faces.ravel()] = True
        return r

    def corner_fans(self, link_a: np.ndarray | None = None, link_b: np.ndarray | None = None) -> np.ndarray:
        """Fan label of each corner (3m,), joining corners of the faces across the given half-edge pairs.

        By default every pair of consecutive half-edges of an edge is joined (all faces of
        a non-manifold edge touch each other). Corners of one vertex with different labels
        lie in different fans.
        """
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        if link_a is None:
            link_a, link_b = self._consecutive_pairs
        nc = 3 * self.n_faces
        he = self.half_edges
        same = he[link_a, 0] == he[link_b, 0]
        # int32 indices where they fit: the graph is the largest temporary here
        it = np.int32 if nc < 2**31 else np.int64
        la, lb = link_a.astype(it), link_b.astype(it)
        end_a = la - la % 3 + (la % 3 + 1) % 3
        end_b = lb - lb % 3 + (lb % 3 + 1) % 3
        # corner of a's start vertex in b, and of a's end vertex in b
        u = np.concatenate([la, end_a])
        v = np.concatenate([np.where(same, lb, end_b), np.where(same, end_b, lb)])
        del la, lb, end_a, end_b, same
        g = coo_matrix((np.ones(len(u), dtype=np.int8), (u, v)), shape=(nc, nc)).tocsr()
        del u, v
        _, labels = connected_components(g, directed=False)
        return labels

    @cached_property
    def vertex_fan_count(self) -> np.ndarray:
        """(n,) int64: number of fans around each vertex (0 if unreferenced)."""
        labels = self.corner_fans()
        if len(labels) == 0:
            return np.zeros(self.n_vertices, dtype=np.int64)
        fan_vertex = np.zeros(labels.max() + 1, dtype=np.int64)
        fan_vertex[labels] = self.faces.ravel()
        return np.bincount(fan_vertex, minlength=self.n_vertices)

    @cached_property
    def non_manifold_vertices(self) -> np.ndarray:
        return np.flatnonzero(self.vertex_fan_count > 1)

    # ---- faces -------------------------------------------------------------------------
    @cached_property
    def face_components(self) -> np.ndarray:
        """(m,) int64 component label per face, largest component 0 (ties: first face first)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        m = self.n_faces
        a, b = self._consecutive_pairs
        g = coo_matrix((np.ones(len(a), dtype=np.int8), (a // 3, b // 3)), shape=(m, m)).tocsr()
        _, labels = connected_components(g, directed=False)
        return _relabel_by_size(labels)

    @property
    def n_components(self) -> int:
        return int(self.face_components.max()) + 1 if self.n_faces else 0

    @cached_property
    def duplicate_faces(self) -> np.ndarray:
        """Indices of faces whose vertex set equals that of an earlier face (either winding)."""
        s = np.sort(self.faces, axis=1)
        n = max(self.n_vertices, 1)
        if n**3 < 2**62:
            order = stable_argsort((s[:, 0] * n + s[:, 1]) * n + s[:, 2], n**3)
        else:
            order = np.lexsort((s[:, 2], s[:, 1], s[:, 0]))
        ss = s[order]
        dup = np.zeros(len(s), dtype=bool)
        if len(s) > 1:
            dup[1:] = np.all(ss[1:] == ss[:-1], axis=1)
        # within a group the stable lexsort keeps the first face first, so later ones are duplicates
        return np.sort(order[dup])

    @cached_property
    def face_areas(self) -> np.ndarray:
        if self.vertices is None:
            raise InputError("face areas need vertex coordinates")
        tri = self.vertices[self.faces]
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite input gives nan areas, not warnings
            return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    @cached_property
    def degenerate_faces(self) -> np.ndarray:
        """Faces repeating a vertex index or (with coordinates) of area below ``tol.area * diag**2``."""
        f = self.faces
        bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
        if self.vertices is not None and len(f):
            used = self.vertices[self.referenced]
            used = used[np.isfinite(used).all(axis=1)]
            diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0))) if len(used) else 0.0
            bad |= self.face_areas <= tol.area * diag * diag
        return np.flatnonzero(bad)

    @cached_property
    def _orientation(self):
        from recon_cli._topology_kernel import propagate_orientation

        m = self.n_faces
        a, b, e = self._manifold_pairs
        k = len(a)
        src = np.concatenate([a // 3, b // 3])
        ptr = np.zeros(m + 1, dtype=np.int64)
        np.cumsum(np.bincount(src, minlength=m), out=ptr[1:])
        order = stable_argsort(src, m)
        del src
        # entry j of the CSR is adjacency order[j] % k seen from one of its two faces
        dst = np.concatenate([b // 3, a // 3])[order]
        order %= k if k else 1
        flip, comp, conflict = propagate_orientation(
            m, ptr, dst, self.face_adjacency_same[order], np.arange(m, dtype=np.int64)
        )
        return flip, comp, np.unique(e[order[conflict]])

    def orientation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Breadth-first orientation across manifold edges, each component rooted at its first face.

        Returns
        -------
        flip : (m,) bool
            Faces to flip so that windings agree with the root's.
        component : (m,) int64
            Component (across manifold edges only) in order of first face.
        conflict_edges : (k,) int64
            Manifold edges whose two faces still disagree (non-orientable cycles); empty if orientable.
        """
        return self._orientation

    @property
    def is_orientable(self) -> bool:
        """Faces can be flipped so that every manifold edge is used in opposite directions."""
        return len(self._orientation[2]) == 0

    @cached_property
    def is_consistently_oriented(self) -> bool:
        """No directed edge is used by two faces."""
        he = self.half_edges
        e = self.half_edge_edge
        ok = e >= 0
        fwd = (he[:, 0] < he[:, 1])[ok]
        nf = np.bincount(e[ok], weights=fwd, minlength=self.n_edges)
        nb = np.bincount(e[ok], weights=~fwd, minlength=self.n_edges)
        return bool(np.all(nf <= 1) and np.all(nb <= 1))

    # ---- boundary ----------------------------------------------------------------------
    @cached_property
    def boundary_loops(self) -> list[np.ndarray]:
        """Boundary loops as vertex sequences, in the direction of their half-edges."""
        from recon_cli._topology_kernel import trace_boundary_loops

        b = self.boundary_edges
        if len(b) == 0:
            return []
        h = self.edge_half_edges[self.edge_ptr[b]]
        src = self.half_edges[h, 0]
        dst = self.half_edges[h, 1]
        order, verts, starts = trace_boundary_loops(src, dst, self.n_vertices)
        return [verts[starts[i] : starts[i + 1]].copy() for i in range(len(starts) - 1)]

    # ---- per component -----------------------------------------------------------------
    @cached_property
    def component_euler(self) -> np.ndarray:
        """(c,) int64 ``V - E + F`` of each component."""
        c = self.n_components
        comp = self.face_components
        if c == 0:
            return np.zeros(0, dtype=np.int64)
        fc = np.bincount(comp, minlength=c)
        he_face_comp = np.repeat(comp, 3)
        e_first = self.edge_half_edges[self.edge_ptr[:-1]]
        ec = np.bincount(he_face_comp[e_first], minlength=c)
        key = np.sort(np.repeat(comp, 3) * max(self.n_vertices, 1) + self.faces.ravel())
        key = key[np.r_[True, key[1:] != key[:-1]]]
        vc = np.bincount(key // max(self.n_vertices, 1), minlength=c)
        return vc - ec + fc

    @cached_property
    def component_closed_manifold(self) -> np.ndarray:
        """(c,) bool: component has no boundary or non-manifold edge, no non-manifold vertex, and is orientable."""
        c = self.n_components
        comp = self.face_components
        bad = np.zeros(c, dtype=bool)
        e_first = self.edge_half_edges[self.edge_ptr[:-1]]
        bad_edges = self.edge_face_count != 2
        bad[comp[e_first[bad_edges] // 3]] = True
        nmv = self.vertex_fan_count > 1
        bad[comp[np.flatnonzero(nmv[self.faces].any(axis=1))]] = True
        conflict_edges = self._orientation[2]
        bad[comp[e_first[conflict_edges] // 3]] = True
        degenerate = self.faces[:, 0] == self.faces[:, 1]
        degenerate |= (self.faces[:, 1] == self.faces[:, 2]) | (self.faces[:, 0] == self.faces[:, 2])
        bad[comp[degenerate]] = True
        return ~bad

    @cached_property
    def component_genus(self) -> list[int | None]:
        chi = self.component_euler
        ok = self.component_closed_manifold
        return [int((2 - x) // 2) if good else None for x, good in zip(chi.tolist(), ok.tolist())]

    def signed_volume(self, per_component: bool = False):
        """Signed volume (divergence theorem); meaningful for closed, oriented parts."""
        if self.vertices is None:
            raise InputError("volume needs vertex coordinates")
        tri = self.vertices[self.faces]
        # centre first: the sum of large, nearly cancelling terms loses digits far from the origin
        if len(tri):
            tri = tri - self.vertices[self.referenced].mean(axis=0)
        with np.errstate(invalid="ignore", over="ignore"):
            six = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
        if per_component:
            return np.bincount(self.face_components, weights=six, minlength=self.n_components) / 6.0
        return float(six.sum() / 6.0)


EdgeTopology = Connectivity  # alias (the other name for it)


def _relabel_by_size(labels: np.ndarray) -> np.ndarray:
    if len(labels) == 0:
        return labels.astype(np.int64)
    sizes = np.bincount(labels)
    first = np.full(len(sizes), len(labels), dtype=np.int64)
    np.minimum.at(first, labels, np.arange(len(labels)))
    rank = np.lexsort((first, -sizes))
    new = np.empty(len(sizes), dtype=np.int64)
    new[rank] = np.arange(len(sizes))
    return new[labels]


# ---- predicates ----------------------------------------------------------------------------
def is_edge_manifold(faces: Any) -> bool:
    """No edge is shared by more than two faces (boundary edges allowed)."""
    return len(Connectivity(faces).non_manifold_edges) == 0


def is_vertex_manifold(faces: Any) -> bool:
    """Every referenced vertex has a single fan of faces."""
    return len(Connectivity(faces).non_manifold_vertices) == 0


def is_watertight(faces: Any) -> bool:
    """Every edge is shared by exactly two faces (and there is at least one face)."""
    c = Connectivity(faces)
    return c.n_faces > 0 and bool(np.all(c.edge_face_count == 2))


def is_consistently_oriented(faces: Any) -> bool:
    """No directed edge is used by two faces."""
    return Connectivity(faces).is_consistently_oriented


def boundary_loops(faces: Any) -> list[np.ndarray]:
    """Boundary loops of ``faces`` as vertex index arrays, each following its half-edges."""
    return Connectivity(faces).boundary_loops


def report(mesh: Any) -> dict[str, Any]:
    """Topology figures of ``mesh`` (a :class:`~recon_cli.geometry.TriangleMesh`).

    Returns
    -------
    dict
        Stable keys: ``vertices``, ``edges``, ``faces``, ``components``, ``boundary_edges``,
        ``boundary_loops``, ``non_manifold_edges``, ``non_manifold_vertices``,
        ``duplicate_faces``, ``degenerate_faces``, ``unreferenced_vertices``,
        ``consistently_oriented``, ``orientable``, ``edge_manifold``, ``vertex_manifold``,
        ``watertight``, ``euler_characteristic`` (``V - E + F`` over referenced vertices),
        ``genus`` (sum over components; None unless every component is a closed orientable
        manifold), ``component_genus`` (per component, largest first, at most
        :data:`MAX_LISTED_COMPONENTS`; None for a component that is not closed manifold),
        ``area``, ``volume`` (None unless watertight, manifold and consistently oriented).
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    c = Connectivity(mesh.faces, len(vertices), vertices)
    n_ref = int(c.referenced.sum())
    edge_manifold = len(c.non_manifold_edges) == 0
    vertex_manifold = len(c.non_manifold_vertices) == 0
    watertight = c.n_faces > 0 and bool(np.all(c.edge_face_count == 2))
    oriented = c.is_consistently_oriented
    genus_list = c.component_genus
    closed_manifold = c.n_faces > 0 and all(g is not None for g in genus_list)
    closed_oriented = watertight and edge_manifold and vertex_manifold and oriented
    return {
        "vertices": int(len(vertices)),
        "edges": int(c.n_edges),
        "faces": int(c.n_faces),
        "components": int(c.n_components),
        "boundary_edges": int(len(c.boundary_edges)),
        "boundary_loops": int(len(c.boundary_loops)),
        "non_manifold_edges": int(len(c.non_manifold_edges)),
        "non_manifold_vertices": int(len(c.non_manifold_vertices)),
        "duplicate_faces": int(len(c.duplicate_faces)),
        "degenerate_faces": int(len(c.degenerate_faces)),
        "unreferenced_vertices": int(len(vertices) - n_ref),
        "consistently_oriented": bool(oriented),
        "orientable": bool(c.is_orientable),
        "edge_manifold": bool(edge_manifold),
        "vertex_manifold": bool(vertex_manifold),
        "watertight": bool(watertight),
        "euler_characteristic": int(n_ref - c.n_edges + c.n_faces),
        "genus": int(sum(genus_list)) if closed_manifold else None,
        "component_genus": genus_list[:MAX_LISTED_COMPONENTS],
        "area": float(c.face_areas.sum()),
        "volume": c.signed_volume() if closed_oriented else None,
    }
