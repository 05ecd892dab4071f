"""``recon smooth``: Taubin's lambda|mu smoothing, which removes noise without shrinking.

Each iteration is two umbrella steps, ``x += lambda * L(x)`` then ``x += mu * L(x)`` with
``mu < -lambda < 0``, where ``L(x)_i`` is the mean of vertex i's neighbours minus ``x_i``
(uniform weights, as Taubin's paper, Open3D's ``filter_smooth_taubin`` and MeshLab's Taubin
filter use: they need no well-shaped triangles, unlike cotangent weights). The pair is a
low-pass filter whose pass-band frequency ``k_PB = 1/lambda + 1/mu`` is the parameter
``pass_band``: ``mu = 1 / (pass_band - 1/lambda)`` (-0.526 for the defaults 0.5 and 0.1).
Frequencies below ``k_PB`` keep their amplitude, so the shape and its volume stay while
noise (high frequencies) is damped.

Boundary vertices move along the boundary only (their neighbours are the boundary
neighbours: an open mesh's rim is smoothed as a curve and does not pull inwards), or stay
with ``fixed_boundary``. Faces, colours, attributes and history are kept; vertex normals,
when present, are computed again from the smoothed faces (area-weighted), in their type.

Report keys (stable): ``vertices``, ``faces``, ``iterations``, ``mu``, ``boundary_vertices``,
``mean_displacement`` and ``max_displacement`` (fractions of the bounding-box diagonal),
``volume_in``, ``volume_out`` and ``volume_change`` (relative; None unless the mesh is
closed).

References
----------
Taubin, G. (1995). A signal processing approach to fair surface design. SIGGRAPH (the
lambda|mu filter, its pass-band frequency, uniform umbrella weights).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh, bbox_diagonal, float64, local_origin
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult

# iterations per progress step
CHUNK = 5

SPEC = StageSpec(
    name="smooth",
    summary="Taubin lambda|mu smoothing of a mesh (keeps its volume).",
    description="""Taubin lambda|mu smoothing of a mesh (keeps its volume).

    Each iteration is a shrinking umbrella step (lambda) and an inflating one (mu < -lambda),
    uniform weights; mu = 1 / (pass-band - 1/lambda). Noise is removed, the shape and its
    volume kept. Boundary vertices move along the boundary (or stay: --fixed-boundary).""",
    takes=("mesh",),
    gives=("mesh",),
    params=(
        Param("iterations", "int", 10, "Lambda|mu pairs.", unit="pairs", min=1, metavar="K"),
        Param(
            "step",
            "float",
            0.5,
            "The shrinking step lambda.",
            unit="fraction of the umbrella vector",
            min=0.0,
            max=1.0,
            min_open=True,
            max_open=True,
        ),
        Param(
            "pass_band",
            "float",
            0.1,
            "Pass-band frequency 1/lambda + 1/mu: what stays unsmoothed.",
            unit="frequency",
            min=0.0,
            max=1.0,
            min_open=True,
            max_open=True,
        ),
        Param("fixed_boundary", "bool", False, "Boundary vertices stay where they are."),
    ),
)

# recon warmup's runs of this stage: an input of its Files, then options (one per kernel path)
WARMUP = (("m64",), ("open", "--fixed-boundary"))


def taubin_mu(step: float, pass_band: float) -> float:
    """Taubin's inflating factor ``mu`` for ``lambda = step`` and ``k_PB = pass_band``."""
    return 1.0 / (pass_band - 1.0 / step)


