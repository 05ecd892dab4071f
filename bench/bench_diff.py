"""``recon diff``: ours vs PyMeshLab's ``get_hausdorff_distance``, both directions.

Two ~1M-face meshes (the Armadillo subdivided twice, 800k faces, and a copy whose vertices
are moved by 0.2 % of the diagonal), 1M area-uniform samples each way. Ours is measured
twice: the whole ``compare_meshes`` (all metrics, topology of both meshes) and the distance
part alone (sampling + exact distances both ways), which is what PyMeshLab computes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from _util import measure, measure_once, row

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint 1-to-4 split of every triangle."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = len(v) + inv.reshape(3, -1).T  # (m, 3): midpoints of edges 01, 12, 20
    v2 = np.vstack([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    f2 = np.concatenate(
        [
            np.column_stack([a, ab, ca]),
            np.column_stack([ab, b, bc]),
            np.column_stack([ca, bc, c]),
            np.column_stack([ab, bc, ca]),
        ]
    )
    return v2, f2


def meshes(levels: int):
    """A subdivided armadillo with 0.2 % of the diagonal of noise, and the clean one.

    Returns (candidate, reference) meshes, subdivided ``levels`` times.
    """
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io import read_ply

    m = read_ply(SHARED / "armadillo.ply")
    v, f = m.vertices, m.faces
    for _ in range(levels):
        v, f = subdivide(v, f)
    ref = TriangleMesh(v, f)
    diag = np.linalg.norm(v.max(0) - v.min(0))
    cand = TriangleMesh(v + np.random.default_rng(1).normal(scale=0.002 * diag, size=v.shape), f)
    return cand, ref


def rows(quick: bool) -> list[dict]:
    """The section's rows: our distances and ``compare_meshes`` against PyMeshLab's Hausdorff.

    Each in a forked child, once, on ``n`` samples each way (200k quick, 1M else) of the noisy and
    clean subdivided armadillo.
    """
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from recon_cli.backends import pymeshlab_backend as pml
    from recon_cli.eval.metrics import compare_meshes, samples_of, surface_distances

    levels = 1 if quick else 2
    n = 200_000 if quick else 1_000_000
    rep = 1  # one 1M-sample run each takes minutes on 2 cores
    cand, ref = meshes(levels)
    # fill numba's on-disk caches in a child of its own (the parent must not start numba's
    # OpenMP threads: every measurement forks)
    measure_once(lambda: compare_meshes(cand, ref, samples=1000)["accuracy"])

    def ours_distances():
        a, _ = samples_of(cand, n, 0)
        b, _ = samples_of(ref, n, 1)
        da, _ = surface_distances(a, ref)
        db, _ = surface_distances(b, cand)
        return {"mean": float(da.mean()), "max": float(max(da.max(), db.max()))}

    def ours_full():
        r = compare_meshes(cand, ref, samples=n, seed=0)
        return {"mean": r["accuracy"], "max": r["hausdorff"]}

    def theirs():
        a = pml.hausdorff(cand, ref, n)
        b = pml.hausdorff(ref, cand, n)
        return {"mean": a["mean"], "max": max(a["max"], b["max"])}

    t_ref = measure(theirs, rep)
    t_dist = measure(ours_distances, rep)
    t_full = measure(ours_full, rep)
    case = f"{len(ref.faces) // 1000}k faces, {n // 1000}k samples each way"

    def note(ours: dict) -> str:
        o, t = ours["result"], t_ref["result"]
        if not isinstance(o, dict) or not isinstance(t, dict):
            return f"target ≤ 0.5×; {o or t}"
        return (
            f"target ≤ 0.5×; mean {o['mean']:.4g} vs {t['mean']:.4g}, max {o['max']:.4g} vs "
            f"{t['max']:.4g}"
        )

    return [
        row(
            "diff",
            f"distances both ways, {case}",
            t_dist,
            "pymeshlab get_hausdorff_distance ×2",
            t_ref,
            note(t_dist),
        ),
        row(
            "diff",
            f"compare_meshes (all metrics + topology), {case}",
            t_full,
            "pymeshlab get_hausdorff_distance ×2",
            t_ref,
            note(t_full),
        ),
    ]


if __name__ == "__main__":
    import json

    print(json.dumps(rows("--quick" in sys.argv), indent=1, default=str))
