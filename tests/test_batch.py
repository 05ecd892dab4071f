"""recon batch: input expansion, skip rules, the per-input task, real batches on a LocalCluster.

Real batches run on a 2-worker LocalCluster. The batch pipelines use test-only stages from
``tests/_batch_stages.py`` (registered in the workers through ``run_batch(extra_stages=...)``, in
this process through monkeypatch), on the real files of ../shared/data.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from shared_data import shared_path

TESTS = str(Path(__file__).resolve().parent)
if (
    TESTS not in sys.path
):  # the workers (spawned) inherit sys.path and import _batch_stages from here
    sys.path.insert(0, TESTS)

from recon_cli import batch  # noqa: E402
from recon_cli.errors import InputError, ParameterError  # noqa: E402
from recon_cli.progress import Progress  # noqa: E402

from _batch_stages import EXTRA_STAGES  # noqa: E402
from interrupt import RUN_RECON, SIGINT_AS_A_TERMINAL, interrupt_when  # noqa: E402


@pytest.fixture
def test_stages(monkeypatch):
    """The test stages registered in this process (workers get them through extra_stages)."""
    from recon_cli import stages

    for name, target in EXTRA_STAGES.items():
        monkeypatch.setitem(stages.STAGES, name, target)
    return EXTRA_STAGES


def _pipeline(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def _recon(argv: list[str]) -> int:
    """Run the real CLI entry point in-process; return its exit status."""
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


def _leftover_temporaries(folder: Path) -> list[str]:
    return sorted(
        p.name for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")
    )


# ----------------------------------------------------------------------------- inputs and plan


def test_expand_inputs_files_folders_globs(tmp_path):
    """Folders give their .ply/.npz files sorted, globs and files add none twice; misses named."""
    d = tmp_path / "scans"
    d.mkdir()
    for name in ("b.ply", "a.PLY", "g.npz", "notes.txt"):
        (d / name).write_bytes(b"x")
    (tmp_path / "empty").mkdir()
    got = batch.expand_inputs(
        [
            d,
            str(tmp_path / "scans" / "b.ply"),
            str(tmp_path / "sc*" / "*.ply"),
            str(tmp_path / "empty"),
            str(tmp_path / "nope*.ply"),
            str(tmp_path / "missing.ply"),
        ]
    )
    paths = [p for p, problem in got if problem is None]
    # folder: .ply/.npz only, sorted; the explicit file and the glob name files already listed
    assert paths == [str(d / "a.PLY"), str(d / "b.ply"), str(d / "g.npz")]
    problems = {p: problem for p, problem in got if problem is not None}
    assert problems == {
        str(tmp_path / "empty"): "folder holds no .ply or .npz file",
        str(tmp_path / "nope*.ply"): "no file matches this pattern",
        str(tmp_path / "missing.ply"): "no such file",
    }


def test_plan_skips_only_outputs_newer_than_input_and_pipeline(tmp_path):
    """Only an output newer than its input and the pipeline is skipped; ``force`` reruns all."""
    pipe = tmp_path / "p.toml"
    pipe.write_text("x")
    ins = []
    for name in ("a", "b", "c"):
        p = tmp_path / f"{name}.ply"
        p.write_bytes(b"x")
        ins.append(str(p))
    out = tmp_path / "out"
    out.mkdir()
    t = time.time() - 1000
    for p in ins:
        os.utime(p, (t, t))
    os.utime(pipe, (t, t))
    (out / "a.ply").write_bytes(b"done")  # newer than input and pipeline: skip
    (out / "b.npz").write_bytes(b"done")  # a grid output counts as well
    os.utime(out / "b.npz", (t - 10, t - 10))  # ... but older than its input: redo
    plan = batch.plan_batch(pipe, ins, out)
    assert [e["action"] for e in plan] == ["skip", "run", "run"]
    assert plan[0]["output"] == str((out / "a.ply").resolve())
    assert [e["action"] for e in batch.plan_batch(pipe, ins, out, force=True)] == [
        "run",
        "run",
        "run",
    ]
    os.utime(pipe, None)  # pipeline edited after the output: everything reruns
    assert [e["action"] for e in batch.plan_batch(pipe, ins, out)] == ["run", "run", "run"]


def test_plan_refuses_clashing_names_and_overwriting_inputs(tmp_path):
    """Two inputs writing one output, an output over its input, or no inputs: refused."""
    (tmp_path / "x").mkdir()
    (tmp_path / "y").mkdir()
    (tmp_path / "x" / "s.ply").write_bytes(b"x")
    (tmp_path / "y" / "s.npz").write_bytes(b"x")
    pipe = tmp_path / "p.toml"
    pipe.write_text("x")
    with pytest.raises(ParameterError, match="would both write"):
        batch.plan_batch(
            pipe, [tmp_path / "x" / "s.ply", tmp_path / "y" / "s.npz"], tmp_path / "out"
        )
    with pytest.raises(ParameterError, match="overwrite its input"):
        batch.plan_batch(pipe, [tmp_path / "x" / "s.ply"], tmp_path / "x")
    with pytest.raises(InputError, match="no inputs"):
        batch.plan_batch(pipe, [], tmp_path / "out")


def test_run_batch_rejects_bad_options_before_starting(tmp_path, test_stages):
    """Bad scheduler, workers, memory limit, pipeline or clashing names: refused, none written."""
    pipe = _pipeline(tmp_path / "p.toml", '[[stage]]\nname = "t_centre"\n')
    src = str(shared_path("mug"))
    with pytest.raises(ParameterError, match="local cluster"):
        batch.run_batch(pipe, [src], tmp_path / "o", scheduler="tcp://127.0.0.1:1", workers=2)
    with pytest.raises(ParameterError, match="whole number"):
        batch.run_batch(pipe, [src], tmp_path / "o", workers=0)
    with pytest.raises(ParameterError, match="not a size"):
        batch.run_batch(pipe, [src], tmp_path / "o", memory_limit="lots")
    assert batch.cluster._check_memory_limit("4GiB") == 4 * 2**30
    assert (
        batch.cluster._check_memory_limit("none") == 0
        and batch.cluster._check_memory_limit(None) == "auto"
    )
    bad = _pipeline(tmp_path / "bad.toml", '[[stage]]\nname = "t_centre"\nwobble = 1\n')
    with pytest.raises(ParameterError, match="bad.toml:3"):
        batch.run_batch(bad, [src], tmp_path / "o")
    (tmp_path / "copy").mkdir()
    shutil.copy(src, tmp_path / "copy" / "mug.ply")
    with pytest.raises(ParameterError, match="would both write"):
        batch.run_batch(
            pipe,
            [src, str(shared_path("kitten")), str(tmp_path / "copy" / "mug.ply")],
            tmp_path / "o",
        )
    assert not (tmp_path / "o").exists()


def test_temporaries_of_a_dead_write_are_removed(tmp_path):
    """A killed write's temporaries are removed for the batch's own outputs only.

    What atomic_open leaves when its process is killed mid-write (.<name>.<random>.tmp) is cleaned
    up for the batch's own outputs only.
    """
    import tempfile

    for name in ("scan.ply", "scan.npz", "other.ply"):
        fd, _ = tempfile.mkstemp(prefix="." + name + ".", suffix=".tmp", dir=tmp_path)
        os.close(fd)
    (tmp_path / "scan.ply").write_bytes(b"kept")
    batch.cluster._remove_temporaries(str(tmp_path / "scan"))
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left[-1] == "scan.ply" and len(left) == 2 and left[0].startswith(".other.ply.")


# ----------------------------------------------------------------------------- the task, in this
# process


def test_process_one_ok_failed_and_grid(tmp_path, test_stages):
    """One input's task: a mesh's record and file, one-line failures with no output, a grid."""
    from recon_cli.io import read_ply
    from recon_cli.io.npz import read_grid
    from recon_cli.pipeline import load_pipeline

    pipe = load_pipeline(
        _pipeline(tmp_path / "p.toml", '[[stage]]\nname = "t_centre"\nfail_above = 38000\n')
    )
    rec = batch.process_one(pipe, str(shared_path("kitten")), str(tmp_path / "kitten"))
    assert rec["status"] == "ok" and rec["output"] == str(tmp_path / "kitten.ply")
    mesh = read_ply(rec["output"])
    assert np.abs(mesh.vertices.mean(axis=0)).max() < 1e-5  # centred (float32 file)
    assert rec["output_stats"] == {"kind": "mesh", "vertices": 6050, "faces": 12100}
    assert rec["input_stats"] == rec["output_stats"]
    assert [s["stage"] for s in rec["stages"]] == ["t_centre"] and rec["stages"][0]["seconds"] >= 0
    assert set(rec["timings"]) == {"read", "pipeline", "write"}
    assert rec["peak_memory_mb"] >= rec["memory_at_start_mb"] > 10
    assert rec["worker"]["pid"] == os.getpid()

    rec = batch.process_one(pipe, str(shared_path("bunny_scan_000")), str(tmp_path / "bunny"))
    assert rec["status"] == "failed" and rec["error_type"] == "StageFailed"
    assert rec["error"].startswith(
        str(shared_path("bunny_scan_000")) + ": t_centre: 40256 vertices"
    )
    assert "\n" not in rec["error"]
    assert not list(tmp_path.glob("bunny*"))

    corrupt = tmp_path / "corrupt.ply"
    corrupt.write_bytes(shared_path("kitten").read_bytes()[:100_000])
    rec = batch.process_one(pipe, str(corrupt), str(tmp_path / "c"))
    assert (
        rec["status"] == "failed"
        and rec["error_type"] == "InputError"
        and "truncated" in rec["error"]
    )

    gpipe = load_pipeline(_pipeline(tmp_path / "g.toml", '[[stage]]\nname = "t_grid"\nn = 6\n'))
    rec = batch.process_one(gpipe, str(shared_path("mug")), str(tmp_path / "mug"))
    assert rec["status"] == "ok" and rec["output"] == str(tmp_path / "mug.npz")
    assert rec["output_stats"]["grid_shape"] == [6, 6, 6]
    g = read_grid(rec["output"])
    assert (
        g.shape == (6, 6, 6)
        and g.history[-1].startswith("recon ")
        and "t_grid n=6" in g.history[-1]
    )


def test_process_one_interrupted_write_leaves_nothing(tmp_path, test_stages, monkeypatch):
    """A full disk during the write: a one-line NoSpace failure naming the output, no file left."""
    from recon_cli.io import atomic
    from recon_cli.pipeline import load_pipeline

    pipe = load_pipeline(_pipeline(tmp_path / "p.toml", '[[stage]]\nname = "t_centre"\n'))

    def broken_fsync(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", broken_fsync)
    rec = batch.process_one(pipe, str(shared_path("mug")), str(tmp_path / "mug"))
    assert rec["status"] == "failed" and "No space left" in rec["error"]
    # a full disk is the output's problem, reported in one line naming the path (not a bug with a
    # traceback)
    assert rec["error_type"] == "NoSpace" and "traceback" not in rec  # an OutputError, exit 1
    assert str(tmp_path / "mug.ply") in rec["error"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml"]  # no output, no temporary


# ----------------------------------------------------------------------------- real batches on Dask


@pytest.mark.slow
def test_batch_survives_a_killed_worker_then_rerun_skips_everything(tmp_path, test_stages, capsys):
    """A worker killed mid-input: the input reruns elsewhere and all end ok; a rerun skips all.

    A worker killed while running an input: that input is rerun on a live worker, every input
    ends ok, no partial output; a rerun does nothing and takes seconds.
    """
    markers = tmp_path / "markers"
    markers.mkdir()
    pipe = _pipeline(
        tmp_path / "p.toml",
        '[[stage]]\nname = "t_centre"\n\n[[stage]]\nname = "t_sleep"\nseconds = 1.5\n'
        f'marker_dir = "{markers}"\n',
    )
    names = ["kitten", "mug", "stereo_fragment"]
    inputs = [str(shared_path(n)) for n in names]
    out = tmp_path / "out"
    bar = io.StringIO()
    with _killing_the_first_marked_worker(markers) as killed:
        summary = batch.run_batch(
            pipe,
            inputs,
            out,
            workers=2,
            threads_per_worker=1,
            extra_stages=EXTRA_STAGES,
            progress=Progress(stream=bar, enabled=True),
        )
    assert len(killed) == 1
    drawn = bar.getvalue()
    final = drawn.rstrip().split("\r")[
        -1
    ]  # rich redraws the line; the last frame is the finished bar
    assert (
        "batch (3 inputs)" in drawn
        and "  0%" in drawn
        and "batch (3 inputs)" in final
        and final.count("100%") == 1
    )
    assert summary["counts"] == {"ok": 3, "failed": 0, "skipped": 0}
    assert summary["cluster"]["scheduler"] == "local" and summary["cluster"]["workers"] == 2
    assert (
        summary["cluster"]["threads_per_worker"] == [1]
        and summary["cluster"]["memory_limit"] == "auto"
    )
    assert summary["cluster"]["memory_limit_per_worker"] > 2**28
    # the killed input ran exactly twice (the second time in another process), the others once
    runs: dict[int, list[int]] = {}
    for m in markers.iterdir():
        nverts, pid = map(int, m.name.split("-"))
        runs.setdefault(nverts, []).append(pid)
    victim = next(n for n, pids in runs.items() if killed[0] in pids)
    assert sorted(len(p) for p in runs.values()) == [1, 1, 2] and len(runs[victim]) == 2
    assert killed[0] not in {r["worker"]["pid"] for r in summary["inputs"]}
    assert sorted(p.name for p in out.iterdir()) == ["batch.json"] + [f"{n}.ply" for n in names]
    assert _leftover_temporaries(out) == []
    _assert_outputs_equal_a_run_here(tmp_path, out, names)
    _assert_rerun_skips_everything(pipe, inputs, out, names, markers, capsys)


@contextlib.contextmanager
def _killing_the_first_marked_worker(markers):
    """Kill (SIGKILL) the worker of the first marker file that appears; the pids killed."""
    killed: list[int] = []
    stop = threading.Event()

    def killer():
        while not stop.is_set():
            found = sorted(markers.iterdir())
            if found:
                pid = int(found[0].name.split("-")[1])
                os.kill(pid, signal.SIGKILL)  # a worker process in the middle of a task
                killed.append(pid)
                return
            time.sleep(0.02)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    try:
        yield killed
    finally:
        stop.set()
        th.join(5)


def _assert_outputs_equal_a_run_here(tmp_path, out, names):
    """The batch's outputs equal a run of the same pipeline in this process."""
    from recon_cli.pipeline import load_pipeline

    quiet = load_pipeline(
        _pipeline(
            tmp_path / "q.toml", '[[stage]]\nname = "t_centre"\n\n[[stage]]\nname = "t_sleep"\n'
        )
    )
    for n in names:
        rec = batch.process_one(quiet, str(shared_path(n)), str(tmp_path / f"alone_{n}"))
        got = (out / f"{n}.ply").read_bytes()
        want = (tmp_path / f"alone_{n}.ply").read_bytes()
        assert rec["status"] == "ok"
        # provenance lines differ only in the t_sleep parameters
        assert got.split(b"end_header")[1] == want.split(b"end_header")[1]


