"""COPC (cloud-optimised point cloud, ``.copc.laz``) by laspy's ``CopcReader`` (``recon[las]``).

A COPC file is a LAZ 1.4 file (point format 6-8) whose points are stored node by node of an
octree, each node one LAZ chunk, and whose hierarchy (pages of 32-byte entries, the root page
in the EVLR ``copc``/1000) gives each node's key (level, x, y, z), byte range and point count.

Read with a :class:`~recon_cli.io.hint.ReadHint` (``recon filter --crop --level
--resolution``), only the nodes whose cube meets the box, at the levels asked, are fetched and
decoded (laspy's ``CopcReader.query``); the points inside the box (faces included) are then
kept by their float64 coordinates, computed as the LAS reader computes them: the cloud is the
whole file's cloud cropped (the same points, in the same order, the same bits), restricted to
the levels asked. A window with no point is an error, never an empty cloud. Read without a
hint, every node is decoded the same way. Either way the cloud is what the LAS reader
(``recon_cli.io.las``) gives: attributes, scale, offset, VLRs and EVLRs such as the WKT
coordinate system, COPC's and LASzip's own records left out.

Before laspy reads anything, the header is checked against the file's size (as for LAS) and
the whole hierarchy is walked and checked: every page inside the file and reached once, every
key inside its level's grid and its parent present, every node's chunk inside the point data
and apart from the others, and the nodes' counts adding up to the header's. laspy walks the
hierarchy as it finds it: a page that does not hold its own key, or points back at itself,
would make it loop forever. The chunks to decode are checked too: each one's own point count
and layer sizes (lazrs allocates every layer by its declared size). :func:`summary` describes
a file from its header and hierarchy without decoding a point (``recon info``).

References
----------
Hobu Inc. et al., "COPC: Cloud Optimized Point Cloud specification 1.0", https://copc.io, 2021;
ASPRS, "LAS specification 1.4 R15", 2019.
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.io.hint import LEVELS_KEY, ReadHint
from recon_cli.io.las import (
    check_counts,
    cloud_from_points,
    coordinates,
    first_line,
    laspy_module,
)

_HEADER, _VLR_HEADER, _INFO = 375, 54, 160
#: the bytes :func:`is_copc` reads: the LAS 1.4 header, the first VLR's header, COPC's info
HEAD_BYTES = _HEADER + _VLR_HEADER + _INFO
# one hierarchy entry: key (level, x, y, z), chunk offset, chunk bytes, points (-1: a page)
_ENTRY = np.dtype(
    [
        ("level", "<i4"),
        ("x", "<i4"),
        ("y", "<i4"),
        ("z", "<i4"),
        ("offset", "<u8"),
        ("byte_size", "<i4"),
        ("point_count", "<i4"),
    ]
)
_KEY = ["level", "x", "y", "z"]
# keys are int32: a level's grid has at most 2**30 cells along an axis
_MAX_LEVEL = 30


def is_copc(head: bytes) -> bool:
    """Whether a file's first bytes (:data:`HEAD_BYTES` of them) are a COPC file's.

    LAS 1.4 whose first VLR is COPC's info record (user ``copc``, record 1).
    """
    if len(head) < _HEADER or head[:4] != b"LASF" or head[24:26] != b"\x01\x04":
        return False
    at = int.from_bytes(head[94:96], "little")
    if len(head) < at + _VLR_HEADER:
        return False
    return head[at + 2 : at + 18].rstrip(b"\0") == b"copc" and head[at + 18 : at + 20] == b"\1\0"


def is_copc_file(path: str | os.PathLike) -> bool:
    """Whether the file at ``path`` is a COPC file (its first bytes; False when unreadable)."""
    try:
        with open(path, "rb") as f:
            return is_copc(f.read(HEAD_BYTES))
    except OSError:
        return False


@dataclass(frozen=True)
class Octree:
    """A COPC file's octree as its header and hierarchy give it (no point decoded).

    ``nodes``: the hierarchy entries (fields ``level x y z offset byte_size point_count``) of
    the nodes that hold points, in the order the pages were read.
    """

    center: np.ndarray
    halfsize: float
    spacing: float
    nodes: np.ndarray
    point_count: int

    def cubes(self) -> tuple[np.ndarray, np.ndarray]:
        """The nodes' cubes: (m, 3) minimum and maximum corners, as laspy computes them."""
        lo = self.center - self.halfsize
        side = (2.0 * self.halfsize) / np.exp2(self.nodes["level"].astype(np.float64))
        ijk = np.column_stack([self.nodes[c] for c in "xyz"]).astype(np.float64)
        return lo + ijk * side[:, None], lo + (ijk + 1.0) * side[:, None]

    def select(self, lo: np.ndarray, hi: np.ndarray, last: int | None) -> np.ndarray:
        """Which nodes a query of the box ``lo``-``hi`` (closed) down to level ``last`` reads."""
        a, b = self.cubes()
        hit = np.asarray(((a <= hi) & (b >= lo)).all(axis=1))
        return hit if last is None else hit & (self.nodes["level"] <= last)

    def per_level(self) -> tuple[list[int], list[int]]:
        """Nodes and points of each level, from level 0 to the deepest."""
        depth = int(self.nodes["level"].max()) + 1 if len(self.nodes) else 0
        lv = self.nodes["level"]
        nodes = np.bincount(lv, minlength=depth)
        points = np.bincount(lv, weights=self.nodes["point_count"], minlength=depth)
        return nodes.astype(int).tolist(), points.astype(np.int64).tolist()


