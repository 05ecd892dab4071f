"""A distributed Poisson slab's memory per point: the figure behind ``SLAB_BYTES_PER_POINT``.

``python bench/slab_memory.py N DEPTH SLABS [WORKERS]``: noisy armadillo samples (0.25 % of
the diagonal, as ``bench_distributed.py``) in a binary PLY, then ``recon poisson --workers
WORKERS --partitions SLABS`` as a process. A worker's peak is the report's (each step's
``VmHWM``: ``distributed.phases``), its whole resident memory (imports, compiled kernels,
Dask) as a memory limit counts it; the idle figure is a worker's peak in the ``scan`` phase
(imports and one chunk). Prints one line: the largest worker peak, the slab's own and read
points (the largest slab), the bytes per own point, wall seconds and the load average.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))


def main(n: int, depth: int, slabs: int, workers: int = 2) -> dict:
    """Peak memory of ``recon poisson`` in ``slabs`` slabs on ``workers`` workers, as a process.

    On ``n`` noisy armadillo samples at ``depth``; the row gives the largest step's peak, the idle
    worker's and the points each slab owns and reads.
    """
    from recon_cli.io.load import save
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.sampling import sample_surface

    with tempfile.TemporaryDirectory(prefix="slab-memory-") as folder:
        src = os.path.join(folder, f"armadillo_{n}.ply")
        save(sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0, noise=0.0025), src)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "recon_cli.cli.main", "poisson", src]
            + [os.path.join(folder, "m.ply"), "--depth", str(depth), "--workers", str(workers)]
            + ["--partitions", str(slabs), "--json", "-q"],
            capture_output=True,
            text=True,
        )
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()[0]
    if proc.returncode:
        sys.exit(proc.stderr)
    rep = json.loads(proc.stdout)["distributed"]
    phases = rep["phases"]
    peak = max(p["peak_mb_max"] for k, p in phases.items() if k not in ("scan", "sort"))
    idle = phases["scan"]["peak_mb_max"]
    own = max(s["points"] for s in rep["slabs"])
    read = max(s["points_read"] for s in rep["slabs"])
    out = {
        "points": n,
        "depth": depth,
        "slabs": slabs,
        "workers": workers,
        "worker_peak_mib": round(peak),
        "worker_idle_mib": round(idle),
        "own_points": own,
        "read_points": read,
        "bytes_per_own_point": round(peak * 2**20 / own),
        "bytes_per_own_point_above_idle": round((peak - idle) * 2**20 / own),
        "largest_step": max(
            (k for k in phases if k not in ("scan", "sort")), key=lambda k: phases[k]["peak_mb_max"]
        ),
        "wall_s": round(wall),
        "load": f"{load0:.1f}-{load1:.1f}",
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
