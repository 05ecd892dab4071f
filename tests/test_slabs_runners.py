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


def _grow(state, nbytes):
    """A step that gives its part's state ``nbytes`` more of an array."""
    import numpy as np

    state["a"] = np.zeros(len(state["a"]) + nbytes, np.uint8)
    return {"held": len(state["a"])}


@pytest.mark.parametrize("spill_bytes", [0, 1000, 2500])
def test_small_states_held_in_memory_stay_under_the_spill_bytes(tmp_path, spill_bytes):
    """The states a local runner keeps in memory, but the next part's, total < ``spill_bytes``.

    Before, any state under the threshold stayed: 20 parts of 500 bytes held 9,500 bytes
    beside the one that runs next, as 32 slabs of a 4M-point cloud held 0.8 GiB.
    """
    import numpy as np

    from recon_cli.slabs.runners import LocalRunner, Spilled, state_bytes

    n = 20
    runner = LocalRunner(
        # dicts: Dask's sizeof (once Dask is imported) and state_bytes both count their arrays
        [{"a": np.zeros(0, np.uint8)} for _ in range(n)],
        spill_dir=str(tmp_path),
        spill_bytes=spill_bytes,
    )
    try:
        for step in range(3):
            out = runner.run("grow", _grow, lambda k, step=step: (100 + 200 * step,))
            assert [m["held"] for m in out] == [sum(100 + 200 * s for s in range(step + 1))] * n
            # the part that runs next (the last of the snake order) is in memory whatever its size
            nxt = n - 1 if step % 2 == 0 else 0
            live = [k for k, s in enumerate(runner.states) if not isinstance(s, Spilled)]
            held = sum(state_bytes(runner.states[k]) for k in live if k != nxt)
            assert nxt in live and held < max(spill_bytes, 1)
            assert len(os.listdir(tmp_path)) == n - len(live)
    finally:
        runner.close()
    assert os.listdir(tmp_path) == []