def _refuse(what: str, where: str) -> InputError:
    return InputError(f"not a valid COPC file: {what}", where)


def read_octree(f: Any, size: int, where: str) -> Octree:
    """Check a COPC file's header and walk its whole hierarchy (see the module).

    Parameters
    ----------
    f : binary file object, seekable
        The file.
    size : int
        Its size in bytes.
    where : str
        Its name, for messages.

    Raises
    ------
    InputError
        Not COPC, or a header, an info record or a hierarchy that does not fit the file.
    """
    f.seek(0)
    head = f.read(HEAD_BYTES)
    check_counts(head, size, where)
    if not is_copc(head):
        raise InputError(
            "not a COPC file (its first VLR is not COPC's info record): name it .laz, or "
            "read it with --input-format las",
            where,
        )
    at = int.from_bytes(head[94:96], "little") + _VLR_HEADER
    if len(head) < at + _INFO or int.from_bytes(head[at - 34 : at - 32], "little") < _INFO:
        raise _refuse("its COPC info record is cut short", where)
    cx, cy, cz, half, spacing, root, root_size = struct.unpack_from("<5d2Q", head, at)
    center = np.array([cx, cy, cz])
    if not (np.isfinite(center).all() and 0 < half < np.inf and 0 < spacing < np.inf):
        raise _refuse(
            f"its octree's centre {center.tolist()}, half size {half!r} and spacing "
            f"{spacing!r} are not finite and positive",
            where,
        )
    scales, offsets = struct.unpack_from("<3d", head, 131), struct.unpack_from("<3d", head, 155)
    if not all(0 < v < np.inf for v in scales) or not np.isfinite(offsets).all():
        raise _refuse(
            f"its scale {list(scales)} and offset {list(offsets)} are not finite (and the scale "
            "positive)",
            where,
        )
    to_points = int.from_bytes(head[96:100], "little")
    fmt = head[104] & 0x3F
    if fmt not in (6, 7, 8):
        raise _refuse(f"point format {fmt} (COPC stores formats 6, 7 and 8)", where)
    count = int.from_bytes(head[247:255], "little")
    nodes = _walk(f, size, int(root), int(root_size), where)
    _check_nodes(nodes, size, to_points, count, where)
    return Octree(center, float(half), float(spacing), nodes[nodes["point_count"] > 0], count)


def _page(f: Any, size: int, offset: int, length: int, where: str) -> np.ndarray:
    if length <= 0 or length % _ENTRY.itemsize or offset + length > size:
        raise _refuse(
            f"a hierarchy page of {length} bytes at byte {offset} (the file has {size} bytes; "
            f"a page is a multiple of {_ENTRY.itemsize} bytes)",
            where,
        )
    f.seek(offset)
    data = f.read(length)
    if len(data) != length:
        raise _refuse(f"the hierarchy page at byte {offset} is cut short", where)
    return np.frombuffer(data, _ENTRY)


