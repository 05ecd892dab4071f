"""What a ``recon`` process does around the command itself: start-up and exit.

Three steps; what each saves (numba's garbage at exit, OpenBLAS's threads, the collector
during imports), as measured, is in ``docs/design/process.md``:

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
