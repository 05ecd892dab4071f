"""The slab count of a Poisson run on workers: fitted to its largest slab (issue 44, item 3)."""

from __future__ import annotations

import numpy as np

from recon_cli.stages.poisson import memory as PM
from recon_cli.stages.poisson.distributed import distributed_poisson

from shapes import sphere_cloud


def _slab_bytes_per_point(monkeypatch, per_point: float) -> None:
    """A Poisson slab's memory patched to ``per_point`` bytes a point (its rings' share 0)."""
    monkeypatch.setattr(PM, "SLAB_POINT_BYTES", per_point)
    monkeypatch.setattr(PM, "SLAB_RING_BYTES", 0)


class _Workers:
    """A client stand-in: the scheduler's view of two workers of ``limit`` bytes each."""

    def __init__(self, limit: int):
        self.limit = limit

    def scheduler_info(self):
        return {"workers": {f"w{i}": {"memory_limit": self.limit} for i in range(2)}}


def test_workers_slab_count_fits_the_largest_slab_with_its_pads(monkeypatch):
    """On workers the slabs are planned by the largest slab's points read, pads included.

    A sphere sampled five times as densely on one side: an even share of the points fits a
    worker's share of its memory in 2 slabs (the count before the points per sub-slab are known),
    but the densest slab with its pads would take more than the worker may. The run takes the
    fewest whole rounds of the workers whose largest slab's worker figure fits (the slabs run here,
    the runner the one-process one), and the report gives the figure; the mesh is the one of that
    many slabs given.
    """
    import recon_cli.slabs.plan as P
    import recon_cli.stages.poisson.distributed as D

    rng = np.random.default_rng(31)
    pts, nrm = sphere_cloud(12_000, seed=31)
    keep = (pts[:, 0] > 0.3) | (rng.random(len(pts)) < 0.2)
    pts, nrm = pts[keep], nrm[keep]
    mem = 4 * 2**30
    # the cloud's state 0.95 of a worker's memory: an even half of it fits half the memory
    monkeypatch.setattr(P, "SLAB_MEMORY_SHARE", 0.5)
    _slab_bytes_per_point(monkeypatch, 0.95 * mem / len(pts))
    monkeypatch.setattr(PM, "COARSE_RING_BYTES", 0)
    monkeypatch.setattr(PM, "WORKER_STATE_FACTOR", 1.0)
    here = D.make_runner
    monkeypatch.setattr(D, "make_runner", lambda client, *a, **k: here(None, *a, **k))
    res = distributed_poisson(pts, nrm, depth=7, partitions=None, client=_Workers(mem))
    rep = res.report["distributed"]
    part = rep["partitions"]
    count = part["count"]
    assert count % 2 == 0 and count > 2 == D.slab_count(None, len(pts), _Workers(mem), None, 7)[0]
    tree = PM.tree_estimate(len(pts), 7)
    most = max(s["points_read"] for s in rep["slabs"])
    assert part["largest_slab_points"] == most
    assert part["worker_bytes_estimate"] == PM.worker_bytes(len(pts), tree, most / len(pts))
    assert part["worker_bytes_estimate"] <= PM.WORKER_PEAK_SHARE * mem
    assert part["why"].startswith(f"{count // 2} per worker: the largest slab reads {most} points")
    # two slabs fewer would not fit: the fewest
    fewer = distributed_poisson(pts, nrm, depth=7, partitions=count - 2).report["distributed"]
    most = max(s["points_read"] for s in fewer["slabs"])
    assert PM.worker_bytes(len(pts), tree, most / len(pts)) > PM.WORKER_PEAK_SHARE * mem
    ref = distributed_poisson(pts, nrm, depth=7, partitions=count).mesh
    assert np.array_equal(res.mesh.vertices, ref.vertices)
    assert np.array_equal(res.mesh.faces, ref.faces)
