"""Text point clouds (``.xyz``, ``.txt``, ``.csv``, ``.pts``): our own reader and writer.

Reading:

* the delimiter is detected on the first data line: a comma, else a semicolon, else white
  space;
* a header is a first line holding a word (``x,y,z,red,...``), or the last ``#`` / ``//``
  comment line before the data when it has one word per column; its names choose the
  columns (``x y z``, ``nx ny nz`` / ``normal_x``..., ``r g b`` / ``red green blue``
  [``alpha``]; any other column is kept as a per-point attribute of that name);
* without a header the columns are read by their number: 3 ``x y z``; 4 ``x y z
  intensity``; 6 ``x y z`` and normals (every row of unit length), or colours (integers
  0..255, or all in 0..1); 7 ``x y z intensity r g b`` (PTS); 9 ``x y z nx ny nz r g b``;
  otherwise ``x y z`` and attributes ``column_3``, ``column_4``...;
* a PTS file's first line, one integer, is the point count and is checked.

Every row must have the same number of columns (the line of the first that does not is named).
Coordinates are read as float64; rows with a NaN or infinite coordinate are dropped before the
columns are judged, and counted (``invalid_dropped``). Writing puts the history and a ``#`` header
line of column names (a plain header line for ``.csv``, comma-separated), then the rows.
"""

from __future__ import annotations

import os
import re

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud
from recon_cli.io import text

_ALIASES = {
    "x": "x",
    "y": "y",
    "z": "z",
    "nx": "nx",
    "ny": "ny",
    "nz": "nz",
    "normal_x": "nx",
    "normal_y": "ny",
    "normal_z": "nz",
    "normalx": "nx",
    "normaly": "ny",
    "normalz": "nz",
    "r": "red",
    "g": "green",
    "b": "blue",
    "a": "alpha",
    "red": "red",
    "green": "green",
    "blue": "blue",
    "alpha": "alpha",
}
_NUMBER = re.compile(
    rb"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.IGNORECASE
)


def _lines_head(buf: np.ndarray, limit: int = 64):
    """(line bytes, byte offset of the next line) for the first non-blank lines."""
    out: list[tuple[bytes, int, int]] = []
    pos = 0
    n = len(buf)
    while pos < n and len(out) < limit:
        chunk = bytes(buf[pos : pos + 65536])
        nl = chunk.find(b"\n")
        line = chunk if nl < 0 else chunk[:nl]
        nxt = pos + (len(chunk) if nl < 0 else nl + 1)
        if line.strip():
            out.append((line.strip(), pos, nxt))
        pos = nxt
    return out


def _split(line: bytes, delim: bytes | None) -> list[bytes]:
    if delim is None:
        return line.split()
    return [t.strip() for t in line.split(delim)]


