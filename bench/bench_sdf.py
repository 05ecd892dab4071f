"""Signed distance grids: ours (BVH + winding number) vs Open3D ``RaycastingScene``.

The issue's target is the 256^3 row: ``recon sdf`` no slower than Open3D's
``compute_signed_distance`` on the same mesh and grid. Ours is the whole stage
(:func:`recon_cli.stages.sdf.run_stage`: grid frame, BVH, exact distances, sign, float32 grid
and the eikonal report); Open3D's is the scene build plus the query, with the float32
sample coordinates it needs made inside the timed call (its API takes explicit points).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _util import measure, row

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# what --sign winding does on the (closed, oriented) bench meshes: see report["sign_method"]
CLOSED = "closed mesh: exact sign, one winding number per class of samples (report['regions'])"


def _points32(origin, h, shape) -> np.ndarray:
    """All sample coordinates, (n, 3) float32, in the grid's C order."""
    axes = [(origin[a] + h * np.arange(shape[a])).astype(np.float32) for a in range(3)]
    out = np.empty((*shape, 3), np.float32)
    for a in range(3):
        view = [None, None, None]
        view[a] = slice(None)
        out[..., a] = axes[a][tuple(view)]
    return out.reshape(-1, 3)


def _grid_rows(mesh, label: str, res: int, repeat: int) -> list[dict]:
    """Our whole sdf stage against Open3D's signed distance on the same res^3 grid.

    Two rows: --sign winding and pseudonormal.
    """
    from recon_cli.backends.open3d_backend import signed_distance
    from recon_cli.stages.sdf import grid_frame, run_stage

    v = mesh.vertices
    o, h, s = grid_frame(v.min(0), v.max(0), res)

    def ours_fn(sign):
        return lambda: float(
            np.abs(run_stage(mesh, resolution=res, sign=sign).output.sdf).sum(dtype=np.float64)
        )

    ref = measure(
        lambda: float(np.abs(signed_distance(mesh, _points32(o, h, s))).sum()), repeat=repeat
    )
    ours = measure(ours_fn("winding"), repeat=repeat)
    ours_pn = measure(ours_fn("pseudonormal"), repeat=repeat)
    case = f"{label}, {res}^3 grid ({'x'.join(map(str, s))} = {int(np.prod(s)) / 1e6:.1f}M samples)"
    target = "; issue target: time ratio <= 1" if res == 256 else ""
    note = "RaycastingScene.compute_signed_distance" + target + "; " + CLOSED
    return [
        row("sdf", case + " --sign winding", ours, "open3d", ref, note=note),
        row("sdf", case + " --sign pseudonormal", ours_pn, "open3d", ref, note=target.lstrip("; ")),
    ]


def rows(quick: bool) -> list[dict]:
    """The section's rows: our sdf stage and closest points against Open3D's, in-process.

    The armadillo at 128^3 and 256^3 (quick: 64^3), the mug at 256^3, and closest points of random
    queries (the API ``recon diff`` uses).
    """
    import numba

    # measurements fork after the warm-up: GNU OpenMP (numba's default layer here) aborts
    # on fork, the workqueue layer does not (must be chosen before the first parallel call)
    numba.config.THREADING_LAYER = "workqueue"
    from recon_cli.backends.open3d_backend import unsigned_distance
    from recon_cli.io import read_ply
    from recon_cli.mesh.distance import closest_points
    from recon_cli.stages.sdf import run_stage

    mesh = read_ply(DATA / "armadillo.ply")
    v, f = mesh.vertices, mesh.faces
    # compile / load the numba cache outside the timings
    run_stage(mesh, resolution=8)
    run_stage(mesh, resolution=8, sign="pseudonormal")
    out = []
    for res in [64] if quick else [128, 256]:
        out += _grid_rows(
            mesh, "armadillo 50k faces", res, 1 if res >= 256 else (2 if quick else 3)
        )
    if not quick:
        # a small mesh with large triangles (10k faces): Open3D's per-sample cost falls with
        # the face count faster than ours does, so this is the harder comparison
        mug = read_ply(DATA / "mug.ply")
        run_stage(mug, resolution=8)
        out += _grid_rows(mug, "mug 10k faces", 256, 1)
    # closest points on random queries (the API `recon diff` uses)
    rng = np.random.default_rng(0)
    lo, hi = v.min(0), v.max(0)
    k = 200_000 if quick else 1_000_000
    q = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), size=(k, 3))
    ours = measure(lambda: float(closest_points(v, f, q)[0].sum()), repeat=2)
    ref = measure(lambda: float(unsigned_distance(mesh, q).sum()), repeat=2)
    out.append(
        row(
            "distance",
            f"closest_points {k} queries, armadillo",
            ours,
            "open3d",
            ref,
            note="compute_distance",
        )
    )
    return out
