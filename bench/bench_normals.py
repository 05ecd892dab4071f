"""Benchmark of ``recon normals`` against Open3D.

- estimation, 1M points, K=30: ours (kNN + batched PCA) vs Open3D ``estimate_normals``;
- MST orientation, 200k and 1M points: ours (estimation + orientation) vs Open3D
  ``estimate_normals`` + ``orient_normals_consistent_tangent_plane(10)`` (very slow at 1M:
  measured once);
- orientation accuracy (fraction of points facing the same way as the true normal) per closed
  mesh, clean and noisy (0.25 % of the diagonal), ours vs Open3D with the same K;
- an organized depth image (640x480, quick: 320x240, the tabletop of ``tests/sensors.py`` with
  Kinect-like noise and flying pixels), K=30: ours with neighbours from the pixel grid and
  from the kd-tree vs Open3D ``estimate_normals``; the note gives each one's angle to the
  scene's true normals (mean / median over the points that are not flying pixels).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from _util import measure, measure_once, row  # noqa: E402


def _cloud(name: str, n: int, noise: float):
    from shared_data import sampled_cloud

    return sampled_cloud(name, n, noise)


def _ours(points, knn, orient):
    from recon_cli.geometry import PointCloud
    from recon_cli.stages.normals import run_stage

    return run_stage(PointCloud(points), knn=knn, orient=orient).output.normals


def _o3d(points, knn, orient_k):
    from recon_cli.backends import open3d_backend
    from recon_cli.geometry import PointCloud

    return open3d_backend.estimate_normals(
        PointCloud(points), knn=knn, orient_tangent_plane=orient_k
    )


def _organized(width: int, height: int):
    """A noisy depth image of the tabletop: (points, PixelGrid, true normals, not-flying mask)."""
    from recon_cli.geometry import PixelGrid

    from sensors import DepthCamera, depth_image, exact_image, look_at, tabletop_scene, true_normals

    eye = (0.0, -2.5, 1.2)
    cam = DepthCamera(
        eye=np.array(eye), rotation=look_at(eye, (0, 0.3, 0.2)), width=width, height=height
    )
    scene = tabletop_scene()
    org = depth_image(cam, scene, np.random.default_rng(7)).reshape(-1, 3)
    exact = exact_image(cam, scene).reshape(-1, 3)
    valid = np.isfinite(org).all(axis=1)
    depth = np.linalg.norm(exact[valid] - cam.eye, axis=1)
    sigma = 0.0012 + 0.0019 * (depth - 0.4) ** 2
    flying = np.abs(np.linalg.norm(org[valid] - cam.eye, axis=1) - depth) > 6 * sigma
    grid = PixelGrid(((height, width),), np.flatnonzero(valid))
    return org[valid], grid, true_normals(scene, exact[valid]), ~flying


def _angle_note(normals, truth, keep) -> str:
    a = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", normals, truth)), 0, 1)))[keep]
    return f"{a.mean():.2f}/{np.median(a):.2f} deg"


def rows(quick: bool) -> list[dict]:
    """The section's rows: our normals against Open3D's, in forked children.

    Estimation at K=30, estimation + MST orientation, orientation accuracy per closed mesh and an
    organized depth image (see the module docstring).
    """
    # compile/cache the numba kernels in a child: the parent must not start OpenMP threads
    # before forking the measurements (GNU OpenMP aborts a forked child)
    measure_once(lambda: _ours(np.random.default_rng(0).random((2000, 3)), 30, "mst") is not None)
    out = []
    rep = 1 if quick else 3
    n_est = 200_000 if quick else 1_000_000
    pts = _cloud("armadillo", n_est, 0.0025).points
    ours = measure(lambda: _ours(pts, 30, "none") is not None, repeat=rep)
    ref = measure(lambda: _o3d(pts, 30, None) is not None, repeat=rep)
    out.append(
        row(
            "normals",
            f"estimate {n_est // 1000}k K=30 (armadillo, noisy)",
            ours,
            "open3d estimate_normals",
            ref,
        )
    )

    for n in [200_000] if quick else [200_000, 1_000_000]:
        pts = _cloud("armadillo", n, 0.0025).points
        ours = measure(
            lambda pts=pts: _ours(pts, 10, "mst") is not None, repeat=1 if n >= 1_000_000 else rep
        )
        ref = measure(lambda pts=pts: _o3d(pts, 10, 10) is not None, repeat=1)
        out.append(
            row(
                "normals",
                f"estimate+orient mst {n // 1000}k K=10 (armadillo, noisy)",
                ours,
                "open3d estimate + orient_consistent_tangent_plane(10)",
                ref,
                note="Open3D measured once",
            )
        )

    w, h = (320, 240) if quick else (640, 480)
    pts, grid, truth, keep = _organized(w, h)

    def ours_org(pixels):
        from recon_cli.stages.normals import estimate_normals

        return estimate_normals(pts, knn=30, pixels=grid if pixels else None)[0]

    ref = measure(lambda: _o3d(pts, 30, None), repeat=rep)
    for pixels in (True, False):
        ours = measure(lambda pixels=pixels: ours_org(pixels), repeat=rep)
        out.append(
            row(
                "normals",
                f"estimate organized {w}x{h} ({len(pts) // 1000}k) K=30 "
                + ("pixel grid" if pixels else "kd-tree"),
                ours,
                "open3d estimate_normals",
                ref,
                note="angle to truth mean/median: "
                f"ours {_angle_note(ours['result'], truth, keep)}, "
                f"open3d {_angle_note(ref['result'], truth, keep)}",
            )
        )

    n_acc = 30_000 if quick else 50_000
    for name in ("armadillo", "kitten", "mug"):
        for noise in (0.0, 0.0025):
            c = _cloud(name, n_acc, noise)
            ours = measure(
                lambda c=c: float(
                    (np.einsum("ij,ij->i", _ours(c.points, 30, "mst"), c.normals) > 0).mean()
                ),
                1,
            )
            ref = measure(
                lambda c=c: float(
                    (np.einsum("ij,ij->i", _o3d(c.points, 30, 30), c.normals) > 0).mean()
                ),
                1,
            )
            out.append(
                row(
                    "normals",
                    f"orient accuracy {name} {n_acc // 1000}k {'noisy' if noise else 'clean'} K=30",
                    ours,
                    "open3d tangent plane(30)",
                    ref,
                    note=(
                        f"same-way fraction ours {ours['result']:.5f} vs open3d {ref['result']:.5f}"
                    ),
                )
            )
    return out
