"""The batch on Dask: the cluster, submitting the tasks, collecting results, Ctrl-C."""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import shutil
import signal
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recon_cli.batch.plan import (
    OUTPUT_SUFFIXES,
    STATUS_FAILED,
    STATUS_INTERRUPTED,
    STATUS_OK,
    STATUS_SKIPPED,
    SUMMARY_NAME,
    plan_batch,
    read_previous,
)
from recon_cli.batch.task import error_line, process_one, registered_stages
from recon_cli.errors import BackendError, ParameterError, ReconError

# ----------------------------------------------------------------------------- the batch


def _check_count(value: Any, name: str) -> int:
    if isinstance(value, bool):
        raise ParameterError(f"{name} must be a whole number >= 1, got {value!r}")
    try:
        n = int(str(value).strip()) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a whole number >= 1, got {value!r}") from None
    if (not isinstance(value, str) and n != value) or n < 1:
        raise ParameterError(f"{name} must be a whole number >= 1, got {value!r}")
    return n


def _check_memory_limit(value: Any) -> Any:
    if value is None:
        return "auto"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if value < 0:
            raise ParameterError(f"memory limit must be >= 0 bytes, got {value!r}")
        return value
    text = str(value).strip()
    if text.lower() in ("auto", ""):
        return "auto"
    if text.lower() in ("0", "none", "off"):
        return 0
    from dask.utils import parse_bytes

    try:
        return parse_bytes(text)
    except (ValueError, TypeError):
        raise ParameterError(
            f"memory limit {value!r} is not a size (e.g. '4GiB', '2000MB', 'auto', 'none')"
        ) from None


def dask_setup(worker: Any) -> None:
    """Dask preload hook, run in each worker process of the local cluster as it starts.

    The worker ignores SIGINT. Ctrl-C on a terminal signals the whole foreground process
    group; a worker that took it would die with a traceback, and its nanny would restart
    it while the batch is being stopped. The process running the batch takes the
    interrupt alone and closes the cluster, which stops the workers.
    """
    if threading.current_thread() is threading.main_thread():  # signal handlers: main thread only
        signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _dask_log_level(level: int):
    """Dask's loggers in this process at ``level`` for the block (they propagate to the root)."""
    logger = logging.getLogger("distributed")
    old = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(old)


@contextlib.contextmanager
def open_client(
    scheduler: str | None = None,
    workers: Any = None,
    memory_limit: Any = None,
    log_level: int = logging.CRITICAL,
    stealing: bool = True,
):
    """A Dask client for one job.

    On the scheduler at ``scheduler``, or on a local cluster of ``workers`` processes (one thread
    each, ``memory_limit`` each: a size, ``"auto"`` or ``"none"``), the batch's, closed on exit;
    ``stealing`` False turns the local scheduler's work stealing off (tasks that keep big states
    stay where they are). Yields ``(client, info)``.
    """
    if scheduler is not None and (workers is not None or memory_limit is not None):
        raise ParameterError(
            "--workers and --memory-limit size a local cluster; leave them out with --scheduler"
        )
    n = None if workers is None else _check_count(workers, "workers")
    mem = _check_memory_limit(memory_limit)
    with _client(scheduler, n, 1, mem, log_level, stealing) as got:
        yield got


@contextlib.contextmanager
def _client(scheduler, workers, threads_per_worker, memory_limit, log_level, stealing=True):
    """A Client on an existing scheduler, or on a LocalCluster closed on exit."""
    try:
        import distributed  # noqa: F401  (first: importing it configures its loggers)
    except ImportError:
        raise BackendError(
            "recon batch needs dask.distributed: pip install 'recon[batch]'"
        ) from None
    with _dask_log_level(log_level):
        with _client_inner(
            scheduler, workers, threads_per_worker, memory_limit, log_level, stealing
        ) as got:
            yield got