def _walk(f: Any, size: int, root: int, root_size: int, where: str) -> np.ndarray:
    """Every node entry of the hierarchy, its pages followed (each must hold its own key)."""
    found = []
    budget = size  # the pages' bytes: a hierarchy is never larger than its file
    todo: list[tuple[int, int, tuple | None]] = [(root, root_size, None)]
    while todo:
        offset, length, key = todo.pop()
        budget -= max(length, 0)
        if budget < 0:
            raise _refuse("its hierarchy pages add up to more bytes than the file", where)
        page = _page(f, size, offset, length, where)
        _check_keys(page, where)
        keys = page[_KEY].tolist()
        counts = page["point_count"]
        if len(set(keys)) != len(keys):
            raise _refuse(f"a hierarchy page holds a node twice (at byte {offset})", where)
        # the page of a key holds that key's node: laspy would load it again and again
        if key is not None and (key not in keys or counts[keys.index(key)] < 0):
            raise _refuse(f"the hierarchy page of node {key} does not hold that node", where)
        for i in np.flatnonzero(counts == -1):
            todo.append((int(page["offset"][i]), int(page["byte_size"][i]), keys[i]))
        found.append(page[counts >= 0])
    return np.concatenate(found)


def _check_keys(page: np.ndarray, where: str) -> None:
    """Every key of a page inside its level's grid, every count a count or -1 (a page)."""
    level = page["level"]
    bad = (level < 0) | (level > _MAX_LEVEL) | (page["point_count"] < -1)
    cells = np.left_shift(1, np.clip(level, 0, _MAX_LEVEL).astype(np.int64))
    for c in "xyz":
        bad |= (page[c] < 0) | (page[c] >= cells)
    if bad.any():
        e = page[int(np.argmax(bad))]
        raise _refuse(
            f"hierarchy entry {tuple(int(e[c]) for c in _KEY)} with {int(e['point_count'])} "
            "points lies outside the octree",
            where,
        )


def _check_nodes(nodes: np.ndarray, size: int, to_points: int, count: int, where: str) -> None:
    """Each node once, its parent present, its chunk in the point data and apart; counts add up."""
    keys = np.ascontiguousarray(nodes[_KEY])
    order = np.argsort(keys, order=_KEY)
    ordered = keys[order]
    same = ordered[1:] == ordered[:-1]
    if same.any():
        raise _refuse(f"node {tuple(ordered[int(np.argmax(same))])} appears twice", where)
    if not (keys == np.array((0, 0, 0, 0), keys.dtype)).any():
        raise _refuse("its hierarchy has no root node", where)
    deep = keys[keys["level"] > 0]
    parents = np.empty(len(deep), keys.dtype)
    parents["level"] = deep["level"] - 1
    for c in "xyz":
        parents[c] = deep[c] >> 1
    at = np.minimum(np.searchsorted(ordered, parents), len(ordered) - 1)
    orphan = ordered[at] != parents
    if orphan.any():
        raise _refuse(f"node {tuple(deep[int(np.argmax(orphan))])} has no parent node", where)
    full = nodes[nodes["point_count"] > 0]
    start = full["offset"].astype(np.int64)
    stop = start + full["byte_size"].astype(np.int64)
    # the point data starts with the 8-byte offset of the LAZ chunk table
    bad = (full["byte_size"] <= 0) | (start < to_points + 8) | (stop > size)
    if bad.any():
        i = int(np.argmax(bad))
        raise _refuse(
            f"node {tuple(full[_KEY][i])}'s chunk (bytes {start[i]}..{stop[i]}) lies outside "
            f"the point data (bytes {to_points + 8}..{size})",
            where,
        )
    by = np.argsort(start, kind="stable")
    overlap = stop[by][:-1] > start[by][1:]
    if overlap.any():
        raise _refuse(f"the chunks of two nodes overlap at byte {start[by][1:][overlap][0]}", where)
    total = int(full["point_count"].astype(np.int64).sum())
    if total != count:
        raise _refuse(f"its nodes hold {total} points, its header declares {count}", where)


def _open(data: Any, path: str | None, where: str) -> tuple[Any, int]:
    """A binary file object on the file (``path``) or its bytes, and its size."""
    if path is None:
        from recon_cli.io import text

        raw = bytes(text.as_uint8(data).data)
        return io.BytesIO(raw), len(raw)
    try:
        return open(path, "rb"), os.path.getsize(path)
    except FileNotFoundError:
        raise InputError("no such file", where) from None


