"""Fuzz of the PLY reader with broken files: every case is read right or refused in one line.

Small PLY files whose content is known exactly (clouds and meshes; ASCII, little- and
big-endian; list count types from uchar to uint; triangles and quads) are broken in seeded,
reproducible ways: truncated at many offsets, element counts and property types changed in
the header, list counts set to their type's limits, ASCII tokens deleted, inserted, split
across lines or replaced by NaN, infinities and out-of-range numbers. For each case the
reader either returns a valid object or raises one :class:`InputError` whose one line names
the file; a traceback of any other kind, or a NumPy warning (pytest turns them into errors),
fails the test. Mutations that must be refused (a truncated binary body, a token too many or
too few in an ASCII row, an impossible list count) are asserted to be refused.

A sample of the cases goes through the CLI (``recon convert``) in-process: exit 0 with no
message, or exit 2 with exactly one stderr line naming the file; the output that existed
before is untouched and no temporary file is left.
"""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh
from recon_cli.io.load import load

from fuzz_checks import convert_broken_files

# ----------------------------------------------------------------------------- base files

PTS = np.array(
    [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 0.5],
        [0.25, 0.5, 2.0],
    ]
)
NRM = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 0, -1], [0, -1, 0], [-1, 0, 0]], dtype=float)
RGB = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30], [40, 50, 60], [70, 80, 90]])
TRIS = [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]
QUAD = [1, 4, 5, 2]

_PACK = {
    "float": "f",
    "double": "d",
    "uchar": "B",
    "char": "b",
    "ushort": "H",
    "short": "h",
    "uint": "I",
    "int": "i",
}


def _header(fmt: str, elements: list[tuple[str, int, list[str]]]) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment fuzz base"]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {p}" for p in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode()


def cloud_file(fmt: str) -> bytes:
    """6 points with float xyz, float normals and uchar colours."""
    props = [
        "float x",
        "float y",
        "float z",
        "float nx",
        "float ny",
        "float nz",
        "uchar red",
        "uchar green",
        "uchar blue",
    ]
    head = _header(fmt, [("vertex", len(PTS), props)])
    if fmt == "ascii":
        rows = [
            " ".join(
                [
                    *(f"{v:g}" for v in PTS[i]),
                    *(f"{v:g}" for v in NRM[i]),
                    *(str(c) for c in RGB[i]),
                ]
            )
            for i in range(len(PTS))
        ]
        return head + ("\n".join(rows) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(order + "6f3B", *PTS[i], *NRM[i], *RGB[i]) for i in range(len(PTS)))
    return head + body


def mesh_file(
    fmt: str, count_type: str = "uchar", index_type: str = "int", quad: bool = True
) -> bytes:
    """6 double vertices, 4 triangles and (``quad``) one quad; faces carry a uchar ``flag``."""
    faces = TRIS + ([QUAD] if quad else [])
    head = _header(
        fmt,
        [
            ("vertex", len(PTS), ["double x", "double y", "double z"]),
            ("face", len(faces), [f"list {count_type} {index_type} vertex_indices", "uchar flag"]),
        ],
    )
    if fmt == "ascii":
        vrows = [" ".join(f"{v:g}" for v in p) for p in PTS]
        frows = [" ".join([str(len(f)), *map(str, f), str(7)]) for f in faces]
        return head + ("\n".join(vrows + frows) + "\n").encode()
    o = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(o + "3d", *p) for p in PTS)
    for f in faces:
        body += struct.pack(o + _PACK[count_type], len(f)) + struct.pack(
            o + _PACK[index_type] * len(f), *f
        )
        body += struct.pack(o + "B", 7)
    return head + body


BASES = {
    "cloud-ascii": cloud_file("ascii"),
    "cloud-le": cloud_file("binary_little_endian"),
    "cloud-be": cloud_file("binary_big_endian"),
    "mesh-ascii": mesh_file("ascii"),
    "mesh-ascii-tri": mesh_file("ascii", quad=False),
    "mesh-le": mesh_file("binary_little_endian"),
    "mesh-be-ushort": mesh_file("binary_big_endian", "ushort"),
    "mesh-le-uint": mesh_file("binary_little_endian", "uint", "uint"),
    "mesh-le-uint-tri": mesh_file("binary_little_endian", "uint", "int", quad=False),
    "mesh-le-float-index": mesh_file("binary_little_endian", "uchar", "float"),
}


