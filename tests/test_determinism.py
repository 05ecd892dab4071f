"""Every stage's output file is the same bytes whatever the thread count, run after run.

The same holds (the stages that run in slabs) wherever the slabs ran: in this process, spilled to
files, on a Dask cluster of one worker or of two.

The inputs are generated (``tests/shapes.py``); each run is one process (``NUMBA_NUM_THREADS``
is read when numba loads) that runs every stage's command in turn through
``recon_cli.cli.main.main``: NUMBA_NUM_THREADS = 1, 2 and 4, and 2 again. The runs at 2 threads
also run the slab stages on a local Dask cluster (``--workers 1`` in one, ``--workers 2`` in
the other), whose files are compared with the same slabs' in-process files. The PLY history
lines are part of the bytes: they carry no clock, thread count or worker count.

What does not hold to the bit, and the bound that does (each asserted here or there):

- Poisson and normals in a different *number* of slabs: the same surface within half a finest
  cell (``test_poisson_distributed.test_the_mesh_does_not_depend_on_how_the_work_was_cut``);
  the same slab count gives the same bytes wherever the slabs run.
- fit-sdf (torch, not numba): the same bytes for the same ``--seed`` and ``--threads``;
  another ``--threads`` sums torch's reductions in another order, and the fields then agree
  within :data:`FIT_SDF_THREADS_BOUND` of the input's box diagonal.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.grid import Grid
from recon_cli.io.load import save
from recon_cli.io.npz import write_grid

from mesh_damage import duplicate_faces, flip_faces, remove_patches
from shapes import icosphere, single_view_scan, torus, torus_cloud, torus_sdf

# four processes of ~10 s of CPU each
pytestmark = pytest.mark.slow

# the runs: (name, NUMBA_NUM_THREADS, Dask workers for the slab stages' cluster runs or None)
RUNS = (("t1", 1, None), ("t2", 2, 1), ("t4", 4, None), ("t2-again", 2, 2))

# one process runs every job of a run in turn (the argv of ``recon``, OUT under {out})
RUNNER = """
import json, sys
from recon_cli.cli.main import main
codes = {}
for name, argv in json.load(open(sys.argv[1])):
    try:
        main(["-q", *argv])
    except SystemExit as exc:
        codes[name] = exc.code