def decode_copc(
    data: Any, where: str, path: str | None = None, hint: ReadHint | None = None
) -> tuple[Any, dict]:
    """Decode a COPC file (from ``path`` when given, else the bytes ``data``).

    Parameters
    ----------
    data : bytes-like or None
        The file's bytes (when ``path`` is None).
    where : str
        The file's name, for messages.
    path : str, optional
        The file.
    hint : ReadHint, optional
        A box and octree levels: only the nodes they need are decoded (see the module).

    Returns
    -------
    cloud : PointCloud
    details : dict
        The LAS reader's, ``format`` ``"copc"``, the octree (:func:`octree_details`) and, for a
        read by a hint, ``window``: ``box``, ``levels`` (first and last read), ``nodes_read``,
        ``nodes``, ``points_decoded``, ``points_in_file``.

    Raises
    ------
    InputError
        A file that is not valid COPC, or a box and levels that hold no point.
    """
    hint = hint if hint is not None and (hint.box is not None or hint.wants_levels) else None
    f, size = _open(data, path, where)
    with f:
        tree = read_octree(f, size, where)
        cloud, details = _read(f, tree, hint or ReadHint(), where)
    if hint is None:
        del details["window"]
    elif hint.wants_levels:
        cloud.obj_info.append(f"{LEVELS_KEY} {hint.levels_mark()}")
    details.update(format="copc", compressed=True, **octree_details(tree))
    return cloud, details


def _read(f: Any, tree: Octree, hint: ReadHint, where: str) -> tuple[Any, dict]:
    """The points of the box and levels of ``hint``: only the nodes they need decoded."""
    laspy = laspy_module()
    try:
        f.seek(0)
        header = laspy.LasHeader.read_from(f, read_evlrs=True)
    except Exception as exc:  # laspy's own errors
        raise InputError(f"not a readable COPC file ({first_line(exc)})", where) from None
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    last = hint.last_level(tree.spacing)
    chosen = np.ones(len(tree.nodes), bool) if last is None else tree.nodes["level"] <= last
    bounds = None
    if hint.box is not None:
        lo, hi = np.asarray(hint.box[:3], float), np.asarray(hint.box[3:], float)
        # the query is padded by a grid step (a writer may round a point into the next node)
        # and kept inside the cube and the int32 grid (laspy rounds its box to integers)
        pad = np.abs(scales) + 1e-9 * tree.halfsize
        grid = np.abs(scales) * (2.0**31 - 2.0**20)
        qlo = np.fmax(np.fmax(lo - pad, tree.center - tree.halfsize - pad), offsets - grid)
        qhi = np.fmin(np.fmin(hi + pad, tree.center + tree.halfsize + pad), offsets + grid)
        chosen &= tree.select(qlo, qhi, last) if (qlo <= qhi).all() else False
        bounds = laspy.copc.Bounds(qlo, qhi)
    decoded = int(tree.nodes["point_count"][chosen].sum(dtype=np.int64))
    _check_chunks(f, tree.nodes[chosen], header, where)
    records = laspy.ScaleAwarePointRecord.zeros(0, header=header)
    if chosen.any():
        try:
            f.seek(0)
            reader = laspy.CopcReader(f, close_fd=False)
            records = reader.query(
                bounds=bounds, level=None if last is None else range(0, last + 1)
            )
            if bounds is None and len(records) != decoded:  # laspy walked other nodes
                raise ValueError(f"{len(records)} points read of the {decoded} asked for")
        except Exception as exc:  # laspy's and lazrs' errors
            raise InputError(f"not a readable COPC file ({first_line(exc)})", where) from None
        if bounds is not None:
            xyz = coordinates(records.array, scales, offsets)
            records = records[((xyz >= lo) & (xyz <= hi)).all(axis=1)]
    if len(records) == 0 and (hint.box is not None or hint.wants_levels):
        raise InputError(
            f"{hint.asked or 'the window'}: no point of the file there (of {tree.point_count}; "
            f"its points span {_span(header)})",
            where,
        )
    cloud, details = cloud_from_points(records, header, where)
    details["window"] = {
        "box": None if hint.box is None else [float(v) for v in hint.box],
        "levels": [0, int(tree.nodes["level"][chosen].max())] if chosen.any() else None,
        "nodes_read": int(chosen.sum()),
        "nodes": len(tree.nodes),
        "points_decoded": decoded,
        "points_in_file": tree.point_count,
    }
    return cloud, details


