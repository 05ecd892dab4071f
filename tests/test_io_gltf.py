"""glTF reader/writer: exact round trips, large offsets, refusals, other tools' files, validator."""

from __future__ import annotations

import json
import struct
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, Sensor, TriangleMesh, bbox_diagonal
from recon_cli.io.gltf import decode_gltf, glb_bytes
from recon_cli.io.load import format_of, load, save, sniff

from gltf_checks import Builder, assert_valid, glb_join, glb_split, validate
from shapes import cloud_family, mesh_family, random_rotation
from shared_data import SHARED

RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def tetra(dtype=np.float64, **kw) -> TriangleMesh:
    """A closed tetrahedron in ``dtype``, with ``kw``'s normals, colours or attributes."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=dtype)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return TriangleMesh(vertices=v, faces=f, point_dtype=dtype, **kw)


def rich_mesh(seed=1) -> TriangleMesh:
    """A mesh at UTM-like offsets carrying every kind of value the writer encodes."""
    rng = np.random.default_rng(seed)
    m = mesh_family(seed)
    n, k = len(m.vertices), len(m.faces)
    m.vertices = m.vertices + [5.1e5, 5.1e6, 40.0]
    m.attributes = {
        "density": rng.random(n),  # float64 values float32 cannot hold: bits
        "quality": rng.random(n).astype(np.float32),
        "distance": np.where(rng.random(n) < 0.1, np.nan, rng.random(n)).astype(np.float32),
        "classification": rng.integers(0, 32, n).astype(np.uint8),
        "flag": rng.random(n) < 0.5,
        "intensity": rng.integers(0, 65536, n).astype(np.uint16),
        "offset": rng.integers(-30000, 30000, n).astype(np.int16),
        "count": rng.integers(0, 1000, n).astype(np.int64),  # float32 holds them
        "gps_time": 2.4e8 + rng.random(n) * 1e3,  # float64: bits
        "id": rng.integers(0, 2**62, n).astype(np.int64),  # bits
        "half": rng.random(n).astype(np.float16),
    }
    m.face_attributes = {
        "label": rng.integers(0, 2**31, k).astype(np.int32),
        "area": rng.random(k),
    }
    m.history = ["recon 0.1.0 poisson depth=8", "a second line"]
    m.obj_info = ["las_version 1.2"]
    return m


def assert_same(a, b, exact: bool = True) -> None:
    """Same kind, vertices (exactly or within the glTF bound), faces, colours, attributes."""
    assert type(a) is type(b)
    if exact:
        np.testing.assert_array_equal(b.points, a.points)
    else:
        bound = 1e-6 * bbox_diagonal(np.asarray(a.points, np.float64))
        assert np.abs(np.asarray(b.points, np.float64) - a.points).max() <= bound
    if isinstance(a, TriangleMesh):
        np.testing.assert_array_equal(b.faces, a.faces)
        assert sorted(b.face_attributes) == sorted(a.face_attributes)
        for k, v in a.face_attributes.items():
            assert b.face_attributes[k].dtype == v.dtype
            np.testing.assert_array_equal(b.face_attributes[k], v)
    assert (a.colors is None) == (b.colors is None)
    if a.colors is not None:
        assert b.colors.dtype == a.colors.dtype
        np.testing.assert_array_equal(b.colors, a.colors)
    if a.normals is not None:
        na = np.asarray(a.normals, np.float64)
        na = na / np.linalg.norm(na, axis=1, keepdims=True)
        assert np.abs(b.normals - na).max() < 1e-6
    assert sorted(b.attributes) == sorted(a.attributes)
    for k, v in a.attributes.items():
        assert b.attributes[k].dtype == v.dtype, k
        np.testing.assert_array_equal(b.attributes[k], v, err_msg=k)
    assert b.history == a.history


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_round_trip_of_every_value_kind(tmp_path, suffix):
    """A mesh with every kind of value through GLB and glTF: back in float64, with its records."""
    m = rich_mesh()
    save(m, tmp_path / f"m{suffix}")
    back = load(tmp_path / f"m{suffix}")
    assert_same(m, back, exact=False)
    assert back.point_dtype == np.float64 and back.obj_info == ["las_version 1.2"]


@pytest.mark.parametrize("seed", range(6))
def test_float32_meshes_and_clouds_come_back_bit_for_bit(tmp_path, seed):
    """float32 meshes, and clouds with a sensor, come back bit for bit through GLB."""
    m = mesh_family(seed, np.float32)
    save(m, tmp_path / "m.glb")
    back = load(tmp_path / "m.glb")
    assert back.vertices.dtype == np.float32
    assert_same(m, back)
    c = cloud_family(seed)
    c.points = c.points.astype(np.float32)
    c.point_dtype = np.float32
    c.sensors = [Sensor(position=(1.5, 2.5, 3.5), source="test scanner")]
    save(c, tmp_path / "c.glb")
    cb = load(tmp_path / "c.glb")
    assert_same(c, cb)
    assert cb.sensors == c.sensors


def test_float64_values_float32_holds_come_back_exact_and_double(tmp_path):
    """float64 values that float32 holds: no translation written, back exactly as float64."""
    m = tetra(np.float64)
    save(m, tmp_path / "t.glb")
    doc = _json_of((tmp_path / "t.glb").read_bytes())
    assert "translation" not in doc["nodes"][0]  # float32 values: no translation needed
    back = load(tmp_path / "t.glb")
    assert back.vertices.dtype == np.float64 and back.point_dtype == np.float64
    assert_same(m, back)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(3, 60),
    exponent=st.integers(-3, 7),
    scale=st.floats(1e-3, 1e4),
    points=st.booleans(),
)
def test_round_trip_random_meshes_offsets_and_rotations(seed, n, exponent, scale, points):
    """Random clouds and meshes at any offset and rotation come back within 1e-6 of the diagonal.

    Vertices come back within 1e-6 of the diagonal (float32 offsets plus a float64 node
    translation), whatever the offset (up to 1e7) and rotation; faces exactly.
    """
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3)) * scale
    v = v @ random_rotation(rng).T + rng.uniform(-1, 1, 3) * 10.0**exponent
    if points:
        obj: PointCloud | TriangleMesh = PointCloud(points=v)
    else:
        obj = TriangleMesh(vertices=v, faces=rng.integers(0, n, (2 * n, 3)))
    back = decode_gltf(glb_bytes(obj), "r.glb")[0]
    assert_same(obj, back, exact=False)
    err = np.abs(back.points - v).max()
    # float32 offsets from the centre: half a float32 unit of the half-extent, at most
    assert err <= 2.0**-24 * np.abs(v - 0.5 * (v.min(0) + v.max(0))).max() + 1e-9 * np.abs(v).max()


def test_offsets_of_1e6_keep_sub_millimetre_precision(tmp_path):
    """A 100 m mesh at state-plane coordinates (1e6) moves by under 1e-5 m (float32 alone: 0.06)."""
    m = mesh_family(3)
    v = m.vertices - m.vertices.min(0)
    m.vertices = v / np.ptp(v, axis=0).max() * 100.0 + [1.2e6, 4.5e6, 250.0]
    save(m, tmp_path / "utm.glb")
    back = load(tmp_path / "utm.glb")
    assert np.abs(back.vertices - m.vertices).max() < 1e-5
    assert np.abs(m.vertices.astype(np.float32) - m.vertices).max() > 0.01  # what float32 loses


def _autzen_mesh() -> TriangleMesh:
    """The shared LiDAR tile (US feet, state plane) as a mesh: Delaunay triangles of its points."""
    from scipy.spatial import Delaunay

    cloud = load(SHARED / "autzen_trim.laz")
    pts = np.asarray(cloud.points, np.float64)[::4]
    tri = Delaunay(pts[:, :2] - pts[:, :2].mean(0))
    return TriangleMesh(vertices=pts, faces=tri.simplices, obj_info=list(cloud.obj_info))


def test_lidar_tile_mesh_round_trip_within_a_thousandth_of_a_foot(tmp_path):
    """A mesh of the lidar tile at state-plane feet comes back within 1e-3 ft, its VLRs kept."""
    m = _autzen_mesh()
    assert np.abs(m.vertices).max() > 8e5  # state-plane feet
    save(m, tmp_path / "autzen.glb")
    back = load(tmp_path / "autzen.glb")
    assert np.array_equal(back.faces, m.faces)
    assert np.abs(back.vertices - m.vertices).max() <= 1e-3
    assert back.obj_info == m.obj_info  # the coordinate system (LAS VLRs) travels
    assert_valid(tmp_path / "autzen.glb")


def test_validator_passes_every_kind_of_file_we_write(tmp_path):
    """The Khronos validator passes every kind of GLB and glTF file we write."""
    files = []
    m = mesh_family(1, np.float32)  # normals and uint8 colours
    for name, obj in {
        "mesh": mesh_family(0),
        "colours8": m,
        "colours16": TriangleMesh(
            vertices=m.vertices, faces=m.faces, colors=(m.colors.astype(np.uint16) * 257)
        ),
        "colours_float_rgba": TriangleMesh(
            vertices=m.vertices,
            faces=m.faces,
            colors=np.column_stack([m.colors / 255.0, np.ones(len(m.colors))]).astype(np.float32),
        ),
        "attributes": rich_mesh(3),
        "large_offsets": rich_mesh(5),
        "float32": mesh_family(4, np.float32),
        "cloud": cloud_family(2),
        "cloud_float32": PointCloud(
            points=cloud_family(3).points.astype(np.float32),
            sensors=[Sensor(position=(1.5, 2.5, 3.5), source="test scanner")],
        ),
        "big_indices": TriangleMesh(
            vertices=np.random.default_rng(0).random((70_000, 3)),
            faces=np.arange(69_999).reshape(-1, 3),
        ),
    }.items():
        for suffix in (".glb", ".gltf"):
            save(obj, tmp_path / f"{name}{suffix}")
            files.append(tmp_path / f"{name}{suffix}")
    reports = validate(*files)
    assert len(reports) == len(files)
    for rep in reports:
        assert rep["errors"] == 0 and rep["warnings"] == 0, rep
    assert (
        _json_of((tmp_path / "big_indices.glb").read_bytes())["accessors"][-1]["componentType"]
        == 5125
    )  # uint32 past 65535 vertices


# ----------------------------------------------------------------------------- refusals on write


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        (
            TriangleMesh(
                vertices=np.array([[0, 0, 0], [1e39, 0, 0], [0, 1, 0.0]]), faces=[[0, 1, 2]]
            ),
            "more than 1e-06 of the bounding-box diagonal",
        ),
        (
            TriangleMesh(
                vertices=np.array([[0, 0, 0], [3e-42, 0, 0], [0, 5e-42, 0.0]]), faces=[[0, 1, 2]]
            ),
            "more than 1e-06 of the bounding-box diagonal",
        ),
        (
            tetra(normals=np.array([[0, 0, 1.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]])),
            "normal of vertex 1 is zero or not finite",
        ),
        (tetra(colors=np.full((4, 3), 1.5)), "float colours must be float32 values in 0..1"),
        (tetra(colors=np.full((4, 3), 70000, np.int32)), "outside 0..65535"),
        (tetra(attributes={"name": np.array(["a", "b", "c", "d"])}), "attribute 'name' of type"),
        (
            TriangleMesh(
                vertices=np.array([[0, 0, 0], [1, np.nan, 0], [0, 1, 0.0]]), faces=[[0, 1, 2]]
            ),
            "vertex 1 has a NaN or infinite coordinate",
        ),
        (TriangleMesh(vertices=np.zeros((3, 3)), faces=np.zeros((0, 3))), "a mesh with no faces"),
    ],
)
def test_what_gltf_cannot_hold_is_refused_and_nothing_written(tmp_path, obj, message):
    """What glTF cannot hold is refused in one line naming the output; the old file is kept."""
    out = tmp_path / "out.glb"
    out.write_bytes(b"before")
    with pytest.raises(ParameterError) as exc:
        save(obj, out)
    assert message in str(exc.value) and str(exc.value).startswith(f"{out}: ")
    assert out.read_bytes() == b"before" and sorted(p.name for p in tmp_path.iterdir()) == [
        "out.glb"
    ]


def test_non_unit_normals_are_scaled_with_a_warning(tmp_path, caplog):
    """Normals not of unit length are written scaled to unit length, with a warning."""
    m = tetra(normals=np.array([[0, 0, 2.0], [0, 3, 0], [1, 0, 0], [0, 1, 1]]))
    with caplog.at_level("WARNING", logger="recon"):
        save(m, tmp_path / "n.glb")
    assert "normals scaled to unit length" in caplog.text
    assert np.allclose(np.linalg.norm(load(tmp_path / "n.glb").normals, axis=1), 1, atol=1e-7)


# ----------------------------------------------------------------------------- other tools' files


SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], np.float32)


def _pos(b: Builder, v=SQUARE) -> int:
    return b.accessor(v, "VEC3", 5126, min=v.min(0).tolist(), max=v.max(0).tolist())


def test_strips_fans_and_shared_vertices_of_several_primitives():
    """Strips, fans and triangles sharing one vertex set become counter-clockwise triangles."""
    b = Builder()
    p = _pos(b)
    strip = b.accessor(np.array([0, 1, 3, 2, 5], np.uint16), "SCALAR", 5123)
    fan = b.accessor(np.array([0, 1, 2, 3], np.uint8), "SCALAR", 5121)
    tris = b.accessor(np.array([1, 4, 5], np.uint32), "SCALAR", 5125)
    prims = [
        {"attributes": {"POSITION": p}, "indices": strip, "mode": 5},
        {"attributes": {"POSITION": p}, "indices": fan, "mode": 6},
        {"attributes": {"POSITION": p}, "indices": tris},
    ]
    m = decode_gltf(b.glb(b.doc([{"primitives": prims}])), "s.glb")[0]
    assert len(m.vertices) == 6  # one vertex set for the three primitives
    assert m.faces.tolist() == [[0, 1, 3], [3, 1, 2], [3, 2, 5], [1, 2, 0], [2, 3, 0], [1, 4, 5]]
    # every triangle counter-clockwise seen from +z, as the strip and fan rules make them
    t = m.vertices[m.faces].astype(float)
    area = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2]
    assert (area[[0, 1, 3, 4, 5]] > 0).all()


def test_node_transforms_hierarchy_mirror_and_rtc():
    """Nested node transforms, a mirror and CESIUM_RTC apply in float64; mirrored faces turned."""
    b = Builder()
    p = _pos(b)
    idx = b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint16), "SCALAR", 5123)
    nrm = b.accessor(np.tile(np.float32([0, 0, 1]), (6, 1)), "VEC3", 5126)
    mesh = {"primitives": [{"attributes": {"POSITION": p, "NORMAL": nrm}, "indices": idx}]}
    nodes = [
        {"translation": [1e6, 2e6, 0.0], "children": [1, 2]},
        {"mesh": 0, "rotation": [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], "scale": [2, 2, 2]},
        {"mesh": 0, "matrix": [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 5, 1]},  # mirror in x
    ]
    doc = b.doc([mesh], nodes, extensions={"CESIUM_RTC": {"center": [0.5, 0.25, 0.125]}})
    m, details = decode_gltf(b.glb(doc), "n.glb")
    assert m.vertices.dtype == np.float64 and details["mesh_nodes"] == 2
    v = SQUARE.astype(float)
    rotated = np.column_stack([-2 * v[:, 1], 2 * v[:, 0], 2 * v[:, 2]]) + [1e6, 2e6, 0]
    mirrored = np.column_stack([-v[:, 0], v[:, 1], v[:, 2] + 5]) + [1e6, 2e6, 0]
    want = np.vstack([rotated, mirrored]) + [0.5, 0.25, 0.125]
    assert np.abs(m.vertices - want).max() < 1e-9
    # the mirrored copy's triangles are turned over: still counter-clockwise seen from +z
    t = m.vertices[m.faces]
    assert (np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2] > 0).all()
    assert np.allclose(m.normals, [0, 0, 1])


def test_sparse_quantized_and_normalised_colour_accessors():
    """Sparse, quantised positions and normalised uint8 colours decode to their values."""
    b = Builder()
    q = np.array([[0, 0, 0], [32767, 0, 0], [0, 32767, 0], [0, 0, 0]], np.int16)
    p = b.accessor(
        np.column_stack([q, np.zeros(4, np.int16)]), "VEC3", 5122, stride=8, normalized=True
    )
    b.sparse(p, [3], np.array([[0, 0, 32767]], np.int16))
    col = b.accessor(
        np.array([[255, 0, 0, 0], [0, 255, 0, 0], [0, 0, 255, 0], [9, 9, 9, 0]], np.uint8)[
            :, :3
        ].copy(),
        "VEC3",
        5121,
        normalized=True,
    )
    idx = b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint8), "SCALAR", 5121)
    mesh = {"primitives": [{"attributes": {"POSITION": p, "COLOR_0": col}, "indices": idx}]}
    doc = b.doc(
        [mesh],
        extensionsUsed=["KHR_mesh_quantization"],
        extensionsRequired=["KHR_mesh_quantization"],
    )
    m = decode_gltf(b.glb(doc), "q.glb")[0]
    assert np.allclose(m.vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert m.colors.dtype == np.uint8 and m.colors[3].tolist() == [9, 9, 9]


def test_gltf_with_a_sibling_bin_file_and_uris_that_escape(tmp_path):
    """A .gltf reads its sibling .bin; URIs leaving the folder, absolute or remote are refused."""
    b = Builder()
    p = _pos(b)
    idx = b.accessor(np.array([0, 1, 2], np.uint16), "SCALAR", 5123)
    doc = b.doc([{"primitives": [{"attributes": {"POSITION": p}, "indices": idx}]}])
    (tmp_path / "data dir").mkdir()
    (tmp_path / "data dir" / "mesh.bin").write_bytes(bytes(b.bin))
    doc["buffers"][0]["uri"] = "data%20dir/mesh.bin"
    (tmp_path / "m.gltf").write_text(json.dumps(doc))
    assert len(load(tmp_path / "m.gltf").faces) == 1
    for uri, message in (
        ("../mesh.bin", "leads outside the glTF's folder"),
        ("/etc/passwd", "only relative file names are read"),
        ("https://example.com/mesh.bin", "only relative file names are read"),
        ("missing.bin", "cannot read missing.bin"),
    ):
        doc["buffers"][0]["uri"] = uri
        (tmp_path / "m.gltf").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=message):
            load(tmp_path / "m.gltf")


def _json_of(glb: bytes) -> dict:
    return glb_split(glb)[0]


def _tetra_glb() -> tuple[bytes, dict]:
    data = glb_bytes(tetra(colors=np.full((4, 3), 7, np.uint8)))
    return data, _json_of(data)


def _with_json(data: bytes, doc: dict) -> bytes:
    return glb_join(doc, glb_split(data)[1])


def _edit(path: str, value):
    def apply(doc):
        keys = path.split(".")
        obj = doc
        for k in keys[:-1]:
            obj = obj[int(k)] if k.isdigit() else obj.setdefault(k, {})
        if value is KeyError:
            del obj[keys[-1]]
        else:
            obj[keys[-1]] = value
        return doc

    return apply


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            _edit("extensionsRequired", ["KHR_draco_mesh_compression"]),
            "requires KHR_draco_mesh_compression: recon does not decode Draco compression",
        ),
        (_edit("extensionsRequired", ["EXT_meshopt_compression"]), "does not decode meshopt"),
        (_edit("extensionsRequired", ["EXT_unknown_thing"]), "which recon does not read"),
        (
            _edit("bufferViews.0.extensions", {"EXT_meshopt_compression": {}}),
            "bufferViews[0] is meshopt-compressed",
        ),
        (_edit("buffers", []), "not an index into buffers"),
        (_edit("buffers.0.byteLength", 10**9), "declares 1000000000 bytes but holds"),
        (_edit("buffers.0.uri", "data:application/octet-stream;base64,AAAA!"), "malformed"),
        (_edit("accessors.0.count", 10**12), "need"),
        (_edit("accessors.0.count", 0), "accessors[0].count: expected an integer >= 1, got 0"),
        (_edit("accessors.0.count", True), "accessors[0].count: expected an integer >= 1"),
        (_edit("accessors.0.componentType", 5124), "is not a glTF component type"),
        (_edit("accessors.0.type", "MAT4"), "MAT4 accessor"),
        (_edit("accessors.0.byteOffset", 7), "need"),
        (_edit("bufferViews.0.byteStride", 2), "byteStride: expected an integer >= 4"),
        (_edit("bufferViews.0.byteOffset", -4), "expected an integer >= 0"),
        (_edit("meshes.0.primitives.0.mode", 1), "holds lines (mode 1)"),
        (_edit("meshes.0.primitives.0.mode", 9), "mode 9 is not a glTF primitive mode"),
        (_edit("meshes.0.primitives.0.indices", 99), "not an index into accessors"),
        (_edit("meshes.0.primitives.0.attributes.POSITION", "0"), "not an index into accessors"),
        (_edit("meshes.0.primitives.0.attributes", {"NORMAL": 0}), "has no POSITION attribute"),
        (_edit("meshes.0.primitives", []), "must be a non-empty array"),
        (_edit("nodes.0.children", [0]), "reached twice"),
        (_edit("nodes.0.matrix", [1] * 16), "not affine"),
        (_edit("nodes.0.translation", [0, 0]), "expected 3 finite numbers"),
        (_edit("nodes.0.scale", [0, 1, 1]), "transform is singular"),
        (_edit("scenes.0.nodes", [5]), "not an index into nodes"),
        (_edit("scenes", [{"nodes": []}]), "no mesh primitives"),
        (_edit("asset.version", "1.0"), "recon reads glTF 2.0"),
        (_edit("asset", KeyError), "no asset.version"),
        (_edit("nodes.0.extensions", {"EXT_mesh_gpu_instancing": {}}), "instanced"),
    ],
)
def test_bad_documents_are_refused_in_one_line(edit, message):
    """Each malformed or unsupported document is refused in one line naming the fault."""
    data, doc = _tetra_glb()
    with pytest.raises(InputError) as exc:
        decode_gltf(_with_json(data, edit(doc)), "bad.glb")
    text = str(exc.value)
    assert text.startswith("bad.glb: ") and "\n" not in text and message in text, text


def test_draco_read_from_its_fallback_refused_without_one():
    """A Draco primitive is read from its uncompressed fallback, refused without one."""
    data, doc = _tetra_glb()
    doc["meshes"][0]["primitives"][0]["extensions"] = {"KHR_draco_mesh_compression": {}}
    assert len(decode_gltf(_with_json(data, doc), "d.glb")[0].faces) == 4
    del doc["accessors"][0]["bufferView"]
    assert not decode_gltf(
        _with_json(data, _edit("meshes.0.primitives.0.extensions", {})(doc)), "z.glb"
    )[0].vertices.any()
    doc["meshes"][0]["primitives"][0]["extensions"] = {"KHR_draco_mesh_compression": {}}
    with pytest.raises(InputError, match="Draco-compressed: recon does not decode Draco"):
        decode_gltf(_with_json(data, doc), "d.glb")


def test_indices_out_of_range_and_short_glb_refused():
    """An index past the vertices, or a GLB shorter than its header says, is refused."""
    data, doc = _tetra_glb()
    raw = bytearray(data)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    view = doc["bufferViews"][acc["bufferView"]]
    start = 20 + struct.unpack_from("<I", data, 12)[0] + 8 + view["byteOffset"]
    raw[start : start + 2] = struct.pack("<H", 9)
    with pytest.raises(InputError, match="index 9 out of range for 4 vertices"):
        decode_gltf(bytes(raw), "i.glb")
    with pytest.raises(InputError, match="GLB header declares"):
        decode_gltf(data[:-4], "t.glb")


def test_texcoords_dropped_with_a_warning_and_mixed_kinds_refused(caplog):
    """Texture coordinates are dropped with a warning; points mixed with triangles are refused."""
    b = Builder()
    p = _pos(b)
    uv = b.accessor(SQUARE[:, :2].copy(), "VEC2", 5126)
    idx = b.accessor(np.array([0, 1, 2], np.uint16), "SCALAR", 5123)
    prim = {"attributes": {"POSITION": p, "TEXCOORD_0": uv}, "indices": idx}
    with caplog.at_level("WARNING", logger="recon"):
        m = decode_gltf(b.glb(b.doc([{"primitives": [prim]}])), "uv.glb")[0]
    assert len(m.faces) == 1 and "not kept: TEXCOORD_0" in caplog.text
    points = {"attributes": {"POSITION": p}, "mode": 0}
    with pytest.raises(InputError, match="mixes point and triangle primitives"):
        decode_gltf(b.glb(b.doc([{"primitives": [prim, points]}])), "mix.glb")


def test_trimesh_reads_ours_and_we_read_trimesh(tmp_path):
    """Our GLB reads exactly in trimesh, and trimesh's GLB reads here within 1e-6."""
    import trimesh

    m = mesh_family(1, np.float32)
    save(m, tmp_path / "ours.glb")
    theirs = trimesh.load(tmp_path / "ours.glb", force="mesh", process=False)
    np.testing.assert_array_equal(np.asarray(theirs.faces), m.faces)
    assert np.abs(np.asarray(theirs.vertices) - m.vertices).max() == 0
    t = trimesh.creation.icosphere(subdivisions=2)
    t.apply_translation([3.0, -2.0, 7.0])
    t.export(tmp_path / "theirs.glb")
    back = load(tmp_path / "theirs.glb")
    assert np.array_equal(back.faces, t.faces)
    assert np.abs(back.vertices - t.vertices).max() < 1e-6