def _assert_rerun_skips_everything(pipe, inputs, out, names, markers, capsys):
    """A rerun of a finished batch skips every input, in seconds, and starts no cluster."""
    before = {n: (out / f"{n}.ply").stat().st_mtime_ns for n in names}
    capsys.readouterr()
    t0 = time.perf_counter()
    assert _recon(["batch", pipe, *inputs, "--out", str(out), "--workers", "2"]) == 0
    assert time.perf_counter() - t0 < 3.0
    err = capsys.readouterr().err.splitlines()
    assert [ln.split()[0] for ln in err[:3]] == ["skipped"] * 3
    assert err[-1].startswith("0 ok, 0 failed, 3 skipped in ")
    again = json.loads((out / "batch.json").read_text())
    assert again["counts"] == {"ok": 0, "failed": 0, "skipped": 3}
    assert again["cluster"]["scheduler"] is None  # nothing to do: no cluster started
    for r in again["inputs"]:  # a skipped input keeps the figures of the run that made its output
        assert r["previous"]["status"] == "ok" and r["previous"]["output"] == r["output"]
        assert r["previous"]["stages"][1]["seconds"] >= 1.5
    assert {n: (out / f"{n}.ply").stat().st_mtime_ns for n in names} == before
    assert len(list(markers.iterdir())) == len(names) + 1  # nothing ran again


