"""A stage's predicted peak memory (recon_cli.stages.memory_model): figures, report, refusal."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.errors import ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.load import load, save
from recon_cli.stages import memory_model as MM
from recon_cli.stages.poisson import memory as PM

from shapes import sphere_cloud
from shared_data import sampled_cloud


def _recon(argv: list[str]) -> int:
    """The real CLI entry point in-process; its exit status."""
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


def _refuse_loading(monkeypatch):
    import recon_cli.io.load as L

    def refuse(*a, **k):
        raise AssertionError("the command read IN")

    monkeypatch.setattr(L, "load_detailed", refuse)


def test_header_sizes_are_the_loaded_ones(tmp_path):
    """PLY (cloud and mesh), LAS and a grid: the header's counts, without reading the data."""
    from recon_cli.grid import Grid
    from recon_cli.stages.mcubes import marching_cubes

    pts, nrm = sphere_cloud(1234, seed=1)
    cloud = PointCloud(points=pts, normals=nrm)
    g = np.linspace(-1.2, 1.2, 21)
    x, y, z = np.meshgrid(g, g[:17], g[:19], indexing="ij")
    grid = Grid(
        sdf=(np.sqrt(x * x + y * y + z * z) - 1).astype(np.float32),
        origin=np.full(3, -1.2),
        voxel_size=0.12,
    )
    v, f, _ = marching_cubes(grid.sdf, 0.0, grid.voxel_size, tuple(grid.origin))
    mesh = TriangleMesh(vertices=v, faces=f)
    for name, obj in (("c.ply", cloud), ("m.ply", mesh), ("c.las", cloud), ("g.npz", grid)):
        save(obj, str(tmp_path / name))
        got = MM.size_from_header(str(tmp_path / name))
        want = MM.size_of(load(str(tmp_path / name)))
        assert (got.points, got.faces, got.cells) == (want.points, want.faces, want.cells), name
    assert MM.size_of(grid).cells == 21 * 17 * 19
    las = MM.size_from_header(str(tmp_path / "c.las"))
    assert np.allclose(las.lo, pts.min(axis=0), atol=1e-3) and np.allclose(
        las.hi, pts.max(axis=0), atol=1e-3
    )
    assert (
        MM.size_from_header("-") is None and MM.size_from_header(str(tmp_path / "none.ply")) is None
    )
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    assert MM.size_from_header(str(tmp_path / "bad.ply")) is None  # the reader says why later


def _cells(pts, level, scale=1.1):
    """The (k, 3) cells of level ``level`` of the solve's cube holding a point (numpy alone)."""
    n = 1 << level
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    size = float((hi - lo).max()) * scale
    ijk = np.clip(((pts - (0.5 * (lo + hi) - 0.5 * size)) * (n / size)).astype(int), 0, n - 1)
    return np.unique(ijk, axis=0)


def test_poisson_tree_counted_on_the_points():
    """The Poisson tree's depth and ring parents counted on the points.

    The depth from the coarse level's points per cell; the ring parents: the parents of the finest
    cells holding a point and their 26 neighbours inside the cube.
    """
    pts, _ = sphere_cloud(20_000, seed=2)
    for depth, spn in ((5, 1.5), (7, 1.5), (9, 1.5), (9, 20.0)):
        tree = PM.tree_of(pts, depth, 1.1, spn)
        coarse = len(_cells(pts, min(PM.DENSITY_LEVEL, depth)))
        assert tree.depth == PM.tree_depth(len(pts), depth, coarse, spn) <= depth
        parents = np.unique(_cells(pts, tree.depth) >> 1, axis=0)
        side = 1 << (tree.depth - 1)
        steps = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
        ring = (parents[:, None, :] + steps[None]).reshape(-1, 3)
        ring = ring[((ring >= 0) & (ring < side)).all(axis=1)]
        assert tree.rings == len(np.unique(ring, axis=0)), (depth, spn)
    # denser samples a node, a shallower tree; a deeper --depth never a shallower one
    assert PM.tree_of(pts, 9, 1.1, 20.0).depth < PM.tree_of(pts, 9, 1.1, 1.5).depth
    assert PM.tree_depth(10**6, 8, 3000, 1.5) <= PM.tree_depth(10**6, 10, 3000, 1.5)
    assert PM.tree_depth(10**6, 14, 3000, 1.5) < PM.tree_depth(10**7, 14, 3000, 1.5)


