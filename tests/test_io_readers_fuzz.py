"""Generated files for every reader but PLY's and glTF's: read or refused in one line.

Generated files for every reader but PLY's (test_io_fuzz.py) and glTF's: read or refused in one
line, never a traceback, never a hang.

Hypothesis builds each file from its parts, then maybe breaks it:

- PCD: fields of every type and count (padding ``_`` fields, packed ``rgb`` as F, U or I),
  float32 or float64 coordinates, organized (HEIGHT > 1) with NaN pixels, a VIEWPOINT (good or
  not), ``DATA ascii``, ``binary`` or ``binary_compressed``;
- LAS and LAZ (laspy): point formats 0 to 10 (the odd ones: waveform packets, NIR, 1.4's
  extended returns) with extra bytes, coordinate-system records (WKT, GeoKeys, an extended VLR);
- E57 (pye57): one to three scans, structured or not, colours, intensity, poses; a breakage is
  made in the logical bytes and every page's CRC-32C computed again, so it reaches the XML and
  the binary sections instead of stopping at the first checksum;
- OBJ, OFF and STL (ASCII and binary): every kind of line or record, polygons, relative and
  slashed indices, colours, comments, CRLF.

The breakages: none, a cut at any byte, bytes overwritten, junk inserted, a header number or
word replaced by an edge value (0, -1, 2^32, 2^64, NaN, a word), a LAS header field set to an
edge value. Each case is read as a valid object or refused with one :class:`InputError` line
naming the file, in under :data:`CASE_SECONDS` (a watchdog ends the process on a hang); one case
in five (drawn) also goes through ``recon convert``, to PLY or to its own format: exit 0, or exit
2 with one stderr line naming the file, the output that was there before untouched.

``make test`` runs :data:`QUICK` cases a reader; ``make fuzz`` (marker ``fuzz``) :data:`FUZZ`.
LAZ files are broken in their compressed points too, their chunk table included (lazrs, the
decoder under laspy, aborted the process on a table it allocated gigabytes by: the reader checks
the table first).
"""

from __future__ import annotations

import faulthandler
import io
import re
import struct
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh
from recon_cli.io.load import load

from fuzz_checks import convert_broken_files

QUICK = 20
FUZZ = 500
# a case that takes longer is a failure; one that takes CASE_SECONDS * 6 ends the process
CASE_SECONDS = 10.0

EDGE_NUMBERS = [
    "0",
    "-1",
    "1",
    "2",
    "3",
    "65536",
    "2147483648",
    "4294967296",
    "18446744073709551616",
    "1e400",
    "-1e400",
    "nan",
    "inf",
    "1.5",
    "x",
    "",
]


# ----------------------------------------------------------------------------- breakages


@st.composite
def broken(draw, data: bytes, head: int | None = None, allow_body: bool = True) -> tuple:
    """``data`` maybe broken: (label, bytes).

    ``data`` maybe broken: (label, bytes). ``head``: the length of a text header, whose
    words may be replaced; ``allow_body`` False keeps the bytes after ``head`` intact.
    """
    kinds = ["none", "cut"]
    if data and (allow_body or head):  # an empty file has no byte to overwrite
        kinds += ["overwrite", "insert"]
    if head:
        kinds += ["word", "word", "line"]
    kind = draw(st.sampled_from(kinds))
    limit = len(data) if allow_body else max(1, head or 1)
    if kind == "none":
        return "intact", data
    if kind == "cut":
        at = draw(st.integers(0, max(0, len(data) - 1)))
        return f"cut at {at}", data[:at]
    if kind == "overwrite":
        raw = bytearray(data)
        spots = draw(st.lists(st.integers(0, max(0, limit - 1)), min_size=1, max_size=6))
        for at in spots:
            raw[at] = draw(st.integers(0, 255))
        return f"bytes {spots} overwritten", bytes(raw)
    if kind == "insert":
        at = draw(st.integers(0, limit))
        junk = draw(st.binary(min_size=1, max_size=12))
        return f"{junk!r} inserted at {at}", data[:at] + junk + data[at:]
    text = data[:head].decode("latin-1")
    words = [(m.start(), m.end()) for m in _WORD.finditer(text)]
    if kind == "word" and words:
        a, b = words[draw(st.integers(0, len(words) - 1))]
        new = draw(st.sampled_from(EDGE_NUMBERS))
        return f"{text[a:b]!r} -> {new!r}", (text[:a] + new + text[b:]).encode("latin-1") + data[
            head:
        ]
    lines = text.split("\n")
    i = draw(st.integers(0, max(0, len(lines) - 2)))
    if draw(st.booleans()):
        lines = lines[:i] + lines[i + 1 :]
        label = f"header line {i} deleted"
    else:
        lines = lines[: i + 1] + lines[i:]
        label = f"header line {i} doubled"
    return label, "\n".join(lines).encode("latin-1") + data[head:]


