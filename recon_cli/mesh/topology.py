"""Mesh connectivity: one vectorised structure every stage that needs adjacency uses.

Adjacency is kept as arrays, never as objects. The faces' directed edges are the
half-edges: half-edge ``h = 3 f + k`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``
and starts at corner ``h`` (corner ``3 f + k`` is vertex ``faces[f, k]`` seen from face
``f``). Grouping the half-edges by their undirected ends ``(lo, hi)`` gives the twins: an
edge used by one half-edge is a boundary edge, by two a manifold edge, by more a
non-manifold edge.
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

from recon_cli.aot import kernels
from recon_cli.errors import InputError
from recon_cli.tolerances import tol

#: at most this many per-component genera are listed in the report (largest components first)
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
    # int32 faces (repair's working copy) are kept as they are: no int64 copy
    f = np.ascontiguousarray(f, dtype=f.dtype if f.dtype in (np.int32, np.int64) else np.int64)
    if len(f) and f.min() < 0:
        raise InputError("faces hold negative vertex indices")
    top = int(f.max()) + 1 if len(f) else 0
    if n_vertices is None:
        n_vertices = top
    elif top > n_vertices:
        raise InputError(f"faces reference vertex {top - 1} but the mesh has {n_vertices} vertices")
    return f, int(n_vertices)


def index_dtype(*counts: int) -> type[np.int32] | type[np.int64]:
    """int32 when every index below ``max(counts)`` fits in it, else int64 (halves the memory)."""
    return np.int32 if max(counts, default=0) < 2**31 - 1 else np.int64


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
    edges = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64, copy=False)
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


def next_half_edge(h: np.ndarray) -> np.ndarray:
    """The next half-edge in the same face (``3f+k -> 3f+(k+1)%3``): its start is ``h``'s end."""
    nxt = h + 1
    nxt[h % 3 == 2] -= 3
    return nxt


# faces per chunk in the geometric loops: bounds their (chunk, 3) float64 temporaries
CHUNK = 1 << 14


