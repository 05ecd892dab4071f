"""Object File Format (OFF, with the COFF / NOFF / CNOFF variants): our own reader and writer.

Layout: the keyword, the counts ``nv nf ne`` (on the keyword's line or the next), ``nv``
vertex rows ``x y z [nx ny nz] [r g b [a]]`` and ``nf`` face rows ``k i1 .. ik [r g b [a]]``
(0-based). ``#`` starts a comment line. Polygons are fan-triangulated; face colours are kept
as face attributes ``red``/``green``/``blue``[/``alpha``]. Coordinates are read as float64.
Rows are parsed by the shared kernel (:func:`recon_cli.io.text.read_rows`) before any array
is sized from the declared counts, and the counts are then checked against the rows.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, drop_invalid
from recon_cli.io import text

_KEYWORDS = {
    b"OFF": (False, False),
    b"COFF": (True, False),
    b"NOFF": (False, True),
    b"CNOFF": (True, True),
    b"NCOFF": (True, True),
}


def decode_off(data, where: str) -> tuple[PointCloud | TriangleMesh, dict]:
    """Decode the bytes of an OFF file: ``(geometry, details for recon info)``."""
    buf = text.as_uint8(data)
    head = bytes(buf[:64])
    stripped = head.lstrip()
    word = stripped.split(None, 1)[0] if stripped.strip() else b""
    if word not in _KEYWORDS:
        raise InputError("not an OFF file (first word is not OFF, COFF, NOFF or CNOFF)", where)
    has_col, has_nrm = _KEYWORDS[word]
    start = len(head) - len(stripped) + len(word)
    values, row_start, row_line = text.read_rows(buf, start, len(buf), where)
    lens = np.diff(row_start)
    if len(lens) == 0 or lens[0] < 2:
        raise InputError("line 1-2: missing the counts 'vertices faces edges'", where)
    counts = values[row_start[0] : row_start[0] + min(3, int(lens[0]))]
    if (
        not np.isfinite(counts).all()
        or np.any(counts < 0)
        or np.any(counts != np.round(counts))
        or lens[0] > 3
    ):
        raise InputError(
            f"line {int(row_line[0])}: the counts must be 2 or 3 non-negative integers", where
        )
    nv, nf = int(counts[0]), int(counts[1])
    rows = len(lens) - 1
    if nv + nf > rows:
        raise InputError(
            f"truncated: the header declares {nv} vertices and {nf} faces but the file has "
            f"{rows} rows",
            where,
        )
    if nv + nf < rows:
        raise InputError(
            f"line {int(row_line[1 + nv + nf])}: more rows than the {nv} vertices and {nf} "
            "faces declared",
            where,
        )
    base = 3 + (3 if has_nrm else 0)
    vl = lens[1 : 1 + nv]
    allowed = (base + 3, base + 4) if has_col else (base,)
    wrong = ~np.isin(vl, allowed) | (vl != (vl[0] if nv else 0))
    if wrong.any():
        bad = int(np.flatnonzero(wrong)[0])
        raise InputError(
            f"line {int(row_line[1 + bad])}: a {word.decode()} vertex row holds "
            f"{' or '.join(map(str, allowed))} numbers, not {int(vl[bad])}",
            where,
        )
    width = int(vl[0]) if nv else base
    vtab = values[row_start[1] : row_start[1] + nv * width].reshape(nv, width)
    pts = np.ascontiguousarray(vtab[:, :3])
    normals = np.ascontiguousarray(vtab[:, 3:6]) if has_nrm else None
    colors = _colours(vtab[:, base:]) if has_col else None
    details = {"format": "off", "variant": word.decode(), "declared": [nv, nf]}
    common: dict[str, Any] = dict(normals=normals, colors=colors, point_dtype=np.float64)
    if nf == 0:
        cloud = text.apply_float32_mark(PointCloud(points=pts, **common), _comments(buf))
        return drop_invalid(cloud, where), details
    faces, face_attrs = _faces(
        values, row_start[1 + nv : 2 + nv + nf], row_line[1 + nv :], nv, where
    )
    mesh = TriangleMesh(vertices=pts, faces=faces, face_attributes=face_attrs, **common)
    return drop_invalid(text.apply_float32_mark(mesh, _comments(buf)), where), details


def _colours(c: np.ndarray) -> np.ndarray:
    if c.size and np.all(c == np.round(c)) and c.max() > 1 and c.min() >= 0 and c.max() <= 255:
        return c.astype(np.uint8)
    return text.colours_from_unit(np.ascontiguousarray(c))


def _faces(values, starts, lines, nv, where):
    from recon_cli.io._obj_kernel import fan

    first = starts[:-1]
    lens = np.diff(starts)
    k = values[first]
    if np.any(k != np.round(k)) or np.any(k < 3):
        bad = int(np.flatnonzero((k != np.round(k)) | (k < 3))[0])
        raise InputError(
            f"line {int(lines[bad])}: a face must start with its number of corners (3 or more)",
            where,
        )
    if np.any(k > lens - 1):  # before the cast: a count past int64 would not survive it
        bad = int(np.flatnonzero(k > lens - 1)[0])
        raise InputError(
            f"line {int(lines[bad])}: a face of {k[bad]:.0f} corners has {int(lens[bad]) - 1} "
            "values after its count",
            where,
        )
    k = k.astype(np.int64)
    extra = lens - 1 - k
    if np.any((extra != 0) & (extra != 3) & (extra != 4)):
        bad = int(np.flatnonzero((extra != 0) & (extra != 3) & (extra != 4))[0])
        raise InputError(
            f"line {int(lines[bad])}: a face row holds k indices and optionally 3 or 4 colour "
            "values",
            where,
        )
    idx_pos = np.repeat(first + 1, k) + (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k))
    corners = values[idx_pos]
    if np.any(corners != np.round(corners)) or (
        corners.size and (corners.min() < 0 or corners.max() >= nv)
    ):
        bad_corner = int(
            np.flatnonzero((corners != np.round(corners)) | (corners < 0) | (corners >= nv))[0]
        )
        bad = int(np.searchsorted(np.cumsum(k), bad_corner, side="right"))
        raise InputError(
            f"line {int(lines[bad])}: vertex index {corners[bad_corner]:g} out of range for "
            f"{nv} vertices",
            where,
        )
    faces, src = fan(corners.astype(np.int64), k)
    attrs: dict[str, np.ndarray] = {}
    if np.all(extra >= 3):
        ncol = int(extra.min())
        colour = np.column_stack([values[first + 1 + k + c] for c in range(ncol)])
        colour = _colours(colour)
        for c, name in enumerate(("red", "green", "blue", "alpha")[:ncol]):
            attrs[name] = colour[src, c]
    return faces, attrs


def _comments(buf: np.ndarray) -> list[str]:
    head = bytes(buf[: min(len(buf), 1 << 16)])
    out = []
    for line in head.split(b"\n")[1:]:
        s = line.strip()
        if not s:
            continue
        if not s.startswith(b"#"):
            break
        out.append(s[1:].strip().decode("utf-8", "replace"))
    return [h for h in out if h]


def off_bytes(obj: PointCloud | TriangleMesh) -> bytes:
    """The OFF encoding of ``obj`` (COFF / NOFF / CNOFF when it has colours / normals).

    The history as ``#`` lines after the keyword.
    """
    pts = obj.points
    fmt = text.float_format(obj.point_dtype)
    word = (
        ("C" if obj.colors is not None else "") + ("N" if obj.normals is not None else "") + "OFF"
    )
    cols = [pts.astype(np.float64)]
    tmpl = [fmt] * 3
    if obj.normals is not None:
        cols.append(obj.normals.astype(np.float64))
        tmpl += [fmt] * 3
    if obj.colors is not None:
        c = obj.colors
        if c.dtype == np.uint8:
            cols.append(c.astype(np.float64))
            tmpl += ["%d"] * c.shape[1]
        else:
            cols.append(text.colours_to_unit(c))
            tmpl += ["%.9g"] * c.shape[1]
    faces = obj.faces if isinstance(obj, TriangleMesh) else np.zeros((0, 3), np.int64)
    head = word + "\n" + text.mark_lines(obj) + f"{len(pts)} {len(faces)} 0\n"
    body = text.format_rows(" ".join(tmpl) + "\n", np.column_stack(cols))
    fbody = text.format_rows("3 %d %d %d\n", faces)
    return head.encode("utf-8") + body + fbody


def read_off(path: str | os.PathLike, data=None) -> PointCloud | TriangleMesh:
    """Read an OFF file (``-``: standard input): a mesh, or a cloud when it has no faces."""
    from recon_cli.io.ply import read_bytes

    return decode_off(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_off(obj: PointCloud | TriangleMesh, path: str | os.PathLike) -> None:
    """Write ``obj`` as OFF atomically (``-``: standard output)."""
    from recon_cli.io.atomic import write_bytes

    write_bytes(path, off_bytes(obj))