_WORD = re.compile(r"[^\s]+")


# ----------------------------------------------------------------------------- PCD

_PCD_EXTRAS = [
    ("intensity", "F", 4, 1),
    ("ring", "U", 2, 1),
    ("label", "I", 4, 1),
    ("t", "F", 8, 1),
    ("histogram", "F", 4, 3),
    ("_", "U", 1, 3),
    ("curvature", "F", 4, 1),
    ("tiny", "I", 1, 2),
]


def _pcd_values(rng, t: str, size: int, count: int, n: int) -> np.ndarray:
    dt = np.dtype(f"<{ {'F': 'f', 'U': 'u', 'I': 'i'}[t] }{size}")
    if t == "F":
        return rng.normal(size=(n, count)).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, size=(n, count), endpoint=True).astype(dt)


@st.composite
def pcd_case(draw) -> tuple[str, str, bytes]:
    """A generated PCD file, maybe broken: (label, name, bytes)."""
    from recon_cli.io._lzf_kernel import lzf_compress

    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    width = draw(st.integers(1, 12))
    height = draw(st.sampled_from([1, 1, 2, 3, 5]))
    n = width * height
    size = draw(st.sampled_from([4, 8]))
    fields = [(c, "F", size, 1) for c in "xyz"]
    if draw(st.booleans()):
        fields += [(c, "F", 4, 1) for c in ("normal_x", "normal_y", "normal_z")]
    rgb = draw(st.sampled_from([None, "F", "U", "I"]))
    if rgb:
        fields.append(("rgb", rgb, 4, 1))
    fields += draw(st.lists(st.sampled_from(_PCD_EXTRAS), max_size=3, unique_by=lambda f: f[0]))
    cols = [_pcd_values(rng, t, s, c, n) for _, t, s, c in fields]
    nan_share = draw(st.sampled_from([0.0, 0.0, 0.2, 1.0]))
    missing = rng.random(n) < nan_share
    for k in range(3):
        cols[k][missing] = np.nan
    data = draw(st.sampled_from(["ascii", "binary", "binary_compressed"]))
    head = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(f[0] for f in fields),
        "SIZE " + " ".join(str(f[2]) for f in fields),
        "TYPE " + " ".join(f[1] for f in fields),
        "COUNT " + " ".join(str(f[3]) for f in fields),
        f"WIDTH {width}",
        f"HEIGHT {height}",
    ]
    view = draw(st.sampled_from(["0 0 0 1 0 0 0", "1.5 -2 3 0.7071 0 0.7071 0", "0 0 0 0 0 0 0"]))
    if draw(st.booleans()):
        head.append(f"VIEWPOINT {view}")
    head += [f"POINTS {n}", f"DATA {data}"]
    header = ("\n".join(head) + "\n").encode()
    if data == "ascii":
        rows = [
            " ".join(" ".join(repr(v.item()) for v in col[i]) for col in cols) for i in range(n)
        ]
        body = ("\n".join(rows) + "\n").encode()
    elif data == "binary":
        body = b"".join(b"".join(col[i].tobytes() for col in cols) for i in range(n))
    else:  # column-major, LZF, sizes first
        raw = np.frombuffer(b"".join(col.tobytes() for col in cols), np.uint8)
        comp = lzf_compress(raw).tobytes()
        body = struct.pack("<II", len(comp), len(raw)) + comp
    label, out = draw(broken(header + body, head=len(header)))
    return f"pcd {data} {width}x{height} {[f[0] for f in fields]}: {label}", "in.pcd", out


# ----------------------------------------------------------------------------- LAS / LAZ

