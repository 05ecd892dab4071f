"""Where a distributed Poisson slab's memory goes, step by step (issue 32).

``python bench/slab_phases.py N DEPTH SLABS [SLAB]``: noisy armadillo samples (0.25 % of the
diagonal, as ``bench_distributed.py``), :func:`.distributed.distributed_poisson` in this
process (every slab in turn, no cluster). For each step of slab ``SLAB`` (default: the
second, an inner slab with two pads), the resident memory before the step, the step's rise
above it (its ``VmHWM`` after a reset: the step's own transient arrays), and the state the
slab keeps after it (:func:`.slab.state_bytes`: numpy buffers, each once), its largest
attributes by name. In a worker that holds one slab at a time (more slabs than workers:
spilled), its peak is about its idle memory + the state before a step + the step's rise.
Prints a JSON line per step, then the figures of the largest steps.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
MIB = 2**20


def breakdown(slab) -> dict[str, float]:
    """MiB of the slab's state per attribute (a buffer counted under the first that holds it)."""
    from recon_cli.stages.poisson.slab import state_bytes

    seen: set = set()
    out = {}
    for name, value in vars(slab).items():
        b = state_bytes(value, 0, seen)
        if b >= MIB:
            out[name] = round(b / MIB, 1)
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def main(n: int, depth: int, slabs: int, watch: int = 1) -> list[dict]:
    """Each step's resident memory on slab ``watch`` of an in-process slab run of Poisson.

    ``n`` noisy armadillo samples at ``depth`` in ``slabs`` slabs: per step, the resident memory
    before, its rise, the slab state's size before and after and its largest arrays; prints JSON
    lines.
    """
    from recon_cli.io.ply import read_ply
    from recon_cli.memory import release_free_heap, rss_mb
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.slabs.runners import LocalRunner
    from recon_cli.stages.poisson import distributed as D
    from recon_cli.stages.poisson.slab import state_bytes

    cloud = sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0, noise=0.0025)
    rows: list[dict] = []

    class Watching(LocalRunner):
        def run(self, name, fn, args):
            def step(s, *a):
                release_free_heap()
                before = rss_mb()
                state0 = state_bytes(s) / MIB
                msg = fn(s, *a)
                if s.index == watch:
                    row = {
                        "step": f"{name}:{fn.__name__}",
                        "rss_before": round(before),
                        "state_before": round(state0),
                        "rise": round(msg["peak_mb"] - before),
                        "state_after": round(state_bytes(s) / MIB),
                        "seconds": round(msg["seconds"], 1),
                        "top": breakdown(s),
                    }
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                return msg

            step.__name__ = fn.__name__
            return super().run(name, step, args)

    def runner(client, states, progress=None, overall=None, spill=None):
        return Watching(states, progress, "poisson", overall)

    D.make_runner = runner
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    res = D.distributed_poisson(
        cloud.points, cloud.normals, depth=depth, partitions=slabs, client=None
    )
    wall = time.perf_counter() - t0
    sl = res.report["distributed"]["slabs"][watch]
    from recon_cli.mesh.topology import report as topology

    topo = topology(res.mesh)
    dup = len(res.mesh.vertices) - len(np.unique(res.mesh.vertices, axis=0))
    worst = sorted(rows, key=lambda r: -(r["state_before"] + r["rise"]))[:4]
    print(
        json.dumps(
            {
                "points": n,
                "depth": depth,
                "slabs": slabs,
                "watched": watch,
                "own_points": sl["points"],
                "read_points": sl["points_read"],
                "largest": [(r["step"], r["state_before"] + r["rise"]) for r in worst],
                "closed_manifold": bool(
                    topo["watertight"] and topo["edge_manifold"] and topo["vertex_manifold"]
                ),
                "pieces": topo["components"],
                "duplicate_vertices": int(dup),
                "wall_s": round(wall),
                "load": f"{load0:.1f}-{os.getloadavg()[0]:.1f}",
            }
        )
    )
    return rows


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
