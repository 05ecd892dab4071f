"""Faults in the runs of the slab stages (poisson, normals), with real processes and signals.

- A Dask worker SIGKILLed mid-run: the run finishes with the bytes of an undisturbed run (Dask
  recomputes the lost slabs' states on the worker the nanny starts again).
- The run's own process SIGKILLed mid-run (nothing can clean up): the output that was there is
  kept and no temporary file is beside it; the spill folder stays, and the next run that
  spills in the same folder removes it (its ``owner.lock`` is no longer held).
- A full disk while spilling (normals; poisson's is in test_poisson_distributed) or while
  writing OUT: exit 1, one line, the old output kept, nothing left.
- SIGTERM mid out-of-core normals: exit 143, one line, nothing left.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from recon_cli.geometry import PointCloud
from recon_cli.io.load import save
from recon_cli.slabs.spill import OWNER, remove_stale, spill_folder

from interrupt import RUN_RECON, interrupt_when
from shapes import sphere_cloud

OLD = b"the output that was there before\n"
RECON = [sys.executable, "-c", "import sys\n" + RUN_RECON, "-q"]


def _cloud(folder: Path, n: int, seed: int, normals: bool = True) -> Path:
    pts, nrm = sphere_cloud(n, seed=seed)
    path = folder / f"sphere{n}-{seed}.ply"
    save(PointCloud(points=pts, normals=nrm if normals else None), str(path))
    return path


def _recon_here(args: list[str]) -> int:
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as ex:
        main(["-q", *map(str, args)])
    return ex.value.code


@contextlib.contextmanager
def _tmpfs(path: Path, size: str):
    path.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True
    )
    if done.returncode != 0:  # pragma: no cover - a machine that does not let us mount
        pytest.skip(f"cannot mount a small file system here: {done.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=False)


# ---- the spill folders of dead runs -----------------------------------------------------------


def test_only_the_folders_of_dead_runs_are_removed(tmp_path):
    """Only the spill folders of dead runs are removed.

    A folder whose owner lock is held (this run's) stays; one whose owner died goes; a ``.recon-``
    folder without an owner file and any other folder stay.
    """
    dead = tmp_path / ".recon-poisson-dead"
    dead.mkdir()
    (dead / OWNER).write_text("999999\n")  # nobody holds its lock
    (dead / "c00000.pts.npy").write_bytes(b"x" * 100)
    foreign = tmp_path / ".recon-unknown"
    foreign.mkdir()
    other = tmp_path / "results"
    other.mkdir()
    with spill_folder(str(tmp_path), "normals") as live:
        assert sorted(os.listdir(live)) == [OWNER]
        assert (Path(live) / OWNER).read_text() == f"{os.getpid()}\n"
        assert not dead.exists()  # a new spill folder removes the dead ones first
        assert remove_stale(str(tmp_path)) == []
        assert os.path.isdir(live)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".recon-unknown", "results"]


def test_a_killed_run_leaves_its_folder_to_the_next_run(tmp_path):
    """A run killed while spilling leaves OUT as it was and its folder for the next run.

    Runs in slabs in this process beside an OUT that exists, SIGKILLed once they spill, poisson then
    normals: OUT is as it was, no temporary file is beside it, the run's spill folder stays with the
    killed process's id in its owner file. Each next run that spills there removes the folder the
    killed one left: normals poisson's, then a small normals run the killed normals'.
    """
    oriented = _cloud(tmp_path, 60_000, seed=3)
    bare = _cloud(tmp_path, 60_000, seed=4, normals=False)
    outs = {"poisson": tmp_path / "mesh.ply", "normals": tmp_path / "normals.ply"}
    for out in outs.values():
        out.write_bytes(OLD)
    runs = {
        "poisson": [*RECON, "poisson", oriented, outs["poisson"], "--depth", "9"],
        "normals": [*RECON, "normals", bare, outs["normals"], "--knn", "60"],
    }
    for stage, argv in runs.items():
        proc = interrupt_when(
            [str(a) for a in [*argv, "--partitions", "4"]],
            lambda stage=stage: list(tmp_path.glob(f".recon-{stage}-*/c00000.pts.npy")),
            f"no sorted chunk of {stage}",
            signum=signal.SIGKILL,
        )
        assert proc.returncode == -signal.SIGKILL, proc.err
        left = list(tmp_path.glob(".recon-*"))
        assert [p.name.split("-")[1] for p in left] == [stage]
        assert (left[0] / OWNER).read_text() == f"{proc.pid}\n"
        assert outs[stage].read_bytes() == OLD
    small = _cloud(tmp_path, 3000, seed=5, normals=False)
    assert _recon_here(["normals", small, tmp_path / "n.ply", "--partitions", "2"]) == 0
    expected = sorted([oriented.name, bare.name, small.name, "mesh.ply", "normals.ply", "n.ply"])
    assert sorted(p.name for p in tmp_path.iterdir()) == expected


# ---- a worker killed --------------------------------------------------------------------------


def _workers(pid: int) -> list:
    """The Dask worker processes of the recon process ``pid`` (spawned by its nannies)."""
    import psutil

    return [
        p
        for p in psutil.Process(pid).children(recursive=True)
        if "spawn_main" in " ".join(p.cmdline())
    ]


@pytest.mark.slow
@pytest.mark.parametrize(
    "stage, args",
    [
        ("poisson", ["--depth", "8"]),
        ("normals", ["--knn", "40"]),
    ],
)
def test_a_killed_worker_gives_the_same_bytes(tmp_path, stage, args):
    """A worker SIGKILLed once the chunks are sorted: exit 0 and the same bytes.

    ``recon STAGE IN OUT --workers 2 --partitions 2``: the bytes of the same two slabs run in this
    process.
    """
    src = _cloud(tmp_path, 40_000, seed=6, normals=stage == "poisson")
    ref = tmp_path / "ref.ply"
    assert _recon_here([stage, src, ref, "--partitions", "2", *args]) == 0
    out = tmp_path / "out.ply"
    argv = [*RECON, stage, src, out, "--partitions", "2", "--workers", "2", *args]
    proc = subprocess.Popen([str(a) for a in argv], stderr=subprocess.PIPE, start_new_session=True)
    killed = None
    try:
        deadline = time.monotonic() + 120
        while killed is None:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no sorted chunk after 120 s"
            if list(tmp_path.glob(f".recon-{stage}-*/c00000.pts.npy")):
                worker = _workers(proc.pid)[0]
                killed = worker.pid
                worker.kill()
            time.sleep(0.02)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err.decode()
    assert out.read_bytes() == ref.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([src.name, "ref.ply", "out.ply"])


# ---- full disks and SIGTERM -------------------------------------------------------------------


def test_a_full_disk_while_writing_out_is_one_line_exit_1(tmp_path, capfd):
    """A full disk while writing OUT: exit 1, one line naming OUT, the old output kept.

    OUT on a 256 KiB file system, too small for the mesh (in one process and in slabs, whose mesh
    goes to OUT a block of rows at a time); nothing else is left on that file system.
    """
    src = _cloud(tmp_path, 8000, seed=7)
    with _tmpfs(tmp_path / "small", "256k") as small:
        out = small / "mesh.ply"
        for extra in ([], ["--partitions", "2", "--temp-dir", str(tmp_path)]):
            out.write_bytes(OLD)
            capfd.readouterr()
            assert _recon_here(["poisson", src, out, "--depth", "7", *extra]) == 1
            assert capfd.readouterr().err == f"recon: error: {out}: No space left on device\n"
            assert out.read_bytes() == OLD
            assert os.listdir(small) == ["mesh.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([src.name, "small"])


def test_normals_full_disk_while_spilling(tmp_path):
    """``recon normals`` in slabs, spill disk full: exit 1, one line, old output kept, folder empty.

    The spill folder on a 256 KiB file system; the line names the folder.
    """
    src = _cloud(tmp_path, 20_000, seed=8, normals=False)
    out = tmp_path / "n.ply"
    out.write_bytes(OLD)
    with _tmpfs(tmp_path / "small", "256k") as small:
        argv = [*RECON, "normals", src, out, "--partitions", "3", "--temp-dir", small]
        run = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=600)
        assert run.returncode == 1, run.stderr
        assert run.stderr == (
            f"recon: error: {small}: no space left on device for the run's spill files\n"
        )
        assert out.read_bytes() == OLD
        assert os.listdir(small) == []


def test_sigterm_mid_out_of_core_normals_leaves_nothing(tmp_path):
    """SIGTERM while normals spill: exit 143, "recon: terminated", only the input left."""
    src = _cloud(tmp_path, 60_000, seed=9, normals=False)
    out = tmp_path / "n.ply"
    argv = [*RECON[:-1], "normals", src, out, "--partitions", "4", "--knn", "60"]
    run = interrupt_when(
        [str(a) for a in argv],
        lambda: list(tmp_path.glob(".recon-normals-*/c00000.pts.npy")),
        "no spill file",
        group=False,
        signum=signal.SIGTERM,
    )
    assert run.returncode == 143, run.err
    assert run.err.strip() == "recon: terminated", run.err
    assert sorted(p.name for p in tmp_path.iterdir()) == [src.name]
