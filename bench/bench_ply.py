"""PLY reading: ours vs a bare ``np.fromfile`` of the same bytes, vs Open3D."""

from __future__ import annotations

import os
import tempfile

import numpy as np

from _util import measure, row


def _make_cloud(path: str, n: int) -> None:
    from recon_cli.geometry import PointCloud
    from recon_cli.io.ply import write_ply

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    write_ply(PointCloud(points=pts, normals=nrm, colors=col), path)


def _make_mesh(path: str, n_side: int) -> None:
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.ply import write_ply

    # a grid of n_side^2 vertices, 2 (n_side-1)^2 triangles
    x, y = np.meshgrid(
        np.arange(n_side, dtype=float), np.arange(n_side, dtype=float), indexing="ij"
    )
    v = np.column_stack([x.ravel(), y.ravel(), np.sin(x.ravel() * 0.01)])
    idx = np.arange(n_side * n_side).reshape(n_side, n_side)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    write_ply(TriangleMesh(vertices=v, faces=f), path)


def rows(quick: bool) -> list[dict]:
    """The section's rows: our PLY reader against bare ``np.fromfile`` and Open3D's readers.

    A binary cloud (xyz, normals, rgb) of 1M points (quick: 200k) and a binary grid mesh, each read
    in a forked child.
    """
    import open3d as o3d

    from recon_cli.io.ply import read_ply

    n = 200_000 if quick else 1_000_000
    rep = 3 if quick else 7
    out = []
    with tempfile.TemporaryDirectory() as d:
        cloud = os.path.join(d, "cloud.ply")
        _make_cloud(cloud, n)
        read_ply(
            cloud
        )  # load the (serial, fork-safe) numba gather kernel once, outside the timings
        ours = measure(lambda: len(read_ply(cloud).points), rep)
        bare = measure(lambda: len(np.fromfile(cloud, dtype=np.uint8)), rep)
        o3d_ = measure(lambda: len(o3d.io.read_point_cloud(cloud).points), rep)
        label = f"read {n // 1000}k-point binary cloud (xyz, normals, rgb)"
        out.append(row("ply", label, ours, "np.fromfile (bare bytes)", bare, "target ≤ 2×"))
        out.append(row("ply", label, ours, "open3d.io.read_point_cloud", o3d_, "target < 1×"))
        mesh = os.path.join(d, "mesh.ply")
        side = 400 if quick else 1000
        _make_mesh(mesh, side)
        ours_m = measure(lambda: len(read_ply(mesh).faces), rep)
        o3d_m = measure(lambda: len(o3d.io.read_triangle_mesh(mesh).triangles), rep)
        out.append(
            row(
                "ply",
                f"read {2 * (side - 1) ** 2 // 1000}k-face binary mesh",
                ours_m,
                "open3d.io.read_triangle_mesh",
                o3d_m,
            )
        )
    return out
