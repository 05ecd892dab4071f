"""COPC files for the tests and the bench, written by copc-lib (``copclib``, the ``test`` extra).

laspy reads COPC but does not write it. Here the octree is built in numpy (each level keeps the
first point, in a seeded random order, of each cell of its grid; the deepest level takes the
rest), each node's records are compressed into one LAZ chunk by lazrs (variable-size chunks)
and copc-lib writes the file around them: header, COPC info, the hierarchy and the WKT. The
nodes of level ``page_level`` and deeper are in hierarchy pages of their own, one per node of
that level (a page holds its top node: its key is that node's), so that readers follow pages.
"""

from __future__ import annotations

import io

import numpy as np

from shared_data import SHARED

AUTZEN = SHARED / "autzen_trim.laz"


def octree(pts: np.ndarray, root_cells: int, max_level: int, seed: int) -> dict:
    """Each point's node: ``level`` (n,), ``key`` (n, 3), and the root cube ``center``, ``half``."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = (lo + hi) / 2
    half = float(np.max(hi - lo)) / 2 * 1.001 + 1e-6
    mins = center - half
    rest = np.random.default_rng(seed).permutation(len(pts))
    level = np.full(len(pts), max_level, np.int64)
    for lv in range(max_level):
        if not len(rest):
            break
        cells = root_cells << lv
        ijk = np.minimum(((pts[rest] - mins) / (2 * half) * cells).astype(np.int64), cells - 1)
        _, first = np.unique((ijk[:, 0] * cells + ijk[:, 1]) * cells + ijk[:, 2], return_index=True)
        take = np.zeros(len(rest), bool)
        take[first] = True
        level[rest[take]] = lv
        rest = rest[~take]
    side = (2 * half) / np.exp2(level)
    key = np.minimum(((pts - mins) / side[:, None]).astype(np.int64), (1 << level)[:, None] - 1)
    return {"level": level, "key": key, "center": center, "half": half}


def write_copc(
    path,
    records: np.ndarray,
    scales,
    offsets,
    point_format: int,
    wkt: str = "",
    root_cells: int = 64,
    max_level: int = 8,
    page_level: int | None = 2,
    seed: int = 0,
) -> dict:
    """Write LAS point ``records`` (a laspy point format 6-8 dtype) as a COPC file.

    Returns the nodes' levels and keys (``levels``, ``keys``: one row per node, in file order)
    and each node's point count (``counts``).
    """
    import copclib
    import lazrs

    scales, offsets = np.asarray(scales, float), np.asarray(offsets, float)
    pts = np.column_stack([records[c] * scales[i] + offsets[i] for i, c in enumerate("XYZ")])
    tree = octree(pts, root_cells, max_level, seed)
    keys = np.column_stack([tree["level"], tree["key"]])
    order = np.lexsort((keys[:, 3], keys[:, 2], keys[:, 1], keys[:, 0]))
    keys = keys[order]
    cut = np.r_[0, np.flatnonzero((keys[1:] != keys[:-1]).any(axis=1)) + 1, len(keys)]
    cfg = copclib.CopcConfigWriter(
        point_format, copclib.Vector3(*scales), copclib.Vector3(*offsets), wkt
    )
    w = copclib.FileWriter(str(path), cfg)
    hdr = w.copc_config.las_header
    hdr.min, hdr.max = copclib.Vector3(*pts.min(axis=0)), copclib.Vector3(*pts.max(axis=0))
    info = w.copc_config.copc_info
    info.center_x, info.center_y, info.center_z = map(float, tree["center"])
    info.halfsize = tree["half"]
    info.spacing = 2 * tree["half"] / root_cells
    sorted_records = records[order]
    buf = io.BytesIO()
    comp = lazrs.LasZipCompressor(buf, lazrs.LazVlr.new_for_compression(point_format, 0, True))
    comp.reserve_offset_to_chunk_table()
    node_keys = keys[cut[:-1]]
    for (lv, x, y, z), a, b in zip(node_keys.tolist(), cut[:-1], cut[1:], strict=True):
        start = buf.tell()
        comp.compress_many(sorted_records[a:b].tobytes())
        comp.finish_current_chunk()
        chunk = np.frombuffer(buf.getbuffer()[start:], np.int8).copy()
        buf.seek(0)
        buf.truncate()
        page = copclib.VoxelKey(0, 0, 0, 0)
        if page_level is not None and lv >= page_level:  # in the page of its ancestor there
            s = lv - page_level
            page = copclib.VoxelKey(page_level, x >> s, y >> s, z >> s)
        w.AddNodeCompressed(
            copclib.VoxelKey(lv, x, y, z), copclib.VectorChar(chunk), int(b - a), page
        )
    w.Close()
    return {"levels": node_keys[:, 0], "keys": node_keys, "counts": np.diff(cut)}


def autzen_records() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """The Autzen tile (110k points, US feet) as point format 7: records, scales, offsets, WKT."""
    import laspy

    src = laspy.read(AUTZEN)
    las = laspy.convert(src, point_format_id=7, file_version="1.4")
    wkt = next(v.string for v in src.header.vlrs if v.record_id == 2112)
    return las.points.array, src.header.scales, src.header.offsets, wkt


def synthetic_records(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points of a rolling terrain at 4 points per m² (format 7, millimetre grid).

    Coordinates near UTM (5e5, 5e6); intensity, classes, GPS time and colours vary smoothly,
    as in a survey (so LAZ compresses them as it would real data).
    """
    import laspy

    rng = np.random.default_rng(seed)
    rec = np.zeros(n, laspy.PointFormat(7).dtype())
    side = np.sqrt(n) * 0.5
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    z = 100 + 10 * np.sin(x / 50) * np.cos(y / 70) + rng.normal(0, 0.05, n)
    rec["X"], rec["Y"], rec["Z"] = (np.rint(v * 1000).astype(np.int32) for v in (x, y, z))
    rec["intensity"] = (1000 + 500 * np.sin(x / 20) + rng.integers(0, 50, n)).astype(np.uint16)
    rec["classification"] = np.where(z > 105, 5, 2)
    rec["gps_time"] = 1e4 * y / side + x / side
    rec["red"] = (30000 + 20000 * np.sin(x / 30)).astype(np.uint16)
    rec["green"] = (30000 + 20000 * np.cos(y / 30)).astype(np.uint16)
    rec["blue"] = 20000
    return rec, np.full(3, 0.001), np.array([5e5, 5e6, 0.0])
