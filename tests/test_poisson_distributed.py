"""Distributed Poisson (recon_cli.stages.poisson.distributed) against the single process.

Seams, slabs of any density, empty slabs, one slab against the single-process solve, killed workers,
the command.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pytest
from slab_checks import closed_pieces

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.io.load import load, save
from recon_cli.mesh.topology import report as topology_report
from recon_cli.slabs.plan import SLAB_MEMORY_SHARE
from recon_cli.stages.poisson import memory as PM
from recon_cli.stages.poisson import screened_poisson
from recon_cli.stages.poisson.distributed import distributed_poisson

from interrupt import RUN_RECON, SIGINT_AS_A_TERMINAL, interrupt_when
from shapes import random_rotation, shape_cloud, single_view_scan, sphere_cloud
from spilling import spilling_runner


def _radial_error(mesh, centre, radius) -> float:
    return float(np.abs(np.linalg.norm(mesh.vertices - centre, axis=1) - radius).mean())


@pytest.mark.parametrize("seed, n, mode", [(0, 12_000, "leaves"), (1, 40_000, "finest")])
def test_sphere_cut_by_every_slab_plane_is_one_closed_piece(seed, n, mode):
    """A sphere cut by every seam of four slabs is one closed manifold piece.

    A rotated, scaled sphere 1e6 from the origin: the mesh is one closed manifold piece, no vertex
    duplicated, the two sides' seam vertices are the same bits, and it is as close to the sphere as
    the single-process mesh; sparse samples (coarse leaves hold surface: the extraction at the
    leaves' own size) and dense ones (the finest-lattice extraction), as the single-process solve
    chooses.
    """
    rng = np.random.default_rng(seed)
    p, nrm0 = sphere_cloud(n, seed=seed)
    r = random_rotation(rng)
    scale = 10.0 ** rng.uniform(-2, 2)
    centre = np.array([1e6, -2e6, 3e5])
    pts, nrm = p @ r.T * scale + centre, nrm0 @ r.T
    res = distributed_poisson(pts, nrm, depth=7, partitions=4)
    closed_pieces(res.mesh)
    dist = res.report["distributed"]
    assert dist["extraction"] == mode
    assert dist["seam_max_deviation"] == 0.0
    assert [s["seam_vertices"] > 0 for s in dist["slabs"]] == [False, True, True, True]
    single = screened_poisson(pts, nrm, depth=7)
    assert abs(len(res.mesh.vertices) - len(single.mesh.vertices)) <= 0.001 * len(
        single.mesh.vertices
    )
    e_single = _radial_error(single.mesh, centre, scale)
    e_dist = _radial_error(res.mesh, centre, scale)
    assert e_dist <= 1.02 * e_single
    assert res.mesh.vertices.dtype == np.float64


def test_sphere_cut_by_level6_seams_is_one_closed_piece():
    """A sphere cut by level-6 seams (40 slabs) is one closed manifold piece.

    More slabs than level-5 planes: seams on level-6 planes, level 6 made complete so no leaf
    crosses one; every seam crosses the sphere and the mesh is still one closed manifold piece with
    no vertex twice, the seams' vertices the same bits on both sides, about as close to the sphere
    as the single-process mesh.
    """
    rng = np.random.default_rng(5)
    p, nrm0 = sphere_cloud(40_000, seed=5)
    r = random_rotation(rng)
    pts, nrm = p @ r.T * 3.0 + 7.0, nrm0 @ r.T
    res = distributed_poisson(pts, nrm, depth=7, partitions=40)
    closed_pieces(res.mesh)
    dist = res.report["distributed"]
    assert len(dist["slabs"]) == 40 and dist["seam_max_deviation"] == 0.0
    assert all(s["seam_vertices"] > 0 for s in dist["slabs"][1:])
    single = screened_poisson(pts, nrm, depth=7)
    centre = np.full(3, 7.0)
    assert _radial_error(res.mesh, centre, 3.0) <= 1.02 * _radial_error(single.mesh, centre, 3.0)


def test_slabs_of_very_different_density():
    """Slabs of 16x different density still give one closed piece as close as the single run.

    One slab holds 16x the samples per area of the other (the seam through the middle of an
    ellipsoid, x its longest axis): one closed piece, as close to the samples' surface as the
    single-process mesh.
    """
    rng = np.random.default_rng(5)
    p, n = sphere_cloud(40_000, seed=5)
    keep = (p[:, 0] > 0) | (rng.random(len(p)) < 1 / 16)
    axes = np.array([1.3, 1.0, 0.9])
    p, n = p[keep] * axes, n[keep] / axes
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    res = distributed_poisson(p, n, depth=7, partitions=2, seams=[16])
    closed_pieces(res.mesh)
    slabs = res.report["distributed"]["slabs"]
    assert slabs[1]["points"] > 12 * slabs[0]["points"]

    def err(mesh):  # the ellipsoid's algebraic distance, about the distance near the surface
        return float(np.abs(np.linalg.norm(mesh.vertices / axes, axis=1) - 1).mean())

    single = screened_poisson(p, n, depth=7)
    assert err(res.mesh) <= 1.02 * err(single.mesh)


def test_noise_blobs_are_specks_across_slabs(monkeypatch):
    """Noise blobs are dropped across slabs by the global noise median; a real sphere stays.

    A depth finer than the noise (about 2 finest cells): the slabs' merge drops the blobs as the
    single process does; a real second sphere stays.
    """
    import recon_cli.stages.poisson as P

    rng = np.random.default_rng(11)
    p, n = shape_cloud("sphere", 60_000, rng)
    q, m = shape_cloud("sphere", 15_000, rng, scale=0.5)
    q += 3.0 * random_rotation(rng)[0]
    pts = np.vstack([p, q]) + rng.normal(scale=0.09, size=(75_000, 3))
    nrm = np.vstack([n, m])
    res = distributed_poisson(pts, nrm, depth=8, partitions=3)
    closed_pieces(res.mesh, pieces=2)
    assert res.report["noise"] > 1.5 and res.report["bubbles_removed"] > 50
    # the folds' rule alone, measured on the vertices the slabs send, drops the larger blobs;
    # without both rules they stay
    monkeypatch.setattr(P, "SPECK_SIGMAS", 0.0)
    folds = distributed_poisson(pts, nrm, depth=8, partitions=3)
    closed_pieces(folds.mesh, pieces=2)
    assert folds.report["folds_removed"] > 20
    monkeypatch.setattr(P, "FOLD_SIGMAS", 0.0)
    blobs = distributed_poisson(pts, nrm, depth=8, partitions=3)
    assert topology_report(blobs.mesh)["components"] > 10


def test_states_pickled_between_steps_give_the_same_mesh(monkeypatch):
    """Slab states pickled after every step give the same mesh, and pickle at their size.

    Every slab state pickled and read back after every step (as Dask spills or moves it): the same
    mesh to the bit, and a pickled state is its size (the fields' views of the solve's arrays are
    not copied).
    """
    import pickle

    from recon_cli.slabs import runners as steps
    from recon_cli.stages.poisson import distributed as D

    pts, nrm = sphere_cloud(6000, seed=9)
    plain = distributed_poisson(pts, nrm, depth=7, partitions=3).mesh
    sizes = []

    class Pickling(steps.LocalRunner):
        def run(self, name, fn, args):
            out = super().run(name, fn, args)
            blobs = [pickle.dumps(s, protocol=5) for s in self.states]
            if name == "restrict":
                sizes.extend(
                    (len(b), steps.state_bytes(s)) for b, s in zip(blobs, self.states, strict=True)
                )
            self.states = [pickle.loads(b) for b in blobs]
            return out

    monkeypatch.setattr(
        D,
        "make_runner",
        lambda c, slabs, p=None, o=None, spill=None, **kw: Pickling(slabs, p, "x", o),
    )
    moved = distributed_poisson(pts, nrm, depth=7, partitions=3).mesh
    assert np.array_equal(moved.vertices, plain.vertices)
    assert np.array_equal(moved.faces, plain.faces)
    assert len(sizes) == 3
    for blob, state in sizes:
        assert state < blob < state + (1 << 20)


def test_an_empty_slab():
    """Two spheres apart along x, the middle slab empty: no faces there, two closed spheres."""
    a, na = sphere_cloud(6000, centre=(-3.0, 0, 0), seed=7)
    b, nb = sphere_cloud(6000, centre=(3.0, 0, 0), seed=8)
    pts, nrm = np.vstack([a, b]), np.vstack([na, nb])
    res = distributed_poisson(pts, nrm, depth=7, partitions=3, seams=[12, 20])
    slabs = res.report["distributed"]["slabs"]
    assert slabs[1]["points"] == 0 and slabs[1]["faces"] == 0
    assert slabs[0]["faces"] > 0 and slabs[2]["faces"] > 0
    closed_pieces(res.mesh, pieces=2)
    single = screened_poisson(pts, nrm, depth=7)
    assert abs(len(res.mesh.vertices) - len(single.mesh.vertices)) < 0.01 * len(
        single.mesh.vertices
    )


class _Bars:
    """A stand-in for recon_cli.progress.Progress recording every task's advances."""

    def __init__(self):
        self.tasks: dict[str, list] = {}

    def task(self, name, total=None):
        bars = self

        class T:
            def __enter__(self):
                bars.tasks[name] = [total, 0.0, 0]
                return self

            def __exit__(self, *exc):
                return None

            def advance(self, amount=1.0):
                bars.tasks[name][1] += amount
                bars.tasks[name][2] += 1

            def expect(self, amount):
                return None

        return T()


@pytest.mark.parametrize("kw", [{}, {"trim": 0.2, "colors": True, "point_weight": 0.0}])
def test_progress_over_the_whole_job_reaches_its_total(kw):
    """The job's progress bar reaches its total exactly, a slab at a time.

    It is advanced by every phase that runs (no phase weighed that does not run, none run
    unweighed).
    """
    pts, nrm = sphere_cloud(6000, seed=13)
    if kw.pop("colors", False):
        kw["colors"] = (np.abs(nrm) * 255).astype(np.uint8)
    bars = _Bars()
    distributed_poisson(pts, nrm, depth=7, partitions=3, progress=bars, **kw)
    total, done, steps = bars.tasks["poisson: the whole job"]
    assert done == pytest.approx(total, rel=1e-12) and steps > 3 * 10
    assert bars.tasks["poisson: solve"][:2] == [3, 3]


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"partitions": 0}, "partitions must be 1..64"),
        ({"partitions": 65}, "partitions must be 1..64"),
        ({"depth": 5}, "needs depth 6 or more"),
        ({"full_depth": 4}, "full_depth >= 5"),
        ({"partitions": 2, "seams": [40]}, "seams must be 1 increasing planes in 1..31"),
    ],
)
def test_refused_options(kw, msg):
    """Out-of-range partitions, depth, full depth and seams are refused with their message."""
    pts, nrm = sphere_cloud(2000, seed=1)
    with pytest.raises(ParameterError, match=msg):
        distributed_poisson(pts, nrm, **{"depth": 7, "partitions": 2, **kw})


