"""Test-only stages for tests/test_batch.py, registered through ``run_batch(extra_stages=...)``.

They must be importable in Dask worker processes too: the batch tests pass them as
``"_batch_stages:<function>"`` and put this folder on the workers' ``sys.path`` (spawned
workers inherit the parent's ``sys.path``).
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np

from recon_cli.errors import StageFailed
from recon_cli.geometry import TriangleMesh
from recon_cli.grid import Grid
from recon_cli.stages import StageResult

EXTRA_STAGES = {
    "t_centre": "_batch_stages:centre",
    "t_sleep": "_batch_stages:sleep",
    "t_grid": "_batch_stages:to_grid",
}


def _copy_with(data, vertices):
    if isinstance(data, TriangleMesh):
        out = data.copy()
        out.vertices = vertices
        return out
    out = data.copy()
    out.points = vertices
    return out


def centre(data, *, fail_above: int = 0, die_below: int = 0, progress=None) -> StageResult:
    """Translate the vertices so their mean is the origin.

    ``fail_above`` > 0: raise StageFailed when the input has more vertices than that.
    ``die_below`` > 0: kill the own process (SIGKILL) when it has fewer vertices than that.
    """
    v = np.asarray(data.vertices, dtype=np.float64)
    if fail_above and len(v) > fail_above:
        raise StageFailed(f"t_centre: {len(v)} vertices is more than fail-above={fail_above}")
    if die_below and len(v) < die_below:
        os.kill(os.getpid(), signal.SIGKILL)
    mean = v.mean(axis=0)
    out = _copy_with(data, v - mean)
    return StageResult(output=out, report={"vertices": int(len(v)), "shift": (-mean).tolist()})


def sleep(data, *, seconds: float = 0.0, marker_dir: str = "", progress=None) -> StageResult:
    """Sleep; first drop ``marker_dir/<vertices>-<pid>`` so a test can find (and kill) us."""
    if marker_dir:
        path = os.path.join(marker_dir, f"{len(data.vertices)}-{os.getpid()}")
        with open(path, "w") as f:
            f.write(str(os.getpid()))
    time.sleep(float(seconds))
    return StageResult(output=data.copy(), report={"slept": float(seconds)})


def to_grid(data, *, n: int = 8, progress=None) -> StageResult:
    """A small grid: distance from each sample to the vertex centroid minus the mean radius."""
    v = np.asarray(data.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    voxel = float((hi - lo).max()) / (int(n) - 1)
    idx = np.stack(np.meshgrid(*(np.arange(int(n)),) * 3, indexing="ij"), axis=-1)
    pos = lo + idx * voxel
    c = v.mean(axis=0)
    r = np.linalg.norm(v - c, axis=1).mean()
    sdf = np.linalg.norm(pos - c, axis=-1) - r
    return StageResult(
        output=Grid(sdf=sdf, origin=lo, voxel_size=voxel, history=list(data.history)),
        report={"grid_shape": [int(n)] * 3},
    )


__all__ = ["EXTRA_STAGES", "centre", "sleep", "to_grid"]
