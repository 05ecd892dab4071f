"""Analytic shapes for tests: meshes with exact distances, volumes and insides."""

from __future__ import annotations

import numpy as np


def box_mesh(lo=(0.0, 0.0, 0.0), hi=(1.0, 2.0, 3.0)):
    """An axis-aligned box as 12 outward triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[(hi if (c >> a) & 1 else lo)[a] for a in range(3)] for c in range(8)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    return v, np.array(f, dtype=np.int64)


def box_distance(p, lo, hi):
    """Signed distance of points ``p`` (n, 3) to the box [lo, hi], negative inside."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    q = np.maximum(lo - p, 0) + np.maximum(p - hi, 0)
    outside = np.linalg.norm(q, axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    return np.where((q > 0).any(axis=1), outside, inside)


def sphere_cloud(n=5000, radius=1.0, centre=(0.0, 0.0, 0.0), seed=0):
    """``n`` points uniform on a sphere and their outward unit normals."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre, float) + radius * d, d


def torus_cloud(n=5000, major=1.0, minor=0.35, center=(0.0, 0.0, 0.0), seed=0):
    """``n`` points on a torus around z (area-uniform) and their outward unit normals."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 2 * np.pi, 4 * n)
    v = rng.uniform(0, 2 * np.pi, 4 * n)
    # area element ~ (major + minor cos v): rejection sampling
    keep = rng.uniform(0, major + minor, 4 * n) < major + minor * np.cos(v)
    u, v = u[keep][:n], v[keep][:n]
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    ring = np.stack([major * np.cos(u), major * np.sin(u), np.zeros_like(u)], axis=1)
    return np.asarray(center, float) + ring + minor * nrm, nrm


def torus_distance(p, major=1.0, minor=0.35, center=(0.0, 0.0, 0.0)):
    """Signed distance to the torus of :func:`torus_cloud` (negative inside)."""
    q = np.asarray(p, float) - np.asarray(center, float)
    ring = np.hypot(q[:, 0], q[:, 1]) - major
    return np.hypot(ring, q[:, 2]) - minor


# --- generated closed meshes (families for sign and topology invariants) ---------------


def icosphere(subdivisions: int = 2, radius: float = 1.0, centre=(0.0, 0.0, 0.0)):
    """A closed, outward sphere: the icosahedron split ``subdivisions`` times, projected."""
    t = (1.0 + 5**0.5) / 2
    v = [
        (-1, t, 0),
        (1, t, 0),
        (-1, -t, 0),
        (1, -t, 0),
        (0, -1, t),
        (0, 1, t),
        (0, -1, -t),
        (0, 1, -t),
        (t, 0, -1),
        (t, 0, 1),
        (-t, 0, -1),
        (-t, 0, 1),
    ]
    f = [
        (0, 11, 5),
        (0, 5, 1),
        (0, 1, 7),
        (0, 7, 10),
        (0, 10, 11),
        (1, 5, 9),
        (5, 11, 4),
        (11, 10, 2),
        (10, 7, 6),
        (7, 1, 8),
        (3, 9, 4),
        (3, 4, 2),
        (3, 2, 6),
        (3, 6, 8),
        (3, 8, 9),
        (4, 9, 5),
        (2, 4, 11),
        (6, 2, 10),
        (8, 6, 7),
        (9, 8, 1),
    ]
    v = np.array(v, float)
    f = np.array(f, np.int64)
    for _ in range(subdivisions):
        v, f = _midpoint_split(v, f)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v / np.linalg.norm(v, axis=1, keepdims=True) * radius + np.asarray(centre, float)
    return v, f


def _midpoint_split(v, f):
    """Each triangle into four (shared edge midpoints)."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1)
    mid = len(v) + inv  # midpoints of ab, bc, ca
    v = np.concatenate([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
    a, b, c = f.T
    ab, bc, ca = mid
    f = np.concatenate(
        [np.stack(x, axis=1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    )
    return v, f


def torus(R: float = 1.0, r: float = 0.3, nu: int = 32, nv: int = 12):
    """A closed, outward torus around z (genus 1), ``nu`` x ``nv`` quads split in two."""
    u = np.arange(nu) * 2 * np.pi / nu
    w = np.arange(nv) * 2 * np.pi / nv
    U, W = np.meshgrid(u, w, indexing="ij")
    rho = R + r * np.cos(W)
    v = np.stack([rho * np.cos(U), rho * np.sin(U), r * np.sin(W)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    f = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return v, f.astype(np.int64)


def implicit_mesh(fn, n: int = 48, lim: float = 1.2):
    """A closed, outward mesh of the zero set of ``fn(X, Y, Z)``, negative inside.

    Our marching cubes at n^3.
    """
    from recon_cli.stages.mcubes import marching_cubes

    x = np.linspace(-lim, lim, n)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    v, f, _ = marching_cubes(fn(X, Y, Z), spacing=x[1] - x[0], origin=(-lim,) * 3)
    return v, f


def dumbbell_fn(X, Y, Z, rod: float = 0.06):
    """Two balls joined by a thin rod of radius ``rod`` (a thin part)."""
    b1 = np.sqrt((X + 0.6) ** 2 + Y**2 + Z**2) - 0.4
    b2 = np.sqrt((X - 0.6) ** 2 + Y**2 + Z**2) - 0.4
    cyl = np.maximum(np.sqrt(Y**2 + Z**2) - rod, np.abs(X) - 0.7)
    return np.minimum(np.minimum(b1, b2), cyl)


def bent_sheet_fn(X, Y, Z, half: float = 0.03):
    """A curved slab of half-thickness ``half`` (thinner than most test voxels)."""
    s = Z - 0.4 * np.sin(2.0 * X)
    return np.maximum(np.abs(s) - half, np.maximum(np.abs(X), np.abs(Y)) - 0.9)


def thin_box(thickness: float = 0.01):
    """A flat plate (12 triangles) much thinner than a voxel."""
    return box_mesh((-1.0, -0.7, -thickness / 2), (1.0, 0.7, thickness / 2))


def hollow_ball():
    """Outer sphere outward, inner sphere inward (a cavity: winding 0 inside it)."""
    v1, f1 = icosphere(3, 1.0)
    v2, f2 = icosphere(2, 0.6)
    return np.concatenate([v1, v2]), np.concatenate([f1, f2[:, ::-1] + len(v1)])


def nested_and_apart():
    """Three shells: a ball, a ball inside a cavity of a bigger one, and one far away."""
    pieces = [
        icosphere(2, 1.0),
        (lambda v, f: (v, f[:, ::-1]))(*icosphere(2, 0.8)),
        icosphere(1, 0.3),
        icosphere(2, 0.5, (2.5, 0.3, 0.0)),
    ]
    v, f, n = [], [], 0
    for pv, pf in pieces:
        v.append(pv)
        f.append(pf + n)
        n += len(pv)
    return np.concatenate(v), np.concatenate(f)


def random_rotation(rng) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3), det +1."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def transformed(v, rng, scale: float = 1.0, offset=(0.0, 0.0, 0.0), rotate: bool = True):
    """``v`` randomly rotated about its centroid (unless not ``rotate``), scaled and moved."""
    c = v.mean(axis=0)
    r = random_rotation(rng) if rotate else np.eye(3)
    return (v - c) @ r.T * scale + np.asarray(offset, float)


def sliver_splits(v, f, rng, fraction: float = 0.3, eps: float = 1e-9):
    """Near-degenerate remesh of a closed mesh, still closed and consistently oriented.

    A ``fraction`` of the triangles get a new vertex ``eps`` (relative) off the middle of one of
    their edges, inside the triangle, and are split into three (one a sliver of height ~eps), and up
    to 300 edges are split ``eps`` from one end (two needles each).
    """
    v = np.array(v, float)
    f = np.array(f, np.int64)
    # 1. interior points near an edge: (a, b, c) -> (a, b, p), (b, c, p), (c, a, p)
    pick = rng.random(len(f)) < fraction
    a, b, c = f[pick].T
    w = np.stack(
        [np.full(len(a), 0.5 - eps / 2), np.full(len(a), 0.5 - eps / 2), np.full(len(a), eps)],
        axis=1,
    )
    p = w[:, :1] * v[a] + w[:, 1:2] * v[b] + w[:, 2:] * v[c]
    pi = len(v) + np.arange(len(a))
    v = np.concatenate([v, p])
    f = np.concatenate(
        [f[~pick], np.stack([a, b, pi], 1), np.stack([b, c, pi], 1), np.stack([c, a, pi], 1)]
    )
    # 2. edge splits eps from an end: both triangles of the edge split in two
    n_split = min(300, int(fraction * len(f) / 4))
    for _ in range(n_split):
        t = rng.integers(len(f))
        k = rng.integers(3)
        ea, eb = f[t, k], f[t, (k + 1) % 3]
        # the other triangle has the directed edge eb -> ea
        other = np.flatnonzero(
            ((f[:, 0] == eb) & (f[:, 1] == ea))
            | ((f[:, 1] == eb) & (f[:, 2] == ea))
            | ((f[:, 2] == eb) & (f[:, 0] == ea))
        )
        if len(other) != 1:
            continue
        s = eps if rng.random() < 0.5 else 1 - eps
        m = len(v)
        v = np.concatenate([v, (v[ea] + s * (v[eb] - v[ea]))[None]])
        new = []
        for tri, (x, y) in ((t, (ea, eb)), (other[0], (eb, ea))):
            r = list(f[tri])
            i = next(i for i in range(3) if r[i] == x and r[(i + 1) % 3] == y)
            z = r[(i + 2) % 3]
            f[tri] = (x, m, z)
            new.append((m, y, z))
        f = np.concatenate([f, np.array(new, np.int64)])
    return v, f


def cut_sphere(rng, subdivisions: int = 4, cap_height: float = 0.35):
    """A sphere and a copy with a cap cut away, randomly rotated, scaled and moved.

    Offsets up to 1e6.

    Returns
    -------
    reference, candidate : TriangleMesh
        The closed sphere and the one without the faces whose centroid is within
        ``cap_height`` (fraction of the radius) of the pole ``direction``.
    direction : (3,) unit vector from the centre to the missing cap's pole
    center : (3,), radius : float
    """
    import trimesh

    from recon_cli.geometry import TriangleMesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    rot = random_rotation(rng)
    radius = float(10.0 ** rng.uniform(-2, 2))
    center = rng.choice([0.0, 1.0, 1e3, 1e6]) * rng.uniform(-1, 1, size=3)
    keep = v[f].mean(axis=1)[:, 2] < 1.0 - cap_height
    world = center + radius * v @ rot.T
    ref = TriangleMesh(world, f, point_dtype=np.float64)
    cand = TriangleMesh(world.copy(), f[keep], point_dtype=np.float64)
    return ref, cand, rot[:, 2].copy(), center, radius


# ---- generated oriented point clouds (surfaces given by exact signed distances) ----------
def _project(sdf, p, iters=4, h=1e-6):
    """Move ``p`` onto the zero set of ``sdf`` along its gradient: (points, unit normals)."""
    for _ in range(iters):
        g = np.stack([(sdf(p + h * e) - sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        p = p - sdf(p)[:, None] * g
    g = np.stack([(sdf(p + h * e) - sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    return p, g / np.linalg.norm(g, axis=1, keepdims=True)


def sphere_sdf(p, radius=1.0):
    """Signed distance to the sphere of ``radius`` about the origin, negative inside."""
    return np.linalg.norm(p, axis=1) - radius


def torus_sdf(p, major=1.0, minor=0.35):
    """Signed distance to a torus about z (``major``, ``minor`` radii), negative inside."""
    q = np.stack([np.hypot(p[:, 0], p[:, 1]) - major, p[:, 2]], axis=1)
    return np.linalg.norm(q, axis=1) - minor


def rounded_box_sdf(p, half=(1.0, 0.7, 0.5), radius=0.15):
    """Signed distance to a box of half sizes ``half`` with edges rounded by ``radius``."""
    q = np.abs(p) - (np.asarray(half) - radius)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0) - radius


def thin_plate_sdf(p):
    """A rounded plate 0.08 thick: a thin part (a few finest cells at depth 7)."""
    return rounded_box_sdf(p, half=(1.0, 0.8, 0.04), radius=0.03)


def plate_with_hole_sdf(p):
    """A rounded slab with a round hole through it."""
    slab = rounded_box_sdf(p, half=(1.0, 1.0, 0.25), radius=0.1)
    hole = 0.4 - np.hypot(p[:, 0], p[:, 1])
    return np.maximum(slab, hole)


SHAPES = {
    "sphere": (sphere_sdf, 1.1),
    "torus": (torus_sdf, 1.4),
    "rounded_box": (rounded_box_sdf, 1.1),
    "thin_plate": (thin_plate_sdf, 1.1),
    "plate_with_hole": (plate_with_hole_sdf, 1.1),
}


def shape_cloud(name: str, n: int, rng, *, rotate=True, scale=1.0, offset=0.0):
    """``n`` points near-uniform on a shape of :data:`SHAPES` with outward normals, moved at random.

    Randomly rotated, scaled and offset; the surface is found by projecting uniform points of its
    bounding cube along the distance's gradient.
    """
    sdf, ext = SHAPES[name]
    pts = np.zeros((0, 3))
    nrm = np.zeros((0, 3))
    while len(pts) < n:
        p = rng.uniform(-ext, ext, size=(4 * n, 3))
        # keep the points near the surface: projection from far away clusters them
        p = p[np.abs(sdf(p)) < 0.1]
        p, g = _project(sdf, p)
        ok = np.abs(sdf(p)) < 1e-6
        pts, nrm = np.concatenate([pts, p[ok]]), np.concatenate([nrm, g[ok]])
    pts, nrm = pts[:n], nrm[:n]
    if rotate:
        rot = random_rotation(rng)
        pts, nrm = pts @ rot.T, nrm @ rot.T
    return pts * scale + offset, nrm


def single_view_scan(name: str, rays: int, rng, direction=(0.0, 0.0, -1.0)):
    """A partial scan: a shape's first hits of parallel rays, with outward normals.

    The rays (a ``rays`` x ``rays`` grid, jittered) are cast along ``direction`` at a shape of
    :data:`SHAPES`; an open surface, as a single-view depth sensor sees it.
    """
    sdf, ext = SHAPES[name]
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    s = np.linspace(-ext, ext, rays)
    a, b = np.meshgrid(s, s, indexing="ij")
    jit = rng.uniform(-0.3, 0.3, size=(2,) + a.shape) * (s[1] - s[0])
    o = (a + jit[0]).reshape(-1, 1) * u + (b + jit[1]).reshape(-1, 1) * v - 2 * ext * d
    t = np.zeros(len(o))
    hit = np.zeros(len(o), bool)
    for _ in range(200):  # sphere tracing
        f = sdf(o + t[:, None] * d)
        hit |= f < 1e-7
        t = np.where(hit, t, t + f)
    p = o + t[:, None] * d
    p = p[hit & (t < 4 * ext)]
    return _project(sdf, p)


# offsets at which coordinates lose digits in float32 (and in naive float64 formulas): none,
# 1e6 on every axis, and UTM-like easting/northing (x ~ 5.1e5, y ~ 5.1e6, z ~ 2e2)
FAR_OFFSETS = {
    "origin": (0.0, 0.0, 0.0),
    "1e6": (1e6, 1e6, 1e6),
    "utm": (512345.678, 5123456.789, 234.5),
}


def mesh_family(seed, dtype=np.float64):
    """A torus under a random rotation, scale (1e-3 .. 1e3) and offset (up to 1e6), in ``dtype``.

    Returns a :class:`recon_cli.geometry.TriangleMesh` (random per-vertex normals and uint8
    colours on odd seeds).
    """
    from recon_cli.geometry import TriangleMesh

    rng = np.random.default_rng(seed)
    v, f = torus(nu=int(rng.integers(5, 30)), nv=int(rng.integers(4, 16)))
    scale = 10.0 ** rng.uniform(-3, 3)
    offset = rng.uniform(-1, 1, 3) * 10.0 ** rng.integers(0, 7)
    v = (v @ random_rotation(rng).T) * scale + offset
    normals = colors = None
    if seed % 2:
        normals = rng.normal(size=v.shape)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals.astype(dtype)
        colors = rng.integers(0, 256, size=(len(v), 3)).astype(np.uint8)
    return TriangleMesh(
        vertices=v.astype(dtype), faces=f, normals=normals, colors=colors, point_dtype=dtype
    )


def cloud_family(seed, n=500):
    """A :class:`recon_cli.geometry.PointCloud` on a moved ellipsoid with every kind of property.

    Points on a rotated, scaled, offset (up to 1e6) ellipsoid with unit normals, uint8 colours and
    attributes ``intensity`` (int64) and ``curvature`` (float64).
    """
    from recon_cli.geometry import PointCloud

    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    R = random_rotation(rng)
    scale = 10.0 ** rng.uniform(-2, 3)
    pts = (d * [1.0, 0.5, 0.3]) @ R.T * scale + rng.uniform(-1, 1, 3) * 10.0 ** rng.integers(0, 7)
    normals = (d / [1.0, 0.5, 0.3]) @ R.T
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    attrs = {"intensity": rng.integers(0, 4096, n).astype(np.int64), "curvature": rng.random(n)}
    return PointCloud(
        points=pts, normals=normals, colors=colors, attributes=attrs, point_dtype=np.float64
    )
