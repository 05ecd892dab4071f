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


def sphere_cloud(n=5000, radius=1.0, center=(0.0, 0.0, 0.0), seed=0):
    """``n`` points uniform on a sphere and their outward unit normals."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center, float) + radius * d, d


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
