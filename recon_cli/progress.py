"""Progress reporting for long steps, free of click (bars drawn by `rich <https://rich.readthedocs.io>`_).

The library takes an optional :class:`Progress`; the CLI makes one that draws on stderr
only when stderr is a terminal and ``--quiet`` is off. ``None`` means silent. Stages use
:func:`task`::

    with task(progress, "estimating normals", total=n) as t:
        t.advance(k)          # weighted by work: ``total`` is in the stage's own units

A step done by one long call (a numba kernel) announces its work first, so that the bar
keeps moving while the call runs::

    with task(progress, "poisson: solve", total=sum(work)) as t:
        for w in work:
            t.expect(w)       # the bar moves on an estimate (the rate of the steps so far)
            ...               # until the step's advance
            t.advance(w)

A task with a total shows a bar, the percentage, the elapsed time and an estimate of the
time left; one without a total shows a spinner and the elapsed time. The display is
redrawn by rich's own thread, so it keeps moving while a kernel runs.

When numba has to compile a kernel (the first run after an install without
``recon warmup``, or after an upgrade), an enabled :class:`Progress` says so on a line of
its own ("compiling kernels, first run after install") for as long as compiling lasts,
instead of a bar frozen at 0 %. A disabled one imports neither rich nor numba, and an
enabled one does not import numba either: it starts listening when numba is loaded (by the
first kernel module a command imports, see :func:`numba_loaded`; a command that runs
ahead-of-time kernels only never loads it).
"""

from __future__ import annotations

import sys
import threading
import weakref
from typing import IO, Any

COMPILING = "compiling kernels, first run after install"

# enabled Progress objects made before numba was loaded: they listen from numba_loaded() on
_WAITING: weakref.WeakSet[Progress] = weakref.WeakSet()


def numba_loaded() -> None:
    """Called by ``recon_cli._kernels.numba_setup`` once numba is imported.

    The enabled :class:`Progress` objects made before start listening to its compiler.
    """
    for p in list(_WAITING):
        _WAITING.discard(p)
        if p.enabled and p._listener is None:
            p._listen_to_numba()


