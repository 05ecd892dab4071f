"""PLY reading and writing, our own code (no PLY library).

Two layers:

* :func:`parse_ply` / :func:`serialize_ply` convert between bytes and a :class:`PlyData`
  (the header and one array per property, every element and property kept);
* :func:`read_ply` / :func:`write_ply` convert between files and the data model
  (:class:`~recon_cli.geometry.PointCloud`, :class:`~recon_cli.geometry.TriangleMesh`).

Binary bodies are decoded with numpy structured dtypes, never a per-vertex Python loop.
Before anything is allocated, the counts in the header are checked against the bytes the
file actually holds, so a lying header is an error, not a huge allocation.
"""

from __future__ import annotations

import io
import os
import stat
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from recon_cli.aot import kernels
from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, drop_invalid, storage_dtype
from recon_cli.io._ply_decode import memory_of, parse_ascii_body, parse_binary_body
from recon_cli.io._ply_types import (
    FORMATS,
    PLY_TYPES,
    PlyData,
    PlyElement,
    PlyProperty,
    ply_name,
)
from recon_cli.io.text import as_uint8, check_header_words, one_line, where_of

# the classes of a decoded file live with the type names (the body decoder uses them too)
__all__ = [
    "MAX_HEADER_BYTES",
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "compile_ply_kernels",
    "emit_body",
    "emit_ply",
    "geometry_to_ply",
    "header_bytes",
    "parse_header",
    "parse_ply",
    "ply_bytes",
    "ply_to_geometry",
    "read_bytes",
    "read_ply",
    "serialize_ply",
    "write_ply",
]

MAX_HEADER_BYTES = 1 << 20

_VERTEX_XYZ = ("x", "y", "z")
_VERTEX_NORMAL = ("nx", "ny", "nz")
_VERTEX_COLOR = ("red", "green", "blue", "alpha")
_VERTEX_COLOR_ALT = ("r", "g", "b", "a")
_VERTEX_COLOR_DIFFUSE = ("diffuse_red", "diffuse_green", "diffuse_blue", "diffuse_alpha")
_FACE_INDEX_NAMES = ("vertex_indices", "vertex_index")


# --------------------------------------------------------------------------- reading


def _describe(path: str | None) -> str:
    return "<stdin>" if path in (None, "-") else str(path)


def parse_header(buf: bytes | np.ndarray, path: str | None = None) -> tuple[PlyData, int]:
    """Parse the header of ``buf``; return the (empty) :class:`PlyData` and the body offset."""
    where = _describe(path)
    lines, body_start = _header_lines(buf, where)
    ply = PlyData(format="")
    current: PlyElement | None = None
    for lineno, raw in enumerate(lines[1:], start=2):
        line = raw.strip()
        if not line:
            continue
        key, _, rest = line.partition(" ")
        at = f"header line {lineno}"
        if key == "format":
            _format_line(ply, line, at, where)
        elif key == "comment":
            ply.comments.append(rest.strip() if rest else "")
        elif key == "obj_info":
            ply.obj_info.append(rest.strip() if rest else "")
        elif key == "element":
            current = _element_line(ply, line, at, where)
        elif key == "property":
            if current is None:
                raise InputError(f"{at}: property before any element", where)
            _property_line(current, line, at, where)
        else:
            raise InputError(f"{at}: unknown keyword {key!r}", where)
    if not ply.format:
        raise InputError("header has no 'format' line", where)
    return ply, body_start


def _header_lines(buf: bytes | np.ndarray, where: str) -> tuple[list[str], int]:
    """The header's lines (the magic line first) and the offset of the body."""
    if len(buf) == 0:
        raise InputError("empty file", where)
    total = len(buf)
    if not isinstance(buf, bytes):
        # a numpy buffer (see read_bytes): the header is text, parse a bytes copy of its start
        buf = bytes(memory_of(buf)[: MAX_HEADER_BYTES + 1024])
    if not (buf.startswith(b"ply\n") or buf.startswith(b"ply\r\n") or buf.startswith(b"ply\r")):
        raise InputError("not a PLY file (missing 'ply' magic line)", where)
    end = _find_end_header(buf)
    if end is None:
        if total > MAX_HEADER_BYTES:
            raise InputError(f"no 'end_header' in the first {MAX_HEADER_BYTES} bytes", where)
        raise InputError("header has no 'end_header' line (truncated file?)", where)
    head_end, body_start = end
    try:
        text = buf[:head_end].decode("ascii")
    except UnicodeDecodeError:
        raise InputError("header is not ASCII text", where) from None
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), body_start


