"""The process's memory: resident high-water mark, and giving freed heap back.

One place for what the batch runner, ``recon compare``, the Poisson solver and the
benchmarks measure. Linux figures come from ``/proc/self/status``; elsewhere the peak is
the process's lifetime maximum (``getrusage``) and the reset is not possible.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from typing import Any

# the process before a stage's work, the figures the stages' memory models build on
# (bench/calibration.md, Memory model: the bases): numba and the cached kernels loaded, or the
# kernels built ahead of time without numba (recon_cli.aot), or torch and its threads
JIT_BASE = 160 << 20
AOT_BASE = 40 << 20
TORCH_BASE = 285 << 20


def status_kb(field: str) -> int | None:
    """A ``/proc/self/status`` figure (``"VmRSS"``, ``"VmHWM"``, ...) in KiB, or None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def rss_mb() -> float | None:
    """Current resident memory in MiB (None where unknown)."""
    kb = status_kb("VmRSS")
    return None if kb is None else kb / 1024.0


def peak_mb() -> float | None:
    """Resident high-water mark in MiB since the last :func:`reset_peak` or the process's start."""
    kb = status_kb("VmHWM")
    if kb is not None:
        return kb / 1024.0
    try:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0
    except (ImportError, OSError):  # pragma: no cover - non-POSIX
        return None


def reset_peak() -> bool:
    """Reset the high-water mark to the current RSS (Linux >= 4.0); False where not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:  # "5" resets VmHWM
            f.write("5")
        return True
    except OSError:
        return False


_LIBC: Any = None
# while set (:func:`heap_kept`), freed memory stays in the process for reuse
_KEEP = False
# glibc's mallopt parameters, and where its own dynamic thresholds end after large frees
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_MAX, TRIM_THRESHOLD_MAX = 32 << 20, 64 << 20


def _libc() -> Any:
    """glibc, or False elsewhere."""
    global _LIBC
    if _LIBC is None:
        import ctypes

        try:
            _LIBC = ctypes.CDLL("libc.so.6")
            _LIBC.malloc_trim, _LIBC.mallopt  # noqa: B018  (both or neither)
        except (OSError, AttributeError):  # not glibc
            _LIBC = False
    return _LIBC


def release_free_heap() -> None:
    """Give freed heap memory back to the system (glibc's ``malloc_trim(0)``; elsewhere a no-op).

    glibc serves arrays below its mmap threshold (up to 32 MB) from the heap, and freed
    ones stay resident as holes that later, larger (mmapped) arrays cannot reuse. Within
    :func:`heap_kept`, nothing.
    """
    libc = _libc()
    if libc and not _KEEP:
        libc.malloc_trim(0)


@contextlib.contextmanager
def heap_kept(keep: bool = True) -> Iterator[None]:
    """Keep freed memory in the process for the next arrays, while the block runs.

    Every array the system gives is a page fault per page on first touch; a run that frees
    and makes arrays of the same sizes phase after phase pays them again each time once the
    memory went back (glibc maps its large arrays and trims its heap). Where memory is not
    the constraint (``keep``: the caller's memory plan leaves room), large arrays come from
    the heap, which is not trimmed, and :func:`release_free_heap` does nothing. The resident
    peak grows (the heap's holes stay); on leaving, glibc's thresholds are set where its own
    adjustment takes them and the heap is trimmed. Nothing where ``keep`` is false or on
    other C libraries, and when already inside.
    """
    global _KEEP
    libc = _libc()
    if not keep or not libc or _KEEP:
        yield
        return
    libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    libc.mallopt(M_MMAP_THRESHOLD, 2**31 - 1)
    _KEEP = True
    try:
        yield
    finally:
        _KEEP = False
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)
        libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_MAX)
        libc.malloc_trim(0)


def available_bytes() -> int | None:
    """Memory a new allocation can still get, in bytes.

    ``MemAvailable`` of ``/proc/meminfo``, lowered to the room left under a cgroup (v2) limit; None
    where unknown (not Linux).
    """
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        return None
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        with open("/sys/fs/cgroup/memory.current") as f:
            used = int(f.read().strip())
        if limit != "max":
            room = max(0, int(limit) - used)
            avail = room if avail is None else min(avail, room)
    except (OSError, ValueError):
        pass
    return avail