@pytest.fixture(scope="module")
def cluster():
    """A 2-worker, 1-thread-each LocalCluster set up as ``recon batch`` sets up its own.

    Worker processes; an input whose worker dies is rerun once. Shared by the tests that pass
    --scheduler.
    """
    import logging

    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        c = LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": ":0"},
            silence_logs=logging.CRITICAL,
        )
    with c:
        yield c


@pytest.mark.slow
def test_batch_real_normals_on_an_existing_cluster(tmp_path, cluster):
    """The real ``normals`` stage via --scheduler writes the same files as ``recon run`` alone.

    The real `normals` stage on the real scans through --scheduler: the same files as `recon run`
    alone.
    """
    from recon_cli.stages import get_stage

    get_stage("normals")  # built
    pipe = _pipeline(
        tmp_path / "n.toml",
        '[[stage]]\nname = "normals"\nknn = 30\norient = "camera"\ncamera = "0,0,1"\n',
    )
    scans = [str(shared_path(n)) for n in ("bunny_scan_000", "stereo_fragment")]
    out = tmp_path / "out"
    code = _recon(
        ["-q", "batch", pipe, *scans, "--out", str(out), "--scheduler", cluster.scheduler_address]
    )
    assert code == 0
    summary = json.loads((out / "batch.json").read_text())
    assert (
        summary["cluster"]["scheduler"] == cluster.scheduler_address
        and summary["cluster"]["workers"] == 2
    )
    assert summary["counts"] == {"ok": 2, "failed": 0, "skipped": 0}
    for src, r in zip(scans, summary["inputs"], strict=True):
        name = Path(src).stem
        alone = tmp_path / f"alone_{name}.ply"
        assert _recon(["-q", "run", pipe, src, str(alone)]) == 0
        assert (out / f"{name}.ply").read_bytes() == alone.read_bytes(), name
        assert r["output_stats"]["normals"] is True
        assert (
            r["output_stats"]["points"] == {"bunny_scan_000": 40256, "stereo_fragment": 3748}[name]
        )
        assert (
            r["stages"][0]["stage"] == "normals"
            and r["stages"][0]["points"] == r["output_stats"]["points"]
        )


