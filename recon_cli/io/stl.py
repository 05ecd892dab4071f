"""STL (binary and ASCII): our own reader and writer.

STL stores each triangle's three corners on their own. On reading, corners with exactly
equal coordinates (bit for bit, after -0 = +0) are welded into one vertex, so the mesh's
topology is meaningful; the weld tolerance is 0 and is reported by ``recon info`` with the
corner and vertex counts. Nothing closer than equal is merged: a file whose triangles do
not share exact corners stays unwelded there (``recon repair`` can weld with a tolerance).

Binary files hold float32: a float64 mesh written to STL is rounded, and the writer says by
how much (a warning). The facet normals are recomputed on writing and not kept on reading
(they follow from the winding); a non-zero attribute word is kept as the face attribute
``attribute``. A binary file's size must be exactly ``84 + 50 * count``.
"""

from __future__ import annotations

import os

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh, bbox_diagonal
from recon_cli.io import text

_ROW = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attribute", "<u2")])
_ASCII_ERRORS = {
    1: (
        "unexpected word (expected solid / facet normal / outer loop / vertex / endloop / endfacet "
        "/ endsolid)"
    ),
    2: "is not a number",
    3: "a facet must have exactly 3 vertices",
    4: "the file ends inside a facet (truncated?)",
}


def is_binary_stl(buf: np.ndarray) -> bool:
    """True when ``buf`` has the size a binary STL with the count at byte 80 would have."""
    if len(buf) < 84:
        return False
    count = int(buf[80:84].view("<u4")[0])
    return len(buf) == 84 + 50 * count


def decode_stl(data, where: str) -> tuple[TriangleMesh, dict]:
    """Decode the bytes of a binary or ASCII STL file: ``(mesh, details for recon info)``."""
    buf = text.as_uint8(data)
    if len(buf) == 0:
        raise InputError("empty file", where)
    stripped = bytes(buf[:512]).lstrip()
    if is_binary_stl(buf):
        return _decode_binary(buf, where)
    if stripped.startswith(b"solid"):
        return _decode_ascii(buf, where)
    if len(buf) < 84:
        raise InputError(
            f"truncated: a binary STL needs at least 84 bytes, the file has {len(buf)}", where
        )
    count = int(buf[80:84].view("<u4")[0])
    raise InputError(
        f"binary STL header declares {count} triangles ({84 + 50 * count} bytes) but the file "
        f"has {len(buf)} bytes",
        where,
    )


def _decode_binary(buf: np.ndarray, where: str) -> tuple[TriangleMesh, dict]:
    count = int(buf[80:84].view("<u4")[0])
    rows = np.frombuffer(buf, dtype=_ROW, count=count, offset=84)
    corners = rows["v"].reshape(-1, 3)
    header = bytes(buf[:80]).rstrip(b"\0 ").decode("latin-1")
    mesh, details = _weld(corners, where, np.float32)
    attr = rows["attribute"]
    if attr.size and attr.any():
        mesh.face_attributes["attribute"] = attr.copy()
    details.update(encoding="binary", header=header)
    if header:
        mesh.history = [header]
    return mesh, details


def _decode_ascii(buf: np.ndarray, where: str) -> tuple[TriangleMesh, dict]:
    from recon_cli.io._stl_kernel import ascii_walk

    # a counting pass, then a filling one into arrays of the counted size
    nf, ns, err, at = ascii_walk(
        buf, np.empty((0, 3), np.float64), np.empty((0, 3), np.int64), False
    )
    if err:
        _ascii_error(buf, err, at, where)
    corners = np.empty((3 * nf, 3), np.float64)
    slow = np.empty((ns, 3), np.int64)
    ascii_walk(buf, corners, slow, True)
    corners.reshape(-1)[slow[:, 0]] = text.slow_values(buf, slow[:, 1:])
    name = bytes(buf[:256]).lstrip()[5:].split(b"\n", 1)[0].strip().decode("latin-1")
    mesh, details = _weld(corners, where, np.float64)
    details.update(encoding="ascii", header=name)
    if name:
        mesh.history = [name]
    return mesh, details


