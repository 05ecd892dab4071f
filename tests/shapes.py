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
