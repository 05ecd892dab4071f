"""Batch runs: one pipeline over many inputs on Dask's distributed scheduler.

:func:`run_batch` expands the inputs (files, folders, globs), decides which ones are
already done (an output newer than both the input and the pipeline file is *skipped*
unless ``force``), and submits one task per remaining input to a ``dask.distributed``
cluster: a :class:`~distributed.LocalCluster` sized to the machine by default, or an
existing cluster given by its scheduler address. Each task (:func:`process_one`) reads
its input, runs the pipeline and writes ``DIR/<stem>.ply`` (``.npz`` when the pipeline
ends in a grid) atomically, and returns a small record; the data never passes through
the scheduler, so the inputs and the output folder must be on a filesystem the workers
share with the caller.

Failures stay per input: an error in one input's task gives it status ``failed`` with a
one-line message, and the others go on. A worker process that dies while running an
input (killed, out of memory) has that input rescheduled once on a live worker, and when
it dies again the input is reported ``failed`` with ``error_type`` ``"KilledWorker"``
(the local cluster's scheduler runs with ``distributed.scheduler.allowed-failures=1``;
an existing cluster keeps its own setting, 3 by default). No more inputs are in flight
than the cluster has threads, so a dying worker only takes down, and makes suspect, the
inputs it was running, never inputs waiting in its queue. Dask's ``retries=1`` is also
set on every task, for errors escaping the task function (which catches recon's own
errors itself, since rerunning a deterministic failure gains nothing).

An interruption (Ctrl-C: KeyboardInterrupt in the calling thread) cancels the running
tasks, records the unfinished inputs as ``interrupted`` in the summary, closes the local
cluster (its workers ignore SIGINT themselves, so a Ctrl-C to the whole process group
stops them through this process only), removes temporaries of cut-short writes and
re-raises; the outputs finished so far stay, and a rerun skips them.

``DIR/batch.json`` is the summary (also returned): per input ``status``, ``error``,
stage ``stages`` (each stage's report with ``seconds``), ``timings`` (read / pipeline /
write), ``peak_memory_mb`` (resident memory high-water mark of the worker process during
the task, see :func:`process_one`), ``input_stats`` and ``output_stats``
(``points`` / ``vertices`` / ``faces`` / ``grid_shape``).
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import os
import signal
import socket
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Iterable

from recon_cli.errors import BackendError, InputError, ParameterError, ReconError

# file suffixes taken from a folder given as an input
INPUT_SUFFIXES = (".ply", ".npz")
# suffixes an output can have (a grid is written as .npz, anything else as PLY)
OUTPUT_SUFFIXES = (".ply", ".npz")
SUMMARY_NAME = "batch.json"

STATUS_OK = "ok"
STATUS_FAILED = "failed"
STATUS_SKIPPED = "skipped"
STATUS_INTERRUPTED = "interrupted"

_GLOB_CHARS = set("*?[")


# ----------------------------------------------------------------------------- inputs and plan


def expand_inputs(inputs: Iterable[str | os.PathLike]) -> list[tuple[str, str | None]]:
    """Expand files, folders and glob patterns into a list of ``(path, problem)``.

    A folder gives its files ending in ``.ply`` or ``.npz`` (not recursive, sorted); a
    pattern (``*``, ``?``, ``[``; ``**`` recurses) gives its matching files, sorted; any
    other argument is taken as a file. ``problem`` is None for a usable path, or a
    one-line reason (no such file, a folder or pattern with nothing in it) so that the
    argument is reported as failed instead of silently dropped. The same file named twice
    is kept once.
    """
    out: list[tuple[str, str | None]] = []
    seen: set[str] = set()

    def add(path: str, problem: str | None = None) -> None:
        key = os.path.realpath(path) if problem is None else "\0" + path
        if key in seen:
            return
        seen.add(key)
        out.append((path, problem))

    for arg in inputs:
        arg = os.fspath(arg)
        if os.path.isdir(arg):
            found = sorted(
                str(p) for p in Path(arg).iterdir() if p.is_file() and p.suffix.lower() in INPUT_SUFFIXES
            )
            if not found:
                add(arg, "folder holds no .ply or .npz file")
            for p in found:
                add(p)
        elif os.path.exists(arg):
            add(arg)
        elif _GLOB_CHARS & set(arg):
            found = sorted(p for p in glob.glob(arg, recursive=True) if os.path.isfile(p))
            if not found:
                add(arg, "no file matches this pattern")
            for p in found:
                add(p)
        else:
            add(arg, "no such file")
    return out


def output_base(out_dir: str | os.PathLike, input_path: str) -> str:
    """``DIR/<stem>`` for ``input_path`` (the suffix is chosen when the output is known)."""
    return os.path.join(os.fspath(out_dir), Path(input_path).stem)


def existing_output(base: str) -> str | None:
    """The newest of ``base.ply`` / ``base.npz`` that exists, or None."""
    best, best_t = None, None
    for suffix in OUTPUT_SUFFIXES:
        p = base + suffix
        try:
            t = os.stat(p).st_mtime_ns
        except OSError:
            continue
        if best_t is None or t > best_t:
            best, best_t = p, t
    return best


def is_up_to_date(output: str | None, input_path: str, pipeline_path: str) -> bool:
    """True when ``output`` exists and is strictly newer than both the input and the pipeline file."""
    if output is None:
        return False
    try:
        t_out = os.stat(output).st_mtime_ns
        t_in = os.stat(input_path).st_mtime_ns
        t_pipe = os.stat(pipeline_path).st_mtime_ns
    except OSError:
        return False
    return t_out > t_in and t_out > t_pipe


def plan_batch(
    pipeline_path: str | os.PathLike,
    inputs: Iterable[str | os.PathLike],
    out_dir: str | os.PathLike,
    force: bool = False,
) -> list[dict]:
    """One entry per input: ``{"input", "base", "action", ...}`` with ``action`` one of
    ``"run"``, ``"skip"`` (up to date, see :func:`is_up_to_date`) or ``"fail"`` (``error``
    says why: a missing file, an empty folder or pattern).

    Raises
    ------
    InputError
        No inputs at all, or none usable (missing, an empty folder, a pattern matching nothing).
    ParameterError
        Two inputs that would write the same output name, or an output that would
        overwrite its input.
    """
    pipeline_path = os.fspath(pipeline_path)
    expanded = expand_inputs(inputs)
    if not expanded:
        raise InputError("no inputs given")
    if all(problem is not None for _, problem in expanded):
        # nothing to run at all (a missing or empty folder, a pattern matching nothing): bad input, not a batch
        path, problem = expanded[0]
        more = f" (and {len(expanded) - 1} more inputs, none usable)" if len(expanded) > 1 else ""
        raise InputError(problem + more, path)
    entries = []
    by_base: dict[str, str] = {}
    for path, problem in expanded:
        if problem is not None:
            entries.append({"input": path, "base": None, "action": "fail", "error": f"{path}: {problem}",
                            "error_type": "InputError"})
            continue
        base = os.path.abspath(output_base(out_dir, path))
        key = base
        if key in by_base:
            raise ParameterError(
                f"inputs {by_base[key]!r} and {path!r} would both write {base}.ply/.npz (rename one or run them apart)"
            )
        by_base[key] = path
        for suffix in OUTPUT_SUFFIXES:
            if os.path.exists(base + suffix) and os.path.samefile(base + suffix, path):
                raise ParameterError(f"output {base + suffix} would overwrite its input; choose another --out folder")
        out = existing_output(base)
        if not force and is_up_to_date(out, path, pipeline_path):
            entries.append({"input": path, "base": base, "action": "skip", "output": out})
        else:
            entries.append({"input": path, "base": base, "action": "run"})
    return entries


# ----------------------------------------------------------------------------- the task


def register_stages(extra_stages: dict[str, str] | None) -> None:
    """Add ``{name: "module:function"}`` to the stage registry of this process.

    For stages that are not part of recon (plugins, tests); they must be importable in
    every worker. A name already registered for another target is refused.
    """
    if not extra_stages:
        return
    from recon_cli.stages import STAGES

    for name, target in extra_stages.items():
        if not isinstance(target, str) or target.count(":") != 1:
            raise ParameterError(f"extra stage {name!r}: target must be 'module:function', got {target!r}")
        current = STAGES.get(name)
        if current is not None and current != target:
            raise ParameterError(f"extra stage {name!r} would replace the registered stage {current!r}")
        STAGES[name] = target


@contextlib.contextmanager
def _registered(extra_stages: dict[str, str] | None):
    """Register ``extra_stages`` in this process for the duration of the block."""
    from recon_cli.stages import STAGES

    if not extra_stages:
        yield
        return
    added = [name for name in extra_stages if name not in STAGES]
    register_stages(extra_stages)
    try:
        yield
    finally:
        for name in added:
            STAGES.pop(name, None)


def data_stats(obj: Any) -> dict:
    """Counts describing a cloud, mesh or grid."""
    from recon_cli.geometry import PointCloud, TriangleMesh
    from recon_cli.grid import Grid

    if isinstance(obj, Grid):
        return {"kind": "grid", "grid_shape": list(obj.shape), "voxel_size": float(obj.voxel_size)}
    if isinstance(obj, TriangleMesh):
        return {"kind": "mesh", "vertices": int(len(obj.vertices)), "faces": int(len(obj.faces))}
    if isinstance(obj, PointCloud):
        return {"kind": "cloud", "points": int(len(obj.points)), "normals": obj.normals is not None}
    return {"kind": type(obj).__name__}


def _error_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def process_one(
    pipeline: Any,
    input_path: str,
    base: str,
    extra_stages: dict[str, str] | None = None,
    ascii: bool = False,
) -> dict:
    """Run ``pipeline`` on one input and write ``base.ply`` (or ``base.npz`` for a grid).

    This is the function each Dask task runs; it never raises for a failure of the input
    (recon's errors, other exceptions, MemoryError) but returns a record with status
    ``failed`` and the error's first line. The output is written atomically, so a task
    that fails or whose process dies leaves no partial output file.

    ``peak_memory_mb`` is the worker process's resident high-water mark during the task
    (``peak_memory_scope`` ``"task"``: reset at the start through ``/proc/self/clear_refs``
    on Linux; with several threads per worker it covers the tasks running alongside), or
    the process's lifetime peak elsewhere (``"process"``). It includes the worker's own
    footprint (Python, numpy, Dask: ``memory_at_start_mb``, resident at the task's start).

    Returns
    -------
    dict
        ``input``, ``status``, ``output``, ``error``, ``error_type``, ``stages``,
        ``timings``, ``seconds``, ``peak_memory_mb``, ``peak_memory_scope``, ``memory_at_start_mb``,
        ``input_stats``, ``output_stats``, ``worker``.
    """
    from recon_cli import memory
    from recon_cli.grid import Grid
    from recon_cli.io.load import load, save
    from recon_cli.pipeline import run_pipeline

    scope = "task" if memory.reset_peak() else "process"
    rss0 = memory.rss_mb()
    t0 = time.perf_counter()
    rec: dict[str, Any] = {"input": input_path, "status": STATUS_FAILED, "output": None}
    timings: dict[str, float] = {}
    try:
        register_stages(extra_stages)
        data = load(input_path)
        t1 = time.perf_counter()
        timings["read"] = t1 - t0
        rec["input_stats"] = data_stats(data)
        out, reports = run_pipeline(pipeline, data)
        del data
        t2 = time.perf_counter()
        timings["pipeline"] = t2 - t1
        path = base + (".npz" if isinstance(out, Grid) else ".ply")
        save(out, path, ascii=ascii)
        timings["write"] = time.perf_counter() - t2
        rec.update(status=STATUS_OK, output=path, stages=reports, output_stats=data_stats(out))
    except ReconError as exc:
        line = _error_line(exc)
        rec.update(error=line if input_path in line else f"{input_path}: {line}", error_type=type(exc).__name__)
    except MemoryError:
        rec.update(error=f"{input_path}: out of memory", error_type="MemoryError")
    except Exception as exc:  # a bug: keep the batch going and say where
        rec.update(
            error=f"{input_path}: internal error: {type(exc).__name__}: {_error_line(exc)}",
            error_type=type(exc).__name__,
            traceback=traceback.format_exc(),
        )
    rec["timings"] = timings
    rec["seconds"] = time.perf_counter() - t0
    rec["peak_memory_mb"] = memory.peak_mb()
    rec["memory_at_start_mb"] = rss0
    rec["peak_memory_scope"] = scope
    rec["worker"] = {"host": socket.gethostname(), "pid": os.getpid()}
    return rec


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
    """Dask's loggers in this process at ``level`` (they propagate to the root logger) for the block."""
    logger = logging.getLogger("distributed")
    old = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(old)


@contextlib.contextmanager
def _client(scheduler, workers, threads_per_worker, memory_limit, log_level):
    """A Client on an existing scheduler, or on a LocalCluster closed on exit."""
    try:
        import distributed  # noqa: F401  (first: importing it configures its loggers)
    except ImportError:
        raise BackendError("recon batch needs dask.distributed: pip install 'recon[batch]'") from None
    with _dask_log_level(log_level):
        with _client_inner(scheduler, workers, threads_per_worker, memory_limit, log_level) as got:
            yield got


@contextlib.contextmanager
def _client_inner(scheduler, workers, threads_per_worker, memory_limit, log_level):
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise BackendError("recon batch needs dask.distributed: pip install 'recon[batch]'") from None

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise ParameterError(f"cannot reach the Dask scheduler at {scheduler}: {_error_line(exc)}") from None
        with client:
            yield client, _cluster_info(client, scheduler)
        return

    from dask.system import CPU_COUNT

    if workers is None:
        workers = max(1, CPU_COUNT // threads_per_worker)
    # numba's thread pool per worker process = its Dask threads, so workers do not oversubscribe the cores
    env = {"NUMBA_NUM_THREADS": str(threads_per_worker)}
    # allowed-failures=1: an input whose worker dies is rescheduled once, then fails with KilledWorker
    with _sigint_held() as interrupted:
        try:
            with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=threads_per_worker,
                    processes=True,
                    memory_limit=memory_limit,
                    dashboard_address=None,
                    # no dashboard; its HTTP server (health, metrics) on a free port, not 8787 (maybe taken)
                    scheduler_kwargs={"dashboard_address": ":0"},
                    silence_logs=log_level,
                    env=env,
                    # each worker process ignores SIGINT (see dask_setup)
                    preload=[__name__],
                )
        except (OSError, RuntimeError, TimeoutError) as exc:
            raise ReconError(f"could not start a local Dask cluster: {_error_line(exc)}") from None
    with cluster:
        if interrupted:  # Ctrl-C while the cluster started: now that it exists, stop (and close it)
            raise KeyboardInterrupt
        with Client(cluster) as client:
            info = _cluster_info(client, "local")
            info["memory_limit"] = memory_limit
            yield client, info


def _sigint_catchable() -> bool:
    """Whether to take Ctrl-C with our own handler: only the main thread can, and a SIGINT
    the parent left ignored (``nohup ... &``) stays ignored."""
    return threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN


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
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a pending SIGINT arrives now, and is recorded
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


def _read_previous(summary_path: str) -> dict[str, dict]:
    try:
        with open(summary_path, encoding="utf-8") as f:
            doc = json.load(f)
        return {r["input"]: r for r in doc.get("inputs", []) if isinstance(r, dict) and "input" in r}
    except (OSError, ValueError, TypeError, KeyError):
        return {}


def _remove_temporaries(base: str) -> None:
    """Remove temporary files that an interrupted atomic write of ``base.*`` left behind."""
    folder, name = os.path.split(base)
    for suffix in OUTPUT_SUFFIXES:
        for tmp in glob.glob(os.path.join(glob.escape(folder), glob.escape("." + name + suffix) + ".*.tmp")):
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _failed_from_future(entry: dict, exc: BaseException | None, status: str) -> dict:
    from distributed import KilledWorker

    rec: dict[str, Any] = {"input": entry["input"], "status": STATUS_FAILED, "output": None}
    if isinstance(exc, KilledWorker):
        deaths = {1: "once", 2: "twice"}.get(exc.allowed_failures + 1, f"{exc.allowed_failures + 1} times")
        rec.update(
            error=f"{entry['input']}: the worker process running it died {deaths} (killed or out of memory)",
            error_type="KilledWorker",
        )
    elif exc is not None:
        rec.update(error=f"{entry['input']}: task failed: {type(exc).__name__}: {_error_line(exc)}",
                   error_type=type(exc).__name__)
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
    if scheduler is not None and (workers is not None or threads_per_worker is not None or memory_limit is not None):
        raise ParameterError("--workers, --threads-per-worker and --memory-limit size a local cluster; "
                             "leave them out with --scheduler")
    threads = 1 if threads_per_worker is None else _check_count(threads_per_worker, "threads per worker")
    if workers is not None:
        workers = _check_count(workers, "workers")
    mem = _check_memory_limit(memory_limit)
    with _registered(extra_stages):
        pipe = load_pipeline(pipeline_path)
        # the workers resolve each stage exactly as this process did (a worker may be on another machine)
        from recon_cli.stages import STAGES

        stage_map = {step.name: STAGES[step.name] for step in pipe.steps}
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ParameterError(f"--out {out_dir} exists and is not a folder")
    entries = plan_batch(pipeline_path, inputs, out_dir, force=force)
    os.makedirs(out_dir, exist_ok=True)
    summary_path = os.path.join(out_dir, SUMMARY_NAME)
    previous = _read_previous(summary_path)

    records: list[dict | None] = [None] * len(entries)
    todo = []
    for i, e in enumerate(entries):
        if e["action"] == "fail":
            records[i] = {"input": e["input"], "status": STATUS_FAILED, "output": None,
                          "error": e["error"], "error_type": e["error_type"]}
        elif e["action"] == "skip":
            rec = {"input": e["input"], "status": STATUS_SKIPPED, "output": e["output"],
                   "reason": "output is newer than the input and the pipeline file (--force to redo)"}
            old = previous.get(e["input"])
            if old and old.get("output") == e["output"]:
                rec["previous"] = old.get("previous", old) if old.get("status") == STATUS_SKIPPED else old
            records[i] = rec
        else:
            todo.append(i)

    cluster_info: dict[str, Any] = {"scheduler": None}
    if todo:
        cluster_info = _submit_and_collect(
            pipe, entries, todo, records, scheduler, workers, threads, mem, progress, ascii, stage_map, log_level,
            summary_path, pipeline_path, out_dir, t_start,
        )

    summary = _summary(pipeline_path, out_dir, cluster_info, records, t_start)
    write_bytes(summary_path, report_json(summary).encode("utf-8") + b"\n")
    return summary


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


def _submit_and_collect(
    pipe, entries, todo, records, scheduler, workers, threads, mem, progress, ascii, stage_map, log_level,
    summary_path, pipeline_path, out_dir, t_start,
) -> dict:
    """Submit one task per input in ``todo`` and fill ``records`` as they finish.

    At most as many inputs are in flight as the cluster has threads: Dask places each
    task, but none waits in a worker's queue behind another, so a worker that dies takes
    down (and makes suspect) only the inputs it was running.
    """
    try:
        with _client(scheduler, workers, threads, mem, log_level) as (client, info):
            _collect(client, info, pipe, entries, todo, records, progress, ascii, stage_map,
                     summary_path, pipeline_path, out_dir, t_start)
    finally:
        # after the cluster is closed (its workers are gone): what a write cut short left behind
        for i in todo:
            _remove_temporaries(entries[i]["base"])
    return info


def _collect(client, info, pipe, entries, todo, records, progress, ascii, stage_map,
             summary_path, pipeline_path, out_dir, t_start) -> None:
    """The submit / collect loop of :func:`_submit_and_collect` on a connected ``client``.

    On an interruption (Ctrl-C) the unfinished inputs are recorded ``interrupted``, their
    futures cancelled and the summary written before the exception goes on (and the
    cluster is closed on its way out).
    """
    from distributed import as_completed

    from recon_cli.io.atomic import write_bytes
    from recon_cli.progress import task
    from recon_cli.stages import report_json

    pending = list(todo)
    in_flight: dict[Any, int] = {}
    done = as_completed()

    def capacity() -> int:
        return max(1, sum(client.nthreads().values()))

    def fill() -> None:
        room = capacity() - len(in_flight)
        while pending and room > 0:
            i = pending.pop(0)
            e = entries[i]
            fut = client.submit(
                process_one, pipe, os.path.abspath(e["input"]), e["base"], stage_map, ascii,
                key=f"recon-batch-{Path(e['input']).name}-{os.urandom(6).hex()}",
                pure=False,
                retries=1,
            )
            in_flight[fut] = i
            done.add(fut)
            room -= 1

    # Ctrl-C only sets a flag, and this loop raises KeyboardInterrupt where it waits: raised
    # inside one of Dask's blocking calls, it races Dask's own clean-up (a NameError
    # traceback from distributed.utils.sync's cancel callback)
    stop: list[bool] = []
    old_handler = None
    if _sigint_catchable():
        old_handler = signal.signal(signal.SIGINT, lambda signum, frame: stop.append(True))

    def finished():
        while True:
            if stop:
                raise KeyboardInterrupt
            if done.has_ready():
                yield from done.next_batch(block=False)
            elif done.is_empty():
                return
            else:
                time.sleep(0.05)

    try:
        with task(progress, f"batch ({len(todo)} inputs)", total=len(todo)) as bar:
            fill()
            for fut in finished():
                i = in_flight.pop(fut)
                if fut.status == "finished":
                    rec = fut.result()
                    rec["input"] = entries[i]["input"]
                else:
                    exc = fut.exception() if fut.status == "error" else None
                    rec = _failed_from_future(entries[i], exc, fut.status)
                records[i] = rec
                fut.release()  # the scheduler forgets the result: a later worker death cannot recompute it
                bar.advance(1)
                fill()
    except BaseException:
        # interrupted: record what is unfinished, keep the summary of what is done, re-raise
        for i in todo:
            if records[i] is None:
                records[i] = {"input": entries[i]["input"], "status": STATUS_INTERRUPTED, "output": None}
        with contextlib.suppress(Exception):
            client.cancel(list(in_flight))
        summary = _summary(pipeline_path, out_dir, info, records, t_start)
        with contextlib.suppress(OSError):
            write_bytes(summary_path, report_json(summary).encode("utf-8") + b"\n")
        raise
    finally:
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)
