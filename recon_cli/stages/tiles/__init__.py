"""``recon tiles``: a 3D Tiles 1.1 tileset of a mesh, its levels of detail made by ``simplify``.

The mesh's faces are split by their centroids into a tree of cells: a cell with more than
``tile_faces`` faces is halved along each axis at least half as long as its longest one (an
octree for a compact mesh, a quadtree for terrain), and each leaf holds its faces at full
resolution (geometric error 0). Bottom-up, each inner tile holds the union of its children's
contents (vertices welded where they coincide exactly) simplified by recon's quadric
simplification to ``tile_faces`` faces (at most half the union's); its geometric error is the
largest distance from its children's vertices to that surface plus the largest error of a
child (so errors never grow down the tree and bound the distance from every full-resolution
vertex under the tile to its surface). Refinement is ``REPLACE``; bounding
volumes are the boxes of each tile's content and its descendants' (axis-aligned in the
tileset's frame), and each content has its own box.

When the mesh carries a coordinate system (the VLRs a LAS/LAZ file gives, kept through the
stages as ``obj_info`` lines) or ``crs`` names one, every vertex is taken through PROJ to
Earth-centred coordinates and into the east-north-up frame at the mesh's centre
(:mod:`.georef`): the tiles then hold metres, the root's ``transform`` places the frame on
the globe, and geometric errors are metres (as 3D Tiles defines them). Otherwise the tileset
is in the mesh's own coordinates and units, with no transform.

Each tile is a GLB (:mod:`recon_cli.io.gltf`): float32 offsets from its box's centre, turned
y-up as 3D Tiles' glTF content is; normals and colours are kept (16-bit colours holding 8-bit
values, as many LAS files do, as 8-bit, so that they show as meant), vertex attributes only
with ``attributes``. The output is a new folder holding ``tileset.json`` and ``tiles/*.glb``,
written whole or not at all (:class:`recon_cli.io.tiles.Tileset`).

Report keys (stable): ``tiles``, ``leaves``, ``levels``, ``faces_in``, ``faces_written``,
``geometric_error`` (the root's), ``units``, ``crs`` (None without one), ``longitude``,
``latitude`` (of the frame's origin, None without a coordinate system).

References
----------
Open Geospatial Consortium (2023). 3D Tiles Specification 1.1, OGC 22-025r4 (tilesets,
bounding volumes, geometric error, REPLACE refinement, glTF content, the y-up convention).
Garland, M. & Heckbert, P. S. (1997). Surface simplification using quadric error metrics.
SIGGRAPH (the levels of detail, through ``recon simplify``).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh, float64
from recon_cli.params import Param, StageSpec
from recon_cli.progress import task
from recon_cli.stages import StageResult

# a cell is not split beyond this depth (faces sharing one centroid stay in one leaf)
MAX_DEPTH = 24
# an axis is split when it is at least this fraction of the cell's longest
SPLIT_FRACTION = 0.5
# bounding boxes are padded to this fraction of their largest half-extent (no flat boxes)
MIN_HALF = 1e-6

SPEC = StageSpec(
    name="tiles",
    summary="A 3D Tiles 1.1 tileset of a mesh: GLB tiles in a tree, coarser levels simplified.",
    description="""A 3D Tiles 1.1 tileset of a mesh: GLB tiles in a tree, coarser levels simplified.

    OUT is a new folder (an existing path is refused): tileset.json and one GLB per tile.
    Leaves hold the mesh's faces; each level above holds its children simplified (recon
    simplify) to --tile-faces faces, with its geometric error measured in the mesh's units. A
    mesh read from LAS/LAZ (or given --crs) is placed on the globe (needs pyproj: pip install
    'recon[tiles]').""",
    takes=("mesh",),
    gives=("tileset",),
    output_suffix="/",
    params=(
        Param(
            "tile_faces",
            "int",
            65536,
            "Faces at most in a tile: a cell with more is split, and each coarser level is "
            "simplified to this many.",
            unit="faces",
            min=64,
            metavar="N",
        ),
        Param(
            "crs",
            "any",
            None,
            "Coordinate system of the mesh's coordinates (an EPSG code such as 2992, WKT or a "
            "PROJ string), placing the tileset on the globe (default: the one the mesh carries "
            "from LAS/LAZ, if any).",
            metavar="CRS",
        ),
        Param(
            "attributes",
            "bool",
            False,
            "Also write the vertex attributes into the tiles (as _NAME accessors).",
        ),
    ),
)


@dataclass
class _Tile:
    """One tile of the tree: a leaf's faces (input indices) or its children, then its content."""

    key: str
    faces: np.ndarray | None = None
    children: list[_Tile] = field(default_factory=list)
    mesh: TriangleMesh | None = None
    error: float = 0.0
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))

    def walk(self) -> Iterator[_Tile]:
        """The tile and its descendants, children before their parent."""
        for c in self.children:
            yield from c.walk()
        yield self


