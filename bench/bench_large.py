"""Large clouds: the ``normals`` and ``poisson`` stages on 5 million points (issue 9).

The cloud is ``sample_surface`` of the shared armadillo, 5M points, seed 0 (1M with
``--quick``). Rows, each run once in a forked child (``measure(repeat=1)``: the memory column
is that run's own peak RSS above its start, which includes the stage's copy of the input
and its output):

- ``normals`` stage, K=30, default orientation (MST), on the points without their normals;
  no reference (Open3D's ``orient_normals_consistent_tangent_plane`` takes far too long at
  this size, see ``bench_normals``);
- normal *estimation* alone (kNN + PCA, K=30), the first part of the stage's time; no
  reference row: Open3D's ``estimate_normals`` (KNN 30) is not quick at this size (once
  measured several times slower than ours here), ``bench_normals`` compares them at 1M;
- ``poisson`` stage, depth 9, on the points with their true normals; no reference row here
  (``bench_poisson`` compares with Open3D and PyMeshLab at 1M).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# measurements fork: numba's GNU OpenMP layer aborts a child forked after its threads started
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from _util import measure, measure_once, row  # noqa: E402

ROOT = HERE.parent
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
KNN = 30
DEPTH = 9


def _cloud(n: int):
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.sampling import sample_surface

    return sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0)


def _normals_stage(points, true_normals=None) -> dict:
    import numpy as np

    from recon_cli.geometry import PointCloud
    from recon_cli.stages.normals import run_stage

    res = run_stage(PointCloud(points=points), knn=KNN)  # orient: the stage's default (mst)
    out = {k: res.report[k] for k in ("orient", "components", "degenerate")}
    if true_normals is not None:  # a sanity figure: share of normals facing like the true ones
        out["agree"] = round(
            float(np.mean(np.einsum("ij,ij->i", res.output.normals, true_normals) > 0)), 4
        )
    return out


def _estimate_ours(points) -> int:
    from recon_cli.stages.normals import estimate_normals

    nrm, _, deg = estimate_normals(points, knn=KNN)
    return int(deg.sum())


def _poisson_stage(cloud) -> dict:
    from recon_cli.stages.poisson import run_stage

    rep = run_stage(cloud, depth=DEPTH).report
    return {k: rep[k] for k in ("vertices", "faces", "solver_iterations")}


def rows(quick: bool) -> list[dict]:
    """The section's rows: the normals and poisson stages on 5M armadillo points, in-process.

    Each run once in a forked child (quick: 1M points), no reference at this size.
    """
    import numpy as np

    # compile / load the numba caches in a child: the parent starts no numba threads before forking
    warm = np.random.default_rng(0).random((5000, 3))
    measure_once(lambda: (_normals_stage(warm), _poisson_stage(_cloud(5000)))[0])

    n = 1_000_000 if quick else 5_000_000
    cloud = _cloud(
        n
    )  # in the parent: the children share its pages (fork), so only their own work counts
    points = np.ascontiguousarray(cloud.points)
    label = f"armadillo {n / 1e6:g}M points"
    out = []

    ours = measure(lambda: _normals_stage(points, cloud.normals), repeat=1)
    info = ours["result"] if isinstance(ours["result"], dict) else {}
    out.append(
        row(
            "large",
            f"{label}: normals stage knn {KNN}, orient mst",
            ours,
            note=f"no reference (Open3D MST orientation far too slow at this size); {info}",
        )
    )

    est = measure(lambda: _estimate_ours(points), repeat=1)
    out.append(
        row(
            "large",
            f"{label}: normal estimation only, knn {KNN}",
            est,
            note=f"kNN (chunked queries) + PCA, part of the row above; {est['result']} degenerate; "
            "Open3D vs ours at 1M in bench_normals",
        )
    )

    pois = measure(lambda: _poisson_stage(cloud), repeat=1)
    info = pois["result"] if isinstance(pois["result"], dict) else {}
    out.append(
        row(
            "large",
            f"{label}: poisson stage depth {DEPTH}, true normals",
            pois,
            note=f"no reference here (see bench_poisson at 1M); {info}",
        )
    )
    return out


if __name__ == "__main__":  # pragma: no cover
    for r in rows(quick="--quick" in sys.argv):
        print(r)
