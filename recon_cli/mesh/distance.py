"""Exact distances to a triangle mesh: closest points through a bounding-volume hierarchy.

:func:`closest_points` is the stable entry point (also used by ``recon diff``);
:func:`distance_grid` evaluates the unsigned distance (and optionally the pseudonormal
sign) on every sample of a regular grid, reusing each sample's answer to bound the next.
The hierarchy (:class:`TriangleBVH`) is built once per mesh and can be passed back in.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from recon_cli.errors import InputError, ParameterError


@dataclass
class TriangleBVH:
    """A BVH over triangles: median splits along the longest axis.

    The kernels are :mod:`recon_cli.mesh._distance_kernel`'s.

    Attributes
    ----------
    tri : (m, 3, 3) float64
        Triangle corners, in tree order.
    sph : (m, 8) float64
        Bounding disk of each tree triangle: centroid xyz, radius, unit normal xyz, 0
        (normal 0 for slivers: a bounding ball).
    order : (m,) int64
        ``order[t]`` = index of tree triangle ``t`` in the input faces.
    lo, hi : (nodes, 3) float64
        Node boxes.
    box : (nodes, 6) float64
        The same boxes packed per node (lo xyz, hi xyz): one cache line per visit.
    left, right, start, end : (nodes,) int64
        Children (-1 for leaves) and the range of tree triangles under each node.
    """

    tri: np.ndarray
    sph: np.ndarray
    order: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    left: np.ndarray
    right: np.ndarray
    start: np.ndarray
    end: np.ndarray
    box: np.ndarray

    def arrays(self) -> tuple:
        """The arguments of the query kernels: tri, sph, box, left, right, start, end."""
        return self.tri, self.sph, self.box, self.left, self.right, self.start, self.end


@contextmanager
def dynamic_schedule(chunk: int = 16):
    """Run the numba ``prange`` loops launched inside in chunks of ``chunk`` iterations.

    The chunks are handed out on demand. Grid lines through thin walls cost far more than lines in
    empty space, and the default static split leaves one core idle while the other (slowed by the
    load or by its share of the walls) finishes. Set from Python: the setting inside a kernel would
    make it uncacheable.
    """
    import numba

    old = numba.set_parallel_chunksize(int(chunk))
    try:
        yield
    finally:
        numba.set_parallel_chunksize(old)


def check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, faces)`` as float64 (n, 3) and integer (m, 3) arrays.

    Raises :class:`~recon_cli.errors.InputError` for any other shape or type.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vertices must have shape (n, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
        raise InputError(f"faces must be an integer (m, 3) array, got {f.dtype} {f.shape}")
    if len(f) == 0:
        raise InputError("mesh has no faces")
    f = np.ascontiguousarray(f, dtype=np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise InputError("faces index vertices that do not exist")
    if not np.isfinite(v[np.unique(f)]).all():
        raise InputError("mesh has non-finite vertex coordinates")
    return v, f


def _morton(points: np.ndarray) -> np.ndarray:
    """63-bit Morton (Z-order) codes of ``points`` quantised to 2**21 cells per axis."""
    lo = points.min(axis=0)
    ext = float((points.max(axis=0) - lo).max()) or 1.0
    q = np.clip(((points - lo) / ext * (2**21 - 1)).astype(np.uint64), 0, 2**21 - 1)

    def spread(x):  # insert two zero bits between the bits of x (21 -> 63 bits)
        x = x & np.uint64(0x1FFFFF)
        x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
        return x

    return spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))


def build_bvh(vertices: np.ndarray, faces: np.ndarray) -> TriangleBVH:
    """Build the hierarchy of a triangle mesh.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int, m >= 1

    Returns
    -------
    TriangleBVH
    """
    from recon_cli.mesh import _distance_kernel as K

    v, f = check_mesh(vertices, faces)
    tri = v[f]
    order, left, right, start, end = K.build_median(tri.mean(axis=1), K.LEAF_SIZE)
    tri = np.ascontiguousarray(tri[order])
    lo, hi = K.node_boxes(tri.min(axis=1), tri.max(axis=1), left, right, start, end)
    box = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    return TriangleBVH(
        tri, K.bounding_spheres(tri), order.astype(np.int64), lo, hi, left, right, start, end, box
    )


def closest_points(
    vertices: np.ndarray,
    faces: np.ndarray,
    query: np.ndarray,
    bvh: TriangleBVH | None = None,
    upper: float | np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest point on a triangle mesh for each query point.

    Parameters
    ----------
    vertices : (n, 3) float
        Mesh vertices.
    faces : (m, 3) int
        Triangles (any orientation; degenerate triangles are handled as segments).
    query : (k, 3) float
        Points to measure, same units as ``vertices``.
    bvh : TriangleBVH, optional
        A hierarchy from :func:`build_bvh` for this mesh, to reuse over several calls.
    upper : float or (k,) floats, optional
        Search radius: points with no triangle closer than it get distance ``inf``,
        face -1 and a NaN closest point (faster when only near points matter).

    Returns
    -------
    distance : (k,) float64
        Euclidean distance to the nearest point of the mesh.
    face_index : (k,) int64
        Index (into ``faces``) of a triangle realising it.
    closest : (k, 3) float64
        The closest point on that triangle.
    """
    from recon_cli.mesh import _distance_kernel as K

    q = np.ascontiguousarray(query, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3:
        raise InputError(f"query must have shape (k, 3), got {q.shape}")
    if not np.isfinite(q).all():
        raise InputError("query has non-finite coordinates")
    if upper is None:
        ub = np.full(len(q), np.inf)
    else:
        ub = np.broadcast_to(np.asarray(upper, dtype=np.float64), (len(q),)).copy()
        if np.isnan(ub).any() or (ub < 0).any():
            raise ParameterError("upper must be non-negative")
    if bvh is None:
        bvh = build_bvh(vertices, faces)
    if len(q) == 0:
        return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
    # visit queries in Z-order: neighbours share tree paths (cache) and seed each other
    perm = np.argsort(_morton(q), kind="stable") if len(q) > 1 else np.zeros(len(q), np.int64)
    with dynamic_schedule(1):  # chunks of 256 queries
        d2p, idxp, closestp, _ = K.query_points(
            np.ascontiguousarray(q[perm]), *bvh.arrays(), ub[perm]
        )
    d2 = np.empty_like(d2p)
    idx = np.empty_like(idxp)
    closest = np.empty_like(closestp)
    d2[perm], idx[perm], closest[perm] = d2p, idxp, closestp
    found = idx >= 0
    face = np.full(len(q), -1, np.int64)
    face[found] = bvh.order[idx[found]]
    dist = np.full(len(q), np.inf)
    dist[found] = np.sqrt(d2[found])
    return dist, face, closest


def pseudonormals(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angle-weighted pseudonormals (Baerentzen & Aanaes 2005) per face, edge and corner.

    Returns
    -------
    face : (m, 3) float64
        Unit face normals.
    edge : (m, 3, 3) float64
        For each face, the sum of the normals of the faces sharing its edges ab, ac, bc.
    vertex : (m, 3, 3) float64
        For each face, the angle-weighted normal sum at its corners a, b, c.
    """
    v, f = check_mesh(vertices, faces)
    t = v[f]
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    ln = np.linalg.norm(cross, axis=1, keepdims=True)
    fn = np.zeros_like(cross)
    np.divide(cross, ln, out=fn, where=ln > 0)
    # corner angles
    ang = np.zeros((len(f), 3))
    for c in range(3):
        e1 = t[:, (c + 1) % 3] - t[:, c]
        e2 = t[:, (c + 2) % 3] - t[:, c]
        ang[:, c] = np.arctan2(
            np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2)
        )
    vn = np.zeros((len(v), 3))
    for c in range(3):
        np.add.at(vn, f[:, c], fn * ang[:, c : c + 1])
    pairs = ((0, 1), (0, 2), (1, 2))  # edge order of the kernel: ab, ac, bc
    ek = np.concatenate([np.sort(f[:, list(p)], axis=1) for p in pairs])
    _, inv = np.unique(ek, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    en = np.zeros((inv.max() + 1, 3))
    np.add.at(en, inv, np.tile(fn, (3, 1)))
    edge = en[inv].reshape(3, len(f), 3).transpose(1, 0, 2)
    return fn, np.ascontiguousarray(edge), np.ascontiguousarray(vn[f])


def distance_grid(
    vertices: np.ndarray,
    faces: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    shape: tuple[int, int, int],
    band: float = np.inf,
    pseudonormal: bool = False,
    bvh: TriangleBVH | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Unsigned distance from every grid sample to the mesh.

    Parameters
    ----------
    vertices, faces
        The mesh.
    origin : (3,) float
        World position of sample [0, 0, 0].
    voxel_size : float
        Sample spacing (world units).
    shape : (3,) int
        Samples per axis.
    band : float
        Search radius in world units: samples farther from the mesh get ``band``.
    pseudonormal : bool
        Also return the sign of each sample from the angle-weighted pseudonormal of its
        closest feature (exact for closed, consistently oriented meshes).

    Returns
    -------
    distance : (nx, ny, nz) float64
    sign : (nx, ny, nz) int8 or None
        -1 inside, +1 outside, 0 where farther than ``band`` (only with ``pseudonormal``).
    """
    from recon_cli.mesh import _distance_kernel as K

    v, f = check_mesh(vertices, faces)
    if bvh is None:
        bvh = build_bvh(v, f)
    org = np.asarray(origin, dtype=np.float64).reshape(3)
    shp = np.asarray(shape, dtype=np.int64).reshape(3)
    if pseudonormal:
        fn, en, vn = pseudonormals(v, f)
        o = bvh.order
        fn, en, vn = fn[o], np.ascontiguousarray(en[o]), np.ascontiguousarray(vn[o])
    else:
        fn, en, vn = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3))
    with dynamic_schedule(16):
        dist, sign = K.query_grid(
            org, float(voxel_size), shp, bvh.arrays(), float(band), (fn, en, vn), bool(pseudonormal)
        )
    return dist, (sign if pseudonormal else None)
