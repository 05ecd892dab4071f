"""Wavefront OBJ: our own reader and writer.

Read: ``v x y z [w]`` or ``v x y z r g b`` (colours in 0..1), ``vn``, ``f`` with the
``v``, ``v/vt``, ``v/vt/vn`` and ``v//vn`` corner forms and negative (relative) indices;
polygons are fan-triangulated. Normals are kept per vertex when every corner of a vertex
names the same normal (or the file has one ``vn`` per ``v`` in order); other per-corner
normals are dropped with a warning. Texture coordinates, groups and materials are not
kept. Leading ``#`` lines are the history (``# recon: float32``, which our writer puts
first for float32 data, makes the coordinates float32 again). A file without faces is a point cloud.
Coordinates are read as float64 (text has no type).

The numbers are parsed by a numba kernel (:mod:`recon_cli.io._obj_kernel`) in one pass
over the bytes (``v x y z`` and triangle lines through a short path, any other line through
the general one), into arrays sized from a sample of the file (they grow when it falls
short); every number reads as Python's ``float`` reads it (see
:mod:`recon_cli.io._text_kernel`; the rare undecided ones are converted by ``float``). The
kernel also reports the largest indices and the first non-finite vertex, which this module
checks (no further pass over the arrays).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, drop_invalid
from recon_cli.io import text

_MESSAGES = {
    1: "is not a number",
    2: "a 'v' line must hold 3, 4 (x y z w) or 6 (x y z r g b) numbers",
    3: "a 'vn' line must hold 3 numbers",
    4: "a face has fewer than 3 corners",
    5: "a face corner is not a vertex index (v, v/vt, v/vt/vn or v//vn; indices start at 1)",
    6: "this 'v' line and an earlier one differ in carrying colours (r g b)",
    7: "a negative (relative) index reaches before the first vertex or normal",
    8: "normal index out of range: the file has no 'vn' line",
}


def decode_obj(data, where: str) -> tuple[PointCloud | TriangleMesh, dict]:
    """Decode the bytes of an OBJ file: ``(geometry, details for recon info)``."""
    from recon_cli.io import _obj_kernel as K

    buf = text.as_uint8(data)
    # arrays from numpy (which asks for huge pages: fewer page faults than the kernel's own),
    # sized from a sample of the file; pages never written cost no memory
    lv, lvn, lf, lc = _estimate(buf, K)
    verts = np.empty((lv, 3), np.float64)
    colours = np.empty((lv, 3), np.float64)  # untouched, so no memory, without colours
    vnorms = np.empty((lvn, 3), np.float64)
    corner_v = np.empty(lc, np.int64)
    corner_n = np.empty(lc if lvn else 0, np.int64)
    face_len = np.empty(lf if lc > 3 * lf else 0, np.int64)  # none while all faces are triangles
    slow = np.empty((64, 4), np.int64)
    out = K.obj_walk(buf, verts, colours, vnorms, corner_v, corner_n, face_len, slow)
    err, at, counts, verts, colours, vnorms, corner_v, corner_n, face_len, slow = out
    if err:
        _raise(buf, err, at, where)
    nv, nvn, nf, nc = (int(counts[k]) for k in (K.NV, K.NVN, K.NF, K.NCORNER))
    verts, vnorms = verts[:nv], vnorms[:nvn]
    colours = colours[:nv] if counts[K.COLOURS] else np.empty((0, 3), np.float64)
    corner_v = corner_v[:nc]
    corner_n = corner_n[:nc] if len(corner_n) else corner_n  # empty: the file has no vn line
    nonfinite = int(counts[K.NONFINITE])
    if counts[K.NSLOW]:
        slow = slow[: counts[K.NSLOW]]
        vals = text.slow_values(buf, slow[:, 2:4])
        for a, target in enumerate((verts, colours, vnorms)):
            pick = slow[:, 0] == a
            if pick.any() and len(target):
                target.reshape(-1)[slow[pick, 1]] = vals[pick]
        bad = (slow[:, 0] == 0) & ~np.isfinite(vals)  # (a value beyond the largest double)
        if bad.any():
            row = int(slow[bad, 1].min()) // 3
            nonfinite = row if nonfinite < 0 else min(nonfinite, row)
    invalid = nonfinite >= 0  # such vertices are dropped (and counted) once the object is made
    # the kernel's largest indices: negative ones it has resolved or refused already
    if int(counts[K.MAX_V]) >= nv:
        bad = int(np.flatnonzero(corner_v >= nv)[0])
        raise InputError(f"face corner {bad}: vertex index out of range for {nv} vertices", where)
    if len(corner_n) and int(counts[K.MAX_VN]) >= nvn:
        bad = int(np.flatnonzero(corner_n >= nvn)[0])
        raise InputError(f"face corner {bad}: normal index out of range for {nvn} normals", where)
    history = _leading_comments(buf)
    details: dict = {"format": "obj", "v": nv, "vn": nvn, "f": nf}
    notes: list[str] = []  # warned once the object is made: a refused file says one line
    normals = _vertex_normals(verts, vnorms, corner_v, corner_n, nf, where, details, notes)
    cols = text.colours_from_unit(colours) if len(colours) else None
    common: dict[str, Any] = dict(normals=normals, colors=cols, point_dtype=np.float64)
    if nf == 0:
        cloud = text.apply_float32_mark(PointCloud(points=verts, **common), history)
        return _warned((drop_invalid(cloud, where) if invalid else cloud), notes), details
    if nc == 3 * nf:  # every face has at least 3 corners: all are triangles
        faces = corner_v.reshape(-1, 3)  # triangles already: no fan to build
    else:
        from recon_cli.io._obj_kernel import fan

        faces, _ = fan(corner_v, face_len[:nf])
    mesh = text.apply_float32_mark(TriangleMesh(vertices=verts, faces=faces, **common), history)
    return _warned((drop_invalid(mesh, where) if invalid else mesh), notes), details


def _warned(obj, notes: list[str]):
    # none when every vertex was dropped: load.check_read refuses the file in one line then
    if len(obj.points) or not getattr(obj, "invalid_dropped", 0):
        for note in notes:
            text.warn(note)
    return obj


def _estimate(buf: np.ndarray, K) -> tuple[int, int, int, int]:
    """Room for the ``v``, ``vn``, ``f`` lines and face corners.

    Counted in a small file, estimated from 32 windows of 32 KiB spread over a large one (10 %
    spare; the kernel's arrays grow when a count falls short).
    """
    n = len(buf)
    width = 1 << 15
    if n <= 64 * width:
        counts = K.line_kinds(buf, np.zeros(1, np.int64), n)
        scale, spare = 1.0, 16
    else:
        counts = K.line_kinds(buf, np.linspace(0, n - width, 32).astype(np.int64), width)
        scale, spare = 1.1 * n / (32 * width), 1024
    # no vn line seen: none expected (no normal arrays: the kernel makes them at the first)
    v, vn, f, corners = (int(c * scale) + spare if c or k != 1 else 0 for k, c in enumerate(counts))
    return v, vn, f, corners


def _raise(buf: np.ndarray, err: int, at: int, where: str):
    if err == 1:
        raise text.bad_number(buf, at, where)
    raise InputError(f"line {text.line_at(buf, at)}: {_MESSAGES[err]}", where)


def _vertex_normals(
    verts, vnorms, corner_v, corner_n, nf, where, details, notes: list[str]
) -> np.ndarray | None:
    nv, nvn = len(verts), len(vnorms)
    if nvn == 0:
        return None
    if nf == 0 or (nvn == nv and np.array_equal(corner_n, corner_v)):
        if nvn == nv:
            return vnorms
        notes.append(
            f"{where}: {nvn} normals for {nv} vertices and no faces naming them: normals not kept"
        )
        details["normals_dropped"] = True
        return None
    if corner_n.min() < 0:
        notes.append(f"{where}: some face corners have no normal: normals not kept")
        details["normals_dropped"] = True
        return None
    # one normal per vertex when every corner of the vertex gives the same vector
    owner = np.full(nv, -1, np.int64)
    owner[corner_v] = corner_n
    same = np.all(vnorms[owner[corner_v]] == vnorms[corner_n])
    if same and np.all(owner >= 0):
        return vnorms[owner]
    notes.append(
        f"{where}: normals differ between the corners of a vertex (split normals): normals not kept"
    )
    details["normals_dropped"] = True
    return None


def _leading_comments(buf: np.ndarray) -> list[str]:
    """The ``#`` lines before the first other line (our writer puts the history there)."""
    head = bytes(buf[: min(len(buf), 1 << 16)])
    out = []
    for line in head.split(b"\n"):
        s = line.strip()
        if not s.startswith(b"#"):
            if s:
                break
            continue
        out.append(s[1:].strip().decode("utf-8", "replace"))
    return [h for h in out if h]


def obj_bytes(obj: PointCloud | TriangleMesh) -> bytes:
    """The OBJ encoding of ``obj``.

    History as ``#`` lines, ``v`` (with ``r g b`` in 0..1 when the object has colours), ``vn`` in
    vertex order and ``f a//a b//b c//c`` (1-based).
    """
    pts = obj.points
    fmt = text.float_format(obj.point_dtype)
    parts = [text.mark_lines(obj).encode("utf-8")]
    if obj.colors is not None:
        table = np.column_stack([pts.astype(np.float64), text.colours_to_unit(obj.colors[:, :3])])
        parts.append(text.format_rows(f"v {fmt} {fmt} {fmt} %.9g %.9g %.9g\n", table))
    else:
        parts.append(text.format_rows(f"v {fmt} {fmt} {fmt}\n", pts))
    if obj.normals is not None:
        parts.append(text.format_rows(f"vn {fmt} {fmt} {fmt}\n", obj.normals))
    if isinstance(obj, TriangleMesh) and len(obj.faces):
        f = obj.faces + 1
        if obj.normals is not None:
            parts.append(text.format_rows("f %d//%d %d//%d %d//%d\n", np.repeat(f, 2, axis=1)))
        else:
            parts.append(text.format_rows("f %d %d %d\n", f))
    return b"".join(parts)


def read_obj(path: str | os.PathLike, data=None) -> PointCloud | TriangleMesh:
    """Read an OBJ file (``-``: standard input) as a mesh, or a cloud when it has no faces.

    Raises
    ------
    InputError
        A malformed line (named by number), a face index out of range, a face using a
        vertex with a NaN or infinite coordinate (such vertices are otherwise dropped).
    """
    from recon_cli.io.ply import read_bytes

    return decode_obj(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_obj(obj: PointCloud | TriangleMesh, path: str | os.PathLike) -> None:
    """Write ``obj`` as OBJ atomically (``-``: standard output)."""
    from recon_cli.io.atomic import write_bytes

    write_bytes(path, obj_bytes(obj))
