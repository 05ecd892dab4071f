"""``recon fit-sdf`` (a neural signed distance field) against our screened Poisson, depth 8.

The issue's targets (section ``learned``): kitten and armadillo, 100k area-uniform samples
with true normals (seed 0), at most 5 minutes of training: F-score at 1 % of the diagonal
>= 0.95 against the true mesh, Chamfer-L1 <= 2x Poisson depth 8's, and |‖∇s‖ − 1| <= 0.1
on >= 90 % of the grid samples within 5 % of the diagonal from the surface (central differences
on the written grid: ``recon info``'s near figure, the kinks of the medial axis left out;
``docs/design/fit-sdf.md`` has the exact distance's figures, the metric's ceiling). A 10 % hole
(the samples nearest to one random surface point, 10 % of them, cut away): Chamfer on the
rest and the distance from the cut-away part of the true surface to the fitted surface.

Chamfer-L1 and F-score as ``bench/quality_poisson.py`` measures them (100k samples of each
surface, seeds 2 and 1). Each method runs once in a forked child (wall time and peak memory
of the whole stage: training, grid at 256^3, marching cubes).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from _util import measure, row

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
N_POINTS = 100_000
N_EVAL = 100_000


def _chamfer_f(a, b, tau):
    from scipy.spatial import cKDTree

    da = cKDTree(b).query(a)[0]
    db = cKDTree(a).query(b)[0]
    p, r = float((da < tau).mean()), float((db < tau).mean())
    return 0.5 * (da.mean() + db.mean()), (2 * p * r / (p + r) if p + r > 0 else 0.0)


def _fit_metrics(cloud, truth, seconds, res, hole=None):
    """Run the fit-sdf stage and measure its mesh (runs in the measured child)."""
    from scipy.spatial import cKDTree

    from recon_cli.geometry import TriangleMesh, bbox_diagonal
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.learned import run_stage

    r = run_stage(cloud, resolution=res, iterations=10**7, max_seconds=seconds, threads=2)
    grid = r.output
    diag = bbox_diagonal(truth.vertices)
    from recon_cli.stages.mcubes import marching_cubes

    v, f, _ = marching_cubes(grid.sdf, spacing=grid.voxel_size, origin=grid.origin)
    mesh = TriangleMesh(vertices=v, faces=f)
    from recon_cli.mesh.topology import report

    topo = report(mesh)
    tsamp = sample_surface(truth, N_EVAL, seed=1).points
    msamp = sample_surface(mesh, N_EVAL, seed=2).points
    out = {
        "iterations": r.report["iterations"],
        "train_s": r.report["train_seconds"],
        "eik": r.report["eikonal_near"]["fraction_within_0.1"],
        "components": topo.get("components"),
        "genus": topo.get("genus"),
        "load": os.getloadavg()[0],
    }
    if hole is None:
        out["chamfer"], out["f1"] = _chamfer_f(msamp, tsamp, 0.01 * diag)
    else:
        centre, radius = hole
        keep = np.linalg.norm(tsamp - centre, axis=1) > radius
        mkeep = np.linalg.norm(msamp - centre, axis=1) > radius
        out["chamfer"], out["f1"] = _chamfer_f(msamp[mkeep], tsamp[keep], 0.01 * diag)
        d = cKDTree(msamp).query(tsamp[~keep])[0]
        out["hole_mean"], out["hole_max"] = float(d.mean() / diag), float(d.max() / diag)
    out["diag"] = diag
    return out


def _poisson_metrics(cloud, truth):
    from recon_cli.geometry import bbox_diagonal
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.poisson import screened_poisson

    m = screened_poisson(cloud.points, cloud.normals, depth=8).mesh
    diag = bbox_diagonal(truth.vertices)
    ch, f1 = _chamfer_f(
        sample_surface(m, N_EVAL, seed=2).points,
        sample_surface(truth, N_EVAL, seed=1).points,
        0.01 * diag,
    )
    return {"chamfer": ch, "f1": f1}


def rows(quick: bool) -> list[dict]:
    """The section's rows: ``recon fit-sdf`` against our screened Poisson at depth 8.

    On kitten (and armadillo) samples: fit-sdf's Chamfer, F-score and eikonal figures against
    Poisson's, each in a forked child; one skipped row when torch is not installed.
    """
    import numba

    numba.config.THREADING_LAYER = "workqueue"
    import importlib.util

    # never import torch here: the measured children must import it themselves (recon sets
    # OMP_WAIT_POLICY=PASSIVE before the import; busy-waiting threads crawl on a loaded CPU)
    if importlib.util.find_spec("torch") is None:
        return [
            {
                "stage": "fit-sdf",
                "case": "skipped: torch not installed (pip install recon[learned])",
            }
        ]
    from recon_cli.io import read_ply
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.poisson import screened_poisson

    seconds = 20.0 if quick else 240.0
    res = 128 if quick else 256
    out = []
    for name in ["kitten"] if quick else ["kitten", "armadillo"]:
        truth = read_ply(DATA / f"{name}.ply")
        cloud = sample_surface(truth, N_POINTS, seed=0)
        screened_poisson(
            cloud.points[:2000], cloud.normals[:2000], depth=5
        )  # compile outside the timing
        ref = measure(lambda cloud=cloud, truth=truth: _poisson_metrics(cloud, truth), repeat=1)
        ours = measure(
            lambda cloud=cloud, truth=truth: _fit_metrics(cloud, truth, seconds, res), repeat=1
        )
        o, p = ours["result"], ref["result"]
        if not isinstance(o, dict) or not isinstance(p, dict):
            out.append({"stage": "fit-sdf", "case": f"{name}: FAILED {o!r} / {p!r}"})
            continue
        ok = o["f1"] >= 0.95 and o["chamfer"] <= 2 * p["chamfer"] and o["eik"] >= 0.9
        note = (
            f"F@1% {o['f1']:.4f} (Poisson {p['f1']:.4f}); Chamfer-L1 "
            f"{o['chamfer'] / o['diag']:.3g} diag = "
            f"{o['chamfer'] / p['chamfer']:.2f}x Poisson d8; eikonal within 0.1 on "
            f"{100 * o['eik']:.1f}% of "
            f"samples within 5% diag (kinks out); {o['iterations']} steps in {o['train_s']:.0f}s "
            f"({o['iterations'] / o['train_s']:.1f}/s, load {o['load']:.1f}); "
            f"{o['components']} component(s), genus {o['genus']}; "
            f"targets F>=0.95, <=2x, >=90%: {'met' if ok else 'NOT met'}"
        )
        out.append(
            row(
                "fit-sdf",
                f"{name} 100k samples + true normals, {seconds:.0f}s training, {res}^3 grid",
                ours,
                "poisson d8 (ours)",
                ref,
                note=note,
            )
        )
        if name == "kitten" or quick:
            rng = np.random.default_rng(3)
            c = cloud.points[rng.integers(len(cloud.points))]
            d = np.linalg.norm(cloud.points - c, axis=1)
            radius = float(np.sort(d)[len(d) // 10])
            holed = cloud.subset(d > radius)
            hm = measure(
                lambda holed=holed, truth=truth, c=c, radius=radius: _fit_metrics(
                    holed, truth, min(seconds, 150.0), res, hole=(c, radius)
                ),
                repeat=1,
            )
            h = hm["result"]
            if isinstance(h, dict):
                note = (
                    f"hole radius {radius / h['diag']:.3f} diag; Chamfer-L1 on the rest "
                    f"{h['chamfer'] / h['diag']:.3g} "
                    f"diag, F@1% {h['f1']:.4f}; cut-away true surface to fitted surface: mean "
                    f"{h['hole_mean']:.3g}, max {h['hole_max']:.3g} diag; {h['components']} "
                    "component(s), genus "
                    f"{h['genus']}; {h['iterations']} steps in {h['train_s']:.0f}s"
                )
            else:
                note = f"FAILED {h!r}"
            out.append(
                row(
                    "fit-sdf",
                    f"{name} with a 10% hole, {min(seconds, 150.0):.0f}s training",
                    hm,
                    note=note,
                )
            )
    return out