# ----------------------------------------------------------------------------- registry and CLI


def test_registry_sniffing_and_stdout(tmp_path):
    """.glb/.gltf name the format, their bytes are sniffed without one, and GLB goes to stdout."""
    assert format_of("x.GLB").name == "gltf" and format_of("x.gltf").name == "gltf"
    save(tetra(), tmp_path / "t.glb")
    save(tetra(), tmp_path / "t.gltf")
    assert sniff((tmp_path / "t.glb").read_bytes()).name == "gltf"
    assert sniff((tmp_path / "t.gltf").read_bytes()).name == "gltf"
    (tmp_path / "noext").write_bytes((tmp_path / "t.gltf").read_bytes())
    assert len(load(tmp_path / "noext").faces) == 4
    r = subprocess.run(
        [*RECON, "convert", "--output-format", "glb", tmp_path / "t.glb", "-"],
        capture_output=True,
        timeout=120,
    )
    assert r.returncode == 0 and r.stdout[:4] == b"glTF", r.stderr


def test_cli_stage_reads_and_writes_glb_and_refuses_bad_glb(tmp_path):
    """A stage reads GLB and writes glTF; a truncated GLB is exit 2 with one line, no output."""
    m = mesh_family(2, np.float32)
    save(m, tmp_path / "m.glb")
    r = subprocess.run(
        [*RECON, "smooth", "--iterations", "1", tmp_path / "m.glb", tmp_path / "s.gltf"],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    s = load(tmp_path / "s.gltf")
    assert np.array_equal(s.faces, m.faces) and "smooth" in s.history[-1]
    (tmp_path / "bad.glb").write_bytes((tmp_path / "m.glb").read_bytes()[:100])
    r = subprocess.run(
        [*RECON, "convert", tmp_path / "bad.glb", tmp_path / "o.ply"],
        capture_output=True,
        timeout=120,
    )
    err = r.stderr.decode()
    assert r.returncode == 2 and err.count("\n") == 1 and str(tmp_path / "bad.glb") in err
    assert not (tmp_path / "o.ply").exists()
