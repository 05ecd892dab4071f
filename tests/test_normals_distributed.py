"""Distributed normals (recon_cli.stages.normals.distributed).

Halos give the single-process neighbourhoods, orientation joined across slabs, the command reading
and writing by chunks.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from recon_cli import run_on
from recon_cli.errors import ParameterError
from recon_cli.geometry import PointCloud
from recon_cli.io.load import load, save
from recon_cli.stages.normals import estimate_normals, orient_normals
from recon_cli.stages.normals.distributed import HALO, SUB_SLABS, distributed_normals

from shapes import random_rotation, single_view_scan
from shared_data import sampled_cloud
from spilling import spilling_runner


def _single(points, method="mst", **kw):
    n, curv, _ = estimate_normals(points, 30)
    o, _ = orient_normals(points, n, method, **kw)
    return o, curv


@pytest.mark.parametrize("name, parts", [("armadillo", 4), ("mug", 3)])
def test_slabs_give_the_single_process_normals(name, parts):
    """Rotated samples 1e6 from the origin in slabs: the single-process normals, oriented alike.

    Every normal and curvature is the single-process one (halos make the neighbourhoods exact),
    oriented alike (the slabs' components joined across seams).
    """
    rng = np.random.default_rng(3)
    c = sampled_cloud(name, 40_000, 0.001, 1)
    pts = c.points @ random_rotation(rng).T + 1e6
    ref, curv = _single(pts)
    with run_on(partitions=parts):
        nrm, dcurv, rep = distributed_normals(pts, orient="mst", curvature=True)
    dots = np.einsum("ij,ij->i", nrm, ref)
    assert dots.min() > 1 - 1e-9
    assert np.allclose(dcurv, curv, atol=1e-12)
    assert rep["components"] == 1
    assert sum(rep["distributed"]["slab_points"]) == len(pts)


def test_halo_widens_until_neighbourhoods_are_exact():
    """Sparse points: the halo widens until neighbourhoods are exact, as in the single process.

    With a few points per sub-slab the first halo cannot hold every point's 30 neighbours; it is
    widened and the normals are the single-process ones.
    """
    rng = np.random.default_rng(4)
    p = rng.normal(size=(3000, 3))
    p[:, 0] *= 5
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    ref, _ = _single(p)
    with run_on(partitions=4):
        nrm, _, rep = distributed_normals(p, orient="mst")
    assert rep["distributed"]["halo"] > HALO / SUB_SLABS
    assert np.einsum("ij,ij->i", nrm, ref).min() > 1 - 1e-9


def test_camera_and_keep():
    """Camera orientation in 3 slabs: the single-process normals; ``keep``: the input's signs."""
    rng = np.random.default_rng(5)
    pts, truth = single_view_scan("torus", 120, rng, direction=(0.3, 0.2, -1.0))
    cam = -5 * np.array([0.3, 0.2, -1.0])
    with run_on(partitions=3):
        nrm, _, _ = distributed_normals(pts, orient="camera", camera=cam)
    ref, _ = _single(pts, "camera", camera=cam)
    assert np.einsum("ij,ij->i", nrm, ref).min() > 1 - 1e-9
    # keep: the input's signs, whatever they are
    signs = np.where(rng.random(len(pts)) < 0.5, -1.0, 1.0)[:, None]
    with run_on(partitions=3):
        nrm, _, _ = distributed_normals(pts, truth * signs, orient="keep")
    assert (np.einsum("ij,ij->i", nrm, truth * signs) > 0).mean() > 0.99


def test_camera_towards_each_points_own_scanner():
    """``--orient camera`` without ``--camera`` in slabs: each point towards its own scanner.

    The scanner is the cloud's sensor of the point's scan index, as in the single-process run.
    """
    from recon_cli.geometry import SCAN_ATTRIBUTE, Sensor
    from recon_cli.stages.normals import run_stage, sensor_views

    rng = np.random.default_rng(7)
    p = rng.normal(size=(6000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p = p * np.array([3.0, 1.0, 1.0]) + 1e5
    which = (p[:, 0] < 1e5).astype(np.int64)
    sensors = [Sensor(position=(1e5 + 8.0, 1e5, 1e5)), Sensor(position=(1e5 - 8.0, 1e5, 1e5))]
    cloud = PointCloud(points=p, sensors=sensors, attributes={SCAN_ATTRIBUTE: which})
    ref = run_stage(cloud, orient="camera").output.normals
    views = sensor_views(sensors, which, len(p), 0)
    with run_on(partitions=3):
        nrm, _, _ = distributed_normals(p, orient="camera", sensors=views)
    assert np.einsum("ij,ij->i", nrm, ref).min() > 1 - 1e-9
    # each towards its own scanner (not the other one: the sides facing away flip)
    at = np.array([s.position for s in sensors])
    assert (np.einsum("ij,ij->i", nrm, at[which] - p) >= 0).all()
    assert (np.einsum("ij,ij->i", nrm, at[1 - which] - p) < 0).mean() > 0.2


def test_refused():
    """More than 32 partitions, and ``keep`` without input normals, are refused."""
    p = np.random.default_rng(1).normal(size=(100, 3))
    refused = "--partitions must be 1..32 for normals, got 33"
    with run_on(partitions=33), pytest.raises(ParameterError, match=refused):
        distributed_normals(p)
    with run_on(partitions=2), pytest.raises(ParameterError, match="keep needs input normals"):
        distributed_normals(p, orient="keep")


@pytest.mark.slow
@pytest.mark.parametrize("where", [["--workers", "2"], ["--memory", "1GiB"]])
def test_command_keeps_every_property_and_row(tmp_path, monkeypatch, capsys, where):
    """``recon normals`` in slabs, read and written by chunks, keeps every property and row.

    ``recon normals IN OUT --workers 2``, or in this process with a memory too small for IN in one
    piece (at a patched bytes per point: 3 slabs): IN read by chunks (never whole by the command),
    OUT written a chunk at a time: the same rows in the same order with every property of IN, and
    the single-process normals.
    """
    import recon_cli.io.chunks as C
    import recon_cli.io.load as L
    from recon_cli.cli.main import main
    from recon_cli.slabs.plan import SLAB_MEMORY_SHARE
    from recon_cli.stages.normals import distributed as D

    c = sampled_cloud("kitten", 12_000, 0.0, 2)
    rng = np.random.default_rng(6)
    cloud = PointCloud(
        points=c.points.astype(np.float32),
        colors=rng.integers(0, 255, size=(len(c.points), 3), dtype=np.uint8),
        attributes={"intensity": rng.random(len(c.points)).astype(np.float32)},
        point_dtype=np.float32,
    )
    src, out = tmp_path / "k.ply", tmp_path / "n.ply"
    save(cloud, str(src))
    monkeypatch.setattr(C, "CHUNK_ROWS", 5000)

    def refuse(*a, **k):
        raise AssertionError("the command loaded IN")

    monkeypatch.setattr(L, "load", refuse)
    bpp = 2.5 * SLAB_MEMORY_SHARE * 2**30 / len(cloud.points)
    monkeypatch.setattr(D, "slab_bytes_per_point", lambda knn: bpp)
    with pytest.raises(SystemExit) as exc:
        main(["normals", str(src), str(out), *where, "--json"])
    captured = capsys.readouterr()
    assert exc.value.code == 0, captured.err
    monkeypatch.undo()
    rep = json.loads(captured.out)
    assert rep["distributed"]["chunks"] == 3 and rep["points"] == len(cloud.points)
    assert rep["stage"] == "normals" and rep["backend"] == "native" and "read" not in rep
    assert set(rep["timings"]) >= {"stage", "write"}
    if where[0] == "--workers":
        assert rep["distributed"]["cluster"]["workers"] == 2
    else:
        assert rep["distributed"]["partitions"]["count"] == 3 == rep["distributed"]["slabs"]
        assert rep["distributed"]["partitions"]["why"].startswith("3 slabs in this process")
    assert [f for f in os.listdir(tmp_path) if f.startswith(".recon")] == []
    got = load(str(out))
    assert np.array_equal(got.points, cloud.points)
    assert np.array_equal(got.colors, cloud.colors)
    assert np.array_equal(got.attributes["intensity"], cloud.attributes["intensity"])
    ref, _ = _single(cloud.points.astype(np.float64))
    assert (np.einsum("ij,ij->i", got.normals.astype(np.float64), ref) > 0.999).all()
    assert got.history[-1].startswith("recon ") and " normals " in got.history[-1]


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster of 2 workers for the module's tests (no memory limit, no stealing)."""
    from recon_cli.batch.cluster import open_client

    with open_client(workers=2, memory_limit="none", stealing=False) as (client, _info):
        yield client


@pytest.mark.slow
def test_more_slabs_than_workers_spill_their_states(cluster, tmp_path, monkeypatch):
    """Three slabs on two workers spill their states and give the in-process normals exactly.

    A state is written to its file between steps unless its worker runs it next (a worker holds one
    slab at a time); no file is left.
    """
    from recon_cli.stages.normals import distributed as D

    c = sampled_cloud("armadillo", 30_000, 0.001, 1)
    with run_on(partitions=3):
        ref, _, _ = distributed_normals(c.points, orient="mst")
    runner, seen = spilling_runner(tmp_path, "normals")
    monkeypatch.setattr(D, "make_runner", runner)
    with run_on(scheduler=cluster.scheduler.address, partitions=3):
        nrm, _, rep = distributed_normals(c.points, orient="mst")
    # after the neighbourhoods: the worker with two slabs wrote the one it ran first
    assert seen[1] == 1
    assert np.array_equal(nrm, ref)
    assert rep["components"] == 1
    assert os.listdir(tmp_path) == []


def test_slab_count_from_the_workers_memory():
    """Without --partitions, the slab count is the fewest that fit a share of a worker's memory.

    The fewest slabs (whole rounds of the workers) whose one slab's neighbourhoods and graph fit a
    share of a worker's memory: more neighbours, more slabs; at most 32, and a cloud too large for
    32 is refused with the memory it needs.
    """
    from recon_cli.slabs.plan import SLAB_MEMORY_SHARE
    from recon_cli.stages.normals.distributed import MAX_SLABS, slab_bytes_per_point, slab_count

    class Client:
        def scheduler_info(self):
            return {"workers": {"a": {"memory_limit": 2**32}, "b": {"memory_limit": 2**32}}}

    per_slab = SLAB_MEMORY_SHARE * 2**32 / slab_bytes_per_point(30)
    n, rep = slab_count(None, int(2 * per_slab), Client(), 30)
    assert n == 2 and rep["why"].startswith("one per worker")
    assert slab_count(None, int(2 * per_slab) + 1, Client(), 30)[0] == 4
    assert slab_bytes_per_point(60) > slab_bytes_per_point(30) == slab_bytes_per_point(None)
    assert slab_count(None, int(2 * per_slab), Client(), 60)[0] == 4
    assert slab_count(None, int(MAX_SLABS * per_slab), Client(), 30)[0] == MAX_SLABS
    with pytest.raises(ParameterError, match=r"normals: .* need at least \d+ MiB"):
        slab_count(None, 10**10, Client(), 30)
    # in this process: its budget
    assert slab_count(None, int(3 * per_slab), None, 30, 2**32)[0] == 3
