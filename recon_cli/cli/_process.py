"""What a ``recon`` process spends around the command itself: start-up and exit.

Measured on the shared 2-core machine (``perf stat`` task-clock and elapsed, a process that
imports numba and calls one cached kernel, numba's floor, ~1.0 CPU s): Python's exit collects
the garbage of every object numba's start-up made (its typing registries, LLVM wrappers) in
several full passes, ~0.3 CPU s; OpenBLAS (numpy's and scipy's, which numba loads to look for
BLAS) starts a worker thread per core that spins on load and is joined at exit, ~0.2 s of wall
time; the cyclic collector runs dozens of times while numba's modules import, ~0.06 s.
None of it is work the user asked for:

* :func:`start` (first thing of :func:`recon_cli.cli.main.main`, before numpy is imported):
  OpenBLAS single-threaded unless the user said otherwise (recon computes with numba's own
  threads; BLAS only ever sees (n, 3) products), and the cyclic collector paused;
* :func:`resume` (when the command's own work starts: before a stage runs, or at once for the
  other commands): everything made so far frozen (never scanned again), the collector back on
  for what the command makes;
* :func:`finish` (after the command): everything frozen again, so the exit does not walk it.
  Objects are still freed by reference counting at exit (files closed, ``__del__`` run): only
  the collector's passes over them are skipped.
"""

from __future__ import annotations

import gc
import os

_state = {"paused": False}


def start() -> None:
    """Before anything imports numpy: single-threaded OpenBLAS by default, collector paused."""
    if "OPENBLAS_NUM_THREADS" not in os.environ and "OMP_NUM_THREADS" not in os.environ:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
    if gc.isenabled():
        gc.disable()
        _state["paused"] = True


def resume() -> None:
    """End of start-up: freeze what exists, collect again what the command makes (idempotent)."""
    if _state["paused"]:
        _state["paused"] = False
        gc.freeze()
        gc.enable()


def finish() -> None:
    """After the command: nothing made so far is scanned again by the collector at exit."""
    resume()
    gc.freeze()