def decode_xyz(data, where: str, ext: str = ".xyz") -> tuple[PointCloud, dict]:
    """Decode a text point cloud: ``(cloud, details for recon info)``."""
    buf = text.as_uint8(data)
    head = _lines_head(buf)
    comments = [(ln, s, e) for ln, s, e in head if ln.startswith((b"#", b"//"))]
    data_lines = [(ln, s, e) for ln, s, e in head if not ln.startswith((b"#", b"//"))]
    if not data_lines:
        raise InputError("no data rows", where)
    first, first_start, first_end = data_lines[0]
    delim = b"," if b"," in first else (b";" if b";" in first else None)
    # a second data line decides the delimiter when the first is a header or a count
    if len(data_lines) > 1 and delim is None:
        nxt = data_lines[1][0]
        delim = b"," if b"," in nxt else (b";" if b";" in nxt else None)
    names = None
    start = first_start
    count_line = None
    toks = _split(first, delim)
    if not all(_NUMBER.match(t) for t in toks):
        names = [t.decode("latin-1").strip().strip('"').strip("'") for t in toks]
        start = first_end
    elif len(toks) == 1 and len(data_lines) > 1 and len(_split(data_lines[1][0], delim)) >= 3:
        count_line = first
        start = first_end
    pre = [c for c in comments if c[1] < first_start]
    from_comment = False
    if names is None and pre:
        cand = _split(pre[-1][0].lstrip(b"#/").strip(), delim)
        if cand and not any(_NUMBER.match(t) for t in cand):
            names = [t.decode("latin-1").strip() for t in cand]
            from_comment = True
            pre = pre[:-1]
    history = [c[0].lstrip(b"#/").strip().decode("utf-8", "replace") for c in pre]
    if from_comment:
        start = first_start
    d = 0 if delim is None else delim[0]
    # the value array's first size, from the bytes per value of the first data lines
    sample = [ln for ln, s, _ in data_lines if s >= start][:32]
    per_value = (
        sum(len(ln) + 1 for ln in sample) / max(1, sum(len(_split(ln, delim)) for ln in sample))
        if sample
        else 8
    )
    table = text.read_table(
        buf,
        start,
        len(buf),
        where,
        delim=d,
        cap=int((len(buf) - start) / max(per_value, 2) * 1.03) + 64,
    )
    if len(table) == 0:
        raise InputError("no data rows", where)
    ncol = table.shape[1]
    if count_line is not None:
        declared = int(float(count_line))
        if declared != len(table):
            raise InputError(
                f"line 1 declares {declared} points but the file has {len(table)} rows", where
            )
    if names is not None and len(names) != ncol:
        if not from_comment:
            raise InputError(
                f"the header names {len(names)} columns but the rows have {ncol}", where
            )
        history.append(" ".join(names))  # a comment, not a header
        names = None
    if ncol < 3:
        raise InputError(f"rows have {ncol} columns; x y z needs 3", where)
    cloud, layout = _columns(table, names, where)
    text.apply_float32_mark(cloud, history)
    details = {
        "format": "xyz",
        "delimiter": {None: "white space", b",": "comma", b";": "semicolon"}[delim],
        "header": names is not None,
        "columns": layout,
    }
    return cloud, details


def _columns(
    table: np.ndarray, names: list[str] | None, where: str
) -> tuple[PointCloud, list[str]]:
    n, ncol = table.shape
    if names is not None:
        canon = [_ALIASES.get(nm.lower(), nm) for nm in names]
        if not all(c in canon for c in "xyz"):
            raise InputError(f"the header {' '.join(names)!r} has no x, y and z columns", where)
    else:
        canon = ["x", "y", "z"]  # a table without a header starts with them (_guess)
    idx = {c: i for i, c in enumerate(canon)}
    xyz = [idx["x"], idx["y"], idx["z"]]
    ok = np.isfinite(table[:, xyz]).all(axis=1)
    invalid = int(n - np.count_nonzero(ok))
    if invalid:  # dropped before the columns are judged (a NaN row is no colour, no integer)
        table = table[ok]
    if names is None:
        canon = _guess(table)
        idx = {c: i for i, c in enumerate(canon)}
    pts = _block(table, xyz)
    used = {"x", "y", "z"}
    normals = None
    if all(c in idx for c in ("nx", "ny", "nz")):
        normals = _block(table, [idx["nx"], idx["ny"], idx["nz"]])
        used |= {"nx", "ny", "nz"}
    colors = None
    if all(c in idx for c in ("red", "green", "blue")):
        cc = ["red", "green", "blue"] + (["alpha"] if "alpha" in idx else [])
        c = np.ascontiguousarray(table[:, [idx[k] for k in cc]])
        colors = _colours(c)
        used |= set(cc)
    attributes = {}
    for i, name in enumerate(canon):
        if name in used:
            continue
        col = table[:, i]
        attributes[name] = (
            col.astype(np.int64)
            if col.size and np.all(col == np.round(col)) and np.abs(col).max() < 2**53
            else col.copy()
        )
    cloud = PointCloud(
        points=pts,
        normals=normals,
        colors=colors,
        attributes=attributes,
        point_dtype=np.float64,
        invalid_dropped=invalid,
    )
    return cloud, canon


