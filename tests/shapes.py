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


def random_rotation(rng):
    """A uniformly random rotation matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def torus_mesh(n_major=24, n_minor=12, R=1.0, r=0.3):
    """A closed torus (genus 1) as a triangle grid, outward."""
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    u = 2 * np.pi * i.ravel() / n_major
    v = 2 * np.pi * j.ravel() / n_minor
    verts = np.column_stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)])
    a = (i * n_minor + j).ravel()
    b = (((i + 1) % n_major) * n_minor + j).ravel()
    c = (((i + 1) % n_major) * n_minor + (j + 1) % n_minor).ravel()
    d = (i * n_minor + (j + 1) % n_minor).ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return verts, faces


def mesh_family(seed, dtype=np.float64):
    """A torus under a random rotation, scale (1e-3 .. 1e3) and offset (up to 1e6), in ``dtype``.

    Returns a :class:`recon_cli.geometry.TriangleMesh` (random per-vertex normals and uint8
    colours on odd seeds).
    """
    from recon_cli.geometry import TriangleMesh

    rng = np.random.default_rng(seed)
    v, f = torus_mesh(int(rng.integers(5, 30)), int(rng.integers(4, 16)))
    scale = 10.0 ** rng.uniform(-3, 3)
    offset = rng.uniform(-1, 1, 3) * 10.0 ** rng.integers(0, 7)
    v = (v @ random_rotation(rng).T) * scale + offset
    normals = colors = None
    if seed % 2:
        normals = rng.normal(size=v.shape)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals.astype(dtype)
        colors = rng.integers(0, 256, size=(len(v), 3)).astype(np.uint8)
    return TriangleMesh(vertices=v.astype(dtype), faces=f, normals=normals, colors=colors, point_dtype=dtype)


def cloud_family(seed, n=500):
    """Points on a rotated, scaled, offset (up to 1e6) ellipsoid with unit normals, uint8 colours and
    attributes ``intensity`` (int64) and ``curvature`` (float64): a :class:`recon_cli.geometry.PointCloud`."""
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
    return PointCloud(points=pts, normals=normals, colors=colors, attributes=attrs, point_dtype=np.float64)