def _body_start(data: bytes) -> int:
    return data.index(b"end_header\n") + len(b"end_header\n")


def _expected_faces(quad: bool) -> np.ndarray:
    f = [*TRIS] + ([[QUAD[0], QUAD[1], QUAD[2]], [QUAD[0], QUAD[2], QUAD[3]]] if quad else [])
    return np.array(f)


# ----------------------------------------------------------------------------- the oracle


def _read(path) -> tuple[object | None, str | None]:
    """(object, None) or (None, message) for an InputError; anything else propagates."""
    try:
        return load(path), None
    except InputError as exc:
        return None, str(exc)


def _check(path, label: str, must_fail: bool) -> bool:
    """Read ``path``: a valid object or a one-line InputError naming it.

    Read ``path``: a valid object or a one-line InputError naming it. Returns whether it was
    read.
    """
    obj, msg = _read(path)
    if msg is not None:
        assert "\n" not in msg, f"{label}: message on several lines: {msg!r}"
        assert msg.startswith(f"{path}: "), f"{label}: message does not name the file: {msg!r}"
        return False
    assert not must_fail, f"{label}: accepted a file that must be refused"
    pts = np.asarray(obj.points)
    assert pts.ndim == 2 and pts.shape[1] == 3 and np.isfinite(pts).all(), label
    if isinstance(obj, TriangleMesh):
        assert obj.faces.dtype == np.int64 and obj.faces.shape[1] == 3, label
        assert obj.faces.min() >= 0 and obj.faces.max() < len(pts), label
    return True


def test_bases_read_exactly(tmp_path):
    """Each base PLY file, before any breakage, reads back exactly."""
    for name, data in BASES.items():
        p = tmp_path / f"{name}.ply"
        p.write_bytes(data)
        obj = load(p)
        np.testing.assert_array_equal(np.asarray(obj.points, dtype=float), PTS, err_msg=name)
        if name.startswith("cloud"):
            np.testing.assert_array_equal(np.asarray(obj.normals, dtype=float), NRM, err_msg=name)
            np.testing.assert_array_equal(obj.colors, RGB, err_msg=name)
        else:
            np.testing.assert_array_equal(
                obj.faces, _expected_faces("tri" not in name), err_msg=name
            )


# ----------------------------------------------------------------------------- mutations


def _truncations(data: bytes, rng) -> list[int]:
    start = _body_start(data)
    offsets = set(range(0, min(len(data), 40))) | {start - 1, start, start + 1, len(data) - 1}
    offsets |= set(rng.integers(0, len(data), 60).tolist())
    return sorted(o for o in offsets if o < len(data))


@pytest.mark.parametrize("name", sorted(BASES))
def test_truncations_refused(tmp_path, name):
    """Each base file cut short is refused; an ASCII cut inside its last number may read."""
    data = BASES[name]
    rng = np.random.default_rng(1)
    ascii_ = b"format ascii" in data
    last_token = len(data.rstrip()) - len(data.rstrip().split()[-1])
    p = tmp_path / "t.ply"
    for off in _truncations(data, rng):
        p.write_bytes(data[:off])
        # an ASCII cut inside the last number leaves a shorter valid number: cannot be told
        must_fail = not ascii_ or off <= last_token
        _check(p, f"{name} cut at {off}", must_fail=must_fail)