print(json.dumps(codes))
"""


def _inputs(folder: Path) -> None:
    """The generated inputs every run reads."""
    rng = np.random.default_rng(47)
    pts, nrm = torus_cloud(6000, seed=47)
    pts = pts + rng.normal(scale=0.004, size=pts.shape)
    rgb = rng.integers(0, 256, size=(len(pts), 3)).astype(np.uint8)
    save(PointCloud(points=pts), str(folder / "cloud.ply"))
    save(PointCloud(points=pts, normals=nrm, colors=rgb), str(folder / "oriented.ply"))
    scan, scan_nrm = single_view_scan("rounded_box", 70, rng)
    save(PointCloud(points=scan, normals=scan_nrm), str(folder / "scan.ply"))
    ev, ef = icosphere(2, radius=1.6)
    save(TriangleMesh(vertices=ev, faces=ef), str(folder / "envelope.ply"))
    # a torus mesh: smooth and simplify take it noisy, repair damaged
    v, f = torus(nu=48, nv=20)
    save(
        TriangleMesh(vertices=v + rng.normal(scale=0.01, size=v.shape), faces=f),
        str(folder / "mesh.ply"),
    )
    damaged = TriangleMesh(vertices=v, faces=f)
    for hurt in (flip_faces, duplicate_faces, remove_patches):
        damaged = hurt(damaged, rng)
    save(damaged, str(folder / "damaged.ply"))
    x = np.linspace(-1.5, 1.5, 30)
    lattice = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1).reshape(-1, 3)
    sdf = torus_sdf(lattice).reshape(len(x), len(x), len(x)).astype(np.float32)
    write_grid(Grid(sdf=sdf, origin=np.full(3, -1.5), voxel_size=x[1] - x[0]), folder / "grid.npz")


# fit-sdf's training, short
FIT = ("--iterations", "25", "--seed", "3", "--resolution", "16", "--width", "32", "--depth", "2")
# fit-sdf's fields at another --threads: within this fraction of the input's box diagonal
FIT_SDF_THREADS_BOUND = 0.03

# (name, command, IN, options): OUT is {name}, written in the run's folder (its working folder:
# the history lines name the extra outputs as given)
JOBS: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("normals.ply", "normals", "cloud.ply", ()),
    (
        "normals-radius-camera.ply",
        "normals",
        "cloud.ply",
        ("--radius", "0.12", "--orient", "camera", "--camera", "0.3,0.2,4", "--curvature"),
    ),
    ("normals-slabs3.ply", "normals", "cloud.ply", ("--partitions", "3")),
    (
        "poisson.ply",
        "poisson",
        "oriented.ply",
        ("--depth", "7", "--grid", "poisson-grid.npz"),
    ),
    ("poisson-free.ply", "poisson", "oriented.ply", ("--depth", "6", "--boundary", "free")),
    (
        "poisson-envelope.ply",
        "poisson",
        "oriented.ply",
        ("--depth", "6", "--envelope", "{in}/envelope.ply", "--density"),
    ),
    ("poisson-trim.ply", "poisson", "scan.ply", ("--depth", "6", "--trim", "auto")),
    ("poisson-degree1.ply", "poisson", "oriented.ply", ("--depth", "6", "--degree", "1")),
    ("poisson-slabs3.ply", "poisson", "oriented.ply", ("--depth", "7", "--partitions", "3")),
    ("ballpivot.ply", "ballpivot", "oriented.ply", ()),
    ("repair.ply", "repair", "damaged.ply", ("--fill-holes", "30")),
    ("simplify.ply", "simplify", "mesh.ply", ("--ratio", "0.3")),
    ("smooth.ply", "smooth", "mesh.ply", ("--iterations", "8")),
    ("filter-voxel.ply", "filter", "cloud.ply", ("--voxel", "0.05")),
    ("filter-outliers.ply", "filter", "cloud.ply", ("--outliers", "8,1.0")),
    ("filter-radius.ply", "filter", "cloud.ply", ("--radius-outliers", "0.05,6")),
    ("sdf-mesh.npz", "sdf", "mesh.ply", ("--resolution", "24")),
    ("sdf-pseudonormal.npz", "sdf", "mesh.ply", ("--resolution", "24", "--sign", "pseudonormal")),
    ("sdf-cloud.npz", "sdf", "oriented.ply", ("--resolution", "24")),
    ("mcubes.ply", "mcubes", "grid.npz", ()),
    ("mcubes-mt.ply", "mcubes", "grid.npz", ("--method", "mt")),
    (
        "fit-sdf.npz",
        "fit-sdf",
        "oriented.ply",
        (*FIT, "--threads", "1", "--model", "fit-sdf-model.npz", "--mesh", "fit-sdf-mesh.ply"),
    ),
    ("fit-sdf-threads3.npz", "fit-sdf", "oriented.ply", (*FIT, "--threads", "3")),
    # the same two slabs in this process and, in the runs with workers, on a local Dask cluster
    ("poisson-slabs2.ply", "poisson", "oriented.ply", ("--depth", "7", "--partitions", "2")),
    ("normals-slabs2.ply", "normals", "cloud.ply", ("--partitions", "2")),
)
SLAB_JOBS = ("poisson-slabs2.ply", "normals-slabs2.ply")
# every file the jobs write
FILES = sorted(
    [j[0] for j in JOBS]
    + [o for j in JOBS for o in j[3] if o.endswith((".npz", ".ply")) and "{" not in o]
)


def _jobs(src: Path, workers: int | None) -> list[tuple[str, list[str]]]:
    """(name, argv) of every job of a run."""
    jobs = []
    for name, command, input_, options in JOBS:
        opts = [o.format(**{"in": src}) for o in options]
        if workers is not None and name in SLAB_JOBS:
            opts += ["--workers", str(workers)]
        jobs.append((name, [command, str(src / input_), name, *opts]))
    return jobs


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Every run's output folder, the runs done two at a time (the machine's cores)."""
    root = tmp_path_factory.mktemp("determinism")
    src = root / "in"
    src.mkdir()
    _inputs(src)
    procs = {}
    folders = {}
    for name, threads, workers in RUNS:
        out = root / name
        out.mkdir()
        jobs = root / f"{name}.json"
        jobs.write_text(json.dumps(_jobs(src, workers)))
        env = {**os.environ, "NUMBA_NUM_THREADS": str(threads)}
        procs[name] = subprocess.Popen(
            [sys.executable, "-c", RUNNER, str(jobs)],
            env=env,
            cwd=out,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        folders[name] = out
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err
        codes = json.loads(out.splitlines()[-1])
        assert all(c == 0 for c in codes.values()), (name, codes, err)
    return folders


@pytest.mark.parametrize("name", FILES)
def test_same_bytes_in_every_run(runs, name):
    """Each output file has the same bytes at 1, 2 and 4 threads, in-process and on Dask workers."""
    first = runs[RUNS[0][0]] / name
    data = first.read_bytes()
    assert len(data) > 1000
    for run in RUNS[1:]:
        other = runs[run[0]] / name
        assert other.read_bytes() == data, f"{name}: {RUNS[0][0]} and {run[0]} differ"


def test_runs_leave_only_their_outputs(runs):
    """Each run's folder holds exactly the files its jobs write, nothing else."""
    for folder in runs.values():
        assert sorted(os.listdir(folder)) == FILES


def test_fit_sdf_at_another_thread_count_within_its_bound(runs):
    """fit-sdf at 1 and 3 threads: fields within :data:`FIT_SDF_THREADS_BOUND` of the diagonal."""
    from recon_cli.io.npz import read_grid

    a = read_grid(runs["t1"] / "fit-sdf.npz")
    b = read_grid(runs["t1"] / "fit-sdf-threads3.npz")
    diag = np.linalg.norm(np.ptp(torus_cloud(6000, seed=47)[0], axis=0))
    gap = np.abs(a.sdf - b.sdf).max() / diag
    assert gap <= FIT_SDF_THREADS_BOUND, gap