def test_a_slab_reads_its_part_of_a_global_density_table():
    """A slab's part of a summed density table gives the whole table's density to the bit.

    The cells the coordinator sends a slab (table_part): the density at every point of its usable x
    range is the whole table's, to the bit; the part is a fraction of the whole.
    """
    from recon_cli.stages.poisson import slab as S
    from recon_cli.stages.poisson.distributed import table_part
    from recon_cli.stages.poisson.splat import merge_samples

    rng = np.random.default_rng(2)
    pts, nrm = sphere_cloud(20_000, seed=2)
    unit = (pts - pts.min(axis=0)) / (1.01 * np.ptp(pts, axis=0).max()) + 0.002
    smp = merge_samples(unit, nrm, 9)
    slab = S.slab_of(None, 0, 1, (0.0, 1.0), (0.0, 1.0), (0.0, 1.0))  # type: ignore[arg-type]
    slab.smp, slab.own_s = smp, np.ones(len(smp.count), bool)
    for level in (4, 6):
        msg = S.own_table(slab, level)  # the whole cube's table: the slab owns everything
        keys, dens = msg["keys"], msg["dens"]
        for usable in ((0.0, 0.3), (0.41, 0.58), (0.8, 1.0)):
            k, d = table_part(keys, dens, level, usable)
            assert 0 < len(k) < len(keys)
            q = rng.uniform(0, 1, size=(3000, 3))
            q[:, 0] = rng.uniform(*usable, size=len(q))
            q = np.concatenate([q, [[usable[0], 0.5, 0.5], [np.nextafter(usable[1], 0), 0.5, 0.5]]])
            got = S.eval_density(S.global_table(level, k, d), q)
            want = S.eval_density(S.global_table(level, keys, dens), q)
            assert np.array_equal(got, want)