def _header_mutations(data: bytes) -> list[tuple[str, bytes, bool]]:
    """(label, mutated file, must fail)."""
    start = _body_start(data)
    head, body = data[:start].decode(), data[start:]
    out = []
    for m in re.finditer(r"element (\w+) (\d+)", head):
        n = int(m.group(2))
        for new, fail in (
            (n + 1, True),
            (n - 1, False),
            (0, False),
            (n * 1000, True),
            (2**31, True),
            (2**63, True),
            (-1, True),
        ):
            h = head[: m.start(2)] + str(new) + head[m.end(2) :]
            out.append((f"{m.group(1)} count {new}", h.encode() + body, fail))
    types = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double"]
    for m in re.finditer(r"property (?:list (\w+) )?(\w+) (\w+)", head):
        for t in types:
            for grp in (1, 2):
                if m.group(grp) is None or m.group(grp) == t:
                    continue
                h = head[: m.start(grp)] + t + head[m.end(grp) :]
                out.append((f"{m.group(3)} type {m.group(grp)}->{t}", h.encode() + body, False))
    return out


@pytest.mark.parametrize("name", sorted(BASES))
def test_header_count_and_type_mutations(tmp_path, name):
    """Header counts and types changed: read as valid data, or refused when they must be."""
    p = tmp_path / "h.ply"
    for label, data, must_fail in _header_mutations(BASES[name]):
        p.write_bytes(data)
        _check(p, f"{name}: {label}", must_fail)


_LIMITS = {
    "uchar": (1, "B", [0, 1, 2, 255]),
    "ushort": (2, "H", [0, 2, 65535]),
    "uint": (4, "I", [0, 2, 2**31 - 1, 2**31, 4_000_000_000, 2**32 - 1]),
}


