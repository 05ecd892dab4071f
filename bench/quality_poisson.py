"""Screened Poisson quality table: ours vs Open3D against the true meshes.

Every mesh in ``../shared/data`` (armadillo, kitten, mug, bunny_zipper), 100k area-uniform
samples with true normals (seed 0), clean and with Gaussian noise sigma = 0.25 % of the
bounding-box diagonal, depth 8 and 9. For each output: Chamfer-L1 to the true mesh (mean
of the two mean nearest-neighbour distances between 100k samples of each, seeds 2 and 1)
and F-score at 0.5 % of the diagonal, as ``tests/test_poisson.py`` measures them. The
issue's bound: Chamfer ratio ours / Open3D <= 1.05 and F ours >= F Open3D - 0.01.

Usage: ``python bench/quality_poisson.py [--depth 8,9] [--mesh armadillo,kitten]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
MESHES = ["armadillo", "kitten", "mug", "bunny_zipper"]
N_POINTS = 100_000
N_EVAL = 100_000
NOISE = 0.0025


def chamfer_f(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[float, float]:
    """Chamfer-L1 (mean of the two mean distances) and F-score at ``tau`` of (n, 3) and (m, 3)."""
    from scipy.spatial import cKDTree

    da = cKDTree(b).query(a)[0]
    db = cKDTree(a).query(b)[0]
    p, r = float((da < tau).mean()), float((db < tau).mean())
    return 0.5 * (da.mean() + db.mean()), (2 * p * r / (p + r) if p + r > 0 else 0.0)


def main(argv: list[str]) -> int:
    """Chamfer and F-score of our Poisson against Open3D's on the shared meshes; 1 on a failure.

    Per mesh, noise and depth (``--mesh``, ``--noise``, ``--depth``), samples of the true surface
    against each mesh, with both wall times; prints a table.
    """
    sys.path.insert(0, str(ROOT))
    from recon_cli.backends import open3d_backend
    from recon_cli.geometry import bbox_diagonal
    from recon_cli.io import read_ply
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.poisson import screened_poisson

    ap = argparse.ArgumentParser()
    ap.add_argument("--depth", default="8,9")
    ap.add_argument("--mesh", default=",".join(MESHES))
    ap.add_argument("--noise", default="0,0.0025")
    args = ap.parse_args(argv)
    depths = [int(d) for d in args.depth.split(",")]
    noises = [float(s) for s in args.noise.split(",")]

    head = (
        f"{'mesh':13s} {'noise':>6s} {'d':>2s} {'CD ours':>10s} {'CD o3d':>10s} {'ratio':>6s} "
        f"{'F ours':>7s} {'F o3d':>7s} {'dF':>7s} {'t ours':>7s} {'t o3d':>7s} ok"
    )
    print(head)
    fails = 0
    for name in args.mesh.split(","):
        truth = read_ply(SHARED / f"{name}.ply")
        tau = 0.005 * bbox_diagonal(truth.vertices)
        tsamp = sample_surface(truth, N_EVAL, seed=1).points
        for noise in noises:
            cloud = sample_surface(truth, N_POINTS, seed=0, noise=noise)
            for depth in depths:
                t0 = time.perf_counter()
                ours = screened_poisson(cloud.points, cloud.normals, depth=depth).mesh
                t1 = time.perf_counter()
                ref = open3d_backend.poisson(cloud, depth=depth, threads=-1)[0]
                t2 = time.perf_counter()
                ch_o, f_o = chamfer_f(sample_surface(ours, N_EVAL, seed=2).points, tsamp, tau)
                ch_r, f_r = chamfer_f(sample_surface(ref, N_EVAL, seed=2).points, tsamp, tau)
                ok = ch_o <= 1.05 * ch_r and f_o >= f_r - 0.01
                fails += not ok
                print(
                    f"{name:13s} {noise:6.4f} {depth:2d} {ch_o:10.4g} {ch_r:10.4g} "
                    f"{ch_o / ch_r:6.3f} "
                    f"{f_o:7.4f} {f_r:7.4f} {f_o - f_r:+7.4f} {t1 - t0:7.2f} {t2 - t1:7.2f} "
                    f"{'yes' if ok else 'NO'}",
                    flush=True,
                )
    print(f"{fails} case(s) outside the bound")
    return 1 if fails else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