def _build(centroids: np.ndarray, idx: np.ndarray, lo, hi, limit: int, key: str, depth: int):
    """The tree over the faces ``idx`` (by centroid) in the cell ``lo``..``hi``."""
    while True:
        if len(idx) <= limit or depth >= MAX_DEPTH:
            return _Tile(key, faces=idx)
        ext = hi - lo
        if not ext.max() > 0:
            return _Tile(key, faces=idx)
        axes = np.flatnonzero(ext >= SPLIT_FRACTION * ext.max())
        mid = 0.5 * (lo + hi)
        code = np.zeros(len(idx), np.int64)
        for bit, a in enumerate(axes):
            code |= (centroids[idx, a] >= mid[a]).astype(np.int64) << bit
        order = np.argsort(code, kind="stable")
        counts = np.bincount(code, minlength=1 << len(axes))
        cells = []
        start = 0
        for c, k in enumerate(counts):
            if k:
                clo, chi = lo.copy(), hi.copy()
                for bit, a in enumerate(axes):
                    (clo if c >> bit & 1 else chi)[a] = mid[a]
                cells.append((c, idx[order[start : start + k]], clo, chi))
            start += k
        depth += 1
        if len(cells) == 1:  # all in one cell: split that one in this tile's place
            _, idx, lo, hi = cells[0]
            continue
        children = [_build(centroids, i, a, b, limit, f"{key}-{c}", depth) for c, i, a, b in cells]
        return _Tile(key, children=children)


def _piece(mesh: TriangleMesh, faces: np.ndarray, attributes: bool) -> TriangleMesh:
    """The faces ``faces`` of ``mesh`` with only the vertices they use."""
    used, inverse = np.unique(mesh.faces[faces], return_inverse=True)
    return _subset(mesh, used, inverse.reshape(-1, 3), attributes)


def _subset(mesh: TriangleMesh, rows: np.ndarray, faces: np.ndarray, attributes: bool):
    return TriangleMesh(
        vertices=mesh.vertices[rows],
        faces=faces,
        normals=None if mesh.normals is None else mesh.normals[rows],
        colors=None if mesh.colors is None else mesh.colors[rows],
        attributes={k: v[rows] for k, v in mesh.attributes.items()} if attributes else {},
    )


def _welded(meshes: list[TriangleMesh], attributes: bool) -> TriangleMesh:
    """The union of ``meshes``, vertices at exactly equal coordinates made one."""
    verts = np.concatenate([m.vertices for m in meshes])
    starts = np.cumsum([0] + [len(m.vertices) for m in meshes])
    faces = np.concatenate([m.faces + s for m, s in zip(meshes, starts, strict=False)])
    rows = np.ascontiguousarray(verts).view(np.dtype((np.void, 24))).reshape(-1)
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)  # exact bits
    union = TriangleMesh(
        vertices=verts,
        faces=faces,
        normals=_cat(meshes, "normals"),
        colors=_cat(meshes, "colors"),
        attributes={
            k: np.concatenate([m.attributes[k] for m in meshes]) for k in meshes[0].attributes
        }
        if attributes
        else {},
    )
    return _subset(union, first, inverse.reshape(-1)[faces], attributes)


def _cat(meshes: list[TriangleMesh], name: str) -> np.ndarray | None:
    arrays = [getattr(m, name) for m in meshes]
    return None if arrays[0] is None else np.concatenate(arrays)


def _compact(mesh: TriangleMesh, attributes: bool) -> TriangleMesh:
    used, inverse = np.unique(mesh.faces, return_inverse=True)
    return _subset(mesh, used, inverse.reshape(-1, 3), attributes)


