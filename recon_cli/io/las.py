"""LAS and LAZ (1.2 - 1.4) through laspy with the lazrs backend (the optional extra ``recon[las]``).

Reading gives float64 coordinates ``X * scale + offset`` (LAS stores integers: float32 at
UTM coordinates would round to decimetres), the colours (uint16, as stored) and every other
dimension as a per-point attribute under laspy's name (``intensity``, ``return_number``,
``number_of_returns``, ``classification``, ``gps_time``, ..., and extra-bytes dimensions, one
of k values a point as ``name_0`` .. ``name_{k-1}``);
extra dimensions ``nx ny nz`` (or ``normal_x``...) are the normals. The version, point
format, scale, offset, the VLRs and EVLRs (coordinate system...) are kept in ``obj_info``
lines (``las_*``), so they survive a pass through PLY stages and are written back (a WKT
sets LAS 1.4's WKT bit); the records of the file's layout (COPC's octree pages, LASzip's
compression) are not kept, as they would describe another file wrongly. LAS says
nothing of where its sensor was: a cloud read from it has one sensor far above, "up" (+Z,
as for airborne LiDAR), which ``--orient camera`` uses. LAS stores integer coordinates, so
no point is ever NaN (a scale and offset that overflow float64 are refused).

Writing uses the kept scale and offset (coordinates from a LAS file come back as the same
integers), or else the finest power-of-ten scale that both fits the extent in 32-bit
integers and is at least 1e-9 of the extent (so at most 1e-8 of it), and an offset at the
minimum; a coordinate not on that grid is rounded and the writer says
by how much. Normals and attributes that are not standard dimensions of the point format
are written as extra-bytes dimensions.
"""

from __future__ import annotations

import base64
import contextlib
import io
import logging
import os
import re
from collections.abc import Iterator
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, Sensor, bbox_diagonal
from recon_cli.io import text

_NORMAL_NAMES = (
    ("nx", "ny", "nz"),
    ("normal_x", "normal_y", "normal_z"),
    ("NormalX", "NormalY", "NormalZ"),
)
_WITH_RGB = {0: 2, 1: 3, 4: 5, 6: 7, 9: 10}
_RGB = ("red", "green", "blue")
# the user ids of VLRs that describe a file's layout, not its data
_LAYOUT_USERS = ("copc", "laszip encoded")


def _laspy():
    try:
        import laspy
    except ModuleNotFoundError:
        raise ParameterError("LAS/LAZ needs laspy with lazrs: pip install 'recon[las]'") from None
    return laspy


@contextlib.contextmanager
def _laspy_silent() -> Iterator[None]:
    """The block without laspy's log records.

    What laspy logs of a file (a VLR it cannot parse, fewer points than declared) the reader
    either accepts or refuses in its own one line.
    """
    logger = logging.getLogger("laspy")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)


# a LAZ chunk holds at least a byte for this many bytes of point records (LAZ compresses real
# data 5-10x): a header declaring more points than that is corrupt, not read
_LAZ_MAX_RATIO = 200


def check_counts(head: bytes, size: int, where: str) -> None:
    """Refuse a header whose counts cannot fit in a file of ``size`` bytes, before laspy reads it.

    A corrupted count of VLRs or points made laspy build millions of records or allocate gigabytes
    (a fuzzed file took one test worker to 22 GB). ``head``: the file's first 375 bytes (the largest
    public header, LAS 1.4). Anything else is left to laspy.
    """
    if len(head) < 227 or head[:4] != b"LASF":
        return
    header_size = int.from_bytes(head[94:96], "little")
    to_points = int.from_bytes(head[96:100], "little")
    n_vlr = int.from_bytes(head[100:104], "little")
    fmt = head[104]
    record = int.from_bytes(head[105:107], "little")
    count = int.from_bytes(head[107:111], "little")
    if head[25] >= 4 and len(head) >= 255:
        count = int.from_bytes(head[247:255], "little") or count
        n_evlr = int.from_bytes(head[243:247], "little")
        if n_evlr * 60 > size:
            raise InputError(
                f"header declares {n_evlr} extended VLRs, more than its {size} bytes can hold",
                where,
            )
    if not header_size <= to_points <= size:
        raise InputError(
            f"header puts the points at byte {to_points}, outside the file ({size} bytes) or "
            "inside the header",
            where,
        )
    if n_vlr * 54 > to_points - header_size:
        raise InputError(
            f"header declares {n_vlr} VLRs, more than the {to_points - header_size} bytes "
            "before the points hold",
            where,
        )
    room = size - to_points
    compressed = bool(fmt & 0xC0)
    if count * record > (_LAZ_MAX_RATIO if compressed else 1) * room:
        raise InputError(
            f"header declares {count} points of {record} bytes, more than the file's {room} "
            "bytes of points can hold",
            where,
        )


