"""PCD (Point Cloud Library), ``DATA ascii``, ``binary`` and ``binary_compressed``.

Our own reader and writer.

Fields ``x y z`` are the points (float32 or float64 as in the file), ``normal_x normal_y
normal_z`` the normals, ``rgb`` / ``rgba`` (packed 0xAARRGGBB in 4 bytes, type F or U) the
colours (uint8); every other field is kept as a per-point attribute (a field of COUNT k as
``name_0`` .. ``name_{k-1}``); ``_`` padding fields are skipped. The ``VIEWPOINT`` line
is the cloud's sensor (position and orientation; written back). Points with a NaN or
infinite coordinate (a depth camera's missing pixels) are dropped and counted; an
organized cloud (``HEIGHT`` > 1) keeps each point's pixel
(:class:`~recon_cli.geometry.PixelGrid`). Binary bodies are decoded with numpy structured
dtypes; ``binary_compressed`` (column-major, LZF) is decompressed by our own numba kernel
(:mod:`recon_cli.io._lzf_kernel`) into a buffer of the size the header declares, checked
against the file first.
"""

from __future__ import annotations

import os

import numpy as np

from recon_cli.errors import InputError
from recon_cli.geometry import PixelGrid, PointCloud, Sensor, drop_invalid
from recon_cli.io import text

_KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)
_NORMALS = ("normal_x", "normal_y", "normal_z")
MAX_HEADER_LINES = 64


def _dtype(t: str, size: int, where: str, lineno: int) -> np.dtype:
    code = {"F": "f", "I": "i", "U": "u"}.get(t)
    if code is None or (code == "f" and size not in (4, 8)) or size not in (1, 2, 4, 8):
        raise InputError(f"line {lineno}: unsupported field type {t}{size}", where)
    return np.dtype(f"<{code}{size}")


def parse_header(buf: np.ndarray, where: str) -> tuple[dict, int]:
    """The header fields and the byte offset of the body."""
    head, lines, pos = _header_lines(buf, where)
    return _header_fields(head, lines, where, len(buf)), pos


def _header_lines(buf: np.ndarray, where: str) -> tuple[dict, dict, int]:
    """Each header keyword's words and line number, up to the DATA line; the body's offset."""
    pos = 0
    head: dict = {}
    lines: dict = {}
    for lineno in range(1, MAX_HEADER_LINES + 1):
        end = int(np.argmax(buf[pos : pos + 4096] == 10)) if pos < len(buf) else -1
        if pos >= len(buf) or (end == 0 and buf[pos] != 10):
            raise InputError("truncated header (no DATA line)", where)
        line = bytes(buf[pos : pos + end]).decode("latin-1").strip()
        pos += end + 1
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        if key not in _KEYS:
            if lineno == 1:
                raise InputError("not a PCD file (no VERSION/FIELDS header)", where)
            raise InputError(f"line {lineno}: unknown header keyword {ascii(key)}", where)
        head[key] = rest.split()
        lines[key] = lineno
        if key == "DATA":
            break
    else:
        raise InputError(f"no DATA line in the first {MAX_HEADER_LINES} header lines", where)
    return head, lines, pos


def _header_fields(head: dict, lines: dict, where: str, file_bytes: int) -> dict:
    """The fields, their types and counts, the point count and layout a header declares.

    ``file_bytes``: the file's length (a point longer than that is refused).
    """
    for key in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA"):
        if key not in head:
            raise InputError(f"header has no {key} line", where)
    names = head["FIELDS"]
    k = len(names)
    counts = head.get("COUNT", ["1"] * k)
    if not (len(head["SIZE"]) == len(head["TYPE"]) == len(counts) == k):
        raise InputError(
            f"line {lines['FIELDS']}: FIELDS, SIZE, TYPE and COUNT differ in length", where
        )
    try:
        sizes = [int(s) for s in head["SIZE"]]
        counts = [int(c) for c in counts]
        npts = int(head["POINTS"][0])
        width = int(head.get("WIDTH", [npts])[0])
        height = int(head.get("HEIGHT", ["1"])[0])
    except (ValueError, IndexError):
        raise InputError(
            "a SIZE, COUNT, WIDTH, HEIGHT or POINTS value is not an integer", where
        ) from None
    if npts < 0 or width < 0 or height < 0 or any(c < 1 for c in counts):
        raise InputError("a negative POINTS, WIDTH or HEIGHT, or a COUNT below 1", where)
    if width * height != npts:
        raise InputError(f"WIDTH {width} x HEIGHT {height} is not POINTS {npts}", where)
    dtypes = [_dtype(t, s, where, lines["TYPE"]) for t, s in zip(head["TYPE"], sizes, strict=True)]
    row = sum(dt.itemsize * c for dt, c in zip(dtypes, counts, strict=True))
    if row > file_bytes:
        raise InputError(
            f"line {lines.get('COUNT', lines['SIZE'])}: a point of {row} bytes (SIZE x COUNT) is "
            f"longer than the file ({file_bytes} bytes)",
            where,
        )
    if len(set(names)) != len(names):
        raise InputError(f"line {lines['FIELDS']}: a field name is repeated", where)
    for name in names:  # they become PLY and PCD header words, which are ASCII
        if not (name.isascii() and name.isprintable()):
            raise InputError(
                f"line {lines['FIELDS']}: field name {ascii(name)} is not printable ASCII", where
            )
    for c in ("x", "y", "z"):
        if c not in names:
            raise InputError(f"no {c!r} field", where)
    fmt = head["DATA"][0] if head["DATA"] else ""
    if fmt not in ("ascii", "binary", "binary_compressed"):
        raise InputError(f"line {lines['DATA']}: unknown DATA {fmt!r}", where)
    return {
        "names": names,
        "dtypes": dtypes,
        "counts": counts,
        "points": npts,
        "width": width,
        "height": height,
        "data": fmt,
        "viewpoint": head.get("VIEWPOINT"),
        "version": (head.get("VERSION") or ["?"])[0],
        "header_lines": lines["DATA"],
    }