# ---- the slab count -----------------------------------------------------------------------


def test_no_partitions_in_memory_is_one_slab_here():
    """Without a cluster and ``partitions=None``: one slab here, the single mesh, reported so."""
    pts, nrm = sphere_cloud(8000, seed=3)
    res = distributed_poisson(pts, nrm, depth=7, partitions=None)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=1)
    assert res.report["distributed"]["partitions"]["count"] == 1
    assert len(res.report["distributed"]["slabs"]) == 1
    assert np.array_equal(res.mesh.vertices, ref.mesh.vertices)
    with pytest.raises(ParameterError, match="partitions must be 1..64"):
        distributed_poisson(pts, nrm, depth=7, partitions=0)
    with pytest.raises(ParameterError, match="needs depth 7 or more"):
        distributed_poisson(pts, nrm, depth=6, partitions=33)


# ---- on a Dask cluster ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster of 2 workers for the module's tests (no memory limit, no stealing)."""
    from recon_cli.batch.cluster import open_client

    with open_client(workers=2, memory_limit="none", stealing=False) as (client, info):
        yield client


def _kill_a_worker_soon(pids: dict, killed: list[int]) -> None:
    """SIGKILL the first worker 0.3 s from now, from a thread (a step is then under way)."""

    def killer():
        time.sleep(0.3)
        pid = sorted(pids.values())[0]
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)

    threading.Thread(target=killer, daemon=True).start()


@pytest.mark.slow
def test_killed_worker_mid_solve_gives_the_same_mesh(cluster):
    """A worker SIGKILLed mid-solve: its slabs rerun on a live worker, the same mesh bit for bit."""
    from recon_cli.slabs import runners as steps

    pts, nrm = sphere_cloud(12_000, seed=11)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=2, client=cluster)
    pids = cluster.run(os.getpid)
    killed: list[int] = []
    orig = steps.DaskRunner.run

    def run(self, name, fn, args):
        if name == "solve" and not killed:
            _kill_a_worker_soon(pids, killed)
        return orig(self, name, fn, args)

    steps.DaskRunner.run = run
    try:
        res = distributed_poisson(pts, nrm, depth=7, partitions=2, client=cluster)
    finally:
        steps.DaskRunner.run = orig
    assert killed and killed[0] not in cluster.run(os.getpid).values()
    assert np.array_equal(res.mesh.vertices, ref.mesh.vertices)
    assert np.array_equal(res.mesh.faces, ref.mesh.faces)