# layers of each LASzip 1.4 item (type: layers; Byte14, type 14, has one per byte): Point14,
# RGB14, RGBNIR14, Wavepacket14
_LAYERS = {10: 9, 11: 1, 12: 2, 13: 1}


def _chunk_head(header: Any, where: str) -> tuple[int, int] | None:
    """The size of a chunk's raw first point and its count of layers, from the LASzip record.

    None when the items are not LASzip 1.4's layered ones (then lazrs alone checks the chunks).
    """
    zips = [v for v in header.vlrs if v.user_id == "laszip encoded" and v.record_id == 22204]
    if not zips:
        raise _refuse("it has no LASzip record (how its chunks are compressed)", where)
    data = bytes(getattr(zips[0], "record_data", b""))
    count = int.from_bytes(data[32:34], "little")
    if len(data) < 34 + 6 * count:
        raise _refuse("its LASzip record is cut short", where)
    size = layers = 0
    for i in range(count):
        kind, item = struct.unpack_from("<2H", data, 34 + 6 * i)
        if kind != 14 and kind not in _LAYERS:
            return None
        size += item
        layers += item if kind == 14 else _LAYERS[kind]
    return size, layers


def _check_chunks(f: Any, nodes: np.ndarray, header: Any, where: str) -> None:
    """Each chunk's own point count and layer sizes (read before lazrs sizes buffers by them).

    A chunk starts with its first point raw, its point count and the size of each layer; lazrs
    allocates each layer by its size (a corrupted one took a 1 MB file to 3.5 GB).
    """
    layout = _chunk_head(header, where)
    if layout is None:
        return
    raw, layers = layout
    need = raw + 4 + 4 * layers
    for e in nodes:
        size = int(e["byte_size"])
        f.seek(int(e["offset"]))
        head = f.read(need)
        count = int.from_bytes(head[raw : raw + 4], "little") if len(head) == need else -1
        data = int(np.frombuffer(head[raw + 4 :], "<u4").sum(dtype=np.int64)) if count >= 0 else 0
        if size < need or count != e["point_count"] or data > size - need:
            key = tuple(int(e[c]) for c in _KEY)
            raise _refuse(
                f"node {key}'s chunk ({size} bytes at byte {int(e['offset'])}) declares "
                f"{count} points and {data} bytes of layers, its entry {int(e['point_count'])} "
                "points",
                where,
            )


def _span(header: Any) -> str:
    lo, hi = np.asarray(header.mins), np.asarray(header.maxs)
    return ",".join(f"{v:g}" for v in (*lo, *hi))


def octree_details(tree: Octree) -> dict:
    """``recon info``'s description of an octree: its root cube, spacing, nodes and levels."""
    nodes, points = tree.per_level()
    return {
        "octree_center": tree.center.tolist(),
        "octree_halfsize": tree.halfsize,
        "octree_spacing": tree.spacing,
        "octree_nodes": len(tree.nodes),
        "nodes_per_level": nodes,
        "points_per_level": points,
    }


def summary(path: str, where: str) -> dict:
    """What a COPC file holds, from its header and hierarchy only (no point decoded).

    Every node's chunk is checked as a read would check it (its first bytes).

    Returns
    -------
    dict
        ``points`` (the header's count), ``mins`` and ``maxs`` (the header's bounds),
        ``dimensions`` (``"dtype name"`` of each LAS dimension), ``colors`` (the point format
        has RGB), ``normals`` (extra dimensions ``nx ny nz``...), ``attributes`` (the other
        dimensions' names) and ``details`` (:func:`decode_copc`'s, without ``window``).
    """
    from recon_cli.io.las import describe_header

    laspy = laspy_module()
    f, size = _open(None, path, where)
    with f:
        tree = read_octree(f, size, where)
        try:
            f.seek(0)
            header = laspy.LasHeader.read_from(f, read_evlrs=True)
        except Exception as exc:  # laspy's own errors
            raise InputError(f"not a readable COPC file ({first_line(exc)})", where) from None
        _check_chunks(f, tree.nodes, header, where)  # their first bytes only: no point decoded
    out = describe_header(header, where)
    out["details"].update(format="copc", compressed=True, **octree_details(tree))
    out["points"] = tree.point_count
    return out
