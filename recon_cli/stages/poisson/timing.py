"""Wall-clock seconds per named phase of a reconstruction (its report's ``timings``)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager


class Timings:
    """Seconds per phase, in the order run, from the object's creation.

    Attributes
    ----------
    seconds : dict of str to float
        Each finished phase's wall seconds; ``"total"`` once :meth:`total` is called.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._t0 = time.perf_counter()

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as phase ``name`` (a phase that raises is not recorded)."""
        t = time.perf_counter()
        yield
        self.seconds[name] = time.perf_counter() - t

    def total(self) -> dict[str, float]:
        """Record ``"total"``, the seconds since creation, and return :attr:`seconds`."""
        self.seconds["total"] = time.perf_counter() - self._t0
        return self.seconds