@pytest.mark.slow
def test_more_slabs_than_workers_spill_their_states(cluster, tmp_path, monkeypatch):
    """Three slabs on two workers, states spilled, a worker killed: the in-process mesh exactly.

    Every state written to its file between steps and every shared argument to its own, a worker
    SIGKILLed while the slabs solve: the in-process run's mesh, bit for bit, and no file left.
    """
    from recon_cli.stages.poisson import distributed as D

    pts, nrm = sphere_cloud(12_000, seed=14)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=3)
    pids = cluster.run(os.getpid)
    killed: list[int] = []

    def kill_in_solve(name):
        if name == "solve" and not killed:
            _kill_a_worker_soon(pids, killed)

    runner, _ = spilling_runner(tmp_path, "poisson", kill_in_solve)
    monkeypatch.setattr(D, "make_runner", runner)
    res = distributed_poisson(pts, nrm, depth=7, partitions=3, client=cluster)
    assert killed and killed[0] not in cluster.run(os.getpid).values()
    assert np.array_equal(res.mesh.vertices, ref.mesh.vertices)
    assert np.array_equal(res.mesh.faces, ref.mesh.faces)
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_parts_spread_by_their_loads(cluster):
    """Parts are spread by their loads: the heaviest first, each to the least loaded worker.

    Loads 5, 4, 3, 1 on two workers pair the parts (0, 3) and (1, 2), 6 and 7 (in turn: 8 and 5); a
    slab's load is the points it reads, its pads included.
    """
    from types import SimpleNamespace

    from recon_cli.slabs import runners as steps
    from recon_cli.stages.poisson.distributed import make_job, plan_slabs, slab_loads

    def where(state):
        return {"pid": os.getpid()}

    runner = steps.DaskRunner(
        cluster, [SimpleNamespace() for _ in range(4)], loads=[5.0, 4.0, 3.0, 1.0]
    )
    try:
        pid = [m["pid"] for m in runner.run("x", where, lambda k: ())]
    finally:
        runner.close()
    assert pid[0] == pid[3] != pid[1] == pid[2]
    params = dict(
        samples_per_node=1.5,
        point_weight=4.0,
        boundary="neumann",
        full_depth=5,
        cg_tolerance=1e-3,
        density=False,
        trim=0.0,
    )
    job = make_job(np.zeros(3), 1.0, (0, 1, 2), 9, params)
    counts = np.random.default_rng(3).integers(0, 100, 1 << 7)
    plan = plan_slabs(job, counts, 3)
    for (_, (pa, pb), _), work in zip(plan, slab_loads(plan, counts), strict=True):
        assert work == counts[round(pa * len(counts)) : round(pb * len(counts))].sum()
    assert sum(slab_loads(plan, counts)) > counts.sum()  # the pads are read twice


def test_spilled_parts_keep_one_file_each(cluster, tmp_path):
    """Spilled parts keep at most one file each; only a worker with two parts writes.

    Three parts on two workers, every state spilled: after each step the folder holds at most one
    file per part (the file a step read goes once it wrote its own: a 20M-point run's 48 slab states
    are tens of GB a round); each worker keeps the last part it ran in memory and runs it first next
    time, so only the worker with two parts writes, one state a step; a step that only reads its
    state writes none and removes none; the states come back right.
    """
    import time
    from types import SimpleNamespace

    from recon_cli.slabs import runners as steps

    def add(state, x):
        state.v = state.v + x
        return {"v": state.v, "at": time.monotonic(), "pid": os.getpid()}

    @steps.reads_only
    def look(state):
        return {"v": state.v, "at": time.monotonic(), "pid": os.getpid()}

    runner = steps.DaskRunner(
        cluster, [SimpleNamespace(v=k) for k in range(3)], spill_dir=str(tmp_path), spill_bytes=0
    )
    seen = []
    try:
        for step in (add, add, look, add):
            live = set(runner.live)
            out = runner.run("x", step, (lambda k: (10,)) if step is add else (lambda k: ()))
            seen.append(sorted(os.listdir(tmp_path)))
            # on the worker with two parts, the one it kept in memory ran first
            pids = [m["pid"] for m in out]
            a, b = [k for k in range(3) if pids.count(pids[k]) == 2]
            if len({a, b} & live) == 1:
                first = a if a in live else b
                assert out[first]["at"] < out[a + b - first]["at"]
    finally:
        runner.close()
    assert [m["v"] for m in out] == [30, 31, 32]
    assert [len(s) for s in seen] == [1, 1, 1, 1]
    # parts 0 and 2 share a worker: 0 is written, then 2 (0 ran first, from memory), then
    # after the look, 0 again
    assert [s[0].rsplit("-", 2)[1] for s in seen] == ["0", "2", "2", "0"]
    assert seen[2] == seen[1] and seen[3] != seen[2]
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_an_argument_all_parts_share_is_written_once(cluster, tmp_path, monkeypatch):
    """With a spill folder, an argument every part's task shares is written to one file once.

    The tasks carry its path (Dask would pickle it into each of them: 48 copies of the coarse levels
    held the coordinator at 8.5 GiB and queued tasks took workers past their limit); each task reads
    the value, a per-part argument stays in its task, and close() removes the file.
    """
    from types import SimpleNamespace

    from recon_cli.slabs import runners as steps

    big = np.arange(1000, dtype=np.float64)

    def use(state, shared, own):
        state.v = float(shared.sum()) + own
        return {"v": state.v}

    sent = []
    submit = cluster.submit

    def spy(fn, *a, **kw):
        if fn is steps._step:
            sent.append(a[2])
        return submit(fn, *a, **kw)

    monkeypatch.setattr(cluster, "submit", spy)
    runner = steps.DaskRunner(
        cluster,
        [SimpleNamespace(v=0.0) for _ in range(3)],
        spill_dir=str(tmp_path),
        spill_bytes=0,
        shared_bytes=1000,
    )
    try:
        out = runner.run("x", use, lambda k: (big, float(k)))
        files = sorted(os.listdir(tmp_path))
    finally:
        runner.close()
    assert [m["v"] for m in out] == [499500.0, 499501.0, 499502.0]
    assert len(sent) == 3 and all(isinstance(a[0], steps.Shared) for a in sent)
    assert [a[1] for a in sent] == [0.0, 1.0, 2.0]
    assert sum(f.endswith(".arg") for f in files) == 1
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_laz_tiles_read_by_chunks(cluster, tmp_path, monkeypatch):
    """A folder of LAZ tiles read by chunks gives the in-memory mesh; mixed tiles are refused.

    A sphere cut in two at 1e5, read by the workers in chunks of a few rows (laspy seeking in the
    compressed files): the mesh of the in-memory run on the same points, with the LAS classification
    carried as codes; a tile with colours the others lack is refused and leaves no temporary folder.
    """
    import recon_cli.io.chunks as C
    from recon_cli.io.las import write_las
    from recon_cli.stages.poisson.files import reconstruct_files

    pts, nrm = sphere_cloud(10_000, seed=14)
    pts = pts * 20.0 + np.array([1e5, 2e5, 50.0])
    cls = np.where(nrm[:, 2] > 0, 6, 2).astype(np.uint8)
    for name, sel in (("a.laz", pts[:, 0] < 1e5), ("b.laz", pts[:, 0] >= 1e5)):
        write_las(
            PointCloud(points=pts[sel], normals=nrm[sel], attributes={"classification": cls[sel]}),
            str(tmp_path / name),
        )
    monkeypatch.setattr(C, "CHUNK_ROWS", 3000)
    res = reconstruct_files(
        str(tmp_path), client=cluster, depth=7, partitions=2, attributes="classification"
    )
    back = [load(str(tmp_path / n)) for n in ("a.laz", "b.laz")]
    p2 = np.vstack([b.points for b in back])
    n2 = np.vstack([b.normals for b in back])
    c2 = np.concatenate([b.attributes["classification"] for b in back])
    ref = distributed_poisson(p2, n2, depth=7, partitions=2, properties={"classification": c2})
    assert res.report["distributed"]["chunks"] == 4
    # the same mesh: a slab's points come in another row order from the tiles than from memory,
    # so its sums round differently (the last bits); a quad whose two diagonals tie to those bits
    # may be split the other way, nothing else
    assert np.abs(res.mesh.vertices - ref.mesh.vertices).max() < 1e-9
    assert _flipped_quads(res.mesh.faces, ref.mesh.faces) <= 2
    assert np.array_equal(
        res.mesh.attributes["classification"], ref.mesh.attributes["classification"]
    )
    assert res.mesh.attributes["classification"].dtype == np.uint8
    closed_pieces(res.mesh)
    # a tile with colours the others have not: refused before anything is written
    rgb = np.full((100, 3), 40000, np.uint16)
    write_las(PointCloud(points=pts[:100], normals=nrm[:100], colors=rgb), str(tmp_path / "c.laz"))
    with pytest.raises(InputError, match="do not all have the same"):
        reconstruct_files(str(tmp_path), client=cluster, depth=7, temp_dir=str(tmp_path))
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".recon-")]