@pytest.mark.parametrize(
    "name", [n for n in sorted(BASES) if n.startswith("mesh-") and "ascii" not in n]
)
def test_binary_list_counts_at_type_limits(tmp_path, name):
    """The count of the first, a middle and the last face set to 0, 1, 2 and the type's maximum."""
    data = BASES[name]
    ctype = re.search(rb"property list (\w+)", data).group(1).decode()
    itype = re.search(rb"property list \w+ (\w+)", data).group(1).decode()
    size, code, values = _LIMITS[ctype]
    order = ">" if b"big_endian" in data else "<"
    isize = struct.calcsize(_PACK[itype])
    # byte offsets of each face's count
    pos = _body_start(data) + 24 * len(PTS)
    starts = []
    for f in TRIS + ([QUAD] if "tri" not in name else []):
        starts.append(pos)
        pos += size + isize * len(f) + 1
    p = tmp_path / "l.ply"
    for which in (0, len(starts) // 2, len(starts) - 1):
        for v in values:
            mutated = bytearray(data)
            mutated[starts[which] : starts[which] + size] = struct.pack(order + code, v)
            p.write_bytes(bytes(mutated))
            # 0, 1, 2 vertices are never a face; a huge count overruns the file
            _check(p, f"{name}: face {which} count {v}", must_fail=True)


def _ascii_token_mutations(data: bytes, rng) -> list[tuple[str, bytes, bool]]:
    start = _body_start(data)
    head, body = data[:start], data[start:].decode()
    lines = body.split("\n")
    spots = [(i, j) for i, ln in enumerate(lines) for j in range(len(ln.split()))]
    out = []
    for i, j in spots:
        toks = lines[i].split()
        # one token too few / too many on a row: must be refused
        dele = lines[:i] + [" ".join(toks[:j] + toks[j + 1 :])] + lines[i + 1 :]
        out.append((f"line {i} token {j} deleted", head + "\n".join(dele).encode(), True))
        ins = lines[:i] + [" ".join(toks[:j] + ["3"] + toks[j:])] + lines[i + 1 :]
        out.append((f"line {i} token 3 inserted at {j}", head + "\n".join(ins).encode(), True))
        if 0 < j:
            split = lines[:i] + [" ".join(toks[:j]), " ".join(toks[j:])] + lines[i + 1 :]
            out.append((f"line {i} split before token {j}", head + "\n".join(split).encode(), True))
    # one row's value moved to the end of the previous row (both rows wrong, counts add up)
    for i in range(1, len(lines) - 1):
        a, b = lines[i - 1].split(), lines[i].split()
        if a and b:
            shifted = lines[: i - 1] + [" ".join(a + b[:1]), " ".join(b[1:])] + lines[i + 1 :]
            out.append((f"line {i} first token moved up", head + "\n".join(shifted).encode(), True))
    for word in (
        "nan",
        "inf",
        "-inf",
        "1e400",
        "-1e400",
        "3.5e38",
        "-1",
        "1.5",
        "x",
        "0x10",
        "4294967296",
        "1e20",
    ):
        for i, j in [
            spots[k] for k in rng.choice(len(spots), size=min(12, len(spots)), replace=False)
        ]:
            toks = lines[i].split()
            toks[j] = word
            rep = lines[:i] + [" ".join(toks)] + lines[i + 1 :]
            out.append((f"line {i} token {j} -> {word}", head + "\n".join(rep).encode(), False))
    out.append(("an extra row at the end", data + b"1 2 3\n", True))
    out.append(("blank lines", head + body.replace("\n", "\n\n").encode(), False))
    out.append(("CRLF rows", head + body.replace("\n", "\r\n").encode(), False))
    return out


@pytest.mark.parametrize("name", [n for n in sorted(BASES) if "ascii" in n])
def test_ascii_token_mutations(tmp_path, name):
    """ASCII tokens replaced: read as valid data, or refused when they must be."""
    rng = np.random.default_rng(2)
    p = tmp_path / "a.ply"
    for label, data, must_fail in _ascii_token_mutations(BASES[name], rng):
        p.write_bytes(data)
        read = _check(p, f"{name}: {label}", must_fail)
        if label in ("blank lines", "CRLF rows"):
            assert read, f"{name}: {label} refused"
            np.testing.assert_array_equal(np.asarray(load(p).points, dtype=float), PTS)


def test_ascii_row_error_names_the_line(tmp_path):
    """An ASCII row with an extra value is refused, naming its line."""
    data = BASES["cloud-ascii"].replace(b"\n1 0 0 0 1 0 0 255 0\n", b"\n1 0 0 0 1 0 0 255 0 9\n")
    p = tmp_path / "extra.ply"
    p.write_bytes(data)
    with pytest.raises(
        InputError, match=r"extra\.ply: line 16: 'vertex' row 1 has 10 values, expected 9"
    ):
        load(p)


def test_uint_list_count_near_4e9_in_first_row(tmp_path):
    """A face list count of 4e9 in the first row is "truncated", without allocating for it."""
    data = bytearray(BASES["mesh-le-uint"])
    pos = _body_start(bytes(data)) + 24 * len(PTS)
    data[pos : pos + 4] = struct.pack("<I", 4_000_000_000)
    p = tmp_path / "huge.ply"
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"huge\.ply: truncated"):
        load(p)


def test_nan_face_index_refused_without_warning(tmp_path):
    """A NaN float face index is refused in one line, with no numpy warning."""
    data = bytearray(BASES["mesh-le-float-index"])
    pos = _body_start(bytes(data)) + 24 * len(PTS) + 1
    data[pos : pos + 4] = struct.pack("<f", float("nan"))
    p = tmp_path / "nanface.ply"
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"nanface\.ply: face index nan is not a whole number"):
        load(p)


# ----------------------------------------------------------------------------- through the CLI


def test_cli_on_broken_files_one_line_and_output_untouched(tmp_path, capfd):
    """``recon convert`` of broken PLY files: one line, the output untouched."""
    rng = np.random.default_rng(3)
    cases = []
    for name in sorted(BASES):
        data = BASES[name]
        cases += [
            (f"{name} cut {o}", data[:o])
            for o in rng.choice(_truncations(data, rng), 4, replace=False)
        ]
        cases += [(f"{name} {label}", d) for label, d, _ in _header_mutations(data)[::9]]
        if "ascii" in name:
            cases += [
                (f"{name} {label}", d) for label, d, _ in _ascii_token_mutations(data, rng)[::7]
            ]
    codes = convert_broken_files([(label, "in.ply", d) for label, d in cases], tmp_path, capfd)
    assert codes[2] > 0.5 * len(cases)
