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


# offsets at which coordinates lose digits in float32 (and in naive float64 formulas): none,
# 1e6 on every axis, and UTM-like easting/northing (x ~ 5.1e5, y ~ 5.1e6, z ~ 2e2)
FAR_OFFSETS = {
    "origin": (0.0, 0.0, 0.0),
    "1e6": (1e6, 1e6, 1e6),
    "utm": (512345.678, 5123456.789, 234.5),
}


def sphere_cloud(n, radius=1.0, centre=(0.0, 0.0, 0.0), seed=0):
    """``n`` random points on a sphere and their outward unit normals, float64 (n, 3) each.

    The same ``seed`` gives the same points about any ``centre`` (the offset is added last)."""
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(centre, float) + radius * v, v


def icosphere(subdivisions=3, radius=1.0, centre=(0.0, 0.0, 0.0)):
    """A closed, outward-wound icosphere: (vertices (n, 3) float64, faces (m, 3) int64).

    ``20 * 4**subdivisions`` faces; the vertices lie on the sphere (offset added last)."""
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    verts = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        mid: dict = {}

        def midpoint(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[key] = len(verts) - 1
            return mid[key]

        new = []
        for a, b, c in f:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = new
    return np.asarray(centre, float) + radius * np.array(verts), np.array(f, dtype=np.int64)


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
