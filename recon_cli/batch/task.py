"""One input of a batch, as a worker runs it.

Read, run the pipeline, write, and a small record back.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
import traceback
from typing import Any

from recon_cli.batch.plan import STATUS_FAILED, STATUS_OK
from recon_cli.errors import ParameterError, ReconError

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
            raise ParameterError(
                f"extra stage {name!r}: target must be 'module:function', got {target!r}"
            )
        current = STAGES.get(name)
        if current is not None and current != target:
            raise ParameterError(
                f"extra stage {name!r} would replace the registered stage {current!r}"
            )
        STAGES[name] = target


@contextlib.contextmanager
def registered_stages(extra_stages: dict[str, str] | None):
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
    """Counts describing a cloud, mesh, grid or tileset."""
    from recon_cli.geometry import PointCloud, TriangleMesh
    from recon_cli.grid import Grid
    from recon_cli.io.tiles import Tileset

    if isinstance(obj, Grid):
        return {"kind": "grid", "grid_shape": list(obj.shape), "voxel_size": float(obj.voxel_size)}
    if isinstance(obj, Tileset):
        return {"kind": "tileset", "tiles": len(obj)}
    if isinstance(obj, TriangleMesh):
        return {"kind": "mesh", "vertices": int(len(obj.vertices)), "faces": int(len(obj.faces))}
    if isinstance(obj, PointCloud):
        out = {"kind": "cloud", "points": int(len(obj.points)), "normals": obj.normals is not None}
        if obj.invalid_dropped:  # a reader dropped NaN points: never silently
            out["invalid_dropped"] = int(obj.invalid_dropped)
        return out
    return {"kind": type(obj).__name__}


def error_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message (its type's name when it has none)."""
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
    from recon_cli.io.tiles import Tileset
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
        path = base + (
            ".npz" if isinstance(out, Grid) else ".tiles" if isinstance(out, Tileset) else ".ply"
        )
        save(out, path, ascii=ascii)
        timings["write"] = time.perf_counter() - t2
        rec.update(status=STATUS_OK, output=path, stages=reports, output_stats=data_stats(out))
    except ReconError as exc:
        line = error_line(exc)
        rec.update(
            error=line if input_path in line else f"{input_path}: {line}",
            error_type=type(exc).__name__,
        )
    except MemoryError:
        rec.update(error=f"{input_path}: out of memory", error_type="MemoryError")
    except Exception as exc:  # a bug: keep the batch going and say where
        rec.update(
            error=f"{input_path}: internal error: {type(exc).__name__}: {error_line(exc)}",
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
