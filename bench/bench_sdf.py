"""Signed distance grids: ours (BVH + winding number) vs Open3D ``RaycastingScene``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _util import measure, row

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def rows(quick: bool) -> list[dict]:
    import numba

    # measurements fork after the warm-up: GNU OpenMP (numba's default layer here) aborts
    # on fork, the workqueue layer does not (must be chosen before the first parallel call)
    numba.config.THREADING_LAYER = "workqueue"
    from recon_cli.backends.open3d_backend import signed_distance, unsigned_distance
    from recon_cli.distance import closest_points
    from recon_cli.io import read_ply
    from recon_cli.sdf import grid_frame, grid_points, mesh_sdf

    mesh = read_ply(DATA / "armadillo.ply")
    v, f = mesh.vertices, mesh.faces
    # compile / load the numba cache outside the timings
    o, h, s = grid_frame(v.min(0), v.max(0), 8)
    mesh_sdf(v, f, o, h, s)
    mesh_sdf(v, f, o, h, s, sign="pseudonormal")
    out = []
    for res in ([64] if quick else [128, 256]):
        o, h, s = grid_frame(v.min(0), v.max(0), res)
        pts = grid_points(o, h, s)
        repeat = 1 if res >= 256 else (2 if quick else 3)
        ours = measure(lambda: float(np.abs(mesh_sdf(v, f, o, h, s)[0]).sum()), repeat=repeat)
        ours_pn = measure(lambda: float(np.abs(mesh_sdf(v, f, o, h, s, sign="pseudonormal")[0]).sum()), repeat=repeat)
        ref = measure(lambda: float(np.abs(signed_distance(mesh, pts)).sum()), repeat=repeat)
        case = f"armadillo 50k faces, {'x'.join(map(str, s))} samples"
        out.append(row("sdf", case + " --sign winding", ours, "open3d", ref, note="RaycastingScene.compute_signed_distance"))
        out.append(row("sdf", case + " --sign pseudonormal", ours_pn, "open3d", ref))
    # closest points on random queries (the API `recon diff` uses)
    rng = np.random.default_rng(0)
    lo, hi = v.min(0), v.max(0)
    k = 200_000 if quick else 1_000_000
    q = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(k, 3))
    ours = measure(lambda: float(closest_points(v, f, q)[0].sum()), repeat=2)
    ref = measure(lambda: float(unsigned_distance(mesh, q).sum()), repeat=2)
    out.append(row("distance", f"closest_points {k} queries, armadillo", ours, "open3d", ref, note="compute_distance"))
    return out