def _flipped_quads(a: np.ndarray, b: np.ndarray) -> int:
    """How many quads ``a`` splits along the other diagonal than ``b``; fails on any other change.

    Faces in the same order; a quad's two triangles are consecutive rows (as extraction emits them).
    """
    assert a.shape == b.shape
    rows = np.flatnonzero((a != b).any(axis=1))
    assert len(rows) % 2 == 0 and np.all(rows[1::2] == rows[::2] + 1), rows
    for i in rows[::2]:
        quad = set(a[i]) | set(a[i + 1])
        assert len(quad) == 4 and quad == set(b[i]) | set(b[i + 1]), (i, a[i : i + 2], b[i : i + 2])
        assert set(a[i]) != set(b[i]) and set(a[i]) != set(b[i + 1])  # the other diagonal
    return len(rows) // 2


def _recon(argv: list[str]) -> int:
    """The real CLI entry point in-process; its exit status."""
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


@pytest.mark.slow
def test_command_reads_the_file_by_chunks(tmp_path, monkeypatch, capsys):
    """``recon poisson IN OUT --workers 2`` reads IN by chunks: the in-memory distributed mesh.

    The command never loads IN (the workers read its chunks, dropping and counting a NaN row as the
    reader does); the mesh is the in-memory distributed run's, double in, double out, with the
    input's properties in their types.
    """
    import recon_cli.io.chunks as C
    import recon_cli.io.load as L

    pts, nrm = sphere_cloud(12_000, seed=12)
    props = {
        "classification": np.where(pts[:, 2] > 0.2, 6, 2).astype(np.uint8),
        "intensity": (100 + 50 * pts[:, 0]).astype(np.uint16),
    }
    src = tmp_path / "sphere.ply"
    bad = np.insert(pts, 7000, [np.nan, 0.0, 0.0], axis=0)
    attrs = {k: np.insert(v, 7000, 0) for k, v in props.items()}
    save(
        PointCloud(points=bad, normals=np.insert(nrm, 7000, nrm[0], 0), attributes=attrs), str(src)
    )
    monkeypatch.setattr(C, "CHUNK_ROWS", 5000)  # three chunks

    def refuse(*a, **k):
        raise AssertionError("the command loaded IN")

    monkeypatch.setattr(L, "load", refuse)
    out = tmp_path / "mesh.ply"
    code = _recon(["poisson", str(src), str(out), "--workers", "2", "--depth", "7", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)
    assert rep["distributed"]["chunks"] == 3
    assert rep["distributed"]["partitions"]["count"] == 2 == len(rep["distributed"]["slabs"])
    assert set(rep["distributed"]["phases"]) >= {"load", "solve", "extract", "attributes"}
    assert rep["read"] == {"kept": len(pts), "invalid_dropped": 1}
    assert rep["attributes"] == ["classification", "intensity"]
    mesh = load(str(out))
    closed_pieces(mesh)
    assert mesh.vertices.dtype == np.float64
    ref = distributed_poisson(pts, nrm, depth=7, partitions=2, properties=props)
    assert len(ref.mesh.vertices) == len(mesh.vertices)
    for k in props:
        assert mesh.attributes[k].dtype == props[k].dtype
        assert np.array_equal(mesh.attributes[k], ref.mesh.attributes[k])
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".recon-poisson-")]