def _coarsen(tile: _Tile, limit: int, attributes: bool) -> None:
    """The tile's content: its children's simplified, and its geometric error."""
    from recon_cli.mesh.distance import closest_points
    from recon_cli.stages.simplify import simplify

    union = _welded([c.mesh for c in tile.children if c.mesh is not None], attributes)
    target = min(limit, len(union.faces) // 2)
    coarse = union
    if target >= 4:
        coarse = _compact(simplify(union, faces=target)[0], attributes)
    error = 0.0
    if coarse is not union:  # how far the finer surface's vertices are from this one
        error = float(closest_points(coarse.vertices, coarse.faces, union.vertices)[0].max())
    tile.mesh = coarse
    tile.error = error + max(c.error for c in tile.children)


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """A 3D Tiles ``box``: centre and three half-axes (axis-aligned), none of length zero."""
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    half = np.maximum(half, MIN_HALF * max(float(half.max()), 1e-300))
    return [float(x) for x in (*centre, half[0], 0, 0, 0, half[1], 0, 0, 0, half[2])]


def _json(tile: _Tile, uris: dict[str, str], root: bool = False) -> dict:
    assert tile.mesh is not None  # every tile has content once built
    v = tile.mesh.vertices
    out: dict[str, Any] = {
        "boundingVolume": {"box": _box(tile.lo, tile.hi)},
        "geometricError": tile.error,
    }
    if root:
        out["refine"] = "REPLACE"
    out["content"] = {
        "uri": uris[tile.key],
        "boundingVolume": {"box": _box(v.min(axis=0), v.max(axis=0))},
    }
    if tile.children:
        out["children"] = [_json(c, uris) for c in tile.children]
    return out


def _frame(
    mesh: TriangleMesh, crs: Any, obj_info: list[str]
) -> tuple[TriangleMesh, np.ndarray | None, dict]:
    """The mesh in the tileset's frame, the root's transform (None: the mesh's own frame)."""
    from recon_cli.io.las import coordinate_system

    text = coordinate_system(obj_info) if crs is None else str(crs).strip()
    if text is not None and text.isdigit():
        text = f"EPSG:{text}"
    if text is None:
        return mesh, None, {"crs": None, "longitude": None, "latitude": None}
    from recon_cli.stages.tiles import georef

    local, transform, nmap, frame = georef.to_local(mesh.vertices, georef.parse_crs(text))
    normals = None
    if mesh.normals is not None:
        n = np.asarray(mesh.normals, np.float64) @ nmap.T
        length = np.linalg.norm(n, axis=1, keepdims=True)
        normals = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    moved = TriangleMesh(
        vertices=local,
        faces=mesh.faces,
        normals=normals,
        colors=mesh.colors,
        attributes=mesh.attributes,
    )
    return moved, transform, frame


def _shown_colors(mesh: TriangleMesh) -> TriangleMesh:
    """``mesh`` with 16-bit colours that hold 8-bit values (max <= 255) as 8-bit.

    LAS colours are 16-bit, but many files store 8-bit values in them: written as they are,
    glTF's normalised colours would show them near black.
    """
    c = mesh.colors
    if c is not None and c.dtype == np.uint16 and len(c) and int(c.max()) <= 255:
        mesh = copy.copy(mesh)
        mesh.colors = c.astype(np.uint8)
    return mesh


def tiles(
    mesh: TriangleMesh,
    tile_faces: int | str = SPEC.param("tile_faces").default,
    crs: int | str | None = SPEC.param("crs").default,
    attributes: bool | str = SPEC.param("attributes").default,
    progress=None,
) -> tuple[Any, dict]:
    """A 3D Tiles 1.1 tileset of ``mesh``: GLB tiles in a tree, coarser levels simplified.

    Parameters
    ----------
    mesh : TriangleMesh
        Vertices (n, 3), faces (m, 3), m >= 1; normals and colours are carried into the tiles.
    tile_faces : int
        Faces at most in a tile, >= 64: a cell with more is split (octree, or quadtree for a
        flat mesh), and each coarser level is simplified to this many.
    crs : int or str, optional
        The mesh's coordinate system: an EPSG code (``2992``, ``"EPSG:2992"``), WKT or a PROJ
        string (default: the LAS/LAZ coordinate system the mesh carries in ``obj_info``, if
        any). The tileset is then placed on the globe (pyproj).
    attributes : bool
        Also write the vertex attributes into the tiles.
    progress : Progress, optional

    Returns
    -------
    tileset : recon_cli.io.tiles.Tileset
        ``tileset.json`` and the tiles' meshes; ``.write(folder)`` writes them.
    report : dict
        See the module docstring.

    Raises
    ------
    InputError
        Not a mesh, no faces, a used vertex not finite, a coordinate system PROJ cannot use
        or a vertex outside its area.
    ParameterError
        Parameters out of range; pyproj missing for a coordinate system.

    References
    ----------
    OGC 22-025r4, 3D Tiles Specification 1.1 (2023). M. Garland and P. S. Heckbert, "Surface
    simplification using quadric error metrics", SIGGRAPH 1997 (the coarser levels).
    """
    v = SPEC.check(dict(tile_faces=tile_faces, crs=crs, attributes=attributes), complete=True)
    if not isinstance(mesh, TriangleMesh):
        raise InputError(f"tiles needs a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise InputError("the mesh has no faces: no tiles to make")
    history, obj_info = list(mesh.history), list(mesh.obj_info)
    mesh = float64(mesh)
    if np.bincount(mesh.faces.reshape(-1), minlength=len(mesh.vertices)).min(initial=1) == 0:
        mesh = _compact(mesh, True)  # vertices no face uses are not written
    if not np.isfinite(mesh.vertices).all():
        raise InputError("the mesh has a vertex with a NaN or infinite coordinate")
    local, transform, frame = _frame(_shown_colors(mesh), v["crs"], obj_info)
    lv, lf = local.vertices, local.faces
    centroids = (lv[lf[:, 0]] + lv[lf[:, 1]] + lv[lf[:, 2]]) / 3.0
    root = _build(
        centroids,
        np.arange(len(local.faces)),
        local.vertices.min(axis=0),
        local.vertices.max(axis=0),
        v["tile_faces"],
        "0",
        0,
    )
    all_tiles = list(root.walk())
    inner = [t for t in all_tiles if t.children]
    with task(progress, "tiles", total=max(len(inner), 1)) as bar:
        for t in all_tiles:  # children before parents
            if t.faces is not None:
                t.mesh = _piece(local, t.faces, v["attributes"])
            else:
                _coarsen(t, v["tile_faces"], v["attributes"])
                bar.advance(1)
            assert t.mesh is not None
            t.lo = np.minimum.reduce([t.mesh.vertices.min(axis=0), *(c.lo for c in t.children)])
            t.hi = np.maximum.reduce([t.mesh.vertices.max(axis=0), *(c.hi for c in t.children)])
    tileset = _tileset(root, all_tiles, transform, frame, history)
    report = {
        "tiles": len(all_tiles),
        "leaves": len(all_tiles) - len(inner),
        "levels": 1 + max(t.key.count("-") for t in all_tiles),
        "faces_in": int(len(mesh.faces)),
        "faces_written": int(sum(len(m.faces) for m, _ in tileset.tiles.values())),
        "geometric_error": root.error,
        "units": "mesh units" if transform is None else "metres",
        "crs": frame["crs"],
        "longitude": frame["longitude"],
        "latitude": frame["latitude"],
    }
    return tileset, report


def _tileset(root: _Tile, all_tiles: list[_Tile], transform, frame: dict, history: list[str]):
    """The :class:`~recon_cli.io.tiles.Tileset` of the built tree (every tile has content)."""
    from recon_cli import __version__
    from recon_cli.io.tiles import Tileset

    uris = {t.key: f"tiles/{t.key}.glb" for t in all_tiles}
    body = _json(root, uris, root=True)
    if transform is not None:
        body["transform"] = [float(x) for x in transform.T.reshape(-1)]  # column-major
    doc: dict[str, Any] = {
        "asset": {"version": "1.1", "generator": f"recon {__version__}"},
        "geometricError": max(float(np.linalg.norm(root.hi - root.lo)), root.error),
        "root": body,
    }
    if frame["crs"] is not None:
        doc["asset"]["extras"] = {"recon": {"frame": frame}}
    contents = {}
    for t in all_tiles:
        assert t.mesh is not None
        v = t.mesh.vertices
        contents[uris[t.key]] = (t.mesh, 0.5 * (v.min(axis=0) + v.max(axis=0)))
    return Tileset(document=doc, tiles=contents, history=history)


@SPEC.runner
def run_stage(
    data: TriangleMesh, *, tile_faces: int, crs: Any, attributes: bool, progress=None
) -> StageResult:
    """Stage ``tiles``: see :func:`tiles`."""
    out, rep = tiles(data, tile_faces=tile_faces, crs=crs, attributes=attributes, progress=progress)
    return StageResult(output=out, report=rep)
