"""The slabs of a job: how many for the memory, and why (recon_cli.slabs.plan)."""

from __future__ import annotations

import numpy as np
import pytest

from recon_cli.errors import ParameterError
from recon_cli.slabs.plan import (
    SLAB_MEMORY_SHARE,
    choose_seams,
    default_partitions,
    slab_count,
    sub_slab,
)

BPP = 4096.0  # bytes a point, as a stage declares


def test_default_partitions_from_the_workers_memory():
    """Default partitions follow the workers' memory, in whole rounds of the workers.

    One slab per worker when a slab fits the worker's share; a cloud four times too big takes four
    per worker; a count rounded up to whole rounds of the workers, capped; no limit: one per worker.
    """
    mem = 8 * 2**30
    per_slab = SLAB_MEMORY_SHARE * mem / BPP  # the points one slab may hold
    fits = int(4 * per_slab)
    assert default_partitions(fits, 4, mem, BPP) == 4
    assert default_partitions(fits + 1, 4, mem, BPP) == 8
    assert default_partitions(4 * fits, 4, mem, BPP) == 16
    assert default_partitions(5 * int(per_slab), 3, mem, BPP) == 6
    assert default_partitions(10, 4, mem, BPP) == 4
    assert default_partitions(0, 1, mem, BPP) == 1
    assert default_partitions(100 * fits, 4, mem, BPP) == 64
    assert default_partitions(int(31 * per_slab), 3, mem, BPP) == 33  # 11 rounds of 3
    assert default_partitions(int(63 * per_slab), 5, mem, BPP) == 64  # 13 rounds of 5: 65
    assert default_partitions(10**9, 4, None, BPP) == 4
    assert default_partitions(10**9, 4, 0, BPP) == 4
    assert default_partitions(10, 80, mem, BPP) == 64
    with pytest.raises(ParameterError, match="workers must be >= 1"):
        default_partitions(10, 0, mem, BPP)


class _Client:
    """A client stand-in: the scheduler's view of workers of these memory limits."""

    def __init__(self, limits):
        self.limits = limits

    def scheduler_info(self):
        return {"workers": {f"w{i}": {"memory_limit": m} for i, m in enumerate(self.limits)}}


def count(partitions, npoints, client, budget=None):
    """slab_count for poisson at the test's bytes per point, with at most 64 slabs."""
    return slab_count(partitions, npoints, client, BPP, 64, "poisson", "the seams", budget)


def test_slab_count_on_a_cluster_says_how_many_and_why():
    """On a cluster the slab count follows the smallest worker limit, and the report says why."""
    mem = 2**30
    per_slab = int(SLAB_MEMORY_SHARE * mem / BPP)
    # the smallest worker's limit decides; a worker without one does not
    n, rep = count(None, 3 * per_slab, _Client([mem, 2 * mem, 0]))
    assert n == 3 and rep["count"] == 3 and rep["memory_per_worker"] == mem
    assert rep["why"].startswith("one per worker: a slab (~")
    assert f"fits {SLAB_MEMORY_SHARE:.0%} of a worker's 1 GiB" in rep["why"]
    n, rep = count(None, 2 * 3 * per_slab, _Client([mem, 2 * mem, 0]))
    assert n == 6 and rep["why"].startswith("2 per worker")
    n, rep = count(5, 2 * 3 * per_slab, _Client([mem] * 3))
    assert n == 5 and rep["why"] == "given (--partitions)"
    n, rep = count(None, 10**9, _Client([0, None]))
    assert n == 2 and rep["why"] == "one per worker: no memory limit"
    assert rep["memory_per_worker"] is None


def test_slab_count_in_this_process_from_its_budget():
    """No cluster: this process's budget sizes the slabs (any count); none given: one slab."""
    mem = 2**30
    per_slab = int(SLAB_MEMORY_SHARE * mem / BPP)
    assert count(None, 10**9, None) == (
        1,
        {"count": 1, "why": "one slab: no memory limit", "workers": 0, "memory": None,
         "points": 10**9, "slab_bytes_estimate": int(10**9 * BPP)},
    )  # fmt: skip
    n, rep = count(None, per_slab, None, mem)
    assert n == 1 and rep["why"].startswith("one slab: a slab (~")
    n, rep = count(None, per_slab + 1, None, mem)
    assert n == 2 and rep["why"].startswith("2 slabs in this process")
    assert "of this process's 1 GiB" in rep["why"]
    n, rep = count(None, 7 * per_slab - 5, None, mem)
    assert n == 7


def test_a_memory_too_small_for_the_most_slabs_is_refused_with_the_least_that_does():
    """Memory too small even for 64 slabs is refused with the least memory that does."""
    mem = 2**30
    per_slab = int(SLAB_MEMORY_SHARE * mem / BPP)
    npoints = 65 * per_slab
    exact = npoints / 64 * BPP / SLAB_MEMORY_SHARE  # one slab of the most fits its share
    for client, budget in ((None, mem), (_Client([mem]), None)):
        with pytest.raises(ParameterError, match="need at least") as err:
            count(None, npoints, client, budget)
        need = int(str(err.value).split("need at least ")[1].split(" MiB")[0]) * 2**20
        assert exact <= need < exact + 2**20
    assert count(None, npoints, None, need)[0] == 64  # the figure given does


@pytest.mark.parametrize("parts", [1, 2, 5])
def test_seams_balance_the_counts(parts):
    """Seams split the counts within one sub-slab of equal shares, increasing, in 1..31."""
    rng = np.random.default_rng(parts)
    counts = rng.integers(0, 1000, 32)
    seams = choose_seams(counts, parts)
    assert len(seams) == parts - 1 and seams == sorted(set(seams))
    assert all(1 <= s <= 31 for s in seams)
    cum = np.concatenate([[0], np.cumsum(counts)])
    share = np.diff([0, *[cum[s] for s in seams], cum[-1]])
    # each seam within one sub-slab's count of the ideal share
    ideal = cum[-1] * np.arange(1, parts) / parts
    assert np.all(np.abs(cum[seams] - ideal) <= counts.max())
    assert share.sum() == cum[-1]


def test_as_many_seams_as_planes_take_every_plane():
    """32 partitions take every plane; 33 are refused."""
    assert choose_seams(np.ones(32), 32) == list(range(1, 32))
    with pytest.raises(ParameterError, match="at most 32 partitions"):
        choose_seams(np.ones(32), 33)


def test_sub_slab_of_unit_x():
    """sub_slab gives the half of unit x each value falls in, clamped outside [0, 1)."""
    x = np.array([0.0, 0.49999, 0.5, 0.99999, 1.0, -0.1, 1.2])
    assert sub_slab(x, 2).tolist() == [0, 0, 1, 1, 1, 0, 1]