class Progress:
    """Progress bars on ``stream`` (default stderr), drawn only when ``enabled``.

    Parameters
    ----------
    stream : text stream or None
        Where to draw (stderr by default).
    enabled : bool or None
        None: draw when ``stream`` is a terminal.
    """

    def __init__(self, stream: IO[str] | None = None, enabled: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = enabled
        self._lock = threading.RLock()
        self._bars: Any = None  # rich.progress.Progress while a task or a compile is shown
        self._users = 0
        self._compile_task: Any = None
        self._compile_depth = 0
        self._listener: Any = None
        if enabled:
            if "numba" in sys.modules:
                self._listen_to_numba()
            else:
                _WAITING.add(self)

    def task(self, name: str, total: float | None = None) -> _Task:
        """A context manager drawing one bar (or a spinner when ``total`` is None)."""
        if not self.enabled:
            return _Silent()  # type: ignore[return-value]
        return _Task(self, name, total)

    def close(self) -> None:
        """Stop listening to numba's compiler and clear the display."""
        if self._listener is not None:
            from numba.core import event

            event.unregister("numba:compile", self._listener)
            self._listener = None
        with self._lock:
            if self._bars is not None:
                self._bars.stop()
                self._bars = None
                self._users = 0

    # ---------------------------------------------------------------- display
    def _acquire(self):
        with self._lock:
            if self._bars is None:
                from rich.console import Console
                from rich.progress import (
                    BarColumn,
                    SpinnerColumn,
                    TaskProgressColumn,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )
                from rich.progress import Progress as Bars

                console = Console(file=self.stream, force_terminal=True, highlight=False)
                self._bars = Bars(
                    SpinnerColumn(),
                    TextColumn("{task.description:<32}"),
                    BarColumn(),
                    TaskProgressColumn(),
                    TimeElapsedColumn(),
                    TextColumn("eta"),
                    TimeRemainingColumn(),
                    console=console,
                    transient=False,
                    refresh_per_second=8,
                )
                self._bars.start()
            self._users += 1
            return self._bars

    def _release(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users <= 0 and self._bars is not None:
                self._bars.stop()
                self._bars = None
                self._users = 0

    # ---------------------------------------------------------------- numba
    def _listen_to_numba(self) -> None:
        from numba.core import event

        owner = self

        class _CompileListener(event.Listener):
            def on_start(self, ev: Any) -> None:
                owner._compile_started()

            def on_end(self, ev: Any) -> None:
                owner._compile_ended()

        self._listener = _CompileListener()
        event.register("numba:compile", self._listener)

    def _compile_started(self) -> None:
        with self._lock:
            self._compile_depth += 1
            if self._compile_depth == 1 and self._compile_task is None:
                bars = self._acquire()
                self._compile_task = bars.add_task(COMPILING, total=None)

    def _compile_ended(self) -> None:
        with self._lock:
            self._compile_depth -= 1
            if self._compile_depth == 0 and self._compile_task is not None:
                self._bars.remove_task(self._compile_task)
                self._compile_task = None
                self._release()


class _Task:
    TICK = 0.125  # seconds between the estimated moves of an expected step

    def __init__(self, progress: Progress, name: str, total: float | None):
        self.p = progress
        self.name = name
        self.total = total
        self.done = 0.0
        self._id: Any = None
        self._t0 = 0.0
        self._ticker: threading.Thread | None = None
        self._stop = threading.Event()

    def __enter__(self) -> _Task:
        import time

        bars = self.p._acquire()
        self._id = bars.add_task(self.name, total=self.total if self.total else None)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self._end_step()
        bars = self.p._bars
        if bars is not None and self._id is not None:
            if self.total:
                bars.update(self._id, completed=self.total)
            else:  # a spinner task: show it finished
                bars.update(self._id, total=1, completed=1)
            bars.refresh()
        self.p._release()

    def advance(self, amount: float = 1.0) -> None:
        self._end_step()
        self.done += amount
        bars = self.p._bars
        if bars is not None:
            bars.update(self._id, completed=self.done)

    def update(self, done: float) -> None:
        self._end_step()
        self.done = done
        bars = self.p._bars
        if bars is not None:
            bars.update(self._id, completed=done)

    def expect(self, amount: float) -> None:
        """The next ``amount`` units of work run now, in one call that reports nothing (a kernel).

        Until the next :meth:`advance` (or :meth:`update`) the bar moves on at the rate of the work
        done so far, stopping short of the step's end (never past it, nor backwards). Before any
        work is done there is no rate: the bar waits (the spinner and the elapsed time still move).
        Moves need the call to release the GIL (``nogil`` kernels); otherwise the bar catches up
        when it returns.
        """
        import time

        self._end_step()
        elapsed = time.perf_counter() - self._t0
        if amount <= 0 or self.done <= 0 or elapsed <= 0 or self.p._bars is None:
            return
        rate = self.done / elapsed
        start, base = time.perf_counter(), self.done
        stop = self._stop = threading.Event()

        def tick() -> None:
            while not stop.wait(self.TICK):
                bars = self.p._bars
                if bars is None:
                    return
                guess = base + min(0.95 * amount, rate * (time.perf_counter() - start))
                bars.update(self._id, completed=guess)

        self._ticker = threading.Thread(target=tick, name="recon-progress", daemon=True)
        self._ticker.start()

    def _end_step(self) -> None:
        if self._ticker is not None:
            self._stop.set()
            self._ticker.join()
            self._ticker = None


def task(progress: Progress | None, name: str, total: float | None = None):
    """``progress.task(...)`` or a silent stand-in when ``progress`` is None."""
    if progress is None:
        return _Silent()
    return progress.task(name, total)


class _Silent:
    def __enter__(self) -> _Silent:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def advance(self, amount: float = 1.0) -> None:
        return None

    def update(self, done: float) -> None:
        return None

    def expect(self, amount: float) -> None:
        return None