_LAS_VERSIONS = {0: "1.2", 1: "1.2", 2: "1.2", 3: "1.2", 4: "1.3", 5: "1.3"}
_WKT = (
    'PROJCS["NAD83 / Oregon GIC Lambert (ft)",GEOGCS["NAD83",DATUM["North_American_Datum_1983",'
    'SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",'
    '0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic_2SP"],UNIT["foot",0.3048]]'
)
# the public header block's fields: name, offset, struct code
_LAS_FIELDS = [
    (name, int(at), code)
    for name, at, code in (
        row.strip().rsplit(" ", 2)
        for row in """header size 94 <H
            offset to points 96 <I
            number of VLRs 100 <I
            point format 104 <B
            record length 105 <H
            legacy point count 107 <I
            x scale 131 <d
            z scale 147 <d
            x offset 155 <d
            max x 179 <d
            EVLR start 235 <Q
            EVLR count 243 <I
            point count 247 <Q""".split("\n")
    )
]
_LAS_EXTRAS = [("a", "u1"), ("b", "i2"), ("c", "u4"), ("d", "f4"), ("e", "f8"), ("f", "3f4")]
_EDGE_INTS = [0, 1, 2, 3, 7, 11, 94, 227, 375, 2**15, 2**16 - 1, 2**31, 2**32 - 1, 2**63]
_EDGE_FLOATS = [0.0, -0.001, 1e-300, 1e300, float("nan"), float("inf"), 1e-9]


def _las_file(draw, compress: bool) -> tuple[bytes, str]:
    import laspy

    pf = draw(st.integers(0, 10))
    version = _LAS_VERSIONS.get(pf, "1.4")
    if draw(st.booleans()) and pf <= 5:
        version = "1.4"
    n = draw(st.integers(1, 120))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    h = laspy.LasHeader(point_format=pf, version=version)
    h.scales = np.array(draw(st.sampled_from([[0.01] * 3, [0.001, 0.001, 0.0001], [1.0] * 3])))
    h.offsets = np.array(draw(st.sampled_from([[0.0] * 3, [5e5, 5e6, 100.0]])))
    extras = draw(st.lists(st.sampled_from(_LAS_EXTRAS), max_size=3, unique=True))
    if draw(st.booleans()):
        extras = [("nx", "f4"), ("ny", "f4"), ("nz", "f4"), *extras]
    h.add_extra_dims([laspy.ExtraBytesParams(name=name, type=t) for name, t in extras])
    crs = draw(st.sampled_from(["none", "wkt", "geokeys", "evlr", "junk"]))
    if crs == "wkt":
        h.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(_WKT))
    elif crs == "geokeys":
        keys = laspy.vlrs.known.GeoKeyDirectoryVlr()
        keys.parse_record_data(struct.pack("<12H", 1, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 2992))
        h.vlrs.append(keys)
    elif crs == "junk":
        h.vlrs.append(laspy.VLR("LASF_Projection", 2112, "not WKT", b"\xff\x00garbage"))
    las = laspy.LasData(h)
    las.X = rng.integers(-(2**20), 2**20, n)
    las.Y = rng.integers(-(2**20), 2**20, n)
    las.Z = rng.integers(-(2**16), 2**16, n)
    las.intensity = rng.integers(0, 65535, n)
    las.classification = rng.integers(0, 20 if pf < 6 else 255, n)
    las.return_number = rng.integers(1, 4, n)
    las.number_of_returns = np.maximum(las.return_number, rng.integers(1, 4, n))
    if "red" in las.point_format.dimension_names:
        las.red, las.green, las.blue = (rng.integers(0, 65535, n) for _ in range(3))
    if crs == "evlr" and version == "1.4":
        las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.known.WktCoordinateSystemVlr(_WKT)])
    buf = io.BytesIO()
    las.write(buf, do_compress=compress)
    return buf.getvalue(), f"pf {pf} v{version} {extras} crs {crs}"


@st.composite
def _las_broken(draw, compress: bool) -> tuple[str, str, bytes]:
    data, what = _las_file(draw, compress)
    points = struct.unpack_from("<I", data, 96)[0]
    kind = draw(st.sampled_from(["field", "field", "records", "cut", "none", "points"]))
    if kind == "field":
        name, at, code = draw(st.sampled_from(_LAS_FIELDS))
        value = draw(st.sampled_from(_EDGE_FLOATS if code == "<d" else _EDGE_INTS))
        if code != "<d":
            value %= 256 ** struct.calcsize(code)
        raw = bytearray(data)
        struct.pack_into(code, raw, at, value)
        label, data = f"{name} = {value}", bytes(raw)
    elif kind == "records" and not compress:  # anywhere: the VLRs and the points
        label, data = draw(broken(data))
    elif kind in ("records", "points"):  # LAZ: the VLRs, or the compressed points
        # the points: the chunk table's offset (their first 8 bytes), the chunks, the table (the
        # file's last bytes), whose sizes lazrs allocates by (an abort, were they not checked)
        lo, hi = (227, points - 1) if kind == "records" else (points, len(data) - 1)
        ends = st.sampled_from([lo, lo + 4, hi - 8, hi - 4, hi])
        spots = draw(st.lists(st.integers(lo, max(lo, hi)) | ends, min_size=1, max_size=4))
        raw = bytearray(data)
        for at in spots:
            raw[min(at, len(raw) - 1)] = draw(st.integers(0, 255))
        label, data = f"{kind} bytes {spots} overwritten", bytes(raw)
    elif kind == "cut":
        at = draw(st.integers(0, len(data) - 1))
        label, data = f"cut at {at}", data[:at]
    else:
        label = "intact"
    return (
        f"{'laz' if compress else 'las'} {what}: {label}",
        ("in.laz" if compress else "in.las"),
        data,
    )


