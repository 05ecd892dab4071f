"""3D Tiles 1.1 tilesets: ``tileset.json`` and its glTF (GLB) tiles, written into a new folder.

A :class:`Tileset` is what ``recon tiles`` gives (``recon_cli.stages.tiles`` builds it): the
tileset JSON object (every tile's bounding volume, geometric error and content URI) and the
mesh of each tile's content in the tileset's frame (the root's; its ``transform`` places that
frame on the globe). :meth:`Tileset.write` encodes each mesh as GLB (float32 offsets from the
tile's centre, turned y-up as 3D Tiles' glTF content is) into a hidden folder that is renamed to
the output path at the end: a tileset appears whole or not at all, and an existing path is never
replaced or merged into.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.geometry import TriangleMesh

#: z-up to y-up (x, y, z) -> (x, z, -y): 3D Tiles runtimes turn glTF content's y-up back to z-up
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class Tileset:
    """A 3D Tiles 1.1 tileset in memory.

    Parameters
    ----------
    document : dict
        The ``tileset.json`` object; each tile's ``content.uri`` is a key of ``tiles``.
    tiles : dict of str to (TriangleMesh, (3,) float64)
        Each content's mesh in the tileset's frame and the point its float32 positions are
        stored relative to (the centre of its bounding box).
    history : list of str
        Provenance lines, written into ``asset.extras.recon.history``.
    report : dict or None
        The report of the stage that made it (``recon_cli.tiles(...).report``).
    """

    document: dict
    tiles: dict[str, tuple[TriangleMesh, np.ndarray]] = field(default_factory=dict)
    history: list[str] = field(default_factory=list)
    report: dict[str, Any] | None = None

    def write(self, path: str | os.PathLike) -> None:
        """Write ``tileset.json`` and the tiles into the new folder ``path`` (atomically).

        Raises
        ------
        OutputError
            ``path`` exists, its parent does not, or the file system refuses.
        ParameterError
            A tile glTF cannot hold (see :mod:`recon_cli.io.gltf`); nothing is written.
        """
        from recon_cli.io.atomic import new_folder
        from recon_cli.io.gltf import emit_gltf

        doc = json.loads(json.dumps(self.document))  # a copy, the history added
        doc["asset"].setdefault("extras", {}).setdefault("recon", {})["history"] = list(
            self.history
        )
        with new_folder(path) as tmp:
            for uri, (mesh, origin) in self.tiles.items():
                target = os.path.join(tmp, *uri.split("/"))
                os.makedirs(os.path.dirname(target), exist_ok=True)
                with open(target, "wb") as f:
                    emit_gltf(
                        mesh, f.write, where=os.path.join(str(path), uri), origin=origin, up=Y_UP
                    )
            with open(os.path.join(tmp, "tileset.json"), "w", encoding="utf-8") as f:
                json.dump(doc, f, separators=(",", ":"), allow_nan=False)

    def __len__(self) -> int:
        return len(self.tiles)
