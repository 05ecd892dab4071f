"""A slab runner that spills every state and shared argument (the distributed stages' tests)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


def spilling_runner(
    folder: Path, label: str, before: Callable[[str], None] | None = None
) -> tuple[Callable[..., Any], list[int]]:
    """A ``make_runner`` stand-in and the list it fills.

    The runner is a :class:`recon_cli.slabs.runners.DaskRunner` writing every state and every
    argument the parts share to ``folder`` (thresholds 0); it asserts that the stage asked for a
    spill folder. After each step the list gets the count of state files in ``folder``;
    ``before(name)`` runs before step ``name``.
    """
    from recon_cli.slabs import runners as steps

    seen: list[int] = []

    class Spilling(steps.DaskRunner):
        def run(self, name, fn, args):
            if before is not None:
                before(name)
            out = super().run(name, fn, args)
            seen.append(sum(f.endswith(".state") for f in os.listdir(folder)))
            return out

    def runner(client, slabs, progress=None, overall=None, spill_dir=None, loads=None):
        assert spill_dir is not None  # more slabs than workers: the run spills by itself
        return Spilling(client, slabs, progress, label, overall, str(folder), 0, 0, loads=loads)

    return runner, seen