def _block(table: np.ndarray, cols: list[int]) -> np.ndarray:
    """Columns ``cols`` of ``table``.

    A view when they are adjacent and in order (the whole table when that is all it holds), else a
    copy.
    """
    if cols == list(range(cols[0], cols[0] + len(cols))):
        return table if table.shape[1] == len(cols) else table[:, cols[0] : cols[0] + len(cols)]
    return np.ascontiguousarray(table[:, cols])


def _colours(c: np.ndarray) -> np.ndarray:
    if c.size and np.all(c == np.round(c)) and c.min() >= 0 and c.max() <= 255 and c.max() > 1:
        return c.astype(np.uint8)
    if c.size and np.all(c == np.round(c)) and c.min() >= 0 and c.max() <= 65535 and c.max() > 255:
        return c.astype(np.uint16)
    return text.colours_from_unit(c)


def _guess(table: np.ndarray) -> list[str]:
    ncol = table.shape[1]
    rest = [f"column_{i}" for i in range(ncol)]
    if ncol == 3:
        return ["x", "y", "z"]
    if ncol == 4:
        return ["x", "y", "z", "intensity"]
    if ncol == 6 and len(table):
        b = table[:, 3:6]
        if np.all(np.abs(np.linalg.norm(b, axis=1) - 1) < 1e-3):
            return ["x", "y", "z", "nx", "ny", "nz"]
        if (np.all(b == np.round(b)) and b.min() >= 0 and b.max() <= 255) or (
            b.min() >= 0 and b.max() <= 1
        ):
            return ["x", "y", "z", "red", "green", "blue"]
        return ["x", "y", "z"] + rest[3:]
    if ncol == 7:
        return ["x", "y", "z", "intensity", "red", "green", "blue"]
    if ncol == 9:
        return ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    return ["x", "y", "z"] + rest[3:]


def xyz_bytes(obj, csv: bool = False) -> bytes:
    """The text encoding of a cloud (a mesh's vertices).

    Space-separated with a ``#`` header line, or comma-separated with a plain header line when
    ``csv``.
    """
    pts = obj.points
    fmt = text.float_format(obj.point_dtype)
    names = ["x", "y", "z"]
    cols = [pts.astype(np.float64)]
    tmpl = [fmt] * 3
    if obj.normals is not None:
        names += ["nx", "ny", "nz"]
        cols.append(obj.normals.astype(np.float64))
        tmpl += [text.float_format(obj.normals.dtype)] * 3
    if obj.colors is not None:
        c = obj.colors
        names += ["red", "green", "blue", "alpha"][: c.shape[1]]
        cols.append(c.astype(np.float64))
        tmpl += (["%d"] if c.dtype.kind in "ui" else ["%.9g"]) * c.shape[1]
    for name, v in obj.attributes.items():
        names.append(re.sub(r"[\s,;#]+", "_", name) or "attribute")
        cols.append(v.astype(np.float64).reshape(-1, 1))
        tmpl.append("%d" if v.dtype.kind in "uib" else text.float_format(v.dtype))
    sep = "," if csv else " "
    hist = text.mark_lines(obj) if not csv else ""
    head = (sep.join(names) + "\n") if csv else ("# " + " ".join(names) + "\n")
    body = text.format_rows(sep.join(tmpl) + "\n", np.column_stack(cols))
    return (hist + head).encode("utf-8") + body


def read_xyz(path: str | os.PathLike, data=None) -> PointCloud:
    """Read a text point cloud (``-``: standard input)."""
    from recon_cli.io.ply import read_bytes

    return decode_xyz(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_xyz(obj, path: str | os.PathLike, csv: bool | None = None) -> None:
    """Write a cloud as text atomically (``csv`` defaults to a ``.csv`` suffix)."""
    from recon_cli.io.atomic import write_bytes

    if csv is None:
        csv = str(path).lower().endswith(".csv")
    write_bytes(path, xyz_bytes(obj, csv=csv))
