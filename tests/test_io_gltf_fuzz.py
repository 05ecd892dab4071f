"""Fuzz of the glTF reader, as tests/test_io_fuzz.py fuzzes the PLY one.

Small files whose content is known (a mesh with normals, colours, attributes and face
attributes at a large offset; a cloud; the same as ``.gltf`` JSON; a file of strips, sparse
and quantized accessors) are broken in seeded, reproducible ways: truncated at many offsets,
chunk lengths changed, every JSON value replaced by values of other types and out-of-range
numbers, every JSON key deleted, bytes of the binary buffer flipped, random bytes after a
GLB header. Each case is read as a valid object or refused with one :class:`InputError` line
naming the file; any other exception, or a NumPy warning (pytest makes them errors), fails.
A sample goes through ``recon convert``: exit 0, or exit 2 with one stderr line naming the
file and the output that was there before left untouched.
"""

from __future__ import annotations

import copy
import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.gltf import decode_gltf, glb_bytes

from fuzz_checks import convert_broken_files
from gltf_checks import Builder
from gltf_checks import glb_join as _join
from gltf_checks import glb_split as _split
from shapes import cloud_family, mesh_family


def _mesh() -> TriangleMesh:
    m = mesh_family(1)  # normals, uint8 colours, an offset
    rng = np.random.default_rng(0)
    m.attributes = {
        "d": rng.random(len(m.vertices)),
        "c": np.arange(len(m.vertices), dtype=np.uint8),
    }
    m.face_attributes = {"f": np.arange(len(m.faces), dtype=np.int32)}
    m.history = ["fuzz base"]
    return m


def _gltf_json(obj) -> bytes:
    out: list[bytes] = []
    from recon_cli.io.gltf import emit_gltf

    emit_gltf(obj, lambda b: out.append(bytes(b)), binary=False)
    return b"".join(out)


def _strips_file() -> bytes:
    """Strips, a fan, a sparse accessor and quantized positions in one GLB."""
    b = Builder()
    corners = np.array([[0, 0, 0], [32767, 0, 0], [0, 32767, 0], [0, 0, 32767]], np.int16)
    q = b.accessor(corners, "VEC3", 5122, normalized=True)
    b.sparse(q, [2], np.array([[0, 16000, 16000]], np.int16))
    strip = b.accessor(np.array([0, 1, 2, 3], np.uint16), "SCALAR", 5123)
    fan = b.accessor(np.array([0, 1, 2, 3], np.uint32), "SCALAR", 5125)
    prims = [
        {"attributes": {"POSITION": q}, "indices": strip, "mode": 5},
        {"attributes": {"POSITION": q}, "indices": fan, "mode": 6},
    ]
    nodes = [{"children": [1], "translation": [1e6, 0, 0]}, {"mesh": 0, "scale": [2, 2, 2]}]
    return b.glb(b.doc([{"primitives": prims}], nodes, extensionsUsed=["KHR_mesh_quantization"]))


BASES = {
    "mesh.glb": glb_bytes(_mesh()),
    "cloud.glb": glb_bytes(cloud_family(1, 40)),
    "mesh.gltf": _gltf_json(mesh_family(3, np.float32)),
    "strips.glb": _strips_file(),
}


def _check(data: bytes, name: str, label: str, must_fail: bool = False) -> bool:
    """Read ``data``: a valid object or a one-line InputError naming the file; True when read."""
    try:
        obj = decode_gltf(data, name)[0]
    except InputError as exc:
        msg = str(exc)
        assert "\n" not in msg, f"{label}: message on several lines: {msg!r}"
        assert msg.startswith(f"{name}: "), f"{label}: message does not name the file: {msg!r}"
        return False
    assert not must_fail, f"{label}: accepted a file that must be refused"
    assert isinstance(obj, (PointCloud, TriangleMesh)), label
    pts = np.asarray(obj.points)
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 0, label
    if isinstance(obj, TriangleMesh):
        assert obj.faces.dtype == np.int64 and obj.faces.shape[1] == 3, label
        assert obj.faces.min() >= 0 and obj.faces.max() < len(pts), label
    return True


def test_bases_read():
    """Each base glTF/GLB file, before any breakage, reads."""
    for name, data in BASES.items():
        assert _check(data, name, name)


@pytest.mark.parametrize("name", sorted(BASES))
def test_truncations_refused(name):
    """Each base file cut at any byte is refused in one line."""
    data = BASES[name]
    rng = np.random.default_rng(1)
    offsets = set(range(0, min(len(data), 48))) | set(rng.integers(0, len(data), 80).tolist())
    for off in sorted(offsets | {len(data) - 1}):
        # a GLB declares its length; a cut JSON text is no longer JSON
        _check(data[:off], name, f"cut at {off}", must_fail=True)


def _leaves(obj, path=()):
    """Paths of every value of a JSON tree (containers too)."""
    yield path
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:6]):  # the first items of long arrays (min/max, URIs...)
            yield from _leaves(v, (*path, i))