def las_case() -> st.SearchStrategy:
    """Generated LAS files, maybe broken."""
    return _las_broken(False)


def laz_case() -> st.SearchStrategy:
    """Generated LAZ files, maybe broken (their chunk table too)."""
    return _las_broken(True)


# ----------------------------------------------------------------------------- E57

_CRC32C = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0x82F63B78 if _c & 1 else _c >> 1
    _CRC32C.append(_c)


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli), the checksum of every E57 page."""
    c = 0xFFFFFFFF
    for x in data:
        c = _CRC32C[(c ^ x) & 0xFF] ^ (c >> 8)
    return c ^ 0xFFFFFFFF


def e57_pages(logical: bytes) -> bytes:
    """E57's physical bytes of ``logical`` bytes: pages of 1020 bytes and their CRC-32C."""
    out = bytearray()
    for i in range(0, len(logical), 1020):
        page = logical[i : i + 1020].ljust(1020, b"\0")
        out += page + struct.pack(">I", crc32c(page))
    return bytes(out)


@st.composite
def e57_case(draw, folder=None) -> tuple[str, str, bytes]:
    """A generated E57 file of one to three scans, maybe broken: (label, name, bytes)."""
    import os
    import tempfile

    import pye57

    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    scans = draw(st.integers(1, 3))
    fd, path = tempfile.mkstemp(suffix=".e57")
    os.close(fd)
    os.unlink(path)
    try:
        e = pye57.E57(path, mode="w")
        for k in range(scans):
            rows, cols = draw(st.integers(1, 8)), draw(st.integers(1, 8))
            n = rows * cols
            scan = {c: rng.normal(size=n) * 10 for c in ("cartesianX", "cartesianY", "cartesianZ")}
            if draw(st.booleans()):
                scan["intensity"] = rng.random(n)
            if draw(st.booleans()):
                for c in ("colorRed", "colorGreen", "colorBlue"):
                    scan[c] = rng.integers(0, 256, n).astype(np.uint8)
            if draw(st.booleans()):
                scan["rowIndex"] = np.repeat(np.arange(rows), cols).astype(np.int32)
                scan["columnIndex"] = np.tile(np.arange(cols), rows).astype(np.int32)
            if draw(
                st.booleans()
            ):  # some points flagged invalid, never all (pye57 cannot write that)
                flags = rng.random(n) < 0.2
                flags[0] = False
                scan["cartesianInvalidState"] = flags.astype(np.int8)
            pose = {}
            if draw(st.booleans()):
                pose["translation"] = rng.normal(size=3) * 100
            e.write_scan_raw(scan, name=f"scan{k}", **pose)
        e.close()
        with open(path, "rb") as f:
            raw = f.read()
    finally:
        if os.path.exists(path):
            os.unlink(path)
    logical = bytearray(b"".join(raw[i : i + 1020] for i in range(0, len(raw), 1024)))
    xml_at, xml_len = struct.unpack_from("<QQ", raw, 24)
    kind = draw(st.sampled_from(["none", "logical", "xml", "header", "cut"]))
    label = "intact"
    if kind == "logical":
        spots = draw(st.lists(st.integers(0, len(logical) - 1), min_size=1, max_size=5))
        for at in spots:
            logical[at] = draw(st.integers(0, 255))
        label = f"bytes {spots} overwritten"
    elif kind == "xml":  # printable bytes in the XML section, where the structure is
        lo = xml_at - (xml_at // 1024) * 4
        spots = draw(st.lists(st.integers(lo, lo + xml_len - 1), min_size=1, max_size=3))
        for at in spots:
            logical[at] = draw(st.integers(32, 126))
        label = f"XML bytes {spots} overwritten"
    elif kind == "header":
        at = draw(st.sampled_from([8, 12, 16, 24, 32, 40]))
        code = "<Q" if at >= 16 else "<I"
        value = draw(st.sampled_from(_EDGE_INTS)) % 256 ** struct.calcsize(code)
        struct.pack_into(code, logical, at, value)
        label = f"header field at {at}"
    data = e57_pages(bytes(logical))
    if kind == "cut":
        at = draw(st.integers(0, len(data) - 1))
        data, label = data[:at], f"cut at {at}"
    return f"e57 {scans} scans: {label}", "in.e57", data


# ----------------------------------------------------------------------------- OBJ / OFF / STL

_NUMBER = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False).map(repr),
    st.integers(-5, 5).map(str),
    st.sampled_from(["1e-30", "-0", "0.", ".5", "1E3", "nan", "inf", "1e400", "0x1", "--1"]),
)