@contextlib.contextmanager
def _client_inner(scheduler, workers, threads_per_worker, memory_limit, log_level, stealing=True):
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise BackendError(
            "recon batch needs dask.distributed: pip install 'recon[batch]'"
        ) from None

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise ParameterError(
                f"cannot reach the Dask scheduler at {scheduler}: {error_line(exc)}"
            ) from None
        with client:
            yield client, _cluster_info(client, scheduler)
        return

    from dask.system import CPU_COUNT

    if workers is None:
        workers = max(1, CPU_COUNT // threads_per_worker)
    # numba's thread pool per worker process = its Dask threads, so workers do not oversubscribe the
    # cores
    env = {"NUMBA_NUM_THREADS": str(threads_per_worker)}
    # allowed-failures=1: an input whose worker dies is rescheduled once, then fails with
    # KilledWorker
    with _sigint_held() as interrupted:
        try:
            # no work stealing when the tasks keep big states: a stolen task copies its state
            config = {"distributed.scheduler.allowed-failures": 1}
            if not stealing:
                config["distributed.scheduler.work-stealing"] = False
                # a worker whose live state fills it would pause for good (its memory never
                # drops while the job waits on it): over the limit it is restarted instead
                config["distributed.worker.memory.pause"] = False
            with dask.config.set(config):
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=threads_per_worker,
                    processes=True,
                    memory_limit=memory_limit,
                    dashboard_address=None,
                    # no dashboard; its HTTP server (health, metrics) on a free port, not 8787
                    # (maybe taken)
                    scheduler_kwargs={"dashboard_address": ":0"},
                    silence_logs=log_level,
                    env=env,
                    # each worker process ignores SIGINT (see dask_setup)
                    preload=[__name__],
                )
        except (OSError, RuntimeError, TimeoutError) as exc:
            raise ReconError(f"could not start a local Dask cluster: {error_line(exc)}") from None
    with cluster:
        if interrupted:  # Ctrl-C while the cluster started: now that it exists, stop (and close it)
            raise KeyboardInterrupt
        with Client(cluster) as client:
            info = _cluster_info(client, "local")
            info["memory_limit"] = memory_limit
            yield client, info


def _sigint_catchable() -> bool:
    """Whether to take Ctrl-C with our own handler.

    Only the main thread can, and a SIGINT the parent left ignored (``nohup ... &``) stays ignored.
    """
    return (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
    )


@contextlib.contextmanager
def _sigint_held():
    """Hold Ctrl-C back while a local cluster starts; yields a list that is non-empty if one came.

    A KeyboardInterrupt inside LocalCluster's start would leave a half-started cluster that
    nothing closes. In the main thread, SIGINT is recorded instead of raised, and blocked
    (POSIX): the threads started meanwhile inherit the block, among them Dask's event loop,
    which starts the worker processes (now and when it restarts a dead one), so the workers
    start with SIGINT blocked and do not die of a Ctrl-C while they import (dask_setup then
    ignores it for good).
    """
    got: list[bool] = []
    if not _sigint_catchable():
        yield got
        return
    old_handler = signal.signal(signal.SIGINT, lambda signum, frame: got.append(True))
    mask = None
    if hasattr(signal, "pthread_sigmask"):
        from multiprocessing import resource_tracker

        # starting its helper process unblocks SIGINT in the calling thread: start it first
        resource_tracker.ensure_running()
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield got
    finally:
        if mask is not None:
            signal.pthread_sigmask(
                signal.SIG_SETMASK, mask
            )  # a pending SIGINT arrives now, and is recorded
        signal.signal(signal.SIGINT, old_handler)  # (runs pending handlers first)


def _cluster_info(client, scheduler: str) -> dict:
    workers = client.scheduler_info().get("workers", {})
    limits = sorted({w.get("memory_limit") for w in workers.values()} - {None})
    return {
        "scheduler": scheduler,
        "workers": len(workers),
        "threads_per_worker": sorted({w.get("nthreads") for w in workers.values()} - {None}),
        "memory_limit_per_worker": limits[0] if len(limits) == 1 else limits,
    }


