"""``recon simplify``: quadric edge-collapse decimation that keeps a manifold mesh manifold.

Garland & Heckbert's quadric error metric: every vertex carries the sum of the squared
distances to the planes of its faces (each weighted by the face's area) and, on a boundary,
to the planes through its boundary edges perpendicular to their faces (weighted by
``boundary_weight`` times the edge's squared length: the boundary stays where it is). The
edge whose merged quadric has the smallest minimum is collapsed first; the merged vertex
goes to that minimum, or to the best point of the edge when the quadric is singular (a flat
or cylindrical neighbourhood) or its minimum lies more than two edge lengths away.

A collapse is made only when

- the link condition holds (the vertices adjacent to both ends are exactly the third
  corners of the edge's faces, and an interior edge does not join two boundary vertices):
  an edge- and vertex-manifold mesh stays so, its genus and boundary loops unchanged;
- it closes no tetrahedron and leaves no vertex without faces;
- no other face around the two ends flips, turns by more than 90 degrees, comes to face
  away from its own input normal or becomes degenerate.

Vertices on non-manifold edges, with several fans of faces, or in faces that repeat an
index are locked (never moved): the rest of such a mesh is simplified, those parts are kept.
When the target cannot be reached (a closed mesh has an even number of faces; the tests
above allow no further collapse) the report's ``stopped`` says why; the result is never
silently short of its target. Vertices that no collapse moved keep their exact input
coordinates; a merged vertex's normal, colour and scalar attributes are interpolated
along the edge at the projection of its new position (integer attributes other than
colours, such as class codes, take the nearer end's value), their types kept; faces keep
their attributes.

Report keys (stable): ``vertices_in``, ``faces_in``, ``faces_target``, ``vertices_out``,
``faces_out``, ``collapses``, ``passes``, ``locked_vertices``, ``non_manifold_edges``,
``non_manifold_vertices``, ``boundary_vertices``, ``stopped``.

References
----------
Garland, M. & Heckbert, P. S. (1997). Surface simplification using quadric error metrics.
SIGGRAPH (the quadrics, optimal placement and its fallback, boundary penalty planes).
Dey, T. K., Edelsbrunner, H., Guha, S. & Nekhayev, D. V. (1999). Topology preserving edge
contraction. Publ. Inst. Math. (Beograd) 66 (the link condition).
Cignoni, P., Montani, C. & Scopigno, R. (1998). A comparison of mesh simplification
algorithms. Computers & Graphics 22(1) (the triangle-quality weighting of VCG / MeshLab).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import TriangleMesh, bbox_diagonal, float64, local_origin
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult

# a collapse may turn a surviving face by at most 90 degrees (cosine of the largest turn)
MIN_COS = 0.0
# heap builds before giving up on a target the constraints keep out of reach
MAX_PASSES = 64
# progress steps of the collapse loop
STEPS = 20

SPEC = StageSpec(
    name="simplify",
    summary="Quadric edge-collapse simplification of a mesh (stays manifold).",
    description="""Quadric edge-collapse simplification of a mesh (stays manifold).

    Garland & Heckbert's quadric error metric with optimal vertex placement, boundary
    planes, the link condition (a manifold mesh stays manifold) and no flipped faces.
    Give --faces N or --ratio R (the default is half the faces). Normals, colours and
    per-vertex scalars are interpolated at the merged vertices, their types kept.""",
    takes=("mesh",),
    gives=("mesh",),
    params=(
        Param(
            "faces",
            "int",
            None,
            "Target number of faces (instead of --ratio).",
            unit="faces",
            min=4,
            words={"none": None},
            metavar="N",
        ),
        Param(
            "ratio",
            "float",
            None,
            "Target faces as a fraction of the input's (not set with --faces: 0.5).",
            unit="fraction of the faces",
            min=0.0,
            min_open=True,
            max=1.0,
            words={"none": None},
            metavar="R",
        ),
        Param(
            "boundary_weight",
            "float",
            1000.0,
            "Weight of the planes through boundary edges (0: the boundary may move).",
            unit="times the squared edge length",
            min=0.0,
            metavar="W",
        ),
    ),
)


def zorder(points: np.ndarray) -> np.ndarray:
    """Z-order (Morton) keys of ``points`` (n, 3) on a 1024^3 lattice over their box."""
    lo = points.min(axis=0)
    ext = float((points.max(axis=0) - lo).max()) or 1.0
    q = np.clip((points - lo) / ext * 1023.0, 0, 1023).astype(np.int64)
    key = np.zeros(len(points), dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            key |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return key


def target_faces(m: int, faces: int | None, ratio: float | None) -> int:
    """The face count asked for, checked against the input's ``m`` faces."""
    if faces is not None and ratio is not None:
        raise ParameterError("give --faces or --ratio, not both")
    if faces is not None:
        if faces > m:
            raise ParameterError(f"--faces {faces} is above the input's {m} faces")
        return int(faces)
    r = 0.5 if ratio is None else float(ratio)
    t = int(round(r * m))
    if t < 4:
        raise ParameterError(
            f"--ratio {r:g} of {m} faces leaves {t}: a mesh needs at least 4 faces"
        )
    return t