def test_poisson_tree_estimated_from_the_count_alone():
    """The Poisson tree's estimate from a header's count alone is bounded and monotonic.

    Never more ring parents than the bound per point, the depth within ``depth``; more points or
    depth, more memory; more slabs, less a process.
    """
    for points, depth in ((10, 12), (10**6, 4), (10**6, 10), (10**8, 12)):
        tree = PM.tree_estimate(points, depth)
        assert 0 < tree.rings <= PM.RINGS_PER_POINT * points and tree.depth <= depth
    one = [PM.one_piece_bytes(10**6, PM.tree_estimate(10**6, d)) for d in (6, 8, 10)]
    assert one == sorted(one) and one[0] < one[-1]
    tree = PM.tree_estimate(4 * 10**6, 10)
    runs = [PM.slab_run_bytes(4 * 10**6, tree, k) for k in (1, 2, 4, 8)]
    assert runs == sorted(runs, reverse=True) and runs[0] > runs[-1]
    assert PM.slab_run_bytes(10**6, tree, 4, in_memory=False) < PM.slab_run_bytes(10**6, tree, 4)
    from recon_cli.stages.poisson.distributed import coarse_depth_for

    assert [PM.coarse_depth(d) for d in range(1, 15)] == [coarse_depth_for(d) for d in range(1, 15)]


def test_the_refusal_is_one_line_with_the_least_memory_that_does():
    """The memory refusal is one line with the figure needed and the ``--memory`` that would do."""
    MM.check_fits("sdf", 10 * 2**30, 11 * 2**30)
    MM.check_fits("sdf", None, 2**30)
    MM.check_fits("sdf", 2**30, None)
    with pytest.raises(ParameterError) as exc:
        MM.check_fits("sdf", 3 * 2**30 + 1, 2**30, "in.ply")
    msg = str(exc.value)
    assert msg == (
        "in.ply: sdf needs about 3 GiB of memory, more than the 1 GiB it may use; give "
        "--memory 3073MiB or more (or a machine with it)"
    )


