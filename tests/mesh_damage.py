"""Deliberately damaged meshes for the topology and repair tests (and bench_repair).

Each function returns a new :class:`TriangleMesh`; the intact input is never modified.
"""

from __future__ import annotations

import numpy as np

from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.sampling import face_normals


def _with(m: TriangleMesh, faces: np.ndarray, vertices: np.ndarray | None = None) -> TriangleMesh:
    return TriangleMesh(vertices=m.vertices if vertices is None else vertices, faces=faces)


def flip_faces(m: TriangleMesh, rng, frac: float = 0.05) -> TriangleMesh:
    """Reverse the winding of a random ``frac`` of the faces."""
    f = m.faces.copy()
    i = rng.choice(len(f), max(1, int(frac * len(f))), replace=False)
    f[i] = f[i][:, [0, 2, 1]]
    return _with(m, f)


def duplicate_faces(m: TriangleMesh, rng, k: int = 50) -> TriangleMesh:
    """Append copies of ``k`` random faces, some reversed, some rotated."""
    i = rng.choice(len(m.faces), k, replace=False)
    d = m.faces[i].copy()
    d[::2] = d[::2][:, [0, 2, 1]]
    d[1::3] = np.roll(d[1::3], 1, axis=1)
    return _with(m, np.concatenate([m.faces, d]))


def glue_fins(m: TriangleMesh, rng, k: int = 20) -> TriangleMesh:
    """A third face on ``k`` edges of distinct faces: (b, a, new apex above the edge)."""
    he = m.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    sel = rng.choice(len(m.faces), k, replace=False) * 3
    a, b = he[sel, 0], he[sel, 1]
    n, area = face_normals(m.vertices, m.faces)
    apex = 0.5 * (m.vertices[a] + m.vertices[b]) + n[sel // 3] * np.sqrt(area[sel // 3])[:, None]
    v = np.concatenate([m.vertices, apex])
    new = len(m.vertices) + np.arange(k)
    return _with(m, np.concatenate([m.faces, np.stack([b, a, new], 1)]), v)


def remove_patches(
    m: TriangleMesh, rng, k: int = 3, rings: int = 2, min_sep: float = 0.15
) -> TriangleMesh:
    """Remove ``k`` disk-like patches of faces; unreferenced vertices are kept.

    A patch: the faces within ``rings`` rings of a seed vertex, the seeds at least ``min_sep`` times
    the diagonal apart.
    """
    v = m.vertices
    used = np.unique(m.faces)
    diag = np.linalg.norm(v[used].max(0) - v[used].min(0))
    seeds: list[int] = []
    for s in rng.permutation(used):
        if all(np.linalg.norm(v[s] - v[t]) > min_sep * diag for t in seeds):
            seeds.append(int(s))
            if len(seeds) == k:
                break
    mark = np.zeros(len(v), dtype=bool)
    mark[seeds] = True
    for _ in range(rings - 1):
        mark[m.faces[mark[m.faces].any(axis=1)].ravel()] = True
    return _with(m, m.faces[~mark[m.faces].any(axis=1)])


def split_vertices(m: TriangleMesh, rng, frac: float = 0.02) -> TriangleMesh:
    """Give a random ``frac`` of the faces their own copies of their vertices (a partial soup)."""
    f = m.faces.copy()
    i = rng.choice(len(f), max(1, int(frac * len(f))), replace=False)
    newv = m.vertices[f[i].ravel()]
    f[i] = len(m.vertices) + np.arange(3 * len(i)).reshape(-1, 3)
    return _with(m, f, np.concatenate([m.vertices, newv]))


def two_cones(n: int = 16) -> TriangleMesh:
    """Two closed cones (double cones with caps' apexes) joined at one shared tip, outward."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t), np.zeros(n)], 1)
    v = np.concatenate(
        [[[0.0, 0, 0]], ring + [0, 0, 1], ring - [0, 0, 1], [[0, 0, 1.5]], [[0, 0, -1.5]]]
    )
    r1 = 1 + np.arange(n)
    r2 = 1 + n + np.arange(n)
    c1, c2 = 2 * n + 1, 2 * n + 2
    f = []
    for i in range(n):
        j = (i + 1) % n
        f += [[0, r1[i], r1[j]], [c1, r1[j], r1[i]], [0, r2[j], r2[i]], [c2, r2[i], r2[j]]]
    return TriangleMesh(vertices=v, faces=np.array(f))


def tile(m: TriangleMesh, copies: int) -> TriangleMesh:
    """``copies`` translated copies of ``m`` in a row (separate components)."""
    step = 1.1 * (m.vertices.max(0) - m.vertices.min(0))[0]
    v = np.concatenate([m.vertices + [i * step, 0, 0] for i in range(copies)])
    f = np.concatenate([m.faces + i * len(m.vertices) for i in range(copies)])
    return TriangleMesh(vertices=v, faces=f)