@pytest.mark.slow
def test_command_reports_the_slab_count_and_why(tmp_path, monkeypatch, capsys):
    """Without ``--partitions`` the slab count follows the workers' memory and ``--json`` says why.

    ``--workers 2 --memory 5GiB`` (2 GiB a worker) on a cloud whose slab (at a patched bytes per
    point) fits a worker's share three times over: four slabs, two per worker; with ``--partitions
    3``, three, given.
    """
    pts, nrm = sphere_cloud(6000, seed=15)
    src = tmp_path / "sphere.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    mem = 2 * 2**30
    _slab_bytes_per_point(monkeypatch, 3 * SLAB_MEMORY_SHARE * mem / len(pts))
    # the largest of 4 slabs reads 62 % of this small sphere with its pads: it fits the worker
    # at a worker's figure of its state alone (the fit on the largest slab has its own test)
    monkeypatch.setattr(PM, "WORKER_STATE_FACTOR", 1.0)
    argv = ["poisson", str(src), str(tmp_path / "m.ply"), "--workers", "2", "--depth", "7"]
    argv += ["--memory", "5GiB", "--json", "-q"]
    for extra, count, why in (
        ([], 4, "2 per worker: a slab (~"),
        (["--partitions", "3"], 3, "given"),
    ):
        code = _recon(argv + extra)
        captured = capsys.readouterr()
        assert code == 0, captured.err
        rep = json.loads(captured.out)["distributed"]
        assert rep["partitions"]["count"] == count == len(rep["slabs"])
        assert rep["partitions"]["why"].startswith(why)
        assert rep["partitions"]["memory_per_worker"] == mem
        assert rep["partitions"]["points"] == len(pts)


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--partitions", "2", "--envelope", "e.ply"], "no such file"),
        (["--partitions", "2", "--grid", "-"], "--grid needs a file name"),
        (["--memory", "10MB"], "--memory must be a size of at least 256 MiB"),
        (["--temp-dir", "/nonexistent/x"], "--temp-dir /nonexistent/x: no such folder"),
        (["--workers", "2", "--degree", "1"], "uses degree 2"),
        (["--workers", "2", "--scheduler", "tcp://x:1"], "give one of them"),
        (["--workers", "2", "--backend", "open3d"], "native solver"),
        (["--workers", "2", "--envelope", "e.ply"], "no such file"),
    ],
)
def test_command_refuses(tmp_path, capsys, args, msg):
    """Options the slabs or the workers cannot honour exit 2 with a message naming them."""
    pts, nrm = sphere_cloud(500, seed=1)
    src = tmp_path / "s.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    assert _recon(["poisson", str(src), str(tmp_path / "o.ply"), *args]) == 2
    err = capsys.readouterr().err
    assert msg in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.slow
def test_ctrl_c_mid_job_leaves_nothing(tmp_path):
    """Ctrl-C (SIGINT to the group) once the chunks are sorted: exit 130, one line, nothing left."""
    import sys

    import psutil

    from recon_cli.cli.main import EXIT_INTERRUPTED

    pts, nrm = sphere_cloud(40_000, seed=3)
    src = tmp_path / "sphere.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    out = tmp_path / "mesh.ply"
    argv = [sys.executable, "-c", SIGINT_AS_A_TERMINAL + RUN_RECON, "poisson", str(src), str(out)]
    argv += ["--workers", "2", "--depth", "9"]
    # once a chunk is sorted into the job's temporary folder: the cluster is at work
    run = interrupt_when(
        argv, lambda: list(tmp_path.glob(".recon-poisson-*/*.pts.npy")), "no sorted chunk"
    )
    assert len(run.family) >= 2  # at least the two worker processes
    assert run.returncode == EXIT_INTERRUPTED == 130, run.err
    assert run.err.strip() == "recon: interrupted", run.err
    _, alive = psutil.wait_procs(run.family, timeout=10)
    assert alive == [], [(p.pid, p.name()) for p in alive]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.ply"]


# ---- in slabs in this process (out of core) -------------------------------------------------


def _slab_bytes_per_point(monkeypatch, per_point: float) -> None:
    """A Poisson slab's memory patched to ``per_point`` bytes a point (its rings' share 0)."""
    monkeypatch.setattr(PM, "SLAB_POINT_BYTES", per_point)
    monkeypatch.setattr(PM, "SLAB_RING_BYTES", 0)


def _refuse_loading(monkeypatch):
    import recon_cli.io.load as L

    def refuse(*a, **k):
        raise AssertionError("the command loaded IN")

    monkeypatch.setattr(L, "load", refuse)