@st.composite
def obj_case(draw) -> tuple[str, str, bytes]:
    """A generated OBJ file, maybe broken: (label, name, bytes)."""
    nv = draw(st.integers(0, 12))
    lines = []
    for _ in range(nv):
        extra = draw(st.sampled_from([0, 0, 0, 1, 3]))
        lines.append("v " + " ".join(draw(_NUMBER) for _ in range(3 + extra)))
    nn = draw(st.integers(0, 3))
    lines += ["vn " + " ".join(draw(_NUMBER) for _ in range(3)) for _ in range(nn)]
    nt = draw(st.integers(0, 3))
    lines += ["vt " + " ".join(draw(_NUMBER) for _ in range(2)) for _ in range(nt)]
    for _ in range(draw(st.integers(0, 8))):
        k = draw(st.integers(1, 6))
        form = draw(st.sampled_from(["{v}", "{v}/{t}", "{v}//{n}", "{v}/{t}/{n}"]))
        corners = []
        for _ in range(k):
            v = draw(st.integers(-nv - 1, nv + 1))
            corners.append(
                form.format(v=v, t=draw(st.integers(-nt, nt + 1)), n=draw(st.integers(-nn, nn + 1)))
            )
        lines.append("f " + " ".join(corners))
    others = ["# a comment", "o thing", "g group", "s off", "usemtl red", "mtllib a.mtl", "l 1 2"]
    for _ in range(draw(st.integers(0, 3))):
        at = draw(st.integers(0, len(lines)))
        lines.insert(at, draw(st.sampled_from([*others, "p 1", "v", "f", "\\", "x y z"])))
    end = draw(st.sampled_from(["\n", "\r\n"]))
    text = end.join(lines) + draw(st.sampled_from(["", end]))
    label, data = draw(broken(text.encode(), head=len(text.encode())))
    return f"obj {nv} vertices: {label}", "in.obj", data


@st.composite
def off_case(draw) -> tuple[str, str, bytes]:
    """A generated OFF file, maybe broken: (label, name, bytes)."""
    nv = draw(st.integers(0, 10))
    nf = draw(st.integers(0, 6))
    colour = draw(st.booleans())
    head = draw(st.sampled_from(["OFF", "COFF" if colour else "OFF", "NOFF", "OFF BINARY", "4OFF"]))
    lines = [head, f"{nv} {nf} 0"] if draw(st.booleans()) else [f"{head} {nv} {nf} 0"]
    for _ in range(nv):
        lines.append(" ".join(draw(_NUMBER) for _ in range(3 + (4 if colour else 0))))
    for _ in range(nf):
        k = draw(st.integers(0, 6))
        idx = [str(draw(st.integers(-1, nv))) for _ in range(k)]
        tail = draw(st.sampled_from([[], ["255", "0", "0"], ["0.5", "0.5", "0.5", "1"]]))
        lines.append(" ".join([str(draw(st.sampled_from([k, k, k + 1, 0]))), *idx, *tail]))
    for _ in range(draw(st.integers(0, 2))):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["# c", "", "  "])))
    text = "\n".join(lines) + "\n"
    label, data = draw(broken(text.encode(), head=len(text.encode())))
    return f"off {head} {nv}/{nf}: {label}", "in.off", data