def _check_mesh(mesh: Any) -> TriangleMesh:
    if not isinstance(mesh, TriangleMesh):
        raise InputError(f"simplify needs a triangle mesh, got {type(mesh).__name__}")
    mesh = float64(mesh)
    f = mesh.faces
    n = len(mesh.vertices)
    if len(f) < 4:
        raise InputError(f"the mesh has {len(f)} faces: simplify needs at least 4")
    if f.min() < 0 or f.max() >= n:
        raise InputError(f"faces reference vertices outside 0..{n - 1}")
    used = np.zeros(n, dtype=bool)
    used[f.ravel()] = True
    if not np.isfinite(mesh.vertices[used]).all():
        raise InputError("the mesh has non-finite vertex coordinates")
    return mesh


class Decimator:
    """The collapse state of one mesh (normalised coordinates, quadrics, adjacency, heap).

    Parameters
    ----------
    vertices : (n, 3) float64
        Coordinates (finite where referenced).
    faces : (m, 3) int64
        Triangles (indices checked by the caller).
    boundary_weight : float
        Weight of the boundary planes (see the module docstring).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, boundary_weight: float):
        from recon_cli.stages.simplify import _kernel as K

        self.K = K
        n, m = len(vertices), len(faces)
        used = np.zeros(n, dtype=bool)
        used[faces.ravel()] = True
        self.origin = local_origin(vertices[used])
        self.scale = bbox_diagonal(vertices[used]) or 1.0
        # centred and scaled to a unit diagonal: the tests' thresholds are scale-free and
        # offsets of 1e6 cost no digits
        pos = (vertices - self.origin) / self.scale
        pos[~used] = 0.0
        # vertices in Z-order and faces by their first vertex: a collapse's neighbourhood
        # then sits in few cache lines
        self.order = np.argsort(zorder(pos), kind="stable")
        self.inv = np.empty(n, dtype=np.int64)
        self.inv[self.order] = np.arange(n)
        self.pos = np.ascontiguousarray(pos[self.order])
        faces = self.inv[faces]
        self.forder = np.argsort(faces.min(axis=1), kind="stable")
        self.faces = np.ascontiguousarray(faces[self.forder])
        self.falive = np.ones(m, dtype=bool)
        self.valive = np.ones(n, dtype=bool)
        self.vstart, self.vcount, self.refs = K.vertex_faces(self.faces, n)
        self.boundary, self.locked, self.nm_edges, self.nm_vertices = K.classify(
            self.faces, n, self.vstart, self.vcount, self.refs
        )
        self.Q, self.fn = K.quadrics(
            self.pos,
            self.faces,
            self.vstart,
            self.vcount,
            self.refs,
            self.boundary,
            float(boundary_weight),
        )
        # a boundary edge that may collapse (removing one face) needs two free ends
        self.has_boundary = bool((self.boundary & ~self.locked).any())
        self.ea, self.eb, self.estart, self.ecount, self.erefs = K.vertex_edges(
            self.faces, n, self.vstart, self.vcount, self.refs
        )
        n_edges = len(self.ea)
        self.ealive = np.ones(n_edges, dtype=bool)
        self.epen = np.zeros(n_edges, dtype=bool)
        self.hk = np.empty(n_edges, dtype=np.int64)
        self.hpos = np.full(n_edges, -1, dtype=np.int64)
        self.mark = np.zeros(n, dtype=np.int64)
        self.moved = np.zeros(n, dtype=bool)
        self.meta = np.zeros(K.N_META, dtype=np.int64)
        self.meta[K.M_REFS] = int(self.vcount.sum())
        self.meta[K.M_EREFS] = int(self.ecount.sum())
        self.meta[K.M_FACES] = m
        self.log_u = np.empty(n, dtype=np.int64)
        self.log_v = np.empty(n, dtype=np.int64)
        self.log_t = np.empty(n, dtype=np.float64)

    def result(self) -> dict[str, np.ndarray]:
        """The state in the input's numbering.

        ``valive``, ``moved`` (n,) bool, ``positions`` (n, 3) (in the input's units), ``falive``
        (m,) bool, ``faces`` (m, 3) (input vertex indices), and the collapses in order: ``log_u``
        (kept), ``log_v`` (merged into it), ``log_t`` (where along u -> v the new vertex projects).
        """
        inv, order = self.inv, self.order
        finv = np.empty(len(self.forder), dtype=np.int64)
        finv[self.forder] = np.arange(len(self.forder))
        n_log = int(self.meta[self.K.M_LOG])
        return {
            "valive": self.valive[inv],
            "moved": self.moved[inv],
            "positions": self.pos[inv] * self.scale + self.origin,
            "falive": self.falive[finv],
            "faces": order[self.faces[finv]],
            "log_u": order[self.log_u[:n_log]],
            "log_v": order[self.log_v[:n_log]],
            "log_t": self.log_t[:n_log],
        }

    @property
    def n_faces(self) -> int:
        """The faces left."""
        return int(self.meta[self.K.M_FACES])

    @property
    def stuck(self) -> bool:
        """Whether no edge can collapse any more (the target is out of reach)."""
        return bool(self.meta[self.K.M_STUCK])

    def run(self, target: int, stop_at: int) -> None:
        """Collapse until ``stop_at`` faces remain (never below ``target``) or none can go."""
        K = self.K
        K.collapse(
            K.Surface(
                self.pos,
                self.faces,
                self.falive,
                self.valive,
                self.Q,
                self.fn,
                self.boundary,
                self.locked,
                self.moved,
            ),
            K.Fans(self.vstart, self.vcount, self.refs),
            K.Edges(
                self.ea,
                self.eb,
                self.ealive,
                self.epen,
                self.estart,
                self.ecount,
                self.erefs,
                self.hk,
                self.hpos,
            ),
            K.Log(self.log_u, self.log_v, self.log_t),
            self.mark,
            self.meta,
            int(target),
            int(stop_at),
            MIN_COS,
            MAX_PASSES,
            self.has_boundary,
        )

    def stop_reason(self, target: int) -> str | None:
        """Why fewer collapses were made than asked (None when the target was reached)."""
        K = self.K
        left = self.n_faces
        if left <= target:
            return None
        if left == target + 1 and self.meta[K.M_BUDGET] > 0:
            return (
                f"stopped at {left} faces: every remaining collapse removes 2 faces "
                f"(no free boundary: a closed surface has an even number of faces)"
            )
        why = []
        if self.meta[K.M_LINK]:
            why.append(f"{self.meta[K.M_LINK]} would break the manifold")
        if self.meta[K.M_GEOM]:
            why.append(f"{self.meta[K.M_GEOM]} would flip or degenerate faces")
        if self.meta[K.M_PASSES] >= MAX_PASSES:
            why.append(f"{MAX_PASSES} passes made")
        locked = int(self.locked.sum())
        if locked:
            why.append(f"{locked} vertices locked (non-manifold)")
        return f"stopped at {left} faces: of the last candidate collapses " + (
            ", ".join(why) or "none was left"
        )


def simplify(
    mesh: TriangleMesh,
    faces: int | str | None = SPEC.param("faces").default,
    ratio: float | str | None = SPEC.param("ratio").default,
    boundary_weight: float | str = SPEC.param("boundary_weight").default,
    progress=None,
) -> tuple[TriangleMesh, dict]:
    """Simplify ``mesh`` to ``faces`` triangles (or ``ratio`` of them) by quadric edge collapse.

    Parameters
    ----------
    mesh : TriangleMesh
        Vertices (n, 3), faces (m, 3) with m >= 4; any units, any offset.
    faces : int, optional
        Target number of faces, 4 <= faces <= m. Not together with ``ratio``.
    ratio : float, optional
        Target as a fraction of m, in (0, 1]; 0.5 when neither is given.
    boundary_weight : float
        Weight of the planes through boundary edges, times the squared edge length
        (0: boundaries are simplified like the interior).
    progress : Progress, optional

    Returns
    -------
    mesh : TriangleMesh
        The simplified mesh, float64 coordinates (vertices no collapse moved are the input's
        exact values; unreferenced input vertices are kept), its vertex data interpolated
        and face data kept (see the module docstring); ``history`` and ``point_dtype`` kept.
    report : dict
        See the module docstring; ``stopped`` is None when ``faces_out`` equals the target.

    Raises
    ------
    InputError
        Not a mesh, fewer than 4 faces, indices out of range, non-finite coordinates.
    ParameterError
        Both ``faces`` and ``ratio``, a target above the input's faces or below 4.

    References
    ----------
    M. Garland and P. S. Heckbert, "Surface simplification using quadric error metrics",
    SIGGRAPH 1997. T. K. Dey, H. Edelsbrunner, S. Guha and D. V. Nekhayev, "Topology
    preserving edge contraction", Publ. Inst. Math. (Beograd) 66, 1999 (the link condition).
    """
    v = SPEC.check(dict(faces=faces, ratio=ratio, boundary_weight=boundary_weight), complete=False)
    normal_dtype = None if mesh.normals is None else np.asarray(mesh.normals).dtype
    mesh = _check_mesh(mesh)
    m = len(mesh.faces)
    target = target_faces(m, v["faces"], v["ratio"])
    d = Decimator(mesh.vertices, mesh.faces, v["boundary_weight"])
    todo = m - target
    with task(progress, "simplify", total=max(todo, 1)) as t:
        for i in range(1, STEPS + 1):
            before = d.n_faces
            d.run(target, max(target, m - (todo * i) // STEPS))
            t.advance(before - d.n_faces)
            if d.stuck:
                break
    out = _output(mesh, d, normal_dtype)
    rep = {
        "vertices_in": int(len(mesh.vertices)),
        "faces_in": int(m),
        "faces_target": int(target),
        "vertices_out": int(len(out.vertices)),
        "faces_out": int(len(out.faces)),
        "collapses": int(d.meta[d.K.M_LOG]),
        "passes": int(d.meta[d.K.M_PASSES]),
        "locked_vertices": int(d.locked.sum()),
        "non_manifold_edges": int(d.nm_edges),
        "non_manifold_vertices": int(d.nm_vertices),
        "boundary_vertices": int(np.count_nonzero(d.boundary & d.valive)),
        "stopped": d.stop_reason(target),
    }
    return out, rep


def _output(mesh: TriangleMesh, d: Decimator, normal_dtype=None) -> TriangleMesh:
    """The surviving vertices and faces, with the input's data carried through the collapses.

    Normals are in ``normal_dtype``, default their own.
    """
    n = len(mesh.vertices)
    r = d.result()
    keep_v, falive = r["valive"], r["falive"]
    new_index = np.cumsum(keep_v) - 1
    faces = new_index[r["faces"][falive]]
    verts = np.array(mesh.vertices, dtype=np.float64)
    moved = r["moved"]
    verts[moved] = r["positions"][moved]
    lu, lv, lt = r["log_u"], r["log_v"], r["log_t"]

    # float data interpolated in one table; integer data follows the nearer end
    cols: list[np.ndarray] = []
    if mesh.normals is not None:
        cols.append(np.asarray(mesh.normals, dtype=np.float64))
    if mesh.colors is not None:
        cols.append(np.asarray(mesh.colors, dtype=np.float64))
    floats = [k for k, a in mesh.attributes.items() if a.dtype.kind == "f"]
    for k in floats:
        cols.append(np.asarray(mesh.attributes[k], dtype=np.float64).reshape(n, -1))
    values = np.ascontiguousarray(np.hstack(cols)) if cols else np.zeros((n, 0))
    source = np.arange(n, dtype=np.int64)
    d.K.replay(lu, lv, lt, values, source)
    values = values[keep_v]
    source = source[keep_v]
    c = 0
    normals = colors = None
    if mesh.normals is not None:
        nrm = values[:, c : c + 3]
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        normals = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
        normals = normals.astype(normal_dtype or mesh.normals.dtype)
        c += 3
    if mesh.colors is not None:
        w = mesh.colors.shape[1] if mesh.colors.ndim == 2 else 1
        col = values[:, c : c + w]
        colors = _cast(col, mesh.colors.dtype).reshape((-1,) + mesh.colors.shape[1:])
        c += w
    attrs = {}
    for k, a in mesh.attributes.items():
        if k in floats:
            w = int(np.prod(a.shape[1:], dtype=np.int64))
            attrs[k] = values[:, c : c + w].reshape((-1,) + a.shape[1:]).astype(a.dtype)
            c += w
        else:
            attrs[k] = a[source]
    return TriangleMesh(
        vertices=verts[keep_v],
        faces=faces,
        normals=normals,
        colors=colors,
        attributes=attrs,
        face_attributes={k: a[falive] for k, a in mesh.face_attributes.items()},
        history=list(mesh.history),
        point_dtype=mesh.point_dtype,
        extra_elements=list(mesh.extra_elements),
        obj_info=list(mesh.obj_info),
    )


def _cast(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Interpolated values in ``dtype``: integers rounded and clipped to their range."""
    if np.dtype(dtype).kind in "iu":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


@SPEC.runner
def run_stage(
    data: TriangleMesh,
    *,
    faces: int | None,
    ratio: float | None,
    boundary_weight: float,
    progress=None,
) -> StageResult:
    """Stage ``simplify``: see :func:`simplify`."""
    out, rep = simplify(
        data, faces=faces, ratio=ratio, boundary_weight=boundary_weight, progress=progress
    )
    rep["provenance"] = {"faces": rep["faces_target"]}
    return StageResult(output=out, report=rep)