def _ascii_error(buf, err, at, where):
    if err == 2:
        raise text.bad_number(buf, at, where)
    if err == 4:
        raise InputError(_ASCII_ERRORS[4], where)
    raise InputError(f"line {text.line_at(buf, at)}: {_ASCII_ERRORS[err]}", where)


def _weld(corners: np.ndarray, where: str, dtype) -> tuple[TriangleMesh, dict]:
    from recon_cli.io._stl_kernel import weld_exact

    ok = np.isfinite(corners).all(axis=1)
    if not ok.all():
        bad = int(np.argmin(ok))
        raise InputError(f"triangle {bad // 3} has a NaN or infinite coordinate", where)
    c = np.ascontiguousarray(corners, dtype=dtype) + dtype(0.0)  # -0 == +0
    bits = c.view(np.uint32 if dtype == np.float32 else np.uint64)
    inverse, first = weld_exact(bits)
    verts = c[first]
    faces = inverse.reshape(-1, 3)
    details = {
        "format": "stl",
        "triangles": len(faces),
        "corners": len(c),
        "vertices": len(verts),
        "weld_tolerance": 0.0,
    }
    return TriangleMesh(vertices=verts, faces=faces, point_dtype=dtype), details


def stl_bytes(obj: TriangleMesh, ascii: bool = False) -> bytes:
    """The STL encoding of ``obj`` (binary float32 unless ``ascii``; ASCII keeps float64 digits).

    The facet normals are the triangles' unit normals (zero for degenerate triangles).
    """
    v = obj.vertices
    tri = v[obj.faces]  # (m, 3, 3)
    t64 = tri.astype(np.float64)
    n = np.cross(t64[:, 1] - t64[:, 0], t64[:, 2] - t64[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    head = text.one_line("; ".join(obj.history))[:79]
    if ascii:
        fmt = text.float_format(obj.point_dtype)
        body = text.format_rows(
            "facet normal %.9g %.9g %.9g\n outer loop\n"
            + f"  vertex {fmt} {fmt} {fmt}\n" * 3
            + " endloop\nendfacet\n",
            np.column_stack([n, t64.reshape(len(t64), 9)]),
        )
        return f"solid {head}\n".encode() + body + f"endsolid {head}\n".encode()
    rows = np.zeros(len(tri), dtype=_ROW)
    rows["normal"] = n
    rows["v"] = tri
    if "attribute" in obj.face_attributes:
        rows["attribute"] = obj.face_attributes["attribute"]
    header = head.encode().ljust(80, b" ")
    if header[:5].lower() == b"solid":  # a binary file must not look like an ASCII one
        header = b"binary " + header[:73]
    return header + np.uint32(len(tri)).tobytes() + rows.tobytes()


def float32_rounding(obj) -> float:
    """Largest change of a coordinate of ``obj`` when stored as float32 (0 for float32 data)."""
    v = obj.vertices
    if v.dtype == np.float32 or len(v) == 0:
        return 0.0
    return float(np.max(np.abs(v.astype(np.float32).astype(np.float64) - v)))


def read_stl(path: str | os.PathLike, data=None) -> TriangleMesh:
    """Read a binary or ASCII STL file (``-``: standard input), welding identical corners."""
    from recon_cli.io.ply import read_bytes

    return decode_stl(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_stl(obj: TriangleMesh, path: str | os.PathLike, ascii: bool = False) -> None:
    """Write ``obj`` as STL atomically (``-``: standard output); warns when float32 rounds it."""
    from recon_cli.io.atomic import write_bytes

    if not ascii:
        err = float32_rounding(obj)
        if err > 0:
            text.warn(
                f"{text.where_of(path)}: binary STL stores float32: coordinates rounded by up "
                f"to {err:.3g} "
                f"({err / max(bbox_diagonal(obj.vertices), 1e-300):.2g} of the bounding-box "
                "diagonal; --ascii keeps them)"
            )
    write_bytes(path, stl_bytes(obj, ascii=ascii))