def _row_dtype(h: dict) -> np.dtype:
    fields = []
    for i, (name, dt, c) in enumerate(zip(h["names"], h["dtypes"], h["counts"], strict=True)):
        fname = name if name != "_" else f"_pad{i}"
        fields.append((fname, dt, (c,)) if c > 1 else (fname, dt))
    return np.dtype(fields)


def decode_pcd(data, where: str) -> tuple[PointCloud, dict]:
    """Decode the bytes of a PCD file: ``(cloud, details for recon info)``."""
    buf = text.as_uint8(data)
    if len(buf) == 0:
        raise InputError("empty file", where)
    h, off = parse_header(buf, where)
    rowdt = _row_dtype(h)
    n = h["points"]
    remaining = len(buf) - off
    if h["data"] == "binary":
        if n > remaining // max(rowdt.itemsize, 1):
            raise InputError(
                f"truncated: POINTS {n} need {n * rowdt.itemsize} bytes after the header (byte "
                f"{off}), the file has {remaining}",
                where,
            )
        rows = np.frombuffer(buf, dtype=rowdt, count=n, offset=off)
        cols = {name: rows[name] for name in rowdt.names or ()}
    elif h["data"] == "binary_compressed":
        cols = _decompress(buf, off, h, rowdt, where)
    else:
        cols = _ascii(buf, off, h, rowdt, where)
    cloud = _to_cloud(cols, h, where)
    details = {
        "format": "pcd",
        "data": h["data"],
        "version": h["version"],
        "fields": [
            f"{n_}:{dt.kind.upper()}{dt.itemsize}x{c}"
            for n_, dt, c in zip(h["names"], h["dtypes"], h["counts"], strict=True)
        ],
        "width": h["width"],
        "height": h["height"],
    }
    return cloud, details


def _decompress(buf, off, h, rowdt, where) -> dict:
    from recon_cli.io._lzf_kernel import lzf_decompress

    if len(buf) - off < 8:
        raise InputError(f"truncated: no compressed sizes at byte {off}", where)
    csize, usize = (int(v) for v in buf[off : off + 8].view("<u4"))
    n = h["points"]
    if usize != n * rowdt.itemsize:
        raise InputError(
            f"byte {off}: uncompressed size {usize} is not POINTS {n} x {rowdt.itemsize} bytes",
            where,
        )
    if csize > len(buf) - off - 8:
        raise InputError(
            f"truncated: {csize} compressed bytes declared at byte {off}, {len(buf) - off - 8} "
            "remain",
            where,
        )
    out = np.empty(usize, np.uint8)
    got = lzf_decompress(buf[off + 8 : off + 8 + csize], out) if csize else 0
    if got < 0:
        raise InputError(f"byte {off + 8 - 1 - got}: corrupt LZF data", where)
    if got != usize:
        raise InputError(f"LZF data decompress to {got} bytes, not the {usize} declared", where)
    cols = {}
    pos = 0
    for name in rowdt.names:
        dt, _ = rowdt.fields[name][:2]
        base, shape = (dt.base, dt.shape) if dt.shape else (dt, ())
        size = base.itemsize * int(np.prod(shape, dtype=np.int64)) * n
        cols[name] = out[pos : pos + size].view(base).reshape((n,) + shape)
        pos += size
    return cols


