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
    lo, hi = np.asarray(lo), np.asarray(hi)
    q = np.maximum(lo - p, 0) + np.maximum(p - hi, 0)
    outside = np.linalg.norm(q, axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    return np.where((q > 0).any(axis=1), outside, inside)


def random_rotation(rng) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3), det +1."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def cut_sphere(rng, subdivisions: int = 4, cap_height: float = 0.35):
    """A sphere and a copy with a cap cut away, randomly rotated, scaled and moved (offsets up to 1e6).

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
    """Move ``p`` onto the zero set of ``sdf`` along its gradient; returns (points, unit normals)."""
    for _ in range(iters):
        g = np.stack([(sdf(p + h * e) - sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        p = p - sdf(p)[:, None] * g
    g = np.stack([(sdf(p + h * e) - sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    return p, g / np.linalg.norm(g, axis=1, keepdims=True)


def sphere_sdf(p, radius=1.0):
    return np.linalg.norm(p, axis=1) - radius


def torus_sdf(p, major=1.0, minor=0.35):
    q = np.stack([np.hypot(p[:, 0], p[:, 1]) - major, p[:, 2]], axis=1)
    return np.linalg.norm(q, axis=1) - minor


def rounded_box_sdf(p, half=(1.0, 0.7, 0.5), radius=0.15):
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
    """``n`` points near-uniform on a shape of :data:`SHAPES` with their outward normals,
    randomly rotated, scaled and offset (the surface is found by projecting uniform points
    of its bounding cube along the distance's gradient)."""
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
    """A partial scan: the first hits of parallel rays (a ``rays`` x ``rays`` grid, jittered)
    cast along ``direction`` at a shape of :data:`SHAPES`, with outward normals; an open
    surface, as a single-view depth sensor sees it."""
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