def _format_line(ply: PlyData, line: str, at: str, where: str) -> None:
    """``format <ascii|binary_little_endian|binary_big_endian> 1.0``: set ``ply.format``."""
    words = line.split()
    if len(words) != 3 or words[1] not in FORMATS:
        raise InputError(f"{at}: unknown format {line!r}", where)
    if words[2] not in ("1.0", "1"):
        raise InputError(f"{at}: unsupported PLY version {words[2]!r}", where)
    if ply.format:
        raise InputError(f"{at}: second 'format' line", where)
    ply.format = words[1]


def _element_line(ply: PlyData, line: str, at: str, where: str) -> PlyElement:
    """``element <name> <count>``: a new element of ``ply``, returned."""
    words = line.split()
    if len(words) != 3:
        raise InputError(f"{at}: malformed element line {line!r}", where)
    try:
        count = int(words[2])
    except ValueError:
        raise InputError(f"{at}: element count {words[2]!r} is not an integer", where) from None
    if count < 0:
        raise InputError(f"{at}: negative element count {count}", where)
    if ply.element(words[1]) is not None:
        raise InputError(f"{at}: element {words[1]!r} declared twice", where)
    element = PlyElement(words[1], count)
    ply.elements.append(element)
    return element


def _property_line(element: PlyElement, line: str, at: str, where: str) -> None:
    """``property <type> <name>`` or ``property list <count type> <type> <name>`` of ``element``."""
    words = line.split()
    if len(words) >= 2 and words[1] == "list":
        if len(words) != 5:
            raise InputError(f"{at}: malformed list property {line!r}", where)
        ctype, itype, name = words[2], words[3], words[4]
        for t in (ctype, itype):
            if t not in PLY_TYPES:
                raise InputError(f"{at}: unknown type name {t!r}", where)
        if PLY_TYPES[ctype][0] == "f":
            raise InputError(f"{at}: list count type {ctype!r} is not an integer type", where)
        prop = PlyProperty(name, PLY_TYPES[itype], PLY_TYPES[ctype])
    else:
        if len(words) != 3:
            raise InputError(f"{at}: malformed property {line!r}", where)
        if words[1] not in PLY_TYPES:
            raise InputError(f"{at}: unknown type name {words[1]!r}", where)
        prop = PlyProperty(words[2], PLY_TYPES[words[1]])
    if any(p.name == prop.name for p in element.properties):
        raise InputError(f"{at}: property {prop.name!r} declared twice in {element.name!r}", where)
    element.properties.append(prop)


def _find_end_header(buf: bytes) -> tuple[int, int] | None:
    """(end of header text, start of body), or None when there is no end_header line."""
    limit = min(len(buf), MAX_HEADER_BYTES)
    pos = 0
    while True:
        i = buf.find(b"end_header", pos, limit)
        if i < 0:
            return None
        # must start a line
        if i > 0 and buf[i - 1 : i] not in (b"\n", b"\r"):
            pos = i + 1
            continue
        j = i + len(b"end_header")
        # rest of the line may hold spaces; then \n, \r\n or \r
        while j < len(buf) and buf[j : j + 1] in (b" ", b"\t"):
            j += 1
        if buf[j : j + 2] == b"\r\n":
            return i, j + 2
        if buf[j : j + 1] in (b"\n", b"\r"):
            return i, j + 1
        if j >= len(buf):
            return i, j
        pos = i + 1


def parse_ply(buf: bytes | np.ndarray, path: str | None = None) -> PlyData:
    """Decode a whole PLY file held in ``buf``.

    Raises
    ------
    InputError
        On any malformed, truncated or inconsistent content (the message names ``path``).
    """
    buf = as_uint8(buf)  # writable: the element arrays are views of it
    ply, offset = parse_header(buf, path)
    ply.nbytes = len(buf)
    where = _describe(path)
    if ply.format == "ascii":
        parse_ascii_body(ply, buf, offset, where)
    else:
        parse_binary_body(ply, buf, offset, FORMATS[ply.format], where)
    return ply


# --------------------------------------------------------------------------- writing

# bytes of binary records encoded at a time (a buffer that stays in the CPU's cache)
_BLOCK_BYTES = 1 << 18