@pytest.mark.slow
def test_out_of_core_command_reads_the_file_by_chunks_in_this_process(
    tmp_path, monkeypatch, capsys
):
    """``recon poisson --memory 1GiB`` too small for the cloud runs 3 slabs from IN's chunks.

    The cloud is too large for that in one piece (at a patched bytes per point): this process runs 3
    slabs from IN's chunks, never loading IN; the mesh is the in-memory run's in 3 slabs, closed and
    one piece; the spill folder beside OUT is gone; the report says how many slabs and why.
    """
    import recon_cli.io.chunks as C

    pts, nrm = sphere_cloud(9000, seed=21)
    src = tmp_path / "sphere.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    monkeypatch.setattr(C, "CHUNK_ROWS", 4000)  # three chunks
    mem = 2**30
    _slab_bytes_per_point(monkeypatch, 2.5 * SLAB_MEMORY_SHARE * mem / len(pts))
    _refuse_loading(monkeypatch)
    out = tmp_path / "mesh.ply"
    code = _recon(["poisson", str(src), str(out), "--depth", "7", "--memory", "1GiB", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)["distributed"]
    assert rep["chunks"] == 3 and rep["cluster"]["workers"] == 0
    assert rep["partitions"]["count"] == 3 == len(rep["slabs"])
    assert rep["partitions"]["why"].startswith("3 slabs in this process: a slab (~")
    assert "of this process's 1 GiB" in rep["partitions"]["why"]
    mesh = load(str(out))
    closed_pieces(mesh)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=3).mesh
    assert len(ref.vertices) == len(mesh.vertices) and len(ref.faces) == len(mesh.faces)
    assert np.allclose(np.sort(ref.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-12)
    assert sorted(os.listdir(tmp_path)) == ["mesh.ply", "sphere.ply"]


def test_command_trims_auto_in_slabs_from_the_file(tmp_path, monkeypatch, capsys):
    """``--partitions 3 --trim auto`` on the file, read by chunks: the in-memory 3 slabs' mesh."""
    rng = np.random.default_rng(0)
    pts, nrm = single_view_scan("torus", 120, rng, direction=(0.3, 0.2, -1.0))
    src = tmp_path / "scan.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    _refuse_loading(monkeypatch)
    out = tmp_path / "mesh.ply"
    args = ["poisson", str(src), str(out), "--depth", "6", "--partitions", "3", "--trim", "auto"]
    code = _recon([*args, "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)
    assert rep["trimmed_area"] > 0.5 and len(rep["distributed"]["slabs"]) == 3
    mesh = load(str(out))
    ref = distributed_poisson(pts, nrm, depth=6, partitions=3, trim="auto")
    assert len(ref.mesh.faces) == len(mesh.faces) > 0
    assert np.allclose(np.sort(ref.mesh.vertices, axis=0), np.sort(mesh.vertices, axis=0))
    assert topology_report(mesh)["boundary_loops"] > 0


def test_command_writes_the_grid_in_slabs_from_the_file(tmp_path, monkeypatch, capsys):
    """``--partitions 2 --grid G`` by chunks: G is the in-memory slabs' grid, with its history."""
    from recon_cli.io.npz import read_grid

    pts, nrm = shape_cloud("torus", 20_000, np.random.default_rng(5), offset=1e6)
    src = tmp_path / "torus.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    _refuse_loading(monkeypatch)
    out, grid = tmp_path / "mesh.ply", tmp_path / "field.npz"
    args = ["poisson", str(src), str(out), "--depth", "6", "--partitions", "2"]
    code = _recon([*args, "--grid", str(grid), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)
    g = read_grid(str(grid))
    assert rep["grid"] == str(grid) and rep["grid_shape"] == list(g.sdf.shape)
    assert g.point_dtype == np.float64 and g.history[-1].startswith("poisson: (iso - chi)")
    ref = distributed_poisson(pts, nrm, depth=6, partitions=2, with_grid=True).grid
    assert g.sdf.shape == ref.sdf.shape and np.allclose(g.origin, ref.origin, rtol=1e-15)
    assert np.abs(g.sdf - ref.sdf).max() < 1e-3 * g.voxel_size


def test_spilled_states_give_the_same_mesh(tmp_path, monkeypatch):
    """States spilled between steps: the in-memory slabs' mesh to the bit, the folder left empty."""
    from recon_cli.slabs import runners

    pts, nrm = sphere_cloud(6000, seed=22)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=3)
    monkeypatch.setattr(runners, "SPILL_BYTES", 0)
    got = distributed_poisson(pts, nrm, depth=7, partitions=3, temp_dir=str(tmp_path))
    assert np.array_equal(got.mesh.vertices, ref.mesh.vertices)
    assert np.array_equal(got.mesh.faces, ref.mesh.faces)
    phases = got.report["distributed"]["phases"]
    # two of the three states a step are written (the last one run stays in memory)
    assert phases["solve"]["bytes_moved"] > 0 and phases["extract"]["bytes_moved"] > 0
    assert ref.report["distributed"]["phases"]["solve"]["bytes_moved"] == 0
    assert os.listdir(tmp_path) == []


def test_run_on_memory_puts_the_library_call_in_slabs(monkeypatch):
    """``recon_cli.poisson`` in ``run_on(memory=...)`` runs in slabs when the cloud needs it.

    The cloud needs more than the memory in one piece, so the stage runs in slabs in this process
    (the report says so) and the mesh is the slabs' run; without the limit, the single-process
    solve.
    """
    import recon_cli

    pts, nrm = sphere_cloud(6000, seed=23)
    cloud = PointCloud(points=pts, normals=nrm)
    _slab_bytes_per_point(monkeypatch, 1.5 * SLAB_MEMORY_SHARE * 2**30 / len(pts))
    with recon_cli.run_on(memory="1GiB"):
        mesh = recon_cli.poisson(cloud, depth=7)
    ref = distributed_poisson(pts, nrm, depth=7, partitions=2).mesh
    assert np.array_equal(np.sort(mesh.vertices, axis=0), np.sort(ref.vertices, axis=0))
    single = recon_cli.poisson(cloud, depth=7)
    assert len(single.vertices) == len(screened_poisson(pts, nrm, depth=7).mesh.vertices)


def test_a_memory_too_small_for_the_most_slabs_is_refused_up_front(tmp_path, monkeypatch, capsys):
    """One line with the least memory that would do, exit 2, nothing written, IN not read."""
    pts, nrm = sphere_cloud(3000, seed=24)
    src = tmp_path / "s.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    _slab_bytes_per_point(monkeypatch, 10**9)
    _refuse_loading(monkeypatch)
    out = tmp_path / "o.ply"
    assert _recon(["poisson", str(src), str(out), "--memory", "2GB", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "poisson: 3000 points need at least" in err and "this process's limit is 1.86 GiB" in err
    assert sorted(os.listdir(tmp_path)) == ["s.ply"]


def _tmpfs(path, size: str):
    import subprocess

    path.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True
    )
    if done.returncode != 0:  # pragma: no cover - a machine that does not let us mount
        pytest.skip(f"cannot mount a small file system here: {done.stderr.decode().strip()}")


@pytest.mark.slow
def test_a_full_disk_while_spilling_is_one_line_and_keeps_the_old_output(tmp_path):
    """A full disk while spilling: exit 1, one line, the old output kept, the folder emptied.

    The spill folder on a 1 MiB file system: one line naming the folder, the output that was there
    before left as it was, nothing left in the folder (a real process, a real full file system).
    """
    import subprocess
    import sys

    pts, nrm = sphere_cloud(20_000, seed=25)
    src = tmp_path / "s.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    out = tmp_path / "o.ply"
    out.write_bytes(b"the old output")
    small = tmp_path / "small"
    _tmpfs(small, "1m")
    try:
        argv = [sys.executable, "-c", "import sys\n" + RUN_RECON, "-q", "poisson", str(src)]
        argv.append(str(out))
        argv += ["--depth", "7", "--partitions", "3", "--temp-dir", str(small)]
        run = subprocess.run(argv, capture_output=True, text=True, timeout=600)
        assert run.returncode == 1, run.stderr
        err = run.stderr.strip()
        assert err == f"recon: error: {small}: no space left on device for the run's spill files"
        assert out.read_bytes() == b"the old output"
        assert os.listdir(small) == []
    finally:
        subprocess.run(["umount", str(small)], check=False)


@pytest.mark.slow
def test_sigterm_mid_out_of_core_run_leaves_nothing(tmp_path):
    """SIGTERM once the chunks are spilled beside OUT: exit 143, one line, no output, no folder."""
    import sys

    pts, nrm = sphere_cloud(60_000, seed=26)
    src = tmp_path / "sphere.ply"
    save(PointCloud(points=pts, normals=nrm), str(src))
    out = tmp_path / "mesh.ply"
    argv = [sys.executable, "-c", "import sys\n" + RUN_RECON, "poisson", str(src), str(out)]
    argv += ["--partitions", "4", "--depth", "9"]
    run = interrupt_when(
        argv,
        lambda: (
            list(tmp_path.glob(".recon-poisson-*/states/*.state"))
            or list(tmp_path.glob(".recon-poisson-*/c00000.pts.npy"))
        ),
        "no spill file",
        group=False,
        signum=signal.SIGTERM,
    )
    assert run.returncode == 143, run.err
    assert run.err.strip() == "recon: terminated", run.err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.ply"]


@pytest.mark.slow
def test_the_mesh_does_not_depend_on_how_the_work_was_cut():
    """Noisy armadillo in 1, 2, 4 and 8 slabs: the same closed mesh within half a finest cell.

    Samples turned at random, 1e6 from the origin, in slabs of this process: every pair within half
    a finest cell of each other (Hausdorff, exact point-to-triangle distances both ways), face
    counts within 0.5 % of the one slab's, each closed (0 boundary edges: no face lost at a seam),
    manifold, one piece, no vertex twice.
    """
    from recon_cli.mesh.distance import closest_points

    from shared_data import sampled_cloud

    rng = np.random.default_rng(44)
    c = sampled_cloud("armadillo", 20_000, 0.001, 4)
    r = random_rotation(rng)
    pts = (c.points - c.points.mean(axis=0)) @ r.T + np.array([1e6, -1e6, 5e5])
    nrm = c.normals @ r.T
    runs = {k: distributed_poisson(pts, nrm, depth=7, partitions=k) for k in (1, 2, 4, 8)}
    cell = runs[1].report["finest_cell"]
    faces = len(runs[1].mesh.faces)
    for k, res in runs.items():
        closed_pieces(res.mesh)
        assert abs(len(res.mesh.faces) - faces) <= 0.005 * faces, k
        assert len(res.report["distributed"]["slabs"]) == k
    for a in runs:
        for b in runs:
            if a < b:
                ma, mb = runs[a].mesh, runs[b].mesh
                dab = closest_points(mb.vertices, mb.faces, ma.vertices)[0].max()
                dba = closest_points(ma.vertices, ma.faces, mb.vertices)[0].max()
                assert max(dab, dba) <= 0.5 * cell, (a, b, max(dab, dba) / cell)