def _remove_temporaries(base: str) -> None:
    """Remove temporary files that an interrupted atomic write of ``base.*`` left behind."""
    folder, name = os.path.split(base)
    for suffix in OUTPUT_SUFFIXES:
        for tmp in glob.glob(
            os.path.join(glob.escape(folder), glob.escape("." + name + suffix) + ".*.tmp")
        ):
            if os.path.isdir(tmp):  # a tileset's folder being written
                shutil.rmtree(tmp, ignore_errors=True)
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _failed_from_future(entry: dict, exc: BaseException | None, status: str) -> dict:
    from distributed import KilledWorker

    rec: dict[str, Any] = {"input": entry["input"], "status": STATUS_FAILED, "output": None}
    if isinstance(exc, KilledWorker):
        deaths = {1: "once", 2: "twice"}.get(
            exc.allowed_failures + 1, f"{exc.allowed_failures + 1} times"
        )
        rec.update(
            error=f"{entry['input']}: the worker process running it died {deaths} "
            "(killed or out of memory)",
            error_type="KilledWorker",
        )
    elif exc is not None:
        rec.update(
            error=f"{entry['input']}: task failed: {type(exc).__name__}: {error_line(exc)}",
            error_type=type(exc).__name__,
        )
    else:
        rec.update(error=f"{entry['input']}: task {status}", error_type=status)
    return rec


