"""The rise of a slab's largest calls inside its steps (issue 32): which arrays make a step's peak.

``python bench/slab_probe.py N DEPTH SLABS [SLAB]``: as ``slab_phases.py``, with the heavy calls
a slab step makes (the splat items, the fields, the tree, the right-hand side, each level's solve,
the field's values, the extraction) wrapped: resident memory before the call and its peak above
that (``VmHWM`` reset at the call), for slab ``SLAB``'s calls. The steps' own peaks are not
measured here (the resets inside them move their high-water marks): ``slab_phases.py`` gives those.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
CALLS = (
    "merge_samples",
    "density_table",
    "noise_sigma",
    "clean_fraction",
    "merge_splats",
    "spread_fields",
    "build_levels",
    "level_fields",
    "NormalRHS",
    "solve_level",
    "merge_per_cell_sums",
    "ChiField",
    "set_corners",
    "_finest",
    "marching_cubes_sparse",
)


def main(n: int, depth: int, slabs: int, watch: int = 1) -> None:
    """The memory rise of each probed call on slab ``watch`` of an in-process slab run of Poisson.

    ``n`` noisy armadillo samples at ``depth`` in ``slabs`` slabs; prints a JSON line per call.
    """
    from recon_cli.io.ply import read_ply
    from recon_cli.memory import peak_mb, release_free_heap, reset_peak, rss_mb
    from recon_cli.mesh.sampling import sample_surface
    from recon_cli.stages.poisson import distributed as D
    from recon_cli.stages.poisson import slab as S
    from recon_cli.stages.poisson import slab_surface as M

    cloud = sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0, noise=0.0025)
    current = {"slab": -1}
    real_timed_steps = {}

    def probe(name, fn):
        def call(*a, **k):
            if current["slab"] != watch:
                return fn(*a, **k)
            release_free_heap()
            before = rss_mb()
            reset_peak()
            out = fn(*a, **k)
            rise = peak_mb() - before
            level = getattr(a[0], "depth", None) if name == "solve_level" else None
            row = {"call": name, "level": level, "rss_before": round(before), "rise": round(rise)}
            print(json.dumps(row), flush=True)
            return out

        return call

    for name in CALLS:
        for mod in (S, M):
            if hasattr(mod, name):
                setattr(mod, name, probe(name, getattr(mod, name)))
    # the steps set which slab runs
    for name in ("load", "noise", "items", "restrict", "solve", "field", "extract"):
        mod = M if name in ("field", "extract") else S
        fn = getattr(mod, name)
        real_timed_steps[name] = fn

        def step(slab, *a, _fn=fn):
            current["slab"] = slab.index
            return _fn(slab, *a)

        step.__name__ = fn.__name__
        setattr(mod, name, step)
    load0 = os.getloadavg()[0]
    D.distributed_poisson(cloud.points, cloud.normals, depth=depth, partitions=slabs)
    print(json.dumps({"load": f"{load0:.1f}-{os.getloadavg()[0]:.1f}"}))


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