@st.composite
def stl_case(draw) -> tuple[str, str, bytes]:
    """A generated binary STL file, maybe broken: (label, name, bytes)."""
    nf = draw(st.integers(0, 8))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    tris = rng.normal(size=(nf, 3, 3)).astype(np.float32)
    if nf and draw(st.booleans()):  # shared corners, so that faces weld into a mesh
        tris[1:, 0] = tris[0, 0]
    if draw(st.booleans()):
        lines = ["solid " + draw(st.sampled_from(["", "name", "a b c"]))]
        for t in tris:
            lines += ["facet normal 0 0 1", "outer loop"]
            lines += ["vertex " + " ".join(repr(float(v)) for v in c) for c in t]
            lines += ["endloop", "endfacet"]
        lines.append("endsolid")
        text = "\n".join(lines) + "\n"
        label, data = draw(broken(text.encode(), head=len(text.encode())))
        return f"stl ascii {nf}: {label}", "in.stl", data
    head = draw(st.sampled_from([b"\0" * 80, b"solid binary but not text".ljust(80, b" ")]))
    count = draw(st.sampled_from([nf, nf, nf + 1, max(nf - 1, 0), 2**32 - 1]))
    body = b"".join(struct.pack("<3f", 0, 0, 1) + t.tobytes() + b"\0\0" for t in tris)
    label, data = draw(broken(head + struct.pack("<I", count) + body))
    return f"stl binary {nf} (count {count}): {label}", "in.stl", data


READERS = {
    "pcd": pcd_case,
    "las": las_case,
    "laz": laz_case,
    "e57": e57_case,
    "obj": obj_case,
    "off": off_case,
    "stl": stl_case,
}


# ----------------------------------------------------------------------------- the oracle


def check_case(path, label: str) -> bool:
    """Read ``path``: a valid object or one InputError line naming it, in time; True when read."""
    faulthandler.dump_traceback_later(CASE_SECONDS * 6, exit=True)
    t0 = time.perf_counter()
    try:
        obj = load(str(path))
    except InputError as exc:
        msg = str(exc)
        assert "\n" not in msg, f"{label}: message on several lines: {msg!r}"
        assert msg.startswith(f"{path}: "), f"{label}: message does not name the file: {msg!r}"
        return False
    finally:
        faulthandler.cancel_dump_traceback_later()
        took = time.perf_counter() - t0
        assert took < CASE_SECONDS, f"{label}: {took:.1f} s"
    pts = np.asarray(obj.points)
    assert pts.ndim == 2 and pts.shape[1] == 3 and np.isfinite(pts).all(), label
    if isinstance(obj, TriangleMesh):
        assert obj.faces.dtype == np.int64 and obj.faces.ndim == 2 and obj.faces.shape[1] == 3
        assert len(obj.faces) == 0 or 0 <= obj.faces.min() <= obj.faces.max() < len(pts), label
    return True


def fuzz_reader(reader: str, examples: int, folder, capfd) -> dict:
    """``examples`` cases of ``reader`` read, one in five also through ``recon convert``."""
    counts = {"read": 0, "refused": 0}
    cli = folder / "cli"
    cli.mkdir()

    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        derandomize=examples <= QUICK,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(case=READERS[reader](), via_cli=st.integers(0, 9))
    def run(case, via_cli):
        label, name, data = case
        path = folder / name
        path.write_bytes(data)
        counts["read" if check_case(path, label) else "refused"] += 1
        if via_cli < 2:  # drawn, so that a failing case shrinks the same way
            capfd.readouterr()  # what the reader said (its warnings) when read above
            # to PLY, or back to the reader's own format (its writer's turn)
            out = "out.ply" if via_cli == 0 else "out" + path.suffix
            for left in cli.iterdir():  # a failed case's, while hypothesis shrinks it
                left.unlink()
            convert_broken_files([(label, name, data)], cli, capfd, True, out)

    run()
    return counts


@pytest.mark.parametrize("reader", sorted(READERS))
def test_generated_files_read_or_refused_in_one_line(reader, tmp_path, capfd):
    """:data:`QUICK` generated files a reader: each read, or refused in one line."""
    counts = fuzz_reader(reader, QUICK, tmp_path, capfd)
    assert sum(counts.values()) >= QUICK


@pytest.mark.fuzz
@pytest.mark.parametrize("reader", sorted(READERS))
def test_fuzz_generated_files(reader, tmp_path, capfd):
    """:data:`FUZZ` generated files a reader; some read and some refused."""
    counts = fuzz_reader(reader, FUZZ, tmp_path, capfd)
    assert sum(counts.values()) >= FUZZ
    assert counts["read"] > 0 and counts["refused"] > 0, counts