def neighbours(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The umbrella's neighbour lists.

    Returns ``ptr`` (n + 1,) and ``nbr`` int64 (CSR: the neighbours of vertex i are
    ``nbr[ptr[i]:ptr[i + 1]]``), ``boundary`` (n,) bool and whether every edge has two
    faces. Interior vertices use every neighbour along an edge; boundary vertices only
    their neighbours along boundary edges.
    """
    from recon_cli.mesh.topology import Connectivity

    conn = Connectivity(faces, n)
    edges = conn.edges
    on_rim = conn.edge_face_count == 1
    boundary = np.zeros(n, dtype=bool)
    boundary[edges[on_rim].ravel()] = True
    # an edge counts for an end unless that end is on the boundary and the edge is not
    keep_a = ~boundary[edges[:, 0]] | on_rim
    keep_b = ~boundary[edges[:, 1]] | on_rim
    src = np.concatenate([edges[keep_a, 0], edges[keep_b, 1]])
    dst = np.concatenate([edges[keep_a, 1], edges[keep_b, 0]])
    order = np.argsort(src, kind="stable")
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=ptr[1:])
    closed = bool(np.all(conn.edge_face_count == 2))
    return ptr, np.ascontiguousarray(dst[order], dtype=np.int64), boundary, closed


def _volume(v: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed mesh (about its mean vertex: fewer lost digits)."""
    c = v.mean(axis=0)
    total = 0.0
    for s in range(0, len(faces), 1 << 16):
        f = faces[s : s + (1 << 16)]
        p0 = v[f[:, 0]] - c
        total += float(np.einsum("ij,ij->i", p0, np.cross(v[f[:, 1]] - c, v[f[:, 2]] - c)).sum())
    return total / 6.0


def _vertex_normals(v: np.ndarray, faces: np.ndarray, old: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals; a vertex without faces keeps ``old``'s row."""
    cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    corners = faces.ravel()
    acc = np.stack(
        [np.bincount(corners, np.repeat(cross[:, a], 3), minlength=len(v)) for a in range(3)],
        axis=1,
    )
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.array(old, dtype=np.float64)
    ok = length[:, 0] > 0
    out[ok] = acc[ok] / length[ok]
    return out.astype(old.dtype)


def smooth(
    mesh: TriangleMesh,
    iterations: int | str = SPEC.param("iterations").default,
    step: float | str = SPEC.param("step").default,
    pass_band: float | str = SPEC.param("pass_band").default,
    fixed_boundary: bool | str = SPEC.param("fixed_boundary").default,
    progress=None,
) -> tuple[TriangleMesh, dict]:
    """Smooth ``mesh`` by Taubin's lambda|mu algorithm (uniform weights).

    Parameters
    ----------
    mesh : TriangleMesh
        Vertices (n, 3), faces (m, 3), m >= 1; any units, any offset.
    iterations : int
        Number of lambda|mu pairs, >= 1.
    step : float
        lambda, in (0, 1).
    pass_band : float
        ``k_PB = 1/lambda + 1/mu`` in (0, 1); sets ``mu = 1 / (k_PB - 1/lambda)``.
    fixed_boundary : bool
        Keep boundary vertices in place (else they move along the boundary).
    progress : Progress, optional

    Returns
    -------
    mesh : TriangleMesh
        Same faces and vertex order, float64 coordinates (vertices without neighbours keep
        their exact input values), normals recomputed when present, everything else kept.
    report : dict
        See the module docstring.

    Raises
    ------
    InputError
        Not a mesh, no faces, indices out of range, non-finite coordinates.

    References
    ----------
    G. Taubin, "A signal processing approach to fair surface design", SIGGRAPH 1995.
    """
    v = SPEC.check(
        dict(iterations=iterations, step=step, pass_band=pass_band, fixed_boundary=fixed_boundary),
        complete=False,
    )
    source_normals = mesh.normals if isinstance(mesh, TriangleMesh) else None
    mesh = _check_mesh(mesh)
    lam, kpb = v["step"], v["pass_band"]
    mu = taubin_mu(lam, kpb)
    n, f = len(mesh.vertices), mesh.faces
    ptr, nbr, boundary, closed = neighbours(f, n)
    moves = ~boundary if v["fixed_boundary"] else np.ones(n, dtype=bool)
    moves &= np.diff(ptr) > 0
    origin = local_origin(mesh.vertices[moves]) if moves.any() else np.zeros(3)
    pos = np.ascontiguousarray(mesh.vertices - origin, dtype=np.float64)
    from recon_cli.stages.smooth._kernel import taubin

    k = v["iterations"]
    with task(progress, "smooth", total=k) as t:
        for done in range(0, k, CHUNK):
            todo = min(CHUNK, k - done)
            taubin(pos, ptr, nbr, moves, lam, mu, todo)
            t.advance(todo)
    verts = np.array(mesh.vertices, dtype=np.float64)
    verts[moves] = pos[moves] + origin
    diag = bbox_diagonal(mesh.vertices[np.diff(ptr) > 0]) or 1.0
    disp = np.linalg.norm(verts - mesh.vertices, axis=1)
    vol_in = _volume(mesh.vertices, f) if closed else None
    vol_out = _volume(verts, f) if closed else None
    rep: dict[str, Any] = {
        "vertices": int(n),
        "faces": int(len(f)),
        "iterations": int(k),
        "mu": mu,
        "boundary_vertices": int(boundary.sum()),
        "mean_displacement": float(disp[moves].mean() / diag) if moves.any() else 0.0,
        "max_displacement": float(disp[moves].max() / diag) if moves.any() else 0.0,
        "volume_in": vol_in,
        "volume_out": vol_out,
        "volume_change": (
            (vol_out - vol_in) / abs(vol_in) if vol_in and vol_out is not None else None
        ),
    }
    out = TriangleMesh(
        vertices=verts,
        faces=f,
        normals=None
        if mesh.normals is None
        else _vertex_normals(verts, f, mesh.normals if source_normals is None else source_normals),
        colors=mesh.colors,
        attributes=dict(mesh.attributes),
        face_attributes=dict(mesh.face_attributes),
        history=list(mesh.history),
        point_dtype=mesh.point_dtype,
        extra_elements=list(mesh.extra_elements),
        obj_info=list(mesh.obj_info),
    )
    return out, rep


def _check_mesh(mesh: Any) -> TriangleMesh:
    if not isinstance(mesh, TriangleMesh):
        raise InputError(f"smooth needs a triangle mesh, got {type(mesh).__name__}")
    mesh = float64(mesh)
    f = mesh.faces
    n = len(mesh.vertices)
    if len(f) == 0:
        raise InputError("the mesh has no faces to smooth")
    if f.min() < 0 or f.max() >= n:
        raise InputError(f"faces reference vertices outside 0..{n - 1}")
    used = np.zeros(n, dtype=bool)
    used[f.ravel()] = True
    if not np.isfinite(mesh.vertices[used]).all():
        raise InputError("the mesh has non-finite vertex coordinates")
    return mesh


@SPEC.runner
def run_stage(
    data: TriangleMesh,
    *,
    iterations: int,
    step: float,
    pass_band: float,
    fixed_boundary: bool,
    progress=None,
) -> StageResult:
    """Stage ``smooth``: see :func:`smooth`."""
    out, rep = smooth(
        data,
        iterations=iterations,
        step=step,
        pass_band=pass_band,
        fixed_boundary=fixed_boundary,
        progress=progress,
    )
    rep["provenance"] = {"mu": round(rep["mu"], 6)}
    return StageResult(output=out, report=rep)
