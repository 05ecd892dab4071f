"""Progress reporting for long steps, free of click.

The library takes an optional :class:`Progress`; the CLI makes one that draws on stderr
only when stderr is a terminal and ``--quiet`` is off. ``None`` means silent.
"""

from __future__ import annotations

import sys
import time
from typing import IO


class Progress:
    """A minimal progress reporter.

    Use ``with progress.task("estimating normals", total=n) as t: t.advance(k)``.
    """

    def __init__(self, stream: IO[str] | None = None, enabled: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = enabled

    def task(self, name: str, total: float | None = None) -> "_Task":
        return _Task(self, name, total)


class _Task:
    def __init__(self, progress: Progress, name: str, total: float | None):
        self.p = progress
        self.name = name
        self.total = total
        self.done = 0.0
        self.t0 = time.perf_counter()
        self._last = 0.0

    def __enter__(self) -> "_Task":
        self._draw(force=True)
        return self

    def __exit__(self, *exc) -> None:
        if self.total is not None:
            self.done = self.total
        self._draw(force=True, end=True)

    def advance(self, amount: float = 1.0) -> None:
        self.done += amount
        self._draw()

    def update(self, done: float) -> None:
        self.done = done
        self._draw()

    def _draw(self, force: bool = False, end: bool = False) -> None:
        if not self.p.enabled:
            return
        now = time.perf_counter()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        elapsed = now - self.t0
        if self.total:
            frac = min(1.0, self.done / self.total)
            bar = "#" * int(frac * 30)
            text = f"\r{self.name:<28} [{bar:<30}] {frac * 100:5.1f}% {elapsed:6.1f}s"
        else:
            text = f"\r{self.name:<28} {elapsed:6.1f}s"
        self.p.stream.write(text + ("\n" if end else ""))
        self.p.stream.flush()


def task(progress: Progress | None, name: str, total: float | None = None):
    """``progress.task(...)`` or a silent stand-in when ``progress`` is None."""
    if progress is None:
        return _Silent()
    return progress.task(name, total)


class _Silent:
    def __enter__(self) -> "_Silent":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def advance(self, amount: float = 1.0) -> None:
        return None

    def update(self, done: float) -> None:
        return None
