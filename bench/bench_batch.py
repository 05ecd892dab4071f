"""``recon batch`` on a LocalCluster vs the same inputs one after the other in one process.

The pipeline is ``normals`` (knn 30, MST orientation) on real scans and area-uniform samples
of the shared meshes. The batch time includes starting and closing the cluster (what a user
waits for); its memory column is the largest per-input peak reported in batch.json above
the worker's footprint at the task's start (``peak_memory_mb - memory_at_start_mb``),
comparable with the reference's peak above its start. A second row times the rerun, which
skips everything.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from _util import measure, row

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))

PIPELINE = '[[stage]]\nname = "normals"\nknn = 30\norient = "mst"\n'


def _inputs(folder: str, quick: bool) -> list[str]:
    from recon_cli.io.ply import read_ply, write_ply
    from recon_cli.mesh.sampling import sample_surface

    paths = []
    for name in ("bunny_scan_000", "stereo_fragment"):
        p = os.path.join(folder, f"{name}.ply")
        write_ply(read_ply(SHARED / f"{name}.ply"), p)
        paths.append(p)
    n = 50_000 if quick else 200_000
    meshes = ("kitten", "armadillo") if quick else ("kitten", "armadillo", "mug", "bunny_zipper")
    for name in meshes:
        cloud = sample_surface(read_ply(SHARED / f"{name}.ply"), n, seed=0)
        cloud.normals = None
        p = os.path.join(folder, f"{name}_{n // 1000}k.ply")
        write_ply(cloud, p)
        paths.append(p)
    return paths


def _sequential(pipe_path: str, paths: list[str], out: str) -> int:
    from recon_cli.io.load import load, save
    from recon_cli.pipeline import load_pipeline, run_pipeline

    pipe = load_pipeline(pipe_path)
    for p in paths:
        result, _ = run_pipeline(pipe, load(p))
        save(result, os.path.join(out, Path(p).stem + ".ply"))
    return len(paths)


def rows(quick: bool) -> list[dict]:
    """The section's row: ``run_batch`` on 2 workers against the same inputs in one process.

    The pipeline's wall time and each task's peak memory above its start, against the inputs run one
    after another in this process.
    """
    from recon_cli.batch import run_batch

    out_rows = []
    with tempfile.TemporaryDirectory() as d:
        data = os.path.join(d, "in")
        os.mkdir(data)
        paths = _inputs(data, quick)
        pipe = os.path.join(d, "p.toml")
        with open(pipe, "w") as f:
            f.write(PIPELINE)
        seq_out = os.path.join(d, "seq")
        os.mkdir(seq_out)
        seq = measure(lambda: _sequential(pipe, paths, seq_out), 1)

        out = os.path.join(d, "out")
        t0 = time.perf_counter()
        summary = run_batch(pipe, paths, out, workers=2, threads_per_worker=1)
        first = time.perf_counter() - t0
        done = [r for r in summary["inputs"] if r["status"] == "ok"]
        peaks = [r["peak_memory_mb"] - r["memory_at_start_mb"] for r in done]
        task_s = sum(r["seconds"] for r in done)
        ours = {"seconds": first, "peak_mb": max(peaks) if peaks else float("nan")}
        label = f"{len(paths)} inputs, normals knn 30 mst, 2 workers x 1 thread"
        out_rows.append(
            row(
                "batch",
                label,
                ours,
                "same inputs sequentially, 1 process",
                seq,
                f"{len(done)}/{len(paths)} ok; tasks {task_s:.1f} s in all (first per worker: "
                f"numba load); wall includes cluster start/stop; MB: largest per-input peak above "
                f"the worker's footprint",
            )
        )
        t0 = time.perf_counter()
        again = run_batch(pipe, paths, out, workers=2, threads_per_worker=1)
        rerun = {"seconds": time.perf_counter() - t0, "peak_mb": float("nan")}
        out_rows.append(
            row(
                "batch",
                f"rerun of the above ({again['counts']['skipped']} skipped)",
                rerun,
                note="no cluster is started when nothing is to do",
            )
        )
        with open(os.path.join(out, "batch.json")) as f:
            json.load(f)
    return out_rows


if __name__ == "__main__":  # pragma: no cover
    sys.path.insert(0, str(ROOT))
    for r in rows(quick="--quick" in sys.argv):
        print(r)
