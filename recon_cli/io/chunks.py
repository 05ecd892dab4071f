"""Reading a large point cloud by rows, in chunks, without reading the whole file.

For a job spread over processes (:mod:`recon_cli.stages.poisson.distributed`) whose
coordinator must never hold the cloud: it plans the chunks from the files' headers
(:func:`plan_chunks`), and each worker reads its own (:func:`read_chunk`).

- A binary PLY whose vertex rows have a fixed size (no list property before or in the
  vertex element): rows ``start..stop`` are read from their byte offset.
- LAS / LAZ (``recon[las]``): laspy seeks to the row (a LAZ file's chunk table) and reads
  the rows.
- Any other file (ASCII PLY, other formats) is one chunk, read whole by one worker.

``inputs`` may be several files, folders (their ``.ply``/``.las``/``.laz`` files) or glob
patterns: the tiles of one cloud (their rows are chunked file by file).
"""

from __future__ import annotations

import glob
import os
from dataclasses import dataclass

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, as_point_cloud
from recon_cli.io import ply as P

# rows per chunk: a chunk's arrays (points, normals, colours) stay near 100 MB
CHUNK_ROWS = 2_000_000
TILE_SUFFIXES = (".ply", ".las", ".laz")


@dataclass(frozen=True)
class Chunk:
    """Rows ``start..stop`` of ``path``.

    ``kind`` ``"ply"``, ``"las"`` or ``"whole"`` (the whole file: ``start`` 0, ``stop`` -1).
    """

    path: str
    start: int
    stop: int
    kind: str


def expand_inputs(inputs: list[str] | str) -> list[str]:
    """The files of ``inputs`` (files, folders, glob patterns), in order, each once."""
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [os.fspath(inputs)]
    out: list[str] = []
    for item in inputs:
        item = os.fspath(item)
        if os.path.isdir(item):
            found = sorted(
                os.path.join(item, f)
                for f in os.listdir(item)
                if f.lower().endswith(TILE_SUFFIXES) and not f.startswith(".")
            )
            if not found:
                raise InputError("a folder with no .ply/.las/.laz files", item)
            out += found
        elif glob.has_magic(item):
            found = sorted(glob.glob(item))
            if not found:
                raise InputError("no file matches this pattern", item)
            out += found
        else:
            if not os.path.exists(item):
                raise InputError("no such file", item)
            out.append(item)
    return list(dict.fromkeys(out))  # each file once, in order


def _ply_layout(path: str) -> tuple[P.PlyData, int, np.dtype, int] | None:
    """The layout of a binary PLY whose vertex rows have a fixed size.

    Returns (header, vertex rows' byte offset, row dtype, row count), or None.
    """
    with open(path, "rb") as f:
        head = f.read(P.MAX_HEADER_BYTES + 1024)
    ply, body = P.parse_header(head, path)
    if ply.format == "ascii":
        return None
    order = P.FORMATS[ply.format]
    offset = body
    for el in ply.elements:
        if any(p.is_list for p in el.properties):
            return None
        dt = np.dtype([(p.name, order + p.dtype) for p in el.properties])
        if el.name == "vertex":
            need = offset + dt.itemsize * el.count
            size = os.path.getsize(path)
            if size < need:
                raise InputError(
                    f"truncated: header declares {el.count} 'vertex' rows ({need - offset} "
                    f"bytes) but only {size - offset} bytes remain",
                    path,
                )
            return ply, offset, dt, el.count
        offset += dt.itemsize * el.count
    raise InputError("no 'vertex' element", path)


def _las_count(path: str) -> int:
    from recon_cli.io.las import laspy_module

    laspy = laspy_module()
    try:
        with laspy.open(path) as r:
            return int(r.header.point_count)
    except Exception as exc:  # laspy's own errors
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"not a readable LAS/LAZ file ({msg})", path) from None


def plan_chunks(inputs: list[str] | str, rows: int | None = None) -> list[Chunk]:
    """The chunks of ``inputs`` (files, folders, patterns).

    ``rows`` rows at most each (default :data:`CHUNK_ROWS`).
    """
    rows = CHUNK_ROWS if rows is None else int(rows)
    out = []
    for path in expand_inputs(inputs):
        low = path.lower()
        if low.endswith((".las", ".laz")):
            n, kind = _las_count(path), "las"
        elif low.endswith(".ply"):
            lay = _ply_layout(path)
            n, kind = (lay[3], "ply") if lay is not None else (-1, "whole")
        else:
            n, kind = -1, "whole"
        if kind == "whole":
            out.append(Chunk(path, 0, -1, "whole"))
            continue
        for a in range(0, max(n, 1), rows):
            out.append(Chunk(path, a, min(a + rows, n), kind))
    return out


def read_chunk(chunk: Chunk) -> PointCloud:
    """The rows of ``chunk`` as a cloud, as the whole file's reader would give them.

    Points, normals, colours, the other properties as attributes; rows with a NaN or infinite
    coordinate dropped and counted (``invalid_dropped``).
    """
    if chunk.kind == "whole":
        from recon_cli.io.load import load

        obj = load(chunk.path)
        if isinstance(obj, PointCloud):
            return obj
        if not isinstance(obj, TriangleMesh):
            raise InputError("a grid is not a point cloud", chunk.path)
        return as_point_cloud(obj)
    if chunk.kind == "las":
        return _read_las_rows(chunk)
    layout = _ply_layout(chunk.path)
    if layout is None:
        raise InputError("not a binary PLY with fixed-size vertex rows", chunk.path)
    ply, offset, dt, _ = layout
    n = chunk.stop - chunk.start
    rows = np.fromfile(chunk.path, dtype=dt, count=n, offset=offset + chunk.start * dt.itemsize)
    if len(rows) != n:
        raise InputError(
            f"truncated: vertex rows {chunk.start}..{chunk.stop} are missing", chunk.path
        )
    vert = next(e for e in ply.elements if e.name == "vertex")
    el = P.PlyElement(
        "vertex", n, list(vert.properties), {p: rows[p] for p in rows.dtype.names or ()}, rows
    )
    part = P.PlyData(
        format=ply.format, comments=list(ply.comments), obj_info=list(ply.obj_info), elements=[el]
    )
    obj = P.ply_to_geometry(part, chunk.path)
    return obj if isinstance(obj, PointCloud) else as_point_cloud(obj)


def _read_las_rows(chunk: Chunk) -> PointCloud:
    """Rows of a LAS/LAZ file, decoded as :func:`recon_cli.io.las.decode_las` decodes."""
    import io as _io

    from recon_cli.io.las import decode_las, laspy_module

    laspy = laspy_module()
    n = chunk.stop - chunk.start
    try:
        with laspy.open(chunk.path) as r:
            r.seek(chunk.start)
            pts = r.read_points(n)
            head = r.header
            # a one-chunk LAS file in memory, decoded by the file reader (same conversions)
            sub = laspy.LasData(
                header=laspy.LasHeader(point_format=head.point_format, version=head.version)
            )
            sub.header.scales = head.scales
            sub.header.offsets = head.offsets
            sub.points = pts
            buf = _io.BytesIO()
            sub.write(buf)
    except Exception as exc:  # laspy's own errors
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"not a readable LAS/LAZ file ({msg})", chunk.path) from None
    cloud, _ = decode_las(buf.getvalue(), chunk.path)
    return cloud