def test_a_run_over_the_memory_is_refused_before_in_is_read(tmp_path, monkeypatch, capsys):
    """``recon sdf`` at a resolution the memory cannot hold is refused before IN is read.

    Exit 2, one line with the figure, nothing written, IN not read (its header says enough).
    """
    import recon_cli.memory

    pts, nrm = sphere_cloud(2000, seed=3)
    src, out = tmp_path / "s.ply", tmp_path / "g.npz"
    save(PointCloud(points=pts, normals=nrm), str(src))
    monkeypatch.setattr(recon_cli.memory, "available_bytes", lambda: 2 * 2**30)
    _refuse_loading(monkeypatch)
    assert _recon(["sdf", str(src), str(out), "--resolution", "1024"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"recon: error: {src}: sdf needs about "), err
    assert "more than the 2 GiB it may use; give --memory" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


def test_plan_prints_the_prediction_and_runs_nothing(tmp_path, capsys):
    """``--plan`` prints the prediction from the header and writes nothing."""
    pts, nrm = sphere_cloud(3000, seed=4)
    src, out = tmp_path / "s.ply", tmp_path / "g.npz"
    save(PointCloud(points=pts, normals=nrm), str(src))
    assert _recon(["sdf", str(src), str(out), "--resolution", "64", "--plan", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    want = MM.predict("sdf", MM.Size(points=3000), {"resolution": 64})
    assert rep["memory"]["predicted_bytes"] == want and rep["from"] == "header"
    assert rep["points"] == 3000 and rep["fits"] is True and rep["memory"]["budget_bytes"] > 0
    assert _recon(["filter", str(src), str(out), "--voxel", "0.1", "--plan"]) == 0
    text = capsys.readouterr().err  # the table on stderr, as every report
    assert "predicted_bytes" in text and "fits" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


def test_every_report_says_the_prediction_and_the_peak(tmp_path, capsys):
    """Every ``--json`` report gives the prediction made before and the peak measured."""
    pts, nrm = sphere_cloud(3000, seed=5)
    src, out = tmp_path / "s.ply", tmp_path / "f.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    assert _recon(["filter", str(src), str(out), "--voxel", "0.05", "--json", "-q"]) == 0
    mem = json.loads(capsys.readouterr().out)["memory"]
    assert mem["predicted_bytes"] == MM.predict("filter", MM.Size(points=3000), {"voxel": 0.05})
    assert 50 * 2**20 < mem["peak_bytes"] < 20 * 2**30


def _process(argv: list[str]) -> tuple[int, str, str, int]:
    """``recon ARGV`` as a process: exit status, stdout, stderr and its largest resident memory.

    The memory is sampled every 10 ms (reading IN included; ``wait4``'s figure would keep this
    process's).
    """
    import tempfile
    import time

    cmd = [sys.executable, "-m", "recon_cli.cli.main", *argv]
    peak = 0
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se:
        proc = subprocess.Popen(cmd, stdout=so, stderr=se, text=True)
        while proc.poll() is None:
            try:
                with open(f"/proc/{proc.pid}/status") as f:
                    rss = [ln for ln in f if ln.startswith("VmRSS:")]
                peak = max([peak] + [int(ln.split()[1]) * 1024 for ln in rss])
            except OSError:  # it ended between poll() and open()
                pass
            time.sleep(0.01)
        so.seek(0)
        se.seek(0)
        return proc.returncode, so.read(), se.read(), peak


@pytest.fixture(scope="module")
def million(tmp_path_factory):
    """1M noisy armadillo samples with true normals (bench/memory_model.py's cloud family)."""
    path = tmp_path_factory.mktemp("million") / "arm.ply"
    save(sampled_cloud("armadillo", 1_000_000, 0.0025, 0), str(path))
    return path


# the stages run as processes on 1M points here; bench/memory_model.py runs 250k-10M and the
# mesh and grid stages (bench/calibration.md, "Memory model")
PROCESS_RUNS = [
    ("filter", ["--voxel", "0.5"]),
    ("sdf", ["--resolution", "160"]),
    ("normals", ["--knn", "20"]),
    ("poisson", ["--depth", "8"]),
    ("poisson", ["--depth", "8", "--partitions", "3"]),  # in slabs, from the file
]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("stage", "args"), PROCESS_RUNS, ids=[" ".join([r[0], *r[1]]) for r in PROCESS_RUNS]
)
def test_a_processs_peak_is_within_its_prediction(million, tmp_path, stage, args):
    """``recon STAGE`` on 1M points: its peak memory is within 1.5x of its own prediction.

    As a process: its peak resident memory, sampled and as its report says, is within 1/1.5 to 1.5
    times the prediction it made before.
    """
    out = tmp_path / ("o.npz" if stage == "sdf" else "o.ply")
    code, so, se, rss = _process([stage, str(million), str(out), *args, "--json", "-q"])
    assert code == 0, se
    mem = json.loads(so)["memory"]
    for peak in (max(rss, mem["peak_bytes"]), mem["peak_bytes"]):
        assert 1 / 1.5 <= peak / mem["predicted_bytes"] <= 1.5, (stage, args, mem, rss)


@pytest.mark.parametrize(
    ("stage", "args"),
    [
        ("sdf", ["--resolution", "2048"]),  # 8.6e9 cells: far beyond any machine's memory
        ("poisson", ["--depth", "12", "--memory", "256MiB"]),  # not even in the most slabs
    ],
    ids=["machine", "--memory"],
)
def test_a_process_over_its_memory_is_refused_up_front(million, tmp_path, stage, args):
    """A process over the machine's memory, or over --memory even in slabs, is refused up front.

    Exit 2 before the work, one line naming the figure, no OUT and a small process (IN's header was
    enough for sdf).
    """
    out = tmp_path / "o.npz"
    code, so, se, rss = _process([stage, str(million), str(out), *args])
    lines = se.strip().splitlines()
    assert code == 2 and len(lines) == 1, se
    assert lines[0].startswith("recon: error: ") and ("GiB" in lines[0] or "MiB" in lines[0])
    assert "--memory" in lines[0] and not out.exists() and list(tmp_path.iterdir()) == []