class Connectivity:
    """Edges, adjacency, fans and components of a triangle mesh, built from its faces.

    Everything is computed lazily (cached on first use). Edges come from a counting sort of
    the half-edges by their smaller vertex, each vertex's few then sorted by the larger;
    grouping, fans, components and orientation are numba loops (union-find, breadth-first
    walk) that allocate nothing larger than their outputs. Index arrays use
    :func:`index_dtype` (int32 below 2^31 half-edges and vertices, else int64): the edges are
    two index arrays of about 3m and 1.5m entries (:attr:`half_edge_edge`, 3m more, is built
    on request), and no step holds a key or a copy per half-edge (the memory bound is a
    test). The attributes are arrays computed on first use;
    "int" in their types is :func:`index_dtype`.

    Parameters
    ----------
    faces : (m, 3) int
        Triangles (any winding, any defects). int32 and int64 faces are used without a copy.
    n_vertices : int, optional
        Number of vertices (default: largest index + 1).
    vertices : (n, 3) float, optional
        Coordinates; needed for ``area``, ``volume``, ``face_areas`` and the degenerate test.

    Attributes
    ----------
    half_edges : (3m, 2) int64
        Directed edges, see :func:`faces_to_edges` (built on request only; the structure
        itself reads the half-edge ``h``'s ends as ``faces.ravel()[h]`` and
        ``faces.ravel()[next_half_edge(h)]``).
    edges : (E, 2) int64
        Unique undirected edges ``(lo, hi)``, sorted.
    half_edge_edge : (3m,) int
        Edge of each half-edge (-1 for the zero-length half-edges of repeated-index faces).
    edge_ptr, edge_half_edges : (E+1,), (H,) int
        CSR: half-edges of edge ``e`` are ``edge_half_edges[edge_ptr[e]:edge_ptr[e+1]]``
        in increasing order (their faces are ``// 3``).
    edge_face_count : (E,) int
    boundary_edges, non_manifold_edges : int64 edge indices (count 1, count > 2)
    face_adjacency : (k, 2) int
        Face pairs sharing a manifold edge; ``face_adjacency_edge`` (k,) the edge,
        ``face_adjacency_same`` (k,) bool whether both traverse it the same way.
    vertex_ptr, vertex_faces : (n+1,) int64, (3m,) int
        CSR vertex -> faces (a face twice if it repeats the vertex).
    """

    def __init__(
        self, faces: Any, n_vertices: int | None = None, vertices: np.ndarray | None = None
    ):
        f, n = _check_faces(
            faces,
            n_vertices if n_vertices is not None else (None if vertices is None else len(vertices)),
        )
        self.faces = f
        self.n_vertices = n
        self.n_faces = len(f)
        self.vertices = (
            None
            if vertices is None
            else np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
        )
        self._it = index_dtype(3 * len(f) + 3, n + 1)

    def forget(self) -> None:
        """Drop every array computed so far (edges, adjacency, fans...): recomputed on next use."""
        for name, attr in type(self).__dict__.items():
            if isinstance(attr, cached_property):
                self.__dict__.pop(name, None)

    @property
    def _flat(self) -> np.ndarray:
        # corner c = 3 f + k is vertex _flat[c]; half-edge h starts at corner h
        return self.faces.reshape(-1)

    # ---- edges -------------------------------------------------------------------------
    @cached_property
    def half_edges(self) -> np.ndarray:
        """(3m, 2) int64: the half-edges (a, b) of each face, in corner order."""
        return self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64, copy=False)

    @cached_property
    def _edge_groups(self) -> tuple[np.ndarray, np.ndarray]:
        K = kernels("recon_cli.mesh._topology_kernel")
        group_half_edges = K.group_half_edges

        # bucketed by the smaller vertex: no int64 key or argsort per half-edge (those were
        # most of report()'s memory, see docs/design/topology.md)
        return group_half_edges(self._flat, self.n_vertices, np.zeros(0, self._it))

    @cached_property
    def edges(self) -> np.ndarray:
        """(e, 2) int64: each undirected edge once, its smaller vertex first."""
        h = self.edge_half_edges[self.edge_ptr[:-1]]
        a = self._flat[h]
        b = self._flat[next_half_edge(h)]
        out = np.empty((len(h), 2), dtype=np.int64)
        np.minimum(a, b, out=out[:, 0])
        np.maximum(a, b, out=out[:, 1])
        return out

    @cached_property
    def half_edge_edge(self) -> np.ndarray:
        """(3m,): the edge of each half-edge."""
        K = kernels("recon_cli.mesh._topology_kernel")
        edge_of_half_edges = K.edge_of_half_edges

        return edge_of_half_edges(self.edge_ptr, self.edge_half_edges, 3 * self.n_faces)

    @property
    def edge_ptr(self) -> np.ndarray:
        """(e + 1,): CSR offsets of each edge's half-edges in :attr:`edge_half_edges`."""
        return self._edge_groups[0]

    @property
    def edge_half_edges(self) -> np.ndarray:
        """(3m,): the half-edges grouped by edge (see :attr:`edge_ptr`)."""
        return self._edge_groups[1]

    @property
    def n_edges(self) -> int:
        """The number of undirected edges."""
        return len(self.edge_ptr) - 1

    @cached_property
    def edge_face_count(self) -> np.ndarray:
        """(e,): the number of faces at each edge."""
        return np.diff(self.edge_ptr)

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        """Indices of the edges with one face."""
        K = kernels("recon_cli.mesh._topology_kernel")
        return K.edges_with_count(self.edge_ptr, 1, 1)

    @cached_property
    def non_manifold_edges(self) -> np.ndarray:
        """Indices of the edges with more than two faces."""
        K = kernels("recon_cli.mesh._topology_kernel")
        return K.edges_with_count(self.edge_ptr, 3, 3 * self.n_faces)

    @cached_property
    def _manifold_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Half-edges (a, b) of each manifold edge e, a < b: ``(a, b, e)``."""
        e = np.flatnonzero(self.edge_face_count == 2).astype(self._it)
        s = self.edge_ptr[e]
        a = self.edge_half_edges[s]
        s += 1
        b = self.edge_half_edges[s]
        return a, b, e

    @property
    def face_adjacency(self) -> np.ndarray:
        """(k, 2): the two faces of each manifold edge."""
        a, b, _ = self._manifold_pairs
        return np.stack([a // 3, b // 3], axis=1)

    @property
    def face_adjacency_edge(self) -> np.ndarray:
        """(k,): the manifold edge of each row of :attr:`face_adjacency`."""
        return self._manifold_pairs[2]

    @cached_property
    def face_adjacency_same(self) -> np.ndarray:
        """(k,) bool: the two faces run the shared edge the same way (inconsistent winding)."""
        a, b, _ = self._manifold_pairs
        return self._flat[a] == self._flat[b]

    # ---- vertices ----------------------------------------------------------------------
    @cached_property
    def _vertex_csr(self):
        K = kernels("recon_cli.mesh._topology_kernel")
        counting_sort = K.counting_sort

        ptr, order = counting_sort(self._flat, self.n_vertices, np.zeros(0, self._it))
        order //= 3
        return ptr, order

    @property
    def vertex_ptr(self) -> np.ndarray:
        """(n + 1,): CSR offsets of each vertex's faces in :attr:`vertex_faces`."""
        return self._vertex_csr[0]

    @property
    def vertex_faces(self) -> np.ndarray:
        """(3m,): the faces at each vertex, grouped by vertex (see :attr:`vertex_ptr`)."""
        return self._vertex_csr[1]

    @cached_property
    def referenced(self) -> np.ndarray:
        """(n,) bool: vertex used by some face."""
        r = np.zeros(self.n_vertices, dtype=bool)
        r[self._flat] = True
        return r

    def corner_fans(
        self, link_a: np.ndarray | None = None, link_b: np.ndarray | None = None
    ) -> np.ndarray:
        """Fan label of each corner, (3m,) int: corners joined across the given half-edge pairs.

        By default every pair of consecutive half-edges of an edge is joined (all faces of
        a non-manifold edge touch each other). Corners of one vertex with different labels
        lie in different fans. Labels are numbered in order of first corner (so the fan of
        a smaller label starts at a smaller corner).
        """
        K = kernels("recon_cli.mesh._topology_kernel")
        fan_labels_groups, fan_labels_pairs = K.fan_labels_groups, K.fan_labels_pairs

        labels = np.arange(3 * self.n_faces, dtype=self._it)
        if link_a is None:
            fan_labels_groups(labels, self._flat, self.edge_ptr, self.edge_half_edges)
        else:
            fan_labels_pairs(labels, self._flat, np.asarray(link_a), np.asarray(link_b))
        return labels

    @cached_property
    def vertex_fan_count(self) -> np.ndarray:
        """(n,) int64: number of fans around each vertex (0 if unreferenced)."""
        K = kernels("recon_cli.mesh._topology_kernel")
        return K.fans_per_vertex(self.corner_fans(), self._flat, self.n_vertices)

    @cached_property
    def non_manifold_vertices(self) -> np.ndarray:
        """Indices of the vertices whose faces form more than one fan."""
        return np.flatnonzero(self.vertex_fan_count > 1)

    # ---- faces -------------------------------------------------------------------------
    @cached_property
    def face_components(self) -> np.ndarray:
        """(m,) int component label per face, largest component 0 (ties: first face first)."""
        K = kernels("recon_cli.mesh._topology_kernel")
        face_labels_groups = K.face_labels_groups

        labels = np.arange(self.n_faces, dtype=self._it)
        face_labels_groups(labels, self.edge_ptr, self.edge_half_edges)
        return _relabel_by_size(labels)

    @property
    def n_components(self) -> int:
        """The number of connected components (across manifold edges)."""
        return int(self.face_components.max()) + 1 if self.n_faces else 0

    @cached_property
    def duplicate_faces(self) -> np.ndarray:
        """Indices of faces whose vertex set equals that of an earlier face (either winding)."""
        K = kernels("recon_cli.mesh._topology_kernel")
        # faces bucketed by their smallest vertex: no sorted copy of the faces, no global sort
        dup = K.duplicate_face_flags(self.faces, self.n_vertices, np.zeros(0, self._it))
        return np.flatnonzero(dup)

    @cached_property
    def face_areas(self) -> np.ndarray:
        """(m,) float64 area of each face; needs the vertex coordinates."""
        if self.vertices is None:
            raise InputError("face areas need vertex coordinates")
        v = self.vertices
        out = np.empty(self.n_faces, dtype=np.float64)
        with np.errstate(
            invalid="ignore", over="ignore"
        ):  # non-finite input gives nan areas, not warnings
            for s in range(0, self.n_faces, CHUNK):
                f = self.faces[s : s + CHUNK]
                p0 = v[f[:, 0]]
                out[s : s + len(f)] = np.linalg.norm(
                    np.cross(v[f[:, 1]] - p0, v[f[:, 2]] - p0), axis=1
                )
        out *= 0.5
        return out

    @cached_property
    def degenerate_faces(self) -> np.ndarray:
        """Faces repeating a vertex index or, given coordinates, of area below tolerance.

        The area tolerance is ``tol.area * diag**2``.
        """
        f = self.faces
        bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
        if self.vertices is not None and len(f):
            K = kernels("recon_cli.mesh._topology_kernel")
            # the bounds without a copy of the used vertices (min and max are exact in any order)
            lo, hi, count = K.referenced_bbox(self.vertices, self.referenced)
            diag = float(np.linalg.norm(hi - lo)) if count else 0.0
            bad |= self.face_areas <= tol.area * diag * diag
        return np.flatnonzero(bad)

    @cached_property
    def _orientation(self):
        K = kernels("recon_cli.mesh._topology_kernel")
        orient_faces = K.orient_faces

        flip, comp, conflict = orient_faces(
            self._flat, self.half_edge_edge, self.edge_ptr, self.edge_half_edges
        )
        return flip, comp, np.flatnonzero(conflict)

    @cached_property
    def _conflict_edges(self) -> np.ndarray:
        # consistently oriented: every manifold edge already runs both ways, so the walk would
        # flip nothing and find no conflict (it needs :attr:`half_edge_edge`, 4 bytes a corner)
        if self.is_consistently_oriented:
            return np.zeros(0, dtype=np.int64)
        return self._orientation[2]

    def orientation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Breadth-first orientation across manifold edges, each component rooted at its first face.

        Returns
        -------
        flip : (m,) bool
            Faces to flip so that windings agree with the root's.
        component : (m,) int
            Component (across manifold edges only) in order of first face.
        conflict_edges : (k,) int64
            Manifold edges whose two faces still disagree (non-orientable cycles); empty if
            orientable.
        """
        return self._orientation

    @property
    def is_orientable(self) -> bool:
        """Faces can be flipped so that every manifold edge is used in opposite directions."""
        return len(self._conflict_edges) == 0

    @cached_property
    def is_consistently_oriented(self) -> bool:
        """No directed edge is used by two faces."""
        K = kernels("recon_cli.mesh._topology_kernel")
        consistently_oriented = K.consistently_oriented

        return bool(consistently_oriented(self._flat, self.edge_ptr, self.edge_half_edges))

    # ---- boundary ----------------------------------------------------------------------
    @cached_property
    def boundary_loops(self) -> list[np.ndarray]:
        """Boundary loops as vertex sequences, in the direction of their half-edges."""
        K = kernels("recon_cli.mesh._topology_kernel")
        trace_boundary_loops = K.trace_boundary_loops

        b = self.boundary_edges
        if len(b) == 0:
            return []
        h = self.edge_half_edges[self.edge_ptr[b]]
        src = self._flat[h].astype(np.int64)
        dst = self._flat[next_half_edge(h)].astype(np.int64)
        order, verts, starts = trace_boundary_loops(src, dst, self.n_vertices)
        return [verts[starts[i] : starts[i + 1]].copy() for i in range(len(starts) - 1)]

    # ---- per component -----------------------------------------------------------------
    @cached_property
    def component_euler(self) -> np.ndarray:
        """(c,) int64 ``V - E + F`` of each component."""
        c = self.n_components
        if c == 0:
            return np.zeros(0, dtype=np.int64)
        K = kernels("recon_cli.mesh._topology_kernel")
        vc, ec, fc = K.component_counts(
            self.face_components,
            c,
            self._flat,
            self.edge_ptr,
            self.edge_half_edges,
            self.n_vertices,
        )
        return vc - ec + fc

    @cached_property
    def component_closed_manifold(self) -> np.ndarray:
        """(c,) bool: the component is a closed orientable manifold.

        It has no boundary or non-manifold edge and no non-manifold vertex.
        """
        K = kernels("recon_cli.mesh._topology_kernel")
        bad = K.component_defects(
            self.face_components,
            self.n_components,
            self._flat,
            self.edge_ptr,
            self.edge_half_edges,
            self._conflict_edges,
            self.vertex_fan_count,
        )
        return ~bad

    @cached_property
    def component_genus(self) -> list[int | None]:
        """The genus of each component; None where it is not a closed orientable manifold."""
        chi = self.component_euler
        ok = self.component_closed_manifold
        return [
            int((2 - x) // 2) if good else None
            for x, good in zip(chi.tolist(), ok.tolist(), strict=True)
        ]

    def signed_volume(self, per_component: bool = False):
        """Signed volume (divergence theorem); meaningful for closed, oriented parts."""
        if self.vertices is None:
            raise InputError("volume needs vertex coordinates")
        v = self.vertices
        six = np.empty(self.n_faces, dtype=np.float64)
        # centre first: the sum of large, nearly cancelling terms loses digits far from the origin
        if not self.n_faces:
            centre = np.zeros(3)
        elif self.referenced.all():
            centre = v.mean(axis=0)  # the same sum as below, without a copy of every vertex
        else:
            centre = v[self.referenced].mean(axis=0)
        with np.errstate(invalid="ignore", over="ignore"):
            for s in range(0, self.n_faces, CHUNK):
                f = self.faces[s : s + CHUNK]
                p0 = v[f[:, 0]] - centre
                six[s : s + len(f)] = np.einsum(
                    "ij,ij->i", p0, np.cross(v[f[:, 1]] - centre, v[f[:, 2]] - centre)
                )
        if per_component:
            return np.bincount(self.face_components, weights=six, minlength=self.n_components) / 6.0
        return float(six.sum() / 6.0)


def _relabel_by_size(labels: np.ndarray) -> np.ndarray:
    """Relabel components numbered in order of first member: largest first, ties in that order."""
    if len(labels) == 0:
        return labels
    sizes = np.bincount(labels)
    rank = np.argsort(-sizes, kind="stable")
    new = np.empty(len(sizes), dtype=labels.dtype)
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
    return c.n_faces > 0 and len(c.boundary_edges) == 0 and len(c.non_manifold_edges) == 0


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
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    c = Connectivity(mesh.faces, len(vertices), vertices)
    n_ref = int(c.referenced.sum())
    edge_manifold = len(c.non_manifold_edges) == 0
    vertex_manifold = len(c.non_manifold_vertices) == 0
    # every edge has a face: two each is no boundary and no non-manifold edge
    watertight = c.n_faces > 0 and len(c.boundary_edges) == 0 and edge_manifold
    oriented = c.is_consistently_oriented
    genus_list = c.component_genus
    closed_manifold = c.n_faces > 0 and all(g is not None for g in genus_list)
    closed_oriented = watertight and edge_manifold and vertex_manifold and oriented
    out = {
        "vertices": int(len(vertices)),
        "edges": int(c.n_edges),
        "faces": int(c.n_faces),
        "components": int(c.n_components),
        "boundary_edges": int(len(c.boundary_edges)),
        "boundary_loops": int(len(c.boundary_loops)),
        "non_manifold_edges": int(len(c.non_manifold_edges)),
        "non_manifold_vertices": int(len(c.non_manifold_vertices)),
        "duplicate_faces": int(len(c.duplicate_faces)),
        "degenerate_faces": 0,  # the geometric figures come below
        "unreferenced_vertices": int(len(vertices) - n_ref),
        "consistently_oriented": bool(oriented),
        "orientable": bool(c.is_orientable),
        "edge_manifold": bool(edge_manifold),
        "vertex_manifold": bool(vertex_manifold),
        "watertight": bool(watertight),
        "euler_characteristic": int(n_ref - c.n_edges + c.n_faces),
        "genus": int(sum(g or 0 for g in genus_list)) if closed_manifold else None,
        "component_genus": genus_list[:MAX_LISTED_COMPONENTS],
        "area": 0.0,
        "volume": None,
    }
    # the geometric figures need no adjacency: free it first (the report's peak is the
    # adjacency and the corner fans; the areas would add to it)
    c.forget()
    out["degenerate_faces"] = int(len(c.degenerate_faces))
    out["area"] = float(c.face_areas.sum())
    out["volume"] = c.signed_volume() if closed_oriented else None
    return out