def header_bytes(ply: PlyData) -> bytes:
    """The header of ``ply`` (its elements' counts and properties), ``end_header`` included."""
    if ply.format not in FORMATS:
        raise ValueError(f"unknown PLY format {ply.format!r}")
    head = ["ply", f"format {ply.format} 1.0"]
    head += [f"comment {one_line(c)}" for c in ply.comments]
    head += [f"obj_info {one_line(c)}" for c in ply.obj_info]
    for el in ply.elements:
        head.append(f"element {el.name} {el.count}")
        head += [p.header_line() for p in el.properties]
    head.append("end_header")
    return "\n".join(head).encode("ascii") + b"\n"


def serialize_ply(ply: PlyData) -> bytes:
    """Encode ``ply`` (header and body) as bytes."""
    out = io.BytesIO()
    emit_ply(ply, out.write)
    return out.getvalue()


def emit_ply(ply: PlyData, put: Callable[[bytes | memoryview], Any]) -> None:
    """Encode ``ply`` piece by piece: ``put`` gets the header, then the body in pieces.

    A piece may be a view of a buffer that the next piece overwrites: ``put`` copies or
    writes it before returning.
    """
    put(header_bytes(ply))
    emit_body(ply, put)


def emit_body(ply: PlyData, put: Callable[[bytes | memoryview], Any]) -> None:
    """Encode ``ply``'s elements without the header, piece by piece (as :func:`emit_ply`)."""
    for el in ply.elements:
        if ply.format == "ascii":
            put(_ascii_body(el))
        else:
            _binary_body(el, FORMATS[ply.format], put)


