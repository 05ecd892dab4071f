"""``recon poisson --workers 2`` (one cloud in slabs on a LocalCluster) vs the single-process solve.

Noisy armadillo samples (0.25 % of the diagonal) in a binary PLY. Ours is the command as a
process (cluster start, the workers reading the file by chunks, the write: what a user
waits for); its memory column is the largest process's peak: the launcher's
``RUSAGE_CHILDREN`` (the coordinator's peak, or a worker's last step's: the coordinator reaps
its workers, and each step resets its worker's high-water mark) or a worker's (the report's
per-phase peaks). The first is not the coordinator's alone: sample ``/proc/<pid>/status`` for
that (the 6.58 GiB "coordinator" of a 4M-point depth-11 run was most likely a worker). The
reference is the single-process :func:`screened_poisson` in-process (forked child, peak
above its start, as every section measures). The note
gives the Chamfer distance to the armadillo of both meshes (exact point-to-triangle, 200k
samples each way) as a ratio, the mesh's topology (closed, manifold, pieces, duplicated
vertices) and where the slabs' time and memory went (the report's phases).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _util import measure, row

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))


def _chamfer(mesh, truth) -> float:
    from recon_cli.mesh.distance import closest_points
    from recon_cli.mesh.sampling import sample_surface

    a = sample_surface(mesh, 200_000, seed=1).points
    b = sample_surface(truth, 200_000, seed=2).points
    d1 = closest_points(truth.vertices, truth.faces, a)[0]
    d2 = closest_points(mesh.vertices, mesh.faces, b)[0]
    return float(d1.mean() + d2.mean())


def _topology(mesh) -> str:
    from recon_cli.mesh.topology import report

    r = report(mesh)
    dup = len(mesh.vertices) - len(np.unique(mesh.vertices, axis=0))
    closed = r["watertight"] and r["edge_manifold"] and r["vertex_manifold"]
    shape = "closed manifold" if closed else "NOT closed manifold"
    return f"{shape}, {r['components']} piece(s), {dup} dup. vertices"


_LAUNCH = (
    "import resource, subprocess, sys\n"
    "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
    "sys.stderr.write(r.stderr)\n"
    "print(r.stdout.rstrip())\n"
    "print('maxrss', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
    "sys.exit(r.returncode)\n"
)


def _case(folder: str, n: int, depth: int) -> dict:
    from recon_cli.io.load import load, save
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.poisson import screened_poisson

    truth = read_ply(SHARED / "armadillo.ply")
    cloud = sample_surface(truth, n, seed=0, noise=0.0025)
    src = os.path.join(folder, f"armadillo_{n}.ply")
    save(cloud, src)
    del cloud

    def single():
        c = load(src)
        return screened_poisson(c.points, c.normals, depth=depth).mesh

    ref = measure(single, 1)
    out = os.path.join(folder, "dist.ply")
    t0 = time.perf_counter()
    # a launcher process whose RUSAGE_CHILDREN sees only the command and its workers
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            _LAUNCH,
            sys.executable,
            "-m",
            "recon_cli.cli.main",
            "poisson",
            src,
            out,
            "--depth",
            str(depth),
            "--workers",
            "2",
            "--json",
            "-q",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    wall = time.perf_counter() - t0
    text, _, maxrss = proc.stdout.rpartition("\nmaxrss ")
    peak = float(maxrss) / 1024.0
    rep = json.loads(text)
    mesh = load(out)
    phases = rep["distributed"]["phases"]
    worker_peak = max(p["peak_mb_max"] for p in phases.values())
    ours = {"seconds": wall, "peak_mb": max(peak, worker_peak)}
    spent = ", ".join(
        f"{k} {p['part_seconds_max']:.0f} s/{p['peak_mb_max']:.0f} MB"
        for k, p in phases.items()
        if p["part_seconds_max"] >= 1.0
    )
    cr = (
        _chamfer(mesh, truth) / _chamfer(ref["result"], truth)
        if ref["result"] is not None
        else float("nan")
    )
    note = (
        f"Chamfer {cr:.3f}x single; {_topology(mesh)}; at exit (coordinator or a worker's "
        f"last step) {peak:.0f} MB, "
        f"largest worker {worker_peak:.0f} MB; "
        f"slowest slab per phase: {spent}"
    )
    return row(
        "distributed",
        f"armadillo {n // 1000}k noisy, d{depth}, 2 workers",
        ours,
        "single process",
        ref,
        note,
    )


def rows(quick: bool) -> list[dict]:
    """The section's rows: ``recon poisson --workers 2`` as a process against the single process.

    One row per (points, depth): 200k at depth 9 (quick), else 1M at 10 and 4M at 11.
    """
    cases = [(200_000, 9)] if quick else [(1_000_000, 10), (4_000_000, 11)]
    out = []
    with tempfile.TemporaryDirectory() as d:
        for n, depth in cases:
            out.append(_case(d, n, depth))
    return out