@pytest.mark.slow
def test_batch_mixed_inputs_on_two_workers(tmp_path, test_stages, capsys, cluster):
    """``recon batch`` of good and bad inputs on 2 workers: ``recon run``'s files, one-line errors.

    `recon batch` on a 2-worker LocalCluster: good inputs give the same files as `recon run` on
    each alone; a stage failure, a corrupt file, a missing file and an input whose worker always
    dies are reported with one-line errors; exit status 4.
    """
    from recon_cli.cli.main import EXIT_BATCH_SOME_FAILED
    from recon_cli.io import read_ply
    from recon_cli.io.ply import write_ply

    data = tmp_path / "in"
    data.mkdir()
    good = ["kitten", "mug", "stereo_fragment"]
    for name in good + ["bunny_scan_000"]:
        shutil.copy(shared_path(name), data / f"{name}.ply")
    (data / "corrupt.ply").write_bytes(shared_path("kitten").read_bytes()[:100_000])
    small = read_ply(shared_path("stereo_fragment")).subset(
        np.arange(1000)
    )  # 1000 real points: the worker dies
    write_ply(small, data / "small.ply")
    pipe = _pipeline(
        tmp_path / "p.toml",
        '[[stage]]\nname = "t_centre"\nfail_above = 38000\ndie_below = 2000\n\n'
        '[[stage]]\nname = "t_sleep"\nseconds = 0.1\n',
    )
    out = tmp_path / "out"
    capsys.readouterr()
    # the CLI passes no extra stages: each task carries the stage targets this process resolved
    code = _recon(
        [
            "batch",
            pipe,
            str(data / "*.ply"),
            str(data / "missing.ply"),
            "--out",
            str(out),
            "--scheduler",
            cluster.scheduler_address,
            "--json",
        ]
    )
    assert code == EXIT_BATCH_SOME_FAILED == 4
    summary = json.loads(capsys.readouterr().out)
    assert json.loads((out / "batch.json").read_text()) == summary
    by_name = {Path(r["input"]).stem: r for r in summary["inputs"]}
    assert summary["counts"] == {"ok": 3, "failed": 4, "skipped": 0}
    assert summary["cluster"]["scheduler"] == cluster.scheduler_address
    assert summary["cluster"]["workers"] == 2 and summary["cluster"]["threads_per_worker"] == [1]
    assert {n: by_name[n]["status"] for n in by_name} == {
        "kitten": "ok",
        "mug": "ok",
        "stereo_fragment": "ok",
        "bunny_scan_000": "failed",
        "corrupt": "failed",
        "small": "failed",
        "missing": "failed",
    }
    assert by_name["bunny_scan_000"]["error_type"] == "StageFailed"
    assert "40256 vertices" in by_name["bunny_scan_000"]["error"]
    assert (
        by_name["corrupt"]["error_type"] == "InputError"
        and "truncated" in by_name["corrupt"]["error"]
    )
    assert by_name["small"]["error_type"] == "KilledWorker"
    assert by_name["small"]["error"].endswith(
        "small.ply: the worker process running it died twice (killed or out of memory)"
    )
    assert by_name["missing"]["error"].endswith("no such file")
    for r in summary["inputs"]:
        assert "\n" not in r.get("error", "")
        if r["status"] == "failed":
            assert r["input"] in r["error"] or str(Path(r["input"]).resolve()) in r["error"]
    # outputs exist only for the good inputs, nothing partial is left
    assert sorted(p.name for p in out.iterdir()) == [
        "batch.json",
        "kitten.ply",
        "mug.ply",
        "stereo_fragment.ply",
    ]
    # the same bytes as `recon run` on each input alone
    for name in good:
        alone = tmp_path / f"alone_{name}.ply"
        assert _recon(["run", pipe, str(data / f"{name}.ply"), str(alone)]) == 0
        assert (out / f"{name}.ply").read_bytes() == alone.read_bytes(), name
        r = by_name[name]
        assert r["output"] == str(out / f"{name}.ply")
        n_in = len(read_ply(data / f"{name}.ply").vertices)
        assert r["output_stats"] == (
            {"kind": "cloud", "points": n_in, "normals": False}
            if name == "stereo_fragment"
            else {
                "kind": "mesh",
                "vertices": n_in,
                "faces": 2 * n_in,
            }  # kitten and mug: closed, genus 1
        )
        assert [s["stage"] for s in r["stages"]] == ["t_centre", "t_sleep"]
        assert r["stages"][1]["seconds"] >= 0.1
        assert (
            r["peak_memory_scope"] == "task" and r["peak_memory_mb"] >= r["memory_at_start_mb"] > 10
        )
        assert r["seconds"] >= sum(r["timings"].values()) > 0.1