def _binary_body(el: PlyElement, order: str, put: Callable[[bytes | memoryview], Any]) -> None:
    if el.count == 0:
        return
    if any(p.is_list and el.data[p.name].dtype == object for p in el.properties):
        put(_ragged_records(el, order))
        return
    dtype = _record_dtype(el, order)
    body = _records_as_they_are(el, dtype)
    if body is not None:  # the rows already are the file's records (a filtered PLY's)
        put(body)
        return
    # records made a block at a time in one buffer that stays in cache, each block put
    # out at once: no copy of the whole body, no page faults of a body-sized array
    block = np.empty(min(el.count, max(1, _BLOCK_BYTES // dtype.itemsize)), dtype=dtype)
    for a in range(0, el.count, len(block)):
        rows = block[: min(len(block), el.count - a)]
        for p in el.properties:
            values = el.data[p.name][a : a + len(rows)]
            if p.is_list:
                rows[p.name + "\0n"] = values.shape[1]
                if values.shape[1]:
                    rows[p.name] = values
            else:
                rows[p.name] = values
        put(rows.view(np.uint8).reshape(-1).data)


def _record_dtype(el: PlyElement, order: str) -> np.dtype:
    """The structured type of ``el``'s binary records (its lists all of one length)."""
    fields: list[tuple[Any, ...]] = []
    for p in el.properties:
        if p.is_list:
            k = el.data[p.name].shape[1]
            fields.append((p.name + "\0n", f"{order}{p.count_dtype}"))
            if k:
                fields.append((p.name, order + p.dtype, (k,)))
        else:
            fields.append((p.name, order + p.dtype))
    return np.dtype(fields)


def _ragged_records(el: PlyElement, order: str) -> bytes:
    """``el``'s binary records row by row (lists of differing lengths)."""
    chunks = []
    for r in range(el.count):
        for p in el.properties:
            v = el.data[p.name][r]
            if p.is_list:
                v = np.asarray(v)
                chunks.append(np.array(len(v), dtype=f"{order}{p.count_dtype}").tobytes())
                chunks.append(v.astype(order + p.dtype).tobytes())
            else:
                chunks.append(np.array(v, dtype=order + p.dtype).tobytes())
    return b"".join(chunks)


class _Interface:
    """An object numpy reads as an array through ``__array_interface__`` (no copy)."""

    def __init__(self, interface: dict[str, Any]):
        self.__array_interface__ = interface


def _records_as_they_are(el: PlyElement, dtype: np.dtype) -> memoryview | None:
    """The element's body as it lies in memory, when its columns are the records of ``dtype``.

    That is, when every property is a 1-D view, of the property's exact type and byte order,
    at its offset in consecutive records of ``dtype.itemsize`` bytes of one buffer (the
    columns of a PLY read and subset as records, :func:`recon_cli.geometry.take_rows`);
    None otherwise. The body is then written without encoding it again.
    """
    if el.count < 2 or any(p.is_list for p in el.properties):
        return None
    cols = [el.data[p.name] for p in el.properties]
    if not all(isinstance(c, np.ndarray) and c.ndim == 1 and len(c) == el.count for c in cols):
        return None
    first = cols[0].__array_interface__["data"][0]
    for p, c in zip(el.properties, cols, strict=True):
        field_dtype, offset = dtype.fields[p.name][:2]  # type: ignore[index]
        if (
            c.dtype != field_dtype  # byte order included
            or c.strides[0] != dtype.itemsize
            or c.__array_interface__["data"][0] - first != offset
            or not np.may_share_memory(cols[0], c)
        ):
            return None
    size = el.count * dtype.itemsize
    interface = {"data": (first, True), "shape": (size,), "typestr": "|u1", "version": 3}
    return np.asarray(_Interface(interface)).data


def _fmt(code: str) -> str:
    kind = np.dtype(code).kind
    if kind == "f":
        return "%.9g" if np.dtype(code).itemsize == 4 else "%.17g"
    return "%d"


def _ascii_body(el: PlyElement) -> bytes:
    if el.count == 0:
        return b""
    ragged = any(p.is_list and el.data[p.name].dtype == object for p in el.properties)
    if not ragged:
        columns = []
        for p in el.properties:
            v = el.data[p.name]
            if p.is_list:
                k = v.shape[1]
                columns.append(np.char.mod("%d", np.full(el.count, k)))
                for j in range(k):
                    columns.append(np.char.mod(_fmt(p.dtype), v[:, j].astype(p.dtype)))
            else:
                columns.append(np.char.mod(_fmt(p.dtype), v.astype(p.dtype)))
        rows = columns[0]
        for c in columns[1:]:
            rows = np.char.add(np.char.add(rows, " "), c)
        return ("\n".join(rows.tolist()) + "\n").encode("ascii")
    lines = []
    for r in range(el.count):
        parts = []
        for p in el.properties:
            v = el.data[p.name][r]
            if p.is_list:
                v = np.asarray(v).astype(p.dtype)
                parts.append(str(len(v)))
                parts += [_fmt(p.dtype) % x for x in v]
            else:
                parts.append(_fmt(p.dtype) % np.asarray(v).astype(p.dtype))
        lines.append(" ".join(parts))
    return ("\n".join(lines) + "\n").encode("ascii")


# --------------------------------------------------------------------------- data model


def read_bytes(path: str | os.PathLike) -> np.ndarray:
    """All bytes of ``path`` (``-``: stdin) as a writable ``(n,) uint8`` array.

    A file is read straight into numpy memory, as ``np.fromfile`` does: one buffer that the
    parser views, no ``bytes`` object copied out of it. Writable whatever the source (see
    ``text.as_uint8``): the arrays parsed out of it are views that the stages'
    kernels take.
    """
    if str(path) == "-":
        return as_uint8(sys.stdin.buffer.read())
    try:
        with open(path, "rb", buffering=0) as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(
                st.st_mode
            ):  # a pipe or device (e.g. <(cat scan.ply)): size unknown
                return as_uint8(f.read())
            size = st.st_size
            buf = np.empty(size, dtype=np.uint8)
            got = f.readinto(buf.data)
            while got < size:  # short reads (pipes, network file systems)
                k = f.readinto(buf.data[got:])
                if not k:
                    break
                got += k
            if got < size:  # the file shrank while we read it
                buf = buf[:got]
            return buf
    except FileNotFoundError:
        raise InputError("no such file", str(path)) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a file", str(path)) from None
    except PermissionError:
        raise InputError("permission denied", str(path)) from None


def read_ply(
    path: str | os.PathLike, data: bytes | np.ndarray | None = None
) -> PointCloud | TriangleMesh:
    """Read a PLY file as a point cloud (no faces) or a triangle mesh.

    Parameters
    ----------
    path : str or path-like
        File to read; ``-`` reads standard input.
    data : bytes, optional
        The file's bytes when already read (``path`` then only names it in errors).

    Returns
    -------
    PointCloud or TriangleMesh
        A mesh when the file has a ``face`` element with at least one face; polygons are
        fan-triangulated. Vertices with a NaN or infinite coordinate are dropped and
        counted in ``invalid_dropped``; ``obj_info sensor`` lines are a cloud's sensors.

    Raises
    ------
    InputError
        Malformed or inconsistent file, a face using a NaN/inf vertex, face indices out of
        range.
    """
    ply = parse_ply(read_bytes(path) if data is None else data, str(path))
    return ply_to_geometry(ply, str(path))


def ply_to_geometry(ply: PlyData, path: str | None = None) -> PointCloud | TriangleMesh:
    """Convert a decoded PLY file to the data model (see :func:`read_ply`)."""
    where = _describe(path)
    vert = ply.element("vertex")
    if vert is None:
        raise InputError("no 'vertex' element", where)
    props = {p.name: p for p in vert.properties}
    for c in _VERTEX_XYZ:
        if c not in props:
            raise InputError(f"vertex element has no {c!r} property", where)
        if props[c].is_list:
            raise InputError(f"vertex property {c!r} is a list", where)
    d = vert.data
    raw = vert.raw
    face = ply.element("face")
    pinned = False
    if raw is not None and vert.count and (not raw.flags.writeable or 2 * raw.nbytes < ply.nbytes):
        # the columns below are views of these rows: copy them when they are read-only
        # bytes, or a small part of the file (the views must not pin a mesh's face bytes)
        vert.raw = np.array(raw)
    elif raw is not None and vert.count and face is not None and face.count:
        # a mesh whose rows are most of its file: its columns are copied below instead (the
        # faces are converted copies, so nothing else keeps the file's bytes)
        pinned = True
    groups = _vertex_groups(props)
    pts = _columns(vert, *groups[0])
    # rows with a NaN or infinite coordinate are dropped (and counted) once the object is made
    invalid = _first_nonfinite_row(vert, pts) >= 0
    used = set(_VERTEX_XYZ)
    # float32 only when every coordinate column fits in float32 exactly (float, 8- and 16-bit
    # integers): a double column, or int/uint ones, make the source double (kept through every
    # stage)
    point_dtype = (
        np.float32 if all(props[c].dtype in _FLOAT32_EXACT for c in _VERTEX_XYZ) else np.float64
    )
    normals = colors = None
    for names, dtype in groups[1:]:
        if names == _VERTEX_NORMAL:
            normals = _columns(vert, names, dtype)
        else:
            colors = _columns(vert, names, dtype)
        used |= set(names)
    if pinned:
        pts = np.array(pts)
        normals = None if normals is None else np.array(normals)
        colors = None if colors is None else np.array(colors)
    attributes = {
        p.name: np.array(d[p.name], dtype=np.dtype(p.dtype))
        for p in vert.properties
        if p.name not in used and not p.is_list
    }
    # copies, so a kept element does not pin the whole file's bytes in memory
    extras = [
        PlyElement(e.name, e.count, list(e.properties), {k: np.array(v) for k, v in e.data.items()})
        for e in ply.elements
        if e.name not in ("vertex", "face")
    ]
    common: dict[str, Any] = dict(
        colors=colors,
        attributes=attributes,
        history=list(ply.comments),
        point_dtype=point_dtype,
        extra_elements=extras,
        obj_info=list(ply.obj_info),
    )
    if face is None or face.count == 0:
        cloud = PointCloud(points=pts, normals=normals, **common)
        return drop_invalid(cloud, where) if invalid else cloud
    idx_prop = next((p for p in face.properties if p.name in _FACE_INDEX_NAMES and p.is_list), None)
    if idx_prop is None:
        raise InputError("face element has no 'vertex_indices' list property", where)
    faces, src = _triangulate(face.data[idx_prop.name], where)
    if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
        bad = faces.max() if faces.max() >= len(pts) else faces.min()
        raise InputError(f"face index {int(bad)} out of range for {len(pts)} vertices", where)
    face_attrs = {
        p.name: np.array(face.data[p.name]) if src is None else face.data[p.name][src]
        for p in face.properties
        if p is not idx_prop and not p.is_list
    }
    mesh = TriangleMesh(
        vertices=pts, faces=faces, normals=normals, face_attributes=face_attrs, **common
    )
    return drop_invalid(mesh, where) if invalid else mesh


# PLY types whose every value float32 holds exactly
_FLOAT32_EXACT = ("f4", "i1", "u1", "i2", "u2")


def _vertex_groups(props: dict) -> list[tuple[tuple[str, ...], object]]:
    """The column groups read from a vertex element: xyz, then normals and colours when present.

    Each is ``(names, dtype)``: float32 for coordinates and normals that are all float32 in
    the file, float64 for any other type (doubles, integers, mixed); None keeps the file's
    type (colours).
    """
    groups: list[tuple[tuple[str, ...], object]] = [(_VERTEX_XYZ, _float_type(props, _VERTEX_XYZ))]
    if all(c in props and not props[c].is_list for c in _VERTEX_NORMAL):
        groups.append((_VERTEX_NORMAL, _float_type(props, _VERTEX_NORMAL)))
    for names in (_VERTEX_COLOR, _VERTEX_COLOR_DIFFUSE, _VERTEX_COLOR_ALT):
        if all(c in props and not props[c].is_list for c in names[:3]):
            groups.append((tuple(c for c in names if c in props), None))
            break
    return groups


def _float_type(props: dict, names: tuple[str, ...]) -> type:
    """float32 when every named property is a float32, else float64 (doubles, integers, mixed)."""
    return np.float32 if all(props[c].dtype == "f4" for c in names) else np.float64


def _columns(el: PlyElement, names: tuple[str, ...], dtype) -> np.ndarray:
    """(count, len(names)) array of the named scalar properties, in ``dtype`` (None: the file's).

    Adjacent fields of one native-order type already in ``dtype`` are returned as a view of
    the element's rows (``el.raw``): nothing is copied, so a binary cloud is read in about
    the time its bytes take to arrive. Other layouts are gathered into a new array.
    """
    raw = el.raw
    view = _rows_view(raw, names, dtype) if raw is not None and el.count else None
    if view is not None:
        return view
    plan = _gather_plan(raw.dtype, names, dtype) if raw is not None else None
    if (
        raw is not None
        and plan is not None
        and plan[0] != "mixed"
        and el.count
        and raw.flags.c_contiguous
    ):
        out = np.empty((el.count, len(names)), dtype=plan[5])
        _gather_apply(plan, raw.view(np.uint8).reshape(-1), raw.dtype.itemsize, out)
        if plan[0] == "int":
            out = out.view(plan[6]).astype(plan[7], copy=False)
    else:
        rtype = dtype if dtype is not None else np.result_type(*[el.data[c].dtype for c in names])
        if el.count == 0:
            out = np.zeros((0, len(names)), dtype=rtype)
        else:
            out = np.column_stack([el.data[c].astype(rtype) for c in names])
    return out.astype(dtype, copy=False) if dtype is not None else out


def _rows_view(raw: np.ndarray, names: tuple[str, ...], dtype) -> np.ndarray | None:
    """The named fields of the structured rows ``raw`` as one ``(count, k)`` strided view, or None.

    Possible when the fields are adjacent, in order, of one native-order type equal to
    ``dtype`` (any type when None).
    """
    run = _adjacent_fields(raw.dtype, names)
    if run is None:
        return None
    ftype, _ = run
    if not ftype.isnative or (dtype is not None and ftype != np.dtype(dtype)):
        return None
    return np.lib.stride_tricks.as_strided(
        raw[names[0]], shape=(len(raw), len(names)), strides=(raw.strides[0], ftype.itemsize)
    )


def _adjacent_fields(rowtype: np.dtype, names: tuple[str, ...]) -> tuple[np.dtype, int] | None:
    """(type, byte offset of the first) of the named fields of ``rowtype``, or None.

    None unless they are adjacent, in order, and of one type.
    """
    fields = rowtype.fields
    assert fields is not None  # a structured dtype
    ftype, first = fields[names[0]][:2]
    for k, c in enumerate(names):
        if fields[c][:2] != (ftype, first + k * ftype.itemsize):
            return None
    return ftype, first


def _first_nonfinite_row(el: PlyElement, pts: np.ndarray) -> int:
    """Index of the first row of ``pts`` with a NaN or infinite value, -1 when all are finite.

    ``pts`` are the x, y, z columns of ``el``.

    When x, y, z are adjacent floats of one type in the rows of ``el.raw``, the check reads
    those bytes in one numba pass, in either byte order (numpy's isfinite over an unaligned
    strided view is several times slower).
    """
    K = kernels("recon_cli.io._ply_kernel")
    first_nonfinite_row = K.first_nonfinite_row

    raw = el.raw
    run = (
        _adjacent_fields(raw.dtype, _VERTEX_XYZ)
        if raw is not None and len(raw) and raw.flags.c_contiguous
        else None
    )
    if raw is not None and run is not None and run[0].kind == "f":
        ftype, first = run
        big = ftype.byteorder == ">" or (ftype.byteorder == "=" and sys.byteorder == "big")
        flat = raw.view(np.uint8).reshape(-1)
        return int(
            first_nonfinite_row(flat, raw.strides[0], first, len(_VERTEX_XYZ), ftype.itemsize, big)
        )
    ok = np.isfinite(pts).all(axis=1)
    return -1 if ok.all() else int(np.argmin(ok))


def _gather_plan(rowtype: np.dtype, names: tuple[str, ...], dtype) -> tuple:
    """How to gather ``names`` out of packed rows of ``rowtype``.

    ``(kind, names, offsets, size, big, buffer dtype, field dtype, result dtype)``; kind is
    ``float`` (decoded straight to float64), ``byte`` (one-byte
    fields, e.g. colours) or ``int`` (integers assembled in an unsigned buffer, then viewed
    and cast). Fields of differing types go through ``mixed`` (numpy, field by field).
    """
    fields = rowtype.fields
    assert fields is not None  # a structured dtype
    types = {fields[c][0] for c in names}
    offsets = np.array([fields[c][1] for c in names], dtype=np.int64)
    if len(types) != 1:
        rtype = np.dtype(dtype) if dtype is not None else np.result_type(*types)
        return ("mixed", names, offsets, 0, False, rtype, None, rtype)
    ftype = types.pop()
    big = ftype.byteorder == ">"
    native = ftype.newbyteorder("=")
    rtype = np.dtype(dtype) if dtype is not None else native
    if ftype.kind == "f" and rtype == np.float64:
        return ("float", names, offsets, ftype.itemsize, big, np.dtype(np.float64), native, rtype)
    if ftype.itemsize == 1 and rtype == native:
        return ("byte", names, offsets, 1, False, native, native, rtype)
    return (
        "int",
        names,
        offsets,
        ftype.itemsize,
        big,
        np.dtype(f"u{ftype.itemsize}"),
        native,
        rtype,
    )


def _gather_apply(plan: tuple, flat: np.ndarray, stride: int, out: np.ndarray) -> None:
    """Fill ``out`` (rows, k) from the packed rows in ``flat`` (uint8)."""
    K = kernels("recon_cli.io._ply_kernel")
    gather_bytes, gather_fields, gather_floats = K.gather_bytes, K.gather_fields, K.gather_floats

    kind, names, offsets, size, big = plan[:5]
    if kind == "float":
        gather_floats(flat, stride, offsets, size, big, out)
    elif kind == "byte":
        gather_bytes(flat, stride, offsets, out)
    elif kind == "int":
        gather_fields(flat, stride, offsets, size, big, out)
    else:
        raise ValueError(f"no kernel gathers {kind!r} columns")  # callers handle 'mixed' with numpy


def _indices(values: np.ndarray, where: str) -> np.ndarray:
    """Face vertex indices as int64; indices stored as floats must be whole numbers in range."""
    if values.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            whole = np.isfinite(values) & (values == np.round(values)) & (np.abs(values) < 2.0**62)
        if not whole.all():
            bad = values.reshape(-1)[int(np.argmin(whole.reshape(-1)))]
            raise InputError(f"face index {float(bad)!r} is not a whole number", where)
    return values.astype(np.int64)


def _triangulate(lists: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Fan-triangulate polygons; returns (faces (m, 3) int64, source polygon of each face).

    The source is None when every polygon is a triangle (face ``i`` is polygon ``i``).
    """
    if lists.dtype != object:
        k = lists.shape[1]
        n = lists.shape[0]
        if k < 3:
            raise InputError(f"faces with {k} vertices (fewer than 3)", where)
        poly = _indices(lists, where)
        if k == 3:
            return poly, None  # no index per face: 8 bytes a face at the reader's peak
        fan = [np.column_stack([poly[:, 0], poly[:, j], poly[:, j + 1]]) for j in range(1, k - 1)]
        faces = np.stack(fan, axis=1).reshape(-1, 3)
        return faces, np.repeat(np.arange(n), k - 2)
    lengths = np.fromiter((len(r) for r in lists), dtype=np.int64, count=len(lists))
    if np.any(lengths < 3):
        bad = int(np.flatnonzero(lengths < 3)[0])
        raise InputError(f"face {bad} has {int(lengths[bad])} vertices (fewer than 3)", where)
    flat = _indices(np.concatenate([np.asarray(r) for r in lists]), where)
    start = np.cumsum(lengths) - lengths
    ntri = lengths - 2
    src = np.repeat(np.arange(len(lists)), ntri)
    j = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    base = start[src]
    faces = np.column_stack([flat[base], flat[base + 1 + j], flat[base + 2 + j]])
    return faces, src


def geometry_to_ply(obj: PointCloud | TriangleMesh, ascii: bool = False) -> PlyData:
    """Convert a cloud or mesh to a :class:`PlyData` ready to serialise."""
    fmt = "ascii" if ascii else "binary_little_endian"
    pts = obj.points
    n = len(pts)
    # the data model's rule: the source's type, double when float32 would round computed coordinates
    fcode = "f8" if storage_dtype(obj) == np.float64 else "f4"
    vprops = [PlyProperty(c, fcode) for c in _VERTEX_XYZ]
    vdata = {c: pts[:, i] for i, c in enumerate(_VERTEX_XYZ)}
    if obj.normals is not None:
        vprops += [PlyProperty(c, fcode) for c in _VERTEX_NORMAL]
        vdata.update({c: obj.normals[:, i] for i, c in enumerate(_VERTEX_NORMAL)})
    if obj.colors is not None:
        ccode = f"{obj.colors.dtype.kind}{obj.colors.dtype.itemsize}"
        if ccode not in ("u1", "u2", "f4", "f8", "i1", "i2", "i4", "u4"):
            ccode = "u1"
        for i in range(obj.colors.shape[1]):
            vprops.append(PlyProperty(_VERTEX_COLOR[i], ccode))
            vdata[_VERTEX_COLOR[i]] = obj.colors[:, i]
    for name, values in obj.attributes.items():
        vprops.append(PlyProperty(name, _code(values.dtype)))
        vdata[name] = values
    elements = [PlyElement("vertex", n, vprops, vdata)]
    if isinstance(obj, TriangleMesh):
        fprops = [PlyProperty("vertex_indices", "i4", "u1")]
        fdata = {"vertex_indices": obj.faces}
        for name, values in obj.face_attributes.items():
            fprops.append(PlyProperty(name, _code(values.dtype)))
            fdata[name] = values
        elements.append(PlyElement("face", len(obj.faces), fprops, fdata))
    elements += list(obj.extra_elements)
    # a cloud's sensors as obj_info lines: read back into sensors (PointCloud)
    info = list(obj.obj_info) + [s.to_line() for s in getattr(obj, "sensors", ())]
    return PlyData(format=fmt, comments=list(obj.history), obj_info=info, elements=elements)


def _code(dtype: np.dtype) -> str:
    name = ply_name(dtype)
    return PLY_TYPES[name]


def ply_bytes(obj: PointCloud | TriangleMesh, ascii: bool = False) -> bytes:
    """The PLY encoding of ``obj``."""
    return serialize_ply(geometry_to_ply(obj, ascii=ascii))


def write_ply(obj: PointCloud | TriangleMesh, path: str | os.PathLike, ascii: bool = False) -> None:
    """Write ``obj`` to ``path`` (``-``: standard output) atomically.

    The file is written to a temporary name in the target folder and renamed, so a failed
    run never leaves a partial file.
    """
    from recon_cli.io.atomic import write_pieces

    taken = [*_VERTEX_XYZ, *(_VERTEX_NORMAL if obj.normals is not None else ())]
    taken += _VERTEX_COLOR[: obj.colors.shape[1]] if obj.colors is not None else ()
    check_header_words(obj.attributes, "PLY", where_of(path), taken)
    check_header_words(
        getattr(obj, "face_attributes", ()), "PLY", where_of(path), ["vertex_indices"]
    )
    ply = geometry_to_ply(obj, ascii=ascii)
    write_pieces(path, lambda put: emit_ply(ply, put))


def compile_ply_kernels() -> None:
    """Call each PLY kernel once for every buffer type a file's properties can give it.

    For ``recon warmup``: which types reach the gatherers depends on the files read, not on
    a command, so they are compiled (or loaded from the cache) here for all of them.
    """
    from recon_cli.io._ply_kernel import (
        first_nonfinite_row,
        gather_bytes,
        gather_fields,
        gather_floats,
    )

    offsets = np.array([0, 4, 8], dtype=np.int64)
    for flat in (
        np.zeros(24, np.uint8),
        np.frombuffer(bytes(24), dtype=np.uint8),
    ):  # writable and read-only
        for big in (False, True):
            for size, buf in ((1, np.uint8), (2, np.uint16), (4, np.uint32), (8, np.uint64)):
                k = 2 if size == 8 else 3
                gather_fields(flat, 12, offsets[:k], size, big, np.empty((2, k), buf))
            for size in (4, 8):
                gather_floats(flat, 12, offsets[:1], size, big, np.empty((2, 1), np.float64))
                first_nonfinite_row(flat, 12, 0, 1, size, big)
        for out in (np.empty((2, 3), np.uint8), np.empty((2, 3), np.int8)):
            gather_bytes(flat, 12, offsets, out)