def run_batch(
    pipeline_path: str | os.PathLike,
    inputs: Iterable[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    workers: int | None = None,
    threads_per_worker: int | None = None,
    memory_limit: Any = None,
    scheduler: str | None = None,
    force: bool = False,
    progress: Any = None,
    ascii: bool = False,
    extra_stages: dict[str, str] | None = None,
    log_level: int = logging.CRITICAL,
) -> dict:
    """Run the pipeline file on every input, writing ``out_dir/<stem>.ply`` (or ``.npz``).

    Parameters
    ----------
    pipeline_path : path
        A pipeline TOML file (checked before anything runs).
    inputs : iterable of path or pattern
        Files, folders (their ``.ply``/``.npz`` files) and glob patterns.
    out_dir : path
        Output folder (created if missing); also receives ``batch.json``.
    workers, threads_per_worker, memory_limit
        Local cluster size: worker processes (default: cores // threads_per_worker),
        threads per worker (default 1), memory limit per worker (``"auto"``: the
        machine's memory shared out; a size such as ``"4GiB"``; ``0``/``"none"``: no
        limit). A worker above its limit is restarted by Dask, which counts as dying.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``) to use instead of a
        local cluster; ``workers`` etc. must then be left unset.
    force : bool
        Rerun inputs whose output is up to date.
    progress : Progress, optional
        Progress over inputs (None: silent).
    ascii : bool
        Write ASCII PLY.
    extra_stages : dict, optional
        ``{name: "module:function"}`` stages to register here for this batch (stages
        outside recon: plugins, tests). Every task carries the ``module:function`` of the
        pipeline's stages as resolved here and registers them in its worker, so the
        modules must be importable there.
    log_level : int
        Level of Dask's own log messages (default: only critical ones; the batch reports
        failures itself).

    Returns
    -------
    dict
        The summary written to ``out_dir/batch.json``: ``pipeline``, ``out``,
        ``cluster``, ``seconds``, ``counts`` (ok / failed / skipped) and ``inputs``
        (one record per input, in input order; see :func:`process_one`; a skipped input
        carries ``reason`` and, when known, the ``previous`` run's record).

    Raises
    ------
    InputError, ParameterError
        Bad pipeline file, no inputs, clashing output names, bad cluster options.
    BackendError
        dask.distributed is not installed.
    """
    from recon_cli.io.atomic import write_bytes
    from recon_cli.pipeline import load_pipeline
    from recon_cli.stages import report_json

    t_start = time.perf_counter()
    pipeline_path = os.fspath(pipeline_path)
    out_dir = os.fspath(out_dir)
    workers, threads, mem = _check_cluster(scheduler, workers, threads_per_worker, memory_limit)
    with registered_stages(extra_stages):
        pipe = load_pipeline(pipeline_path)
        # the workers resolve each stage exactly as this process did (a worker may be on another
        # machine)
        from recon_cli.stages import STAGES

        stage_map = {step.name: STAGES[step.name] for step in pipe.steps}
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ParameterError(f"--out {out_dir} exists and is not a folder")
    entries = plan_batch(pipeline_path, inputs, out_dir, force=force)
    os.makedirs(out_dir, exist_ok=True)
    summary_path = os.path.join(out_dir, SUMMARY_NAME)
    records, todo = _planned_records(entries, read_previous(summary_path))
    job = _Job(
        pipe=pipe,
        entries=entries,
        todo=todo,
        records=records,
        stage_map=stage_map,
        ascii=ascii,
        progress=progress,
        summary_path=summary_path,
        pipeline_path=pipeline_path,
        out_dir=out_dir,
        t_start=t_start,
    )
    cluster_info: dict[str, Any] = {"scheduler": None}
    if todo:
        cluster_info = _submit_and_collect(job, scheduler, workers, threads, mem, log_level)

    summary = job.summary(cluster_info)
    write_bytes(summary_path, report_json(summary).encode("utf-8") + b"\n")
    return summary


def _check_cluster(
    scheduler: str | None, workers: Any, threads_per_worker: Any, memory_limit: Any
) -> tuple[int | None, int, Any]:
    """The cluster options checked: (workers, threads per worker, memory limit)."""
    if scheduler is not None and (
        workers is not None or threads_per_worker is not None or memory_limit is not None
    ):
        raise ParameterError(
            "--workers, --threads-per-worker and --memory-limit size a local cluster; "
            "leave them out with --scheduler"
        )
    threads = (
        1 if threads_per_worker is None else _check_count(threads_per_worker, "threads per worker")
    )
    if workers is not None:
        workers = _check_count(workers, "workers")
    return workers, threads, _check_memory_limit(memory_limit)


def _planned_records(entries: list[dict], previous: dict) -> tuple[list[dict | None], list[int]]:
    """The records of the inputs that fail or are skipped, and the indices of those to run."""
    records: list[dict | None] = [None] * len(entries)
    todo = []
    for i, e in enumerate(entries):
        if e["action"] == "fail":
            records[i] = {
                "input": e["input"],
                "status": STATUS_FAILED,
                "output": None,
                "error": e["error"],
                "error_type": e["error_type"],
            }
        elif e["action"] == "skip":
            rec = {
                "input": e["input"],
                "status": STATUS_SKIPPED,
                "output": e["output"],
                "reason": "output is newer than the input and the pipeline file (--force to redo)",
            }
            old = previous.get(e["input"])
            if old and old.get("output") == e["output"]:
                rec["previous"] = (
                    old.get("previous", old) if old.get("status") == STATUS_SKIPPED else old
                )
            records[i] = rec
        else:
            todo.append(i)
    return records, todo


def _summary(pipeline_path, out_dir, cluster_info, records, t_start) -> dict:
    counts = {STATUS_OK: 0, STATUS_FAILED: 0, STATUS_SKIPPED: 0}
    for r in records:
        if r is not None:
            counts[r["status"]] = counts.get(r["status"], 0) + 1
    return {
        "pipeline": pipeline_path,
        "out": out_dir,
        "cluster": cluster_info,
        "seconds": time.perf_counter() - t_start,
        "counts": counts,
        "inputs": [r for r in records if r is not None],
    }


@dataclass
class _Job:
    """One batch run's state, shared by the submit / collect loop and the summary."""

    pipe: Any
    entries: list[dict]
    todo: list[int]
    records: list[dict | None]
    stage_map: dict
    ascii: bool
    progress: Any
    summary_path: str
    pipeline_path: str
    out_dir: str
    t_start: float

    def summary(self, cluster_info: dict) -> dict:
        """The batch summary as it stands (``batch.json``'s content)."""
        return _summary(self.pipeline_path, self.out_dir, cluster_info, self.records, self.t_start)


def _submit_and_collect(
    job: _Job, scheduler: str | None, workers: int | None, threads: int, mem: Any, log_level: int
) -> dict:
    """Submit one task per input in ``job.todo`` and fill ``job.records`` as they finish.

    At most as many inputs are in flight as the cluster has threads: Dask places each
    task, but none waits in a worker's queue behind another, so a worker that dies takes
    down (and makes suspect) only the inputs it was running.
    """
    try:
        with _client(scheduler, workers, threads, mem, log_level) as (client, info):
            _collect(client, info, job)
    finally:
        # after the cluster is closed (its workers are gone): what a write cut short left behind
        for i in job.todo:
            _remove_temporaries(job.entries[i]["base"])
    return info


def _collect(client, info: dict, job: _Job) -> None:
    """The submit / collect loop of :func:`_submit_and_collect` on a connected ``client``.

    On an interruption (Ctrl-C) the unfinished inputs are recorded ``interrupted``, their
    futures cancelled and the summary written before the exception goes on (and the
    cluster is closed on its way out).
    """
    from distributed import as_completed

    from recon_cli.progress import task

    flight = _InFlight(client, job, as_completed())
    # Ctrl-C only sets a flag, and this loop raises KeyboardInterrupt where it waits: raised
    # inside one of Dask's blocking calls, it races Dask's own clean-up (a NameError
    # traceback from distributed.utils.sync's cancel callback)
    old_handler = None
    if _sigint_catchable():
        old_handler = signal.signal(signal.SIGINT, lambda signum, frame: flight.stop.append(True))
    try:
        with task(job.progress, f"batch ({len(job.todo)} inputs)", total=len(job.todo)) as bar:
            flight.fill()
            for fut in flight.finished():
                if fut.status == "lost":
                    # it finished, but the worker holding its record died before this loop read it
                    # (another input's worker death): the scheduler recomputes it, so wait again
                    flight.done.add(fut)
                    continue
                flight.record(fut)
                bar.advance(1)
                flight.fill()
    except BaseException:
        # interrupted: record what is unfinished, keep the summary of what is done, re-raise
        flight.interrupted(info)
        raise
    finally:
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)