def _ascii(buf, off, h, rowdt, where) -> dict:
    values, row_start, row_line = text.read_rows(buf, off, len(buf), where)
    width = sum(h["counts"])
    n = h["points"]
    lens = np.diff(row_start)
    first_line = h["header_lines"]
    if len(lens) != n:
        raise InputError(f"POINTS {n} declared but the data has {len(lens)} rows", where)
    if n and np.any(lens != width):
        bad = int(np.flatnonzero(lens != width)[0])
        raise InputError(
            f"line {first_line + int(row_line[bad])}: {int(lens[bad])} values, the fields need "
            f"{width}",
            where,
        )
    table = values.reshape(n, width)
    cols = {}
    j = 0
    for name, dt, c in zip(h["names"], h["dtypes"], h["counts"], strict=True):
        fname = name if name != "_" else f"_pad{j}"
        block = table[:, j : j + c]
        if dt.kind in "iu":
            info = np.iinfo(dt)
            # a packed rgb written as a float value (old PCL) is an integer type here only when the
            # file says so
            if np.any(block != np.round(block)) or (
                block.size and (block.min() < info.min or block.max() > info.max)
            ):
                raise InputError(
                    f"field {name!r}: values are not {dt.kind.upper()}{dt.itemsize} integers", where
                )
        if name in ("rgb", "rgba") and dt.kind == "f":
            col = block.astype(np.float32)  # the float's bits are the colour
        else:
            col = block.astype(dt)
        cols[fname] = col[:, 0] if c == 1 else col
        j += c
    return cols


def _to_cloud(cols: dict, h: dict, where: str) -> PointCloud:
    # a packed rgb's float bits are the colour, NaN or not
    cols = {k: c if k in ("rgb", "rgba") else text.quiet_nans(c) for k, c in cols.items()}
    xyz_types = {cols[c].dtype for c in ("x", "y", "z")}
    ptype = np.float32 if xyz_types == {np.dtype("<f4")} else np.float64
    pts = np.column_stack([np.asarray(cols[c], dtype=ptype) for c in ("x", "y", "z")])
    used = {"x", "y", "z"}
    normals = None
    if all(c in cols for c in _NORMALS):
        ntypes = {cols[c].dtype for c in _NORMALS}
        ntype = np.float32 if ntypes == {np.dtype("<f4")} else np.float64
        normals = np.column_stack([np.asarray(cols[c], dtype=ntype) for c in _NORMALS])
        used |= set(_NORMALS)
    colors = None
    for name in ("rgba", "rgb"):
        if name in cols and cols[name].ndim == 1 and cols[name].dtype.itemsize == 4:
            packed = np.ascontiguousarray(cols[name]).view("<u4")
            b = (packed & 255).astype(np.uint8)
            g = ((packed >> 8) & 255).astype(np.uint8)
            r = ((packed >> 16) & 255).astype(np.uint8)
            parts = [r, g, b] + ([(packed >> 24).astype(np.uint8)] if name == "rgba" else [])
            colors = np.column_stack(parts)
            used.add(name)
            break
    attributes = {}
    for name, col in cols.items():
        if name in used or name.startswith("_pad"):
            continue
        if col.ndim == 2:
            for k in range(col.shape[1]):
                attributes[f"{name}_{k}"] = np.ascontiguousarray(col[:, k])
        else:
            attributes[name] = np.array(col)
    sensors = []
    if h["viewpoint"] is not None:
        sensors.append(_viewpoint(h["viewpoint"], where))
    organized = h["height"] > 1
    cloud = PointCloud(
        points=pts,
        normals=normals,
        colors=colors,
        attributes=attributes,
        point_dtype=ptype,
        sensors=sensors,
        pixels=PixelGrid(((h["height"], h["width"]),), np.arange(len(pts))) if organized else None,
    )
    return drop_invalid(cloud, where)


def _viewpoint(words: list[str], where: str) -> Sensor:
    """The sensor a ``VIEWPOINT tx ty tz qw qx qy qz`` line gives.

    That is PCL's sensor origin and orientation, in the points' frame.
    """
    try:
        v = [float(x) for x in words]
    except ValueError:
        v = []
    if len(v) != 7 or not np.isfinite(v).all():
        raise InputError(f"VIEWPOINT must be 7 finite numbers, got {' '.join(words)!r}", where)
    q = np.array(v[3:])
    length = float(np.linalg.norm(q))
    # the position is what orients normals; an orientation that is no rotation is not kept
    rot = tuple(q / length) if 0.5 < length < 2.0 else None
    return Sensor(position=(v[0], v[1], v[2]), orientation=rot, source="PCD VIEWPOINT")


def _code(dt: np.dtype) -> tuple[str, int]:
    dt = np.dtype(dt)
    if dt.kind == "b":
        return "U", 1
    if (
        dt.kind not in "iuf"
        or dt.itemsize not in (1, 2, 4, 8)
        or (dt.kind == "f" and dt.itemsize < 4)
    ):
        return "F", 8
    return {"i": "I", "u": "U", "f": "F"}[dt.kind], dt.itemsize