def check_chunk_table(read: Any, size: int, head: bytes, where: str) -> None:
    """Refuse a LAZ whose chunk table cannot describe its points, before lazrs decodes them.

    lazrs sizes its buffers by the table (the number of chunks, each chunk's points and bytes),
    and a failed allocation aborts the process: no Python code can catch that. ``read(at, n)``
    gives the file's ``n`` bytes at byte ``at``; ``head`` its first 375 bytes. The table must lie
    after the points' start, hold no more chunks than the points' bytes (and, with chunks of a
    fixed size, than the points fill), and its chunks' bytes fit before it (variable chunks:
    their points sum to the header's count). A LAS file, or a LAZ without a LASzip record, is
    left to laspy.
    """
    import struct

    if len(head) < 227 or head[:4] != b"LASF" or not head[104] & 0xC0:
        return
    header_size = int.from_bytes(head[94:96], "little")
    to_points = int.from_bytes(head[96:100], "little")
    count = int.from_bytes(head[107:111], "little")
    if head[25] >= 4 and len(head) >= 255:
        count = int.from_bytes(head[247:255], "little") or count
    record = _laszip_record(read, header_size, int.from_bytes(head[100:104], "little"))
    if record is None or len(record) < 34:
        return
    chunk = int.from_bytes(record[12:16], "little")
    (at,) = struct.unpack("<q", read(to_points, 8).ljust(8, b"\0"))
    if at == -1 and size >= 8:  # written as a stream: the table's offset ends the file
        (at,) = struct.unpack("<q", read(size - 8, 8))
    if not to_points + 8 <= at <= size - 8:
        raise InputError(
            f"LAZ chunk table at byte {at}, outside the file's points ({to_points + 8}..{size})",
            where,
        )
    _version, chunks = struct.unpack("<II", read(at, 8))
    room = at - to_points - 8
    variable = chunk == 0xFFFFFFFF
    most = min(room, max(count, 1) if variable else -(-count // max(chunk, 1)))
    if chunks > most:
        raise InputError(
            f"LAZ chunk table declares {chunks} chunks, more than its {count} points in "
            f"{room} bytes can fill",
            where,
        )
    _check_chunk_entries(read, to_points, record, (count, room, variable), where)


def _laszip_record(read: Any, at: int, n_vlr: int) -> bytes | None:
    """The LASzip VLR's payload among the ``n_vlr`` VLRs from byte ``at`` (None: none)."""
    for _ in range(min(n_vlr, 1 << 16)):
        vh = read(at, 54)
        if len(vh) < 54:
            return None
        length = int.from_bytes(vh[20:22], "little")
        if vh[2:18].rstrip(b"\0") == b"laszip encoded" and vh[18:20] == (22204).to_bytes(
            2, "little"
        ):
            return read(at + 54, length)
        at += 54 + length
    return None


def _check_chunk_entries(read: Any, to_points: int, record: bytes, fig: tuple, where: str) -> None:
    """The decoded chunk table's entries against the points (``fig``: count, room, variable)."""
    import lazrs

    count, room, variable = fig

    class _At(io.RawIOBase):  # the file from the points' start, as lazrs reads it
        def __init__(self) -> None:
            self.pos = 0

        def readable(self) -> bool:
            return True

        def seekable(self) -> bool:
            return True

        def seek(self, off: int, whence: int = 0) -> int:
            self.pos = off if whence == 0 else self.pos + off
            return self.pos

        def tell(self) -> int:
            return self.pos

        def readinto(self, b: Any) -> int:
            got = read(self.pos, len(b))
            b[: len(got)] = got
            self.pos += len(got)
            return len(got)

    src = _At()
    src.seek(to_points)
    try:
        table = lazrs.read_chunk_table(src, lazrs.LazVlr(record))
    except Exception as exc:  # lazrs' errors: a table it cannot decode
        raise InputError(f"not a readable LAZ chunk table ({first_line(exc)})", where) from None
    points = sum(int(p) for p, _ in table or ())
    nbytes = sum(int(b) for _, b in table or ())
    if nbytes > room or (variable and points != count):
        raise InputError(
            f"LAZ chunk table gives {points} points in {nbytes} bytes; the header declares "
            f"{count} points in {room} bytes",
            where,
        )


def decode_las(data, where: str, path=None) -> tuple[PointCloud, dict]:
    """Decode a LAS/LAZ file (from ``path`` when given, else the bytes ``data``)."""
    laspy = _laspy()
    if path is not None:
        try:
            with open(path, "rb") as f:
                head = f.read(375)
            size = os.path.getsize(path)
        except FileNotFoundError:
            raise InputError("no such file", where) from None
        check_counts(head, size, where)
        with open(path, "rb") as f:
            check_chunk_table(lambda at, n: _read_at(f, at, n), size, head, where)
        source = path
    else:
        raw = bytes(text.as_uint8(data).data)
        check_counts(raw[:375], len(raw), where)
        check_chunk_table(lambda at, n: raw[at : at + n], len(raw), raw[:375], where)
        source = io.BytesIO(raw)
    try:
        with _laspy_silent():
            # lazrs' one-thread decoder: the parallel one sizes its buffers by the laszip record's
            # chunk size, and a corrupted one aborted the process (a failed allocation)
            las = laspy.read(source, laz_backend=laspy.LazBackend.Lazrs)
    except FileNotFoundError:
        raise InputError("no such file", where) from None
    except Exception as exc:  # laspy raises LaspyException, ValueError, lazrs errors...
        raise InputError(f"not a readable LAS/LAZ file ({first_line(exc)})", where) from None
    if len(las.points) != las.header.point_count:
        raise InputError(
            f"header declares {las.header.point_count} points, the file holds {len(las.points)}",
            where,
        )
    return cloud_from_points(las.points, las.header, where)


def _read_at(f: Any, at: int, n: int) -> bytes:
    f.seek(at)
    return f.read(n)


def first_line(exc: BaseException) -> str:
    """The first line of a library's error message (its type's name when it has none)."""
    return str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__


def cloud_from_points(points, header, where: str) -> tuple[PointCloud, dict]:
    """A cloud (and ``recon info``'s details) from laspy point records and their file's header.

    Parameters
    ----------
    points : laspy.PackedPointRecord
        The records (n of them), in the point format of ``header``.
    header : laspy.LasHeader
        Scales, offsets, version, point format, VLRs and EVLRs of the file.
    where : str
        The file's name, for messages.

    Returns
    -------
    cloud : PointCloud
        Coordinates ``X * scale + offset`` in float64, colours, normals (extra dimensions
        ``nx ny nz``...), every other dimension as an attribute; the header in ``obj_info``.
    details : dict
        ``format``, ``version``, ``point_format``, ``compressed``, ``scale``, ``offset``,
        ``vlrs``, ``crs``, ``software``.
    """
    h = header
    bad = [f"{c} scale {float(v)!r}" for c, v in zip("xyz", h.scales, strict=True) if not v]
    if bad:  # every coordinate would be the offset, and the grid cannot be written back
        raise InputError(f"header's {', '.join(bad)}: a scale must not be 0", where)
    raw = points.array
    pts = coordinates(raw, h.scales, h.offsets)
    if not np.isfinite(pts).all():
        raise InputError(
            f"scale {list(map(float, h.scales))} and offset {list(map(float, h.offsets))} give "
            "coordinates "
            "beyond float64",
            where,
        )
    rgb, trio, others = _dimensions(points.point_format)
    colors = np.column_stack([raw[c] for c in _RGB]) if rgb else None
    normals = None
    if trio:
        normals = text.quiet_nans(np.column_stack([np.asarray(points[c]) for c in trio]))
    attributes = _attribute_columns(points, others, where)
    info = [
        f"las_version {h.version}",
        f"las_point_format {h.point_format.id}",
        "las_scale " + " ".join(repr(float(s)) for s in h.scales),
        "las_offset " + " ".join(repr(float(o)) for o in h.offsets),
    ]
    info += [f"{key} " + _vlr_line(v) for key, v in _kept_records(h)]
    cloud = PointCloud(
        points=pts,
        normals=normals,
        colors=colors,
        attributes=attributes,
        point_dtype=np.float64,
        obj_info=info,
        sensors=las_sensors(),
    )
    return cloud, _details(h, where)


def las_sensors() -> list[Sensor]:
    """The sensor a LAS cloud has: one far above, "up" (+Z, airborne LiDAR)."""
    return [Sensor(direction=(0.0, 0.0, 1.0), source="LAS up (airborne)")]


def coordinates(raw: np.ndarray, scales, offsets) -> np.ndarray:
    """The float64 coordinates ``X * scale + offset`` (n, 3) of LAS point records ``raw``."""
    pts = np.empty((len(raw), 3), np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        for i, c in enumerate("XYZ"):
            np.multiply(raw[c], scales[i], out=pts[:, i])
            pts[:, i] += offsets[i]
    return pts


def _details(h, where: str) -> dict:
    return {
        "format": "las",
        "version": str(h.version),
        "point_format": int(h.point_format.id),
        "compressed": bool(getattr(h, "are_points_compressed", False))
        or str(where).lower().endswith(".laz"),
        "scale": [float(s) for s in h.scales],
        "offset": [float(o) for o in h.offsets],
        "vlrs": [
            f"{_raw_text(v.user_id).decode('latin-1')}/{v.record_id}" for _, v in _kept_records(h)
        ],
        "crs": crs_name(h),
        "software": h.generating_software,
    }


def describe_header(header, where: str) -> dict:
    """What a LAS file holds by its header alone: what its points would read as, and details.

    Returns
    -------
    dict
        ``mins``, ``maxs`` (the header's bounds), ``dimensions`` (``"dtype name"`` of the
        coordinates, colours, normals and each attribute as :func:`cloud_from_points` gives
        them), ``colors``, ``normals`` (bool), ``attributes`` (names), ``sensors`` (as
        :meth:`Sensor.describe` words them) and ``details``.
    """
    colors, trio, others = _dimensions(header.point_format)
    sample = laspy_module().ScaleAwarePointRecord.zeros(1, header=header)
    attributes = {n: np.array(sample[n]).dtype.name for n in others}
    dims = ["float64 x y z"]
    if trio:
        dims.append(f"{np.array(sample[trio[0]]).dtype.name} normals")
    if colors:
        dims.append("uint16 colours x3")
    dims += [f"{t} {n}" for n, t in attributes.items()]
    return {
        "mins": [float(v) for v in header.mins],
        "maxs": [float(v) for v in header.maxs],
        "dimensions": dims,
        "colors": colors,
        "normals": bool(trio),
        "attributes": sorted(attributes),
        "sensors": [s.describe() for s in las_sensors()],
        "details": _details(header, where),
    }


def _dimensions(fmt) -> tuple[bool, tuple[str, ...], list[str]]:
    """A point format's colours (RGB or not), normals (their three names or ()) and the rest."""
    names = list(fmt.dimension_names)
    rgb = all(c in names for c in _RGB)
    extra = {d.name for d in fmt.extra_dimensions}
    trio = next((t for t in _NORMAL_NAMES if all(c in extra for c in t)), ())
    skip = {"X", "Y", "Z", *(_RGB if rgb else ()), *trio}
    return rgb, trio, [n for n in names if n not in skip]


def _attribute_columns(points, names: list[str], where: str) -> dict[str, np.ndarray]:
    """The attributes of dimensions ``names``; one of k values a point as ``name_0`` .. ``_k-1``."""
    attributes = {}
    for name in names:
        if not name or names.count(name) > 1:  # laspy lists them but cannot give their values
            raise InputError(
                f"an extra-bytes dimension's name is empty or repeated: {ascii(name)}", where
            )
        values = text.quiet_nans(np.array(points[name]))
        if values.ndim == 1:
            attributes[name] = values
        else:  # as PCD's COUNT
            for k in range(values.shape[1]):
                attributes[f"{name}_{k}"] = np.ascontiguousarray(values[:, k])
    return attributes


def _kept_records(header) -> list[tuple[str, Any]]:
    """The header's VLRs and EVLRs that describe the data, with their ``obj_info`` key.

    Those of the file's layout are left out: COPC's (the octree's pages and chunks) and LASzip's
    (the compression), which would describe another file wrongly.
    """
    out = [("las_vlr", v) for v in header.vlrs]
    out += [("las_evlr", v) for v in (header.evlrs or ())]
    return [(key, v) for key, v in out if v.user_id not in _LAYOUT_USERS]


def _vlr_line(v) -> str:
    return " ".join(
        (
            base64.b64encode(_raw_text(v.user_id)).decode(),
            str(int(v.record_id)),
            base64.b64encode(_raw_text(v.description)).decode(),
            base64.b64encode(_vlr_bytes(v)).decode(),
        )
    )


def _raw_text(value) -> bytes:
    """A VLR's user id or description as bytes (laspy gives bytes when they are not text)."""
    if isinstance(value, bytes):
        return value
    try:
        return (value or "").encode("latin-1")
    except UnicodeEncodeError:  # laspy decoded it as UTF-8
        return value.encode("utf-8")


def crs_name(header) -> str | None:
    """The coordinate system a LAS header names: its WKT's name and EPSG code, or None."""
    for v in [*header.vlrs, *(header.evlrs or ())]:
        if v.user_id == "LASF_Projection" and v.record_id == 2112:
            wkt = _vlr_bytes(v).decode("latin-1").strip("\0 ")
            name = re.search(r'^\w+\[\s*"([^"]*)"', wkt)
            # the root's own code (one bracket deep), not a unit's or a datum's
            code = [
                m.group(1)
                for m in re.finditer(r'(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)', wkt)
                if wkt.count("[", 0, m.start()) - wkt.count("]", 0, m.start()) == 1
            ]
            label = name.group(1) if name else "WKT"
            return f"{label} (EPSG:{code[0]})" if code else label
    if any(v.user_id == "LASF_Projection" and v.record_id == 34735 for v in header.vlrs):
        return "GeoTIFF keys"
    return None


def _ascii(words: bytes) -> str:
    # laspy writes a VLR's user id and description as ASCII: any other byte is written as "?"
    return words.decode("ascii", "replace").replace("\ufffd", "?")


def _vlr_bytes(v) -> bytes:
    try:
        return bytes(v.record_data_bytes())
    except (AttributeError, TypeError):
        return bytes(getattr(v, "record_data", b""))


def _info(obj) -> dict:
    out: dict = {"vlrs": [], "evlrs": []}
    for line in obj.obj_info:
        key, _, rest = line.partition(" ")
        if key in ("las_vlr", "las_evlr"):
            out[key[4:] + "s"].append(rest.split(" "))
        elif key.startswith("las_"):
            out[key[4:]] = rest
    return out


# GeoTIFF keys of a GeoKeyDirectory VLR that name an EPSG coordinate system
_PROJECTED_KEY, _GEOGRAPHIC_KEY = 3072, 2048


def coordinate_system(obj_info: list[str]) -> str | None:
    """The coordinate system the LAS VLRs and EVLRs kept in ``obj_info`` lines give, or None.

    The OGC WKT record (``LASF_Projection`` 2112, a VLR or an EVLR as COPC files hold it) as its
    text, else the EPSG code of a GeoKeyDirectory record (34735: ``ProjectedCSTypeGeoKey``, else
    ``GeographicTypeGeoKey``) as ``"EPSG:<code>"``. Malformed records are passed over.
    """
    records = {}
    for line in obj_info:
        key, _, rest = line.partition(" ")
        words = rest.split(" ")
        if key not in ("las_vlr", "las_evlr") or len(words) != 4:
            continue
        try:
            user = base64.b64decode(words[0]).decode("latin-1").rstrip("\0")
            records[(user, int(words[1]))] = base64.b64decode(words[3])
        except ValueError:  # binascii.Error is a ValueError
            continue
    wkt = records.get(("LASF_Projection", 2112))
    if wkt:
        text_ = wkt.split(b"\0", 1)[0].decode("latin-1").strip()
        if text_:
            return text_
    keys = records.get(("LASF_Projection", 34735))
    if keys and len(keys) >= 8 and len(keys) % 8 == 0:
        shorts = np.frombuffer(keys, "<u2").reshape(-1, 4)
        found = {int(k): int(v) for k, loc, _, v in shorts[1:] if loc == 0}
        for geokey in (_PROJECTED_KEY, _GEOGRAPHIC_KEY):
            if 0 < found.get(geokey, 0) < 32767:  # 32767: user-defined, not a code
                return f"EPSG:{found[geokey]}"
    return None


def _grid(pts: np.ndarray, info: dict) -> tuple[np.ndarray, np.ndarray]:
    if "scale" in info and "offset" in info:
        scale = np.array(info["scale"].split(), float)
        offset = np.array(info["offset"].split(), float)
        if len(scale) == len(offset) == 3 and np.isfinite([*scale, *offset]).all() and scale.all():
            return scale, offset
    lo = pts.min(axis=0) if len(pts) else np.zeros(3)
    hi = pts.max(axis=0) if len(pts) else np.zeros(3)
    extent = max(float(np.max(hi - lo)), 1e-300)
    scale = 10.0 ** np.ceil(np.log10(max(extent / 2.0e9, extent * 1e-9, 1e-12)))
    return np.full(3, scale), np.floor(lo)


def las_bytes(obj, compress: bool, where: str = "") -> bytes:
    """The LAS (or LAZ when ``compress``) encoding of a cloud (a mesh's vertices)."""
    laspy = _laspy()
    info = _info(obj)
    pts = np.asarray(obj.points, np.float64)
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():  # LAS coordinates are integers: there is no NaN to write
        raise ParameterError(
            f"{where}: LAS cannot store the {int(bad.sum())} points with a NaN or infinite "
            f"coordinate (first: point {int(np.argmax(bad))})"
        )
    version = info.get("version", "1.4")
    pf = int(info.get("point_format", 7 if obj.colors is not None else 6))
    if obj.colors is not None and pf in _WITH_RGB:
        pf = _WITH_RGB[pf]
    header = laspy.LasHeader(point_format=pf, version=version)
    scale, offset = _grid(pts, info)
    header.scales = scale
    header.offsets = offset
    standard = set(laspy.PointFormat(pf).dimension_names)
    extras = []
    if obj.normals is not None:
        ntype = obj.normals.dtype if obj.normals.dtype in (np.float32, np.float64) else np.float64
        extras += [(c, obj.normals[:, i].astype(ntype)) for i, c in enumerate(("nx", "ny", "nz"))]
    for name, v in obj.attributes.items():
        if name not in standard:
            extras.append((name, v))
    if extras:
        header.add_extra_dims(
            [laspy.ExtraBytesParams(name=name, type=_extra_type(v.dtype)) for name, v in extras]
        )
    vlrs = [_vlr(laspy, *fields) for fields in info["vlrs"]]
    evlrs = [_vlr(laspy, *fields) for fields in info["evlrs"]]
    header.vlrs.extend(vlrs)
    if evlrs:
        header.evlrs = laspy.vlrs.vlrlist.VLRList(evlrs)
    wkt = any(v.user_id == "LASF_Projection" and v.record_id == 2112 for v in vlrs + evlrs)
    if wkt and header.version.minor >= 4:
        header.global_encoding.wkt = True  # LAS 1.4: the coordinate system is this WKT
    las = laspy.LasData(header)
    ints = np.rint((pts - offset) / scale)
    if len(pts) and (np.abs(ints).max() > 2**31 - 1):
        raise ParameterError(
            f"{where}: coordinates do not fit LAS integers with scale {scale[0]:g} and offset "
            f"{offset.tolist()}"
        )
    ints = ints.astype(np.int32)
    las.X, las.Y, las.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    err = float(np.max(np.abs(ints * scale + offset - pts))) if len(pts) else 0.0
    if err > 1e-3 * float(scale.min()):
        text.warn(
            f"{where}: LAS stores coordinates as integers of scale {scale.min():g}: rounded by "
            f"up to {err:.3g} "
            f"({err / max(bbox_diagonal(pts), 1e-300):.2g} of the bounding-box diagonal)"
        )
    if obj.colors is not None:
        c = obj.colors[:, :3]
        c16 = (
            c.astype(np.uint16) * 257
            if c.dtype == np.uint8
            else (
                c.astype(np.uint16)
                if c.dtype.kind in "ui"
                else np.clip(np.rint(c * 65535), 0, 65535).astype(np.uint16)
            )
        )
        las.red, las.green, las.blue = c16[:, 0], c16[:, 1], c16[:, 2]
    for name, v in obj.attributes.items():
        if name in standard:
            _assign(las, name, v, where)
    for name, v in extras:
        las[name] = v
    buf = io.BytesIO()
    kw = {"laz_backend": laspy.LazBackend.Lazrs} if compress else {}
    las.write(buf, do_compress=compress, **kw)
    return buf.getvalue()


def _vlr(laspy, user: str, rec: str, desc: str, payload: str):
    """A VLR from the four base64 fields of an ``obj_info`` line."""
    return laspy.VLR(
        user_id=_ascii(base64.b64decode(user)),
        record_id=int(rec),
        description=_ascii(base64.b64decode(desc)),
        record_data=base64.b64decode(payload),
    )


def _extra_type(dt: np.dtype) -> str:
    dt = np.dtype(dt)
    if dt.kind == "b":
        return "u1"
    if (
        dt.kind in "iuf"
        and dt.itemsize in (1, 2, 4, 8)
        and not (dt.kind == "f" and dt.itemsize < 4)
    ):
        return f"{dt.kind}{dt.itemsize}"
    return "f8"


def _assign(las, name: str, v: np.ndarray, where: str) -> None:
    target = np.asarray(las[name]).dtype
    cast = v.astype(target)
    if not np.array_equal(cast.astype(np.float64), v.astype(np.float64)):
        raise ParameterError(
            f"{where}: attribute {name!r} has values a LAS {name} ({target}) cannot hold"
        )
    las[name] = cast
    if not np.array_equal(np.asarray(las[name]).astype(np.float64), v.astype(np.float64)):
        raise ParameterError(
            f"{where}: attribute {name!r} has values out of range for the LAS field"
        )


def read_las(path: str | os.PathLike, data=None) -> PointCloud:
    """Read a LAS/LAZ file (``-``: standard input)."""
    from recon_cli.io.ply import read_bytes

    if data is None and str(path) != "-":
        if not os.path.isfile(path):
            raise InputError("no such file", str(path))
        return decode_las(None, str(path), path=str(path))[0]
    return decode_las(read_bytes(path) if data is None else data, text.where_of(path))[0]


def write_las(obj, path: str | os.PathLike, compress: bool | None = None) -> None:
    """Write ``obj`` as LAS (LAZ for a ``.laz`` suffix or ``compress``) atomically."""
    from recon_cli.io.atomic import write_bytes

    if compress is None:
        compress = str(path).lower().endswith(".laz")
    write_bytes(path, las_bytes(obj, compress, text.where_of(path)))


# public name for the chunked reader (recon_cli.io.chunks)
laspy_module = _laspy
