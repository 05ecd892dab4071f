"""Timing and memory helpers for ``make bench``.

Each measurement runs the callable in a forked child process so the peak resident memory
(``VmHWM``) of that call alone is known, whether the memory is ours (numpy) or a C++
library's (Open3D, PyMeshLab). The child reports its wall time and peak RSS over a pipe.
"""

from __future__ import annotations

import os
import pickle
import statistics
import time
from collections.abc import Callable
from typing import Any

from recon_cli import memory


def _trim_heap() -> None:
    """Give the parent's free heap pages back to the system before forking.

    Otherwise a child reuses pages the parent freed (after an earlier big input) and they
    are already resident: its allocations then never raise its peak RSS, and the memory
    figure reads far too low.
    """
    import gc

    gc.collect()
    memory.release_free_heap()


def measure_once(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Run ``fn`` in a forked child: (seconds, peak MB above the start, fn's small result)."""
    _trim_heap()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(r)
        try:
            memory.reset_peak()
            base = memory.rss_mb() or 0.0
            t0 = time.perf_counter()
            out = fn()
            dt = time.perf_counter() - t0
            peak = max(0.0, (memory.peak_mb() or 0.0) - base)
            try:
                payload = pickle.dumps((dt, peak, out))
            except Exception:
                payload = pickle.dumps((dt, peak, None))
        except BaseException as exc:  # report, never raise in the child
            payload = pickle.dumps((float("nan"), float("nan"), f"error: {exc!r}"))
        with os.fdopen(w, "wb") as f:
            f.write(payload)
        os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        data = f.read()
    os.waitpid(pid, 0)
    return pickle.loads(data)


def measure(fn: Callable[[], Any], repeat: int = 3) -> dict:
    """Median time and peak memory of ``repeat`` runs of ``fn`` (each in its own child)."""
    runs = [measure_once(fn) for _ in range(repeat)]
    times = [t for t, _, _ in runs]
    peaks = [p for _, p, _ in runs]
    return {
        "seconds": statistics.median(times),
        "peak_mb": statistics.median(peaks),
        "runs": times,
        "result": runs[-1][2],
    }


def row(
    stage: str,
    case: str,
    ours: dict,
    ref_name: str | None = None,
    ref: dict | None = None,
    note: str = "",
) -> dict:
    """One table row: ours vs a reference, with ratios ours/theirs."""
    out = {
        "stage": stage,
        "case": case,
        "ours_s": ours["seconds"],
        "ours_mb": ours["peak_mb"],
        "ref": ref_name or "",
        "ref_s": ref["seconds"] if ref else float("nan"),
        "ref_mb": ref["peak_mb"] if ref else float("nan"),
        "note": note,
    }
    out["time_ratio"] = out["ours_s"] / out["ref_s"] if ref and out["ref_s"] > 0 else float("nan")
    out["mem_ratio"] = out["ours_mb"] / out["ref_mb"] if ref and out["ref_mb"] > 0 else float("nan")
    return out
