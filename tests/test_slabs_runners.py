"""The slabs' runners (recon_cli.slabs.runners): how a step's failure on a cluster ends."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster of 2 workers (no memory limit, no stealing)."""
    from recon_cli.batch.cluster import open_client

    with open_client(workers=2, memory_limit="none", stealing=False) as (client, info):
        yield client


def _exit_the_worker(state):
    """A step that kills the worker process running it (as the kernel's OOM killer would)."""
    os._exit(1)


def test_a_step_whose_workers_all_die_is_one_line(cluster):
    """A step whose every worker dies fails as one StageFailed line naming the step.

    The scheduler retries the step on the other worker, which dies too.
    """
    from recon_cli.errors import StageFailed
    from recon_cli.slabs.runners import DaskRunner

    runner = DaskRunner(cluster, [{"part": 0}], label="poisson")
    try:
        with pytest.raises(StageFailed) as err:
            runner.run("solve", _exit_the_worker, lambda k: ())
    finally:
        runner.close()
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("poisson: the worker processes running part 1's")
    assert "solve step died" in msg and "--memory" in msg
