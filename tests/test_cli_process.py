"""The ``recon`` process around its command (recon_cli/cli/_process.py).

OpenBLAS single-threaded unless the user set it, the cyclic collector back on while a stage
computes, outputs and reports complete when the process exits without collecting its start-up
garbage.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.grid import Grid
from recon_cli.io.npz import write_grid
from recon_cli.io.ply import read_ply

# the stage sees the collector's state and the BLAS setting of the process
PROBE = """
import gc, os, sys
import recon_cli.stages as stages
from recon_cli.cli import main as m

real = stages.apply_stage

def probe(*args, **kwargs):
    print("gc", gc.isenabled(), "blas", os.environ.get("OPENBLAS_NUM_THREADS"), file=sys.stderr)
    return real(*args, **kwargs)

stages.apply_stage = probe
sys.argv = ["recon", *sys.argv[1:]]
m.main()
"""


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """A 24^3 grid of a ball's signed distance, written once for the module."""
    n = 24
    x = (np.arange(n) - (n - 1) / 2) / (n / 2)
    sdf = np.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2) - 0.6
    path = tmp_path_factory.mktemp("grid") / "ball.npz"
    write_grid(Grid(sdf=sdf, origin=np.zeros(3), voxel_size=2.0 / n), path)
    return path


def _run(args, env_extra=None):
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
    }
    env.update(env_extra or {})
    return subprocess.run(
        [sys.executable, "-c", PROBE, *map(str, args)], capture_output=True, text=True, env=env
    )


@pytest.mark.parametrize("user", [None, "3"])
def test_stage_runs_with_collector_on_and_blas_setting(grid, tmp_path, user):
    """A stage runs with the collector on, OpenBLAS at 1 thread or the user's; report complete."""
    out = tmp_path / "m.ply"
    r = _run(
        ["mcubes", grid, out, "--json"], None if user is None else {"OPENBLAS_NUM_THREADS": user}
    )
    assert r.returncode == 0, r.stderr
    assert f"gc True blas {user or '1'}" in r.stderr
    report = json.loads(r.stdout)  # stdout flushed in full before the process ends
    mesh = read_ply(out)
    assert report["faces"] == len(mesh.faces) > 0 and report["boundary_edges"] == 0


def test_in_process_main_leaves_collector_alone(grid, tmp_path):
    """``main`` called in a process leaves the collector enabled and nothing frozen."""
    import gc

    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(["-q", "mcubes", str(grid), str(tmp_path / "m.ply")])
    assert exc.value.code == 0
    assert gc.isenabled() and gc.get_freeze_count() == 0