# ----------------------------------------------------------------------------- Ctrl-C

# `recon batch` as a user runs it, with the test stages registered first (the workers get them
# from each task's stage targets; spawned workers inherit sys.path, so they import _batch_stages)
_RUNNER = (
    SIGINT_AS_A_TERMINAL
    + f"sys.path.insert(0, {TESTS!r})\n"
    + "from _batch_stages import EXTRA_STAGES\n"
    + "from recon_cli import stages\n"
    + "stages.STAGES.update(EXTRA_STAGES)\n"
    + RUN_RECON
)


def _sigint_blocked(native_id: int) -> bool:
    with open(f"/proc/self/task/{native_id}/status") as f:
        mask = next(int(line.split()[1], 16) for line in f if line.startswith("SigBlk:"))
    return bool(mask & (1 << (signal.SIGINT - 1)))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/task/*/status")
def test_sigint_is_held_while_a_cluster_starts():
    """A Ctrl-C while the local cluster starts is recorded, not raised mid-start.

    Threads started meanwhile (Dask's event loop, which starts the workers) keep SIGINT blocked;
    afterwards all is as before.
    """
    # the test runner may have been started with SIGINT ignored (nohup, CI): act as a terminal does
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        before = signal.getsignal(signal.SIGINT)
        seen: list[bool] = []

        def thread_body():
            seen.append(_sigint_blocked(threading.get_native_id()))

        with batch.cluster._sigint_held() as interrupted:
            os.kill(os.getpid(), signal.SIGINT)  # recorded (now or on leaving), never raised here
            time.sleep(0.05)
            assert _sigint_blocked(threading.get_native_id())
            th = threading.Thread(target=thread_body)
            th.start()
            th.join()
        assert interrupted == [True] and seen == [True]
        assert signal.getsignal(signal.SIGINT) is before and not _sigint_blocked(
            threading.get_native_id()
        )
        with pytest.raises(KeyboardInterrupt):  # the usual behaviour is back
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        # started with SIGINT ignored (`nohup recon batch ... &`): left ignored, nothing recorded
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with batch.cluster._sigint_held() as interrupted:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        assert interrupted == [] and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, outer)


def _outputs(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("*.ply"))


@pytest.mark.slow
@pytest.mark.parametrize("target", ["group", "main"])
def test_ctrl_c_stops_cleanly_and_a_rerun_resumes(tmp_path, target):
    """SIGINT mid-batch: exit 130, no partial output or process left; a rerun does the rest.

    SIGINT once the first output exists, to the whole process group (Ctrl-C on a terminal) or to
    the recon process alone: exit 130, no partial output, every process of the local cluster gone,
    finished inputs kept; a rerun (after the Ctrl-C) skips those and does the rest.
    """
    import subprocess

    import psutil

    from recon_cli.cli.main import EXIT_INTERRUPTED
    from recon_cli.io import read_ply

    data = tmp_path / "in"
    data.mkdir()
    src = shared_path("stereo_fragment")
    names = [f"part{i}" for i in range(6)]
    for name in names:
        shutil.copy(src, data / f"{name}.ply")
    n_points = len(read_ply(src).vertices)
    pipe = _pipeline(
        tmp_path / "p.toml",
        '[[stage]]\nname = "t_centre"\n\n[[stage]]\nname = "t_sleep"\nseconds = 1.0\n',
    )
    out = tmp_path / "out"
    argv = [
        sys.executable,
        "-c",
        _RUNNER,
        "batch",
        pipe,
        str(data),
        "--out",
        str(out),
        "--workers",
        "2",
    ]
    run = interrupt_when(
        argv, lambda: out.is_dir() and _outputs(out), "no output", group=target == "group"
    )
    assert len(run.family) >= 2  # at least the two worker processes
    assert run.returncode == EXIT_INTERRUPTED == 130, run.err
    assert run.err.rstrip().splitlines()[-1] == "recon: interrupted", run.err
    assert "Traceback" not in run.err, run.err
    assert run.seconds < 20, run.seconds
    # the cluster went with it: no worker (or other) process of the batch outlives it
    _, alive = psutil.wait_procs(run.family, timeout=10)
    assert alive == [], [(p.pid, p.name()) for p in alive]
    # finished inputs are whole files; nothing partial, the unfinished ones are recorded as
    # interrupted
    done = _outputs(out)
    assert 1 <= len(done) < len(names)
    assert _leftover_temporaries(out) == []
    assert sorted(p.name for p in out.iterdir()) == sorted(done + ["batch.json"])
    for name in done:
        assert len(read_ply(out / name).vertices) == n_points
    summary = json.loads((out / "batch.json").read_text())
    status = {Path(r["input"]).stem: r["status"] for r in summary["inputs"]}
    assert set(status) == set(names)
    assert {n for n, s in status.items() if s == "ok"} <= {Path(n).stem for n in done}
    assert {n for n, s in status.items() if s != "ok"} >= set(names) - {Path(n).stem for n in done}
    assert set(status.values()) <= {"ok", "interrupted"} and "interrupted" in status.values()

    if target != "group":
        return
    # the rerun resumes: finished inputs are skipped (untouched), the others run
    before = {n: (out / n).stat().st_mtime_ns for n in done}
    again = subprocess.run(argv + ["--json"], capture_output=True, timeout=180)
    assert again.returncode == 0, again.stderr.decode()
    summary = json.loads(again.stdout)
    assert summary["counts"] == {"ok": len(names) - len(done), "failed": 0, "skipped": len(done)}
    skipped = {Path(r["input"]).name for r in summary["inputs"] if r["status"] == "skipped"}
    assert skipped == set(done)
    assert {n: (out / n).stat().st_mtime_ns for n in done} == before
    assert _outputs(out) == [f"{n}.ply" for n in names] and _leftover_temporaries(out) == []
