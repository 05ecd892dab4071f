"""What a stage will keep of the file it reads, so that a reader able to read only that does.

A :class:`ReadHint` travels from a stage's parameters (``filter --crop --level``, made by the
function its declaration names, ``StageSpec.read_hint``) to the loader
(:func:`recon_cli.io.load.load`). A COPC file (:mod:`recon_cli.io.copc`) then decodes only the
octree nodes the box and levels need; every other format is read whole and the stage crops it
(octree levels exist in COPC files only: asking for them of another file is refused).

A read that chose levels says so in the cloud's ``obj_info`` (a ``copc_read`` line, which PLY
files keep), so that the stage can tell a cloud read with its levels from any other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# the obj_info key of the levels a read chose
LEVELS_KEY = "copc_read"


@dataclass(frozen=True)
class ReadHint:
    """The part of a file a stage keeps.

    Parameters
    ----------
    box : six floats or None
        ``x0, y0, z0, x1, y1, z1`` in the file's units: the points inside (faces included) are
        kept; None: everywhere.
    level : int or None
        The octree levels ``0..level`` of a COPC file (level 0: the root's points).
    resolution : float or None
        The octree levels from 0 to the first whose point spacing is at most this (file
        units). At most one of ``level`` and ``resolution``.
    asked : str
        How the user asked for it (``--crop 1,2,3,4,5,6 --level 3``), for messages.
    """

    box: tuple[float, ...] | None = None
    level: int | None = None
    resolution: float | None = None
    asked: str = ""

    @property
    def wants_levels(self) -> bool:
        """Whether the hint chooses octree levels (which only a COPC file has)."""
        return self.level is not None or self.resolution is not None

    def levels_mark(self) -> str | None:
        """The ``obj_info`` value a read with these levels leaves (None: all levels)."""
        return levels_mark(self.level, self.resolution)

    def last_level(self, spacing: float) -> int | None:
        """The deepest level read from an octree whose root has point ``spacing`` (None: all).

        ``resolution`` R gives the first level whose spacing ``spacing / 2**level`` is at most R
        (laspy's and PDAL's rule).
        """
        if self.level is not None:
            return int(self.level)
        if self.resolution is None:
            return None
        ratio = spacing / self.resolution
        if ratio <= 1:
            return 0
        return math.ceil(math.log2(ratio)) if math.isfinite(ratio) else None


def levels_mark(level: Any, resolution: Any) -> str | None:
    """``"level 3"`` or ``"resolution 0.5"``: the levels asked for, as a read records them."""
    if level is not None:
        return f"level {int(level)}"
    if resolution is not None:
        return f"resolution {float(resolution)!r}"
    return None


def levels_read(obj_info: list[str]) -> str | None:
    """The levels a cloud was read with (its ``copc_read`` line), or None."""
    for line in obj_info:
        key, _, rest = line.partition(" ")
        if key == LEVELS_KEY:
            return rest
    return None