class _InFlight:
    """The inputs of a batch submitted to ``client`` and not yet recorded (:func:`_collect`)."""

    def __init__(self, client, job: _Job, done) -> None:
        self.client = client
        self.job = job
        self.done = done  # distributed.as_completed over the submitted futures
        self.pending = list(job.todo)
        self.futures: dict[Any, int] = {}  # future -> input index
        self.stop: list[bool] = []  # set by the Ctrl-C handler

    def fill(self) -> None:
        """Submit inputs until as many are in flight as the cluster has threads."""
        room = max(1, sum(self.client.nthreads().values())) - len(self.futures)
        while self.pending and room > 0:
            i = self.pending.pop(0)
            e = self.job.entries[i]
            fut = self.client.submit(
                process_one,
                self.job.pipe,
                os.path.abspath(e["input"]),
                e["base"],
                self.job.stage_map,
                self.job.ascii,
                key=f"recon-batch-{Path(e['input']).name}-{os.urandom(6).hex()}",
                pure=False,
                retries=1,
            )
            self.futures[fut] = i
            self.done.add(fut)
            room -= 1

    def finished(self):
        """The futures as they end; KeyboardInterrupt once Ctrl-C was pressed."""
        while True:
            if self.stop:
                raise KeyboardInterrupt
            if self.done.has_ready():
                yield from self.done.next_batch(block=False)
            elif self.done.is_empty():
                return
            else:
                time.sleep(0.05)

    def record(self, fut) -> None:
        """The record of the input of the ended future ``fut``."""
        i = self.futures.pop(fut)
        entry = self.job.entries[i]
        if fut.status == "finished":
            rec = fut.result()
            rec["input"] = entry["input"]
        else:
            exc = fut.exception() if fut.status == "error" else None
            rec = _failed_from_future(entry, exc, fut.status)
        self.job.records[i] = rec
        # the scheduler forgets the result: a later worker death cannot recompute it
        fut.release()

    def interrupted(self, info: dict) -> None:
        """Record the unfinished inputs, cancel their futures, write the summary so far."""
        from recon_cli.io.atomic import write_bytes
        from recon_cli.stages import report_json

        job = self.job
        for i in job.todo:
            if job.records[i] is None:
                job.records[i] = {
                    "input": job.entries[i]["input"],
                    "status": STATUS_INTERRUPTED,
                    "output": None,
                }
        with contextlib.suppress(Exception):
            self.client.cancel(list(self.futures))
        summary = job.summary(info)
        with contextlib.suppress(OSError):
            write_bytes(job.summary_path, report_json(summary).encode("utf-8") + b"\n")