def pcd_bytes(obj, data: str = "binary") -> bytes:
    """The PCD encoding of a cloud (a mesh's vertices).

    ``data`` is ``ascii``, ``binary`` or ``binary_compressed``.
    """
    pts = obj.points
    n = len(pts)
    ptype = np.dtype(np.float64 if np.dtype(obj.point_dtype) == np.float64 else np.float32)
    cols: list[tuple[str, np.ndarray]] = [(c, pts[:, i].astype(ptype)) for i, c in enumerate("xyz")]
    if obj.normals is not None:
        ntype = obj.normals.dtype if obj.normals.dtype in (np.float32, np.float64) else np.float64
        cols += [(c, obj.normals[:, i].astype(ntype)) for i, c in enumerate(_NORMALS)]
    if obj.colors is not None:
        c8 = (
            obj.colors
            if obj.colors.dtype == np.uint8
            else np.clip(np.rint(text.colours_to_unit(obj.colors) * 255), 0, 255).astype(np.uint8)
        )
        packed = (
            (c8[:, 0].astype(np.uint32) << 16)
            | (c8[:, 1].astype(np.uint32) << 8)
            | c8[:, 2].astype(np.uint32)
        )
        if c8.shape[1] == 4:
            cols.append(("rgba", packed | (c8[:, 3].astype(np.uint32) << 24)))
        else:
            cols.append(("rgb", packed))
    for name, v in obj.attributes.items():
        t, s = _code(v.dtype)
        cols.append(
            (
                name.replace(" ", "_"),
                v.astype(np.dtype(f"<{t.lower()}{s}") if t != "F" else np.dtype(f"<f{s}")),
            )
        )
    kinds = [_code(v.dtype) for _, v in cols]
    view = _viewpoint_words(obj)
    head = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(name for name, _ in cols),
        "SIZE " + " ".join(str(s) for _, s in kinds),
        "TYPE " + " ".join(t for t, _ in kinds),
        "COUNT " + " ".join("1" for _ in cols),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT " + view,
        f"POINTS {n}",
        f"DATA {data}",
    ]
    out = ("\n".join(head) + "\n").encode("ascii")
    if data == "ascii":
        fmts = []
        table = []
        for (_name, v), (t, s) in zip(cols, kinds, strict=True):
            fmts.append(("%.9g" if s == 4 else "%.17g") if t == "F" else "%d")
            table.append(v.astype(np.float64))
        return out + text.format_rows(
            " ".join(fmts) + "\n", np.column_stack(table) if table else np.zeros((n, 0))
        )
    dt = np.dtype([(name, v.dtype.newbyteorder("<")) for name, v in cols])
    if data == "binary":
        rows = np.empty(n, dtype=dt)
        for name, v in cols:
            rows[name] = v
        return out + rows.tobytes()
    if data != "binary_compressed":
        raise ValueError(f"unknown PCD data {data!r}")
    from recon_cli.io._lzf_kernel import lzf_compress

    raw = (
        np.concatenate(
            [
                np.ascontiguousarray(v, dtype=v.dtype.newbyteorder("<")).view(np.uint8)
                for _, v in cols
            ]
        )
        if n
        else np.zeros(0, np.uint8)
    )
    comp = lzf_compress(raw)
    return out + np.array([len(comp), len(raw)], dtype="<u4").tobytes() + comp.tobytes()


def _viewpoint_words(obj) -> str:
    """The VIEWPOINT of ``obj``: its one sensor position (and orientation), else PCL's default."""
    sensors = [s for s in getattr(obj, "sensors", []) if s.position is not None]
    if len(sensors) != 1 or len(getattr(obj, "sensors", [])) != 1:
        return "0 0 0 1 0 0 0"
    s = sensors[0]
    q = s.orientation if s.orientation is not None else (1.0, 0.0, 0.0, 0.0)
    return " ".join(repr(float(x)) for x in (*s.position, *q))


def read_pcd(path: str | os.PathLike, data=None) -> PointCloud:
    """Read a PCD file (``-``: standard input)."""
    from recon_cli.io.ply import read_bytes

    return decode_pcd(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_pcd(obj, path: str | os.PathLike, data: str = "binary") -> None:
    """Write ``obj`` as PCD atomically (``-``: standard output)."""
    from recon_cli.io.atomic import write_bytes

    taken = ["x", "y", "z", "rgb", "rgba", *(_NORMALS if obj.normals is not None else ())]
    text.check_header_words(obj.attributes, "PCD", text.where_of(path), taken)
    write_bytes(path, pcd_bytes(obj, data=data))