def _set(doc, path, value):
    out = copy.deepcopy(doc)
    obj = out
    for k in path[:-1]:
        obj = obj[k]
    if value is _DELETE:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value
    return out


_DELETE = object()
_VALUES = [
    -1,
    0,
    1,
    2,
    3,
    7,
    2**31,
    2**63,
    10**30,
    1.5,
    1e308,
    -1e308,
    "x",
    None,
    True,
    [],
    {},
    [0],
    _DELETE,
]


@pytest.mark.parametrize("name", ["mesh.glb", "cloud.glb", "strips.glb"])
def test_every_json_value_replaced_or_deleted(name):
    """Every JSON value replaced or deleted: read or refused in one line, mostly refused."""
    doc, tail = _split(BASES[name])
    read = refused = 0
    for path in _leaves(doc):
        if not path or (path[0] == "buffers" and path[-1] == "uri"):
            continue
        for value in _VALUES:
            if value is _DELETE and isinstance(path[-1], int):
                continue
            label = f"{'.'.join(map(str, path))} -> {value if value is not _DELETE else 'deleted'}"
            if _check(_join(_set(doc, path, value), tail), name, label):
                read += 1
            else:
                refused += 1
    assert refused > read  # most of these are refused; none crashes


def test_gltf_json_values_replaced():
    """A .gltf's values and its data URI replaced: read or refused in one line."""
    doc = json.loads(BASES["mesh.gltf"])
    rng = np.random.default_rng(4)
    paths = [p for p in _leaves(doc) if p and p[-1] != "uri"]
    for k in rng.choice(len(paths), 60, replace=False):
        for value in _VALUES[::3]:
            if value is _DELETE and isinstance(paths[k][-1], int):
                continue
            data = json.dumps(_set(doc, paths[k], value)).encode()
            _check(data, "m.gltf", f"{paths[k]} -> {value}")
    uri = doc["buffers"][0]["uri"]
    for bad in (uri[:-8], uri + "!!", uri.replace(";base64", ""), "data:", uri[:40]):
        d = copy.deepcopy(doc)
        d["buffers"][0]["uri"] = bad
        _check(json.dumps(d).encode(), "m.gltf", f"uri {bad[:50]}", must_fail=True)


@pytest.mark.parametrize("name", ["mesh.glb", "strips.glb"])
def test_chunk_lengths_and_header_fields(name):
    """GLB header fields and chunk lengths changed: read or refused in one line."""
    data = BASES[name]
    jlen = struct.unpack_from("<I", data, 12)[0]
    spots = {
        "version": 4,
        "length": 8,
        "json length": 12,
        "json type": 16,
        "bin length": 20 + jlen,
        "bin type": 24 + jlen,
    }
    for label, at in spots.items():
        for v in (0, 1, 3, 4, jlen - 4, jlen + 4, len(data), 2**31, 2**32 - 1):
            raw = bytearray(data)
            raw[at : at + 4] = struct.pack("<I", v % 2**32)
            if bytes(raw) != data:
                _check(bytes(raw), name, f"{label} = {v}")


@pytest.mark.parametrize("name", ["mesh.glb", "cloud.glb", "strips.glb"])
def test_binary_buffer_bytes_flipped(name):
    """Bytes flipped in the binary chunk: read as finite data or refused in one line."""
    data = BASES[name]
    start = 20 + struct.unpack_from("<I", data, 12)[0] + 8
    rng = np.random.default_rng(5)
    for k in range(150):
        raw = bytearray(data)
        for at in rng.integers(start, len(data), 1 + k % 4):
            raw[at] = int(rng.integers(0, 256))
        _check(bytes(raw), name, f"flip {k}")


@settings(max_examples=150, deadline=None)
@given(
    data=st.binary(max_size=300),
    prefix=st.sampled_from([b"", b"glTF\x02\0\0\0", b'{"asset":{"version":"2.0"},']),
)
def test_random_bytes(data, prefix):
    """Random bytes, alone or after a GLB or JSON start: read or refused in one line."""
    raw = prefix + data
    if prefix[:4] == b"glTF" and len(raw) >= 12:  # a length that matches, so the chunks are parsed
        raw = raw[:8] + struct.pack("<I", len(raw)) + raw[12:]
    _check(raw, "r.glb", "random")


def test_cli_on_broken_files_one_line_and_output_untouched(tmp_path, capfd):
    """``recon convert`` of broken glTF files: one line, the output untouched."""
    rng = np.random.default_rng(3)
    cases = []
    for name, data in BASES.items():
        cases += [(f"{name} cut {o}", name, data[:o]) for o in rng.integers(0, len(data), 3)]
        if name.endswith(".glb"):
            doc, tail = _split(data)
            paths = [p for p in _leaves(doc) if p]
            for k in rng.choice(len(paths), 12, replace=False):
                value = _VALUES[int(rng.integers(0, len(_VALUES) - 1))]
                cases.append(
                    (f"{name} {paths[k]}={value}", name, _join(_set(doc, paths[k], value), tail))
                )
    codes = convert_broken_files(cases, tmp_path, capfd)
    assert codes[2] > 0.5 * len(cases)
