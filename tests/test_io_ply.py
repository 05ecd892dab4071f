"""PLY reader/writer: round trips, every type and format, cross-reads, bad files, fuzzing."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, float64
from recon_cli.io.ply import (
    PlyData,
    PlyElement,
    PlyProperty,
    parse_ply,
    ply_bytes,
    read_ply,
    serialize_ply,
    write_ply,
)

from shared_data import ALL_MESHES, SCANS, load_shared, shared_path

FORMATS = ["ascii", "binary_little_endian", "binary_big_endian"]


def tetra() -> TriangleMesh:
    """A closed tetrahedron, outward faces."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return TriangleMesh(vertices=v, faces=f)


def cube() -> TriangleMesh:
    """The unit cube as 12 triangles."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return TriangleMesh(vertices=v, faces=f)


def colored_cloud() -> PointCloud:
    """50 points with normals, RGBA colours and a float32 ``quality``, exact in float32."""
    rng = np.random.default_rng(3)
    p = rng.normal(size=(50, 3)).astype(np.float32).astype(np.float64)
    n = rng.normal(size=(50, 3)).astype(np.float32).astype(np.float64)
    c = rng.integers(0, 256, size=(50, 4), dtype=np.uint8)
    return PointCloud(
        points=p, normals=n, colors=c, attributes={"quality": rng.random(50).astype(np.float32)}
    )


def single_triangle() -> TriangleMesh:
    """One triangle in float64."""
    return TriangleMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]]),
        faces=np.array([[0, 1, 2]]),
        point_dtype=np.float64,
    )


CANONICAL = {
    "tetra": tetra,
    "cube": cube,
    "colored_cloud": colored_cloud,
    "triangle": single_triangle,
}


def assert_same_geometry(a, b) -> None:
    """Assert ``a`` and ``b`` have the same type, arrays and attributes, value for value."""
    assert type(a) is type(b)
    np.testing.assert_array_equal(a.points, b.points)
    if isinstance(a, TriangleMesh):
        np.testing.assert_array_equal(a.faces, b.faces)
    for attr in ("normals", "colors"):
        x, y = getattr(a, attr), getattr(b, attr)
        assert (x is None) == (y is None)
        if x is not None:
            np.testing.assert_array_equal(x, y)
    assert sorted(a.attributes) == sorted(b.attributes)
    for k in a.attributes:
        np.testing.assert_array_equal(a.attributes[k], b.attributes[k])


@pytest.mark.parametrize("name", sorted(CANONICAL))
@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_canonical(name, fmt):
    """Each canonical object through each PLY format comes back exactly."""
    obj = CANONICAL[name]()
    ply = parse_ply(ply_bytes(obj))
    ply.format = fmt
    back = parse_ply(serialize_ply(ply))
    from recon_cli.io.ply import ply_to_geometry

    assert_same_geometry(obj, ply_to_geometry(back))


@pytest.mark.parametrize("name", ALL_MESHES + SCANS)
def test_round_trip_shared_binary_exact(name, tmp_path):
    """Every shared mesh and scan through binary PLY comes back exactly, in its own precision."""
    obj = load_shared(name)
    out = tmp_path / "x.ply"
    write_ply(obj, out)
    assert_same_geometry(obj, read_ply(out))
    # float32 sources stay float32 on disk, float64 stay float64
    assert read_ply(out).point_dtype == obj.point_dtype


@pytest.mark.parametrize("name", ["kitten", "stereo_fragment"])
def test_round_trip_shared_ascii(name, tmp_path):
    """Shared files through ASCII PLY come back exactly: every float printed in full."""
    obj = load_shared(name)
    out = tmp_path / "x.ply"
    write_ply(obj, out, ascii=True)
    # %.17g / %.9g print every float exactly
    assert_same_geometry(obj, read_ply(out))


@pytest.mark.parametrize(
    "alias",
    [
        ("char", "int8"),
        ("uchar", "uint8"),
        ("short", "int16"),
        ("ushort", "uint16"),
        ("int", "int32"),
        ("uint", "uint32"),
        ("float", "float32"),
        ("double", "float64"),
    ],
)
@pytest.mark.parametrize("fmt", FORMATS)
def test_every_type_name_and_alias(alias, fmt):
    """Each PLY type, by name and alias, in each format, reads as its numpy type with its values."""
    values = np.array([0, 1, 2, 100, 7], dtype=np.float64)
    for tname in alias:
        header = (
            f"ply\nformat {fmt} 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
            "property float z\n"
            f"property {tname} q\nend_header\n"
        )
        order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        from recon_cli.io._ply_types import PLY_TYPES

        code = PLY_TYPES[tname]
        if order is None:
            body = "".join(
                f"{i} {i} {i} {int(v) if code[0] != 'f' else v}\n" for i, v in enumerate(values)
            ).encode()
        else:
            dt = np.dtype(
                [("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4"), ("q", order + code)]
            )
            arr = np.zeros(5, dt)
            for c in "xyz":
                arr[c] = np.arange(5)
            arr["q"] = values
            body = arr.tobytes()
        cloud = read_ply("t.ply", header.encode() + body)
        assert cloud.attributes["q"].dtype == np.dtype(code)
        np.testing.assert_array_equal(cloud.attributes["q"].astype(np.float64), values)
        np.testing.assert_array_equal(cloud.points[:, 0], np.arange(5))


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize(
    "ctype,itype",
    [("uchar", "int"), ("ushort", "uint"), ("int", "int"), ("uint8", "int32"), ("char", "uint16")],
)
def test_list_count_and_item_types(fmt, ctype, itype):
    """Face lists with any count and index types read back the cube's faces."""
    mesh = cube()
    ply = parse_ply(ply_bytes(mesh))
    from recon_cli.io._ply_types import PLY_TYPES

    face = ply.element("face")
    face.properties[0] = PlyProperty("vertex_indices", PLY_TYPES[itype], PLY_TYPES[ctype])
    ply.format = fmt
    back = read_ply("x.ply", serialize_ply(ply))
    np.testing.assert_array_equal(back.faces, mesh.faces)


@pytest.mark.parametrize("fmt", FORMATS)
def test_polygons_fan_triangulated_and_mixed(fmt):
    """Quads and pentagons among triangles are fan-triangulated; face properties follow."""
    # a quad and a pentagon and a triangle: ragged lists, and 'vertex_index' spelling
    verts = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0], [3, 0.5, 0]], float
    )
    polys = np.empty(3, dtype=object)
    polys[0] = np.array([0, 1, 2, 3])
    polys[1] = np.array([1, 4, 6, 5, 2])
    polys[2] = np.array([0, 1, 3])
    ply = PlyData(
        format=fmt,
        elements=[
            PlyElement(
                "vertex",
                7,
                [PlyProperty(c, "f8") for c in "xyz"],
                {c: verts[:, i] for i, c in enumerate("xyz")},
            ),
            PlyElement(
                "face",
                3,
                [PlyProperty("vertex_index", "i4", "u1"), PlyProperty("flag", "u1")],
                {"vertex_index": polys, "flag": np.array([7, 8, 9], np.uint8)},
            ),
        ],
    )
    mesh = read_ply("p.ply", serialize_ply(ply))
    expected = [[0, 1, 2], [0, 2, 3], [1, 4, 6], [1, 6, 5], [1, 5, 2], [0, 1, 3]]
    np.testing.assert_array_equal(mesh.faces, expected)
    np.testing.assert_array_equal(mesh.face_attributes["flag"], [7, 7, 8, 8, 8, 9])


@pytest.mark.parametrize("fmt", FORMATS)
def test_unknown_elements_kept_and_order_free(fmt):
    """Unknown elements and properties, in any order, are kept and written back."""
    # an element before the vertices, one between, unknown properties everywhere
    verts = np.arange(12, dtype=np.float64).reshape(4, 3)
    ply = PlyData(
        format=fmt,
        comments=["hello world", ""],
        obj_info=["scanner 42"],
        elements=[
            PlyElement(
                "camera",
                1,
                [PlyProperty("view_px", "f4"), PlyProperty("k", "i2")],
                {"view_px": np.array([1.5], np.float32), "k": np.array([-3], np.int16)},
            ),
            PlyElement(
                "vertex",
                4,
                [PlyProperty("confidence", "f4")]
                + [PlyProperty(c, "f8") for c in "xyz"]
                + [PlyProperty("id", "u4")],
                {
                    "confidence": np.ones(4, np.float32),
                    "id": np.arange(4, dtype=np.uint32),
                    **{c: verts[:, i] for i, c in enumerate("xyz")},
                },
            ),
            PlyElement(
                "edge",
                2,
                [PlyProperty("vertex1", "i4"), PlyProperty("vertex2", "i4")],
                {"vertex1": np.array([0, 1], np.int32), "vertex2": np.array([2, 3], np.int32)},
            ),
            PlyElement(
                "face",
                2,
                [PlyProperty("vertex_indices", "i4", "u1")],
                {"vertex_indices": np.array([[0, 1, 2], [0, 2, 3]])},
            ),
        ],
    )
    mesh = read_ply("u.ply", serialize_ply(ply))
    np.testing.assert_array_equal(mesh.vertices, verts)
    assert sorted(mesh.attributes) == ["confidence", "id"]
    assert [e.name for e in mesh.extra_elements] == ["camera", "edge"]
    assert mesh.history == ["hello world", ""]
    assert mesh.obj_info == ["scanner 42"]
    again = parse_ply(ply_bytes(mesh))
    assert again.element("camera").data["k"][0] == -3
    np.testing.assert_array_equal(again.element("edge").data["vertex2"], [2, 3])
    assert again.obj_info == ["scanner 42"]


def test_crlf_header_and_comments():
    """A header with CRLF line ends reads, its comment becoming the history."""
    body = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes() + struct.pack(
        "<Biii", 3, 0, 1, 2
    )
    header = (
        "ply\r\nformat binary_little_endian 1.0\r\ncomment made on windows\r\nobj_info x\r\n"
        "element vertex 3\r\nproperty float x\r\nproperty float y\r\nproperty float z\r\n"
        "element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
    )
    mesh = read_ply("crlf.ply", header.encode() + body)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])
    assert mesh.history == ["made on windows"]


# ------------------------------------------------------------------ cross-reads


@pytest.mark.parametrize("name", ["kitten", "stereo_fragment", "bunny_scan_000"])
@pytest.mark.parametrize("ascii", [False, True])
def test_open3d_written_files_read_identically(name, ascii, tmp_path):
    """Files Open3D wrote (mesh or cloud, ASCII or binary) read as Open3D reads them."""
    import open3d as o3d

    src = load_shared(name)
    out = str(tmp_path / "o3d.ply")
    # "identically": our arrays equal Open3D's own reading of the file it wrote
    if isinstance(src, TriangleMesh):
        m = o3d.io.read_triangle_mesh(str(shared_path(name)))
        m.compute_vertex_normals()
        assert o3d.io.write_triangle_mesh(out, m, write_ascii=ascii)
        ref = o3d.io.read_triangle_mesh(out)
        ours = read_ply(out)
        np.testing.assert_array_equal(ours.vertices, np.asarray(ref.vertices))
        np.testing.assert_array_equal(ours.faces, np.asarray(ref.triangles))
        np.testing.assert_array_equal(ours.normals, np.asarray(ref.vertex_normals))
    else:
        pc = o3d.io.read_point_cloud(str(shared_path(name)))
        pc.estimate_normals()
        assert o3d.io.write_point_cloud(out, pc, write_ascii=ascii)
        ref = o3d.io.read_point_cloud(out)
        ours = read_ply(out)
        np.testing.assert_array_equal(ours.points, np.asarray(ref.points))
        np.testing.assert_array_equal(ours.normals, np.asarray(ref.normals))
        if ref.has_colors():
            np.testing.assert_allclose(ours.colors / 255.0, np.asarray(ref.colors), atol=1e-12)


@pytest.mark.parametrize("name", ["kitten", "mug"])
@pytest.mark.parametrize("binary", [True, False])
def test_pymeshlab_written_files_read_identically(name, binary, tmp_path):
    """Files PyMeshLab wrote (binary or ASCII) read as PyMeshLab reads them."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(shared_path(name)))
    out = str(tmp_path / "ml.ply")
    ms.save_current_mesh(out, binary=binary)
    ours = read_ply(out)
    ms2 = pymeshlab.MeshSet()
    ms2.load_new_mesh(out)
    m = ms2.current_mesh()
    np.testing.assert_array_equal(ours.vertices, m.vertex_matrix())
    np.testing.assert_array_equal(ours.faces, m.face_matrix())


@pytest.mark.parametrize("ascii", [False, True])
def test_our_files_open_in_open3d_and_pymeshlab(ascii, tmp_path):
    """Our PLY files (mesh and cloud, ASCII or binary) open in Open3D and PyMeshLab unchanged."""
    import open3d as o3d
    import pymeshlab

    mesh = load_shared("kitten")
    mesh.normals = np.tile([0.0, 0.0, 1.0], (len(mesh.vertices), 1))
    out = str(tmp_path / "ours.ply")
    write_ply(mesh, out, ascii=ascii)
    m = o3d.io.read_triangle_mesh(out)
    np.testing.assert_allclose(np.asarray(m.vertices), mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(m.triangles), mesh.faces)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(out)
    np.testing.assert_allclose(ms.current_mesh().vertex_matrix(), mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(ms.current_mesh().face_matrix(), mesh.faces)
    cloud = load_shared("stereo_fragment")
    out2 = str(tmp_path / "cloud.ply")
    write_ply(cloud, out2, ascii=ascii)
    pc = o3d.io.read_point_cloud(out2)
    np.testing.assert_allclose(np.asarray(pc.points), cloud.points, atol=1e-9)
    np.testing.assert_allclose(np.asarray(pc.colors) * 255, cloud.colors, atol=1e-6)


# ------------------------------------------------------------------ bad files

GOOD_HEADER = (
    "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
)
GOOD_BODY = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes() + struct.pack(
    "<Biii", 3, 0, 1, 2
)

BAD_FILES = {
    "empty": (b"", "empty file"),
    "not ply": (b"solid cube\nfacet normal 0 0 1\n", "not a PLY file"),
    "truncated body": (GOOD_HEADER.encode() + GOOD_BODY[:-5], "truncated"),
    "lying count": (
        GOOD_HEADER.replace("vertex 3", "vertex 3000000000").encode() + GOOD_BODY,
        "truncated",
    ),
    "lying face count": (
        GOOD_HEADER.replace("face 1", "face 999999999999").encode() + GOOD_BODY,
        "truncated",
    ),
    "unknown format": (
        GOOD_HEADER.replace("binary_little_endian", "binary_middle_endian").encode() + GOOD_BODY,
        "unknown format",
    ),
    "bad type": (
        GOOD_HEADER.replace("property float y", "property flaot y").encode() + GOOD_BODY,
        "unknown type name",
    ),
    "float list count": (
        GOOD_HEADER.replace("list uchar int", "list float int").encode() + GOOD_BODY,
        "not an integer type",
    ),
    "index out of range": (
        GOOD_HEADER.encode() + GOOD_BODY[:-4] + struct.pack("<i", 7),
        "out of range",
    ),
    "negative index": (
        GOOD_HEADER.encode() + GOOD_BODY[:-4] + struct.pack("<i", -1),
        "out of range",
    ),
    "nan coordinate": (
        GOOD_HEADER.encode()
        + np.array([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]], "<f4").tobytes()
        + GOOD_BODY[36:],
        "NaN",
    ),
    "inf coordinate": (
        GOOD_HEADER.encode()
        + np.array([[0, 0, 0], [np.inf, 0, 0], [0, 1, 0]], "<f4").tobytes()
        + GOOD_BODY[36:],
        "NaN or infinite",
    ),
    "no end_header": (GOOD_HEADER.replace("end_header\n", "").encode(), "end_header"),
    "no format": (
        GOOD_HEADER.replace("format binary_little_endian 1.0\n", "").encode() + GOOD_BODY,
        "no 'format'",
    ),
    "negative count": (
        GOOD_HEADER.replace("vertex 3", "vertex -3").encode() + GOOD_BODY,
        "negative",
    ),
    "property before element": (
        b"ply\nformat ascii 1.0\nproperty float x\nend_header\n",
        "before any element",
    ),
    "no vertex element": (
        b"ply\nformat ascii 1.0\nelement point 1\nproperty float x\nend_header\n1\n",
        "no 'vertex' element",
    ),
    "missing z": (
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"end_header\n1 2\n",
        "'z'",
    ),
    "ascii text in numbers": (
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n1 two 3\n",
        "not a number",
    ),
    "ascii truncated": (
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n1 2 3\n",
        "truncated",
    ),
    "ascii lying count": (
        b"ply\nformat ascii 1.0\nelement vertex 99999999999\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n1 2 3\n",
        "truncated",
    ),
    "two-vertex face": (
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"end_header\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n",
        "fewer than 3",
    ),
    "bad version": (GOOD_HEADER.replace("1.0", "2.0").encode() + GOOD_BODY, "version"),
    "binary header": (b"ply\nformat ascii 1.0\ncomment \xff\xfe\nend_header\n", "not ASCII"),
    "int property with fraction": (
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nproperty int q\nend_header\n1 2 3 4.5\n",
        "non-integer",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_raise_one_line_input_error(case):
    """Each malformed PLY is a one-line InputError naming the file and the fault."""
    data, needle = BAD_FILES[case]
    with pytest.raises(InputError) as exc:
        read_ply("bad.ply", data)
    msg = str(exc.value)
    assert msg.startswith("bad.ply: "), msg
    assert needle in msg, msg
    assert "\n" not in msg


def test_lying_header_does_not_allocate(tmp_path):
    """A header promising 2^31 rows of doubles is refused without allocating for them."""
    # 2**31 - 1 doubles per row promised: any allocation of that size would take > 40 GB
    data = (
        GOOD_HEADER.replace("vertex 3", "vertex 2147483647").replace("float", "double").encode()
        + GOOD_BODY
    )
    import tracemalloc

    tracemalloc.start()
    with pytest.raises(InputError):
        read_ply("big.ply", data)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 10 * len(data) + (1 << 20)


# ------------------------------------------------------------------ fuzzing

_type_names = st.sampled_from(
    [
        "char",
        "uchar",
        "short",
        "ushort",
        "int",
        "uint",
        "float",
        "double",
        "int8",
        "uint32",
        "float64",
        "flaot",
        "int64",
    ]
)
_prop = st.one_of(
    st.tuples(
        st.just("scalar"), _type_names, st.sampled_from(["x", "y", "z", "nx", "red", "q", "x"])
    ),
    st.tuples(
        st.just("list"),
        st.tuples(_type_names, _type_names),
        st.sampled_from(["vertex_indices", "vertex_index", "l"]),
    ),
)
_element = st.tuples(
    st.sampled_from(["vertex", "face", "edge", "camera", "vertex"]),
    st.one_of(st.integers(0, 5), st.integers(-2, 2**40)),
    st.lists(_prop, max_size=5),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    fmt=st.sampled_from(FORMATS + ["binary", "ascii 2.0"]),
    elements=st.lists(_element, max_size=3),
    body=st.binary(max_size=200),
    crlf=st.booleans(),
)
def test_fuzz_reader_only_returns_data_or_input_error(fmt, elements, body, crlf):
    """Generated headers and bodies read as finite data or a one-line InputError."""
    lines = ["ply", f"format {fmt} 1.0", "comment fuzz"]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        for kind, t, pname in props:
            if kind == "scalar":
                lines.append(f"property {t} {pname}")
            else:
                lines.append(f"property list {t[0]} {t[1]} {pname}")
    lines.append("end_header")
    nl = "\r\n" if crlf else "\n"
    data = (nl.join(lines) + nl).encode() + body
    try:
        obj = read_ply("fuzz.ply", data)
    except InputError as exc:
        assert str(exc).startswith("fuzz.ply: ")
        return
    assert isinstance(obj, (PointCloud, TriangleMesh))
    assert np.isfinite(obj.points).all()


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=400))
def test_fuzz_random_bytes(data):
    """Random bytes, alone or after a PLY header's start, raise nothing but InputError."""
    for prefix in (
        b"",
        b"ply\nformat ascii 1.0\n",
        b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
        b"property float y\nproperty float z\n",
    ):
        try:
            read_ply("r.ply", prefix + data)
        except InputError:
            pass


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(1, 30),
    fmt=st.sampled_from(FORMATS),
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_fuzz_round_trip_random_meshes(n, fmt, seed, dtype):
    """Random meshes in float32 or float64 come back exactly through every format."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n + 2, 3)).astype(dtype)
    f = rng.integers(0, n + 2, size=(n, 3))
    mesh = TriangleMesh(
        vertices=v,
        faces=f,
        point_dtype=dtype,
        attributes={"s": rng.random(n + 2).astype(np.float32)},
    )
    ply = parse_ply(ply_bytes(mesh))
    ply.format = fmt
    from recon_cli.io.ply import ply_to_geometry

    assert_same_geometry(mesh, ply_to_geometry(parse_ply(serialize_ply(ply))))


def test_write_is_atomic_on_failure(tmp_path):
    """A write that fails (a string attribute) leaves the old file and no temporary."""
    target = tmp_path / "out.ply"
    target.write_bytes(b"old content")

    class Boom(TriangleMesh):
        pass

    mesh = tetra()
    mesh.attributes["bad"] = np.array(["a", "b", "c", "d"])  # no PLY type for strings
    with pytest.raises(TypeError):
        write_ply(mesh, target)
    assert target.read_bytes() == b"old content"
    assert os.listdir(tmp_path) == ["out.ply"]


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_from_disk_same_error(case, tmp_path):
    """Malformed files read from disk give the same one-line errors as from bytes."""
    # files are read into a numpy buffer, not bytes: the same one-line errors must come out
    data, needle = BAD_FILES[case]
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    with pytest.raises(InputError) as exc:
        read_ply(path)
    assert str(exc.value).startswith(f"{path}: ") and needle in str(exc.value)


def test_read_from_a_pipe_path(tmp_path):
    """A FIFO path (size unknown until read) reads as the same bytes in memory do."""
    # `recon info <(cat scan.ply)`: a path whose size is unknown until read to the end
    import threading

    fifo = tmp_path / "fifo.ply"
    os.mkfifo(fifo)
    data = ply_bytes(tetra())
    writer = threading.Thread(target=lambda: fifo.write_bytes(data))
    writer.start()
    got = read_ply(fifo)
    writer.join()
    want = read_ply("mem.ply", data)
    assert np.array_equal(got.vertices, want.vertices) and np.array_equal(got.faces, want.faces)


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("ftype", ["f4", "f8"])
def test_float_fields_decode_bit_exact(order, ftype, tmp_path):
    """Floats at an odd row stride, specials and -0.0 included, decode bit for bit, either order."""
    # odd row stride (a uchar first), special values: the byte-assembling decoder equals numpy's
    rng = np.random.default_rng(1)
    n = 1000
    f = np.dtype(order + ftype)
    vals = rng.normal(scale=1e3, size=(n, 6)).astype(f)
    info = np.finfo(f)
    vals[:8, 0] = [0.0, -0.0, info.tiny, info.tiny / 4, info.max, -info.max, info.eps, 1.0]
    dt = np.dtype([("tag", "u1")] + [(c, f) for c in ("x", "y", "z", "nx", "ny", "nz")])
    rows = np.zeros(n, dtype=dt)
    rows["tag"] = 7
    for j, c in enumerate(("x", "y", "z", "nx", "ny", "nz")):
        rows[c] = vals[:, j]
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    name = "float" if ftype == "f4" else "double"
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty uchar tag\n"
        + "".join(f"property {name} {c}\n" for c in ("x", "y", "z", "nx", "ny", "nz"))
        + "end_header\n"
    )
    path = tmp_path / "v.ply"
    path.write_bytes(head.encode() + rows.tobytes())
    cloud = read_ply(path)
    want = vals.astype(np.float64)
    assert cloud.points.dtype == cloud.normals.dtype == f.newbyteorder("=")  # the file's precision
    assert np.array_equal(cloud.points, want[:, :3]) and np.array_equal(cloud.normals, want[:, 3:])
    assert np.array_equal(np.signbit(cloud.points[:, 0]), np.signbit(want[:, 0]))  # -0.0 kept
    assert np.array_equal(cloud.attributes["tag"], np.full(n, 7))


def _big_cloud_bytes(n: int, order: str, before: str = "") -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(3)
    dt = np.dtype(
        [(c, order + "f4") for c in ("x", "y", "z", "nx", "ny", "nz")]
        + [(c, "u1") for c in ("red", "green", "blue")]
    )
    rows = np.zeros(n, dt)
    for c in ("x", "y", "z", "nx", "ny", "nz"):
        rows[c] = rng.normal(size=n)
    for c in ("red", "green", "blue"):
        rows[c] = rng.integers(0, 256, n)
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    head = (
        f"ply\nformat {fmt} 1.0\n{before}element vertex {n}\n"
        + "".join(f"property {'float' if dt[c].kind == 'f' else 'uchar'} {c}\n" for c in dt.names)
        + "end_header\n"
    )
    return head.encode(), rows


@pytest.mark.parametrize(
    "order,before,pre",
    [
        ("<", "", b""),
        (">", "", b""),
        (
            "<",
            "element camera 2\nproperty double cx\nproperty uchar tag\n",
            np.zeros(18, np.uint8).tobytes(),
        ),
        ("<", "element note 1\nproperty list uchar uchar text\n", b"\x02ab"),
    ],
    ids=["le", "be", "fixed-element-first", "list-element-first"],
)
def test_big_file_from_disk_equals_in_memory_parse(order, before, pre, tmp_path):
    """A 300k-row file read from disk equals the parse of its bytes, with elements before it too."""
    # from disk the columns view a writable buffer; from bytes (read-only) the rows are copied
    head, rows = _big_cloud_bytes(300_000, order, before)
    data = head + pre + rows.tobytes()
    path = tmp_path / "big.ply"
    path.write_bytes(data)
    got = read_ply(path)
    want = read_ply("mem.ply", data)
    assert np.array_equal(got.points, want.points) and np.array_equal(got.normals, want.normals)
    assert np.array_equal(got.colors, want.colors)
    assert np.array_equal(got.points[:, 1], rows["y"].astype(np.float64))


def test_big_truncated_file_errors_like_in_memory(tmp_path):
    """A big file cut short is "truncated", as its bytes would be."""
    head, rows = _big_cloud_bytes(300_000, "<")
    path = tmp_path / "cut.ply"
    path.write_bytes(head + rows.tobytes()[:-1000])
    with pytest.raises(InputError, match="truncated"):
        read_ply(path)


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("ftype", ["f4", "f8"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("row,col", [(0, "x"), (4_999, "z"), (2_048, "y"), (9_999, "z")])
def test_nonfinite_rows_found_and_dropped(order, ftype, bad, row, col, tmp_path):
    """Rows with a NaN or infinite coordinate are dropped and counted; NaN normals are kept."""
    # block boundaries (2048 rows) and the last row; NaN in the normals is not an invalid point
    n = 10_000
    dt = np.dtype([("tag", "u1")] + [(c, order + ftype) for c in ("x", "y", "z", "nx")])
    rows = np.zeros(n, dt)
    rows["y"] = np.arange(n)
    rows["nx"][: row + 1] = np.nan
    rows[col][row] = bad
    dropped = [row]
    if row < n - 1:
        rows["x"][n - 1] = np.nan  # a later bad row too
        dropped.append(n - 1)
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    name = "float" if ftype == "f4" else "double"
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty uchar tag\n"
        + "".join(f"property {name} {c}\n" for c in ("x", "y", "z", "nx"))
        + "end_header\n"
    )
    data = head.encode() + rows.tobytes()
    path = tmp_path / "nan.ply"
    path.write_bytes(data)
    keep = np.setdiff1d(np.arange(n), dropped)
    for got in (read_ply(path), read_ply("mem.ply", data)):
        assert got.invalid_dropped == len(dropped) and len(got.points) == n - len(dropped)
        assert np.array_equal(got.points[:, 1], keep) and got.points.dtype == np.dtype(ftype)
        assert np.isnan(got.attributes["nx"][:row]).all() and len(got.attributes["nx"]) == len(keep)


def _root(a):
    """The object at the end of an array's chain of bases (the buffer it views)."""
    while getattr(a, "base", None) is not None:
        a = a.base
    return a


def test_columns_are_views_of_the_rows_in_the_files_precision(tmp_path):
    """Columns are writable views of the rows in the file's precision; float64() copies once."""
    head, rows = _big_cloud_bytes(1000, "<")
    path = tmp_path / "c.ply"
    path.write_bytes(head + rows.tobytes())
    cloud = read_ply(path)
    assert (
        cloud.points.dtype == cloud.normals.dtype == np.float32 and cloud.colors.dtype == np.uint8
    )
    assert (
        _root(cloud.points) is _root(cloud.normals) is _root(cloud.colors)
    )  # views of the rows, not copies
    assert cloud.points.flags.writeable and cloud.colors.flags.writeable
    assert np.array_equal(cloud.points, np.column_stack([rows[c] for c in "xyz"]))
    assert np.array_equal(
        cloud.colors, np.column_stack([rows[c] for c in ("red", "green", "blue")])
    )
    # from read-only bytes the rows are copied once: still views, and writable
    mem = read_ply("mem.ply", head + rows.tobytes())
    assert mem.points.flags.writeable and np.array_equal(mem.points, cloud.points)
    # ready to compute: float64, contiguous, same values; already-float64 objects pass through
    c64 = float64(cloud)
    assert (
        c64.points.dtype == np.float64
        and c64.points.flags.c_contiguous
        and c64.normals.flags.c_contiguous
    )
    assert np.array_equal(c64.points, cloud.points) and c64.colors is cloud.colors
    assert float64(c64) is c64
    # written back in the file's types, byte for byte
    out = tmp_path / "w.ply"
    write_ply(cloud, out)
    assert read_ply(out).points.dtype == np.float32
    assert np.array_equal(read_ply(out).points, cloud.points)


@pytest.mark.parametrize(
    "xyz,want",
    [("double", np.float64), ("int", np.float64), ("short", np.float64), ("float", np.float32)],
)
def test_coordinate_types_map_to_float32_or_float64(xyz, want):
    """Coordinates of type float read as float32; double and integer ones as float64."""
    t = np.dtype({"double": "<f8", "int": "<i4", "short": "<i2", "float": "<f4"}[xyz])
    vals = np.arange(12).reshape(4, 3).astype(t)
    head = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 4\n"
        + "".join(f"property {xyz} {c}\n" for c in "xyz")
        + "end_header\n"
    )
    cloud = read_ply("t.ply", head.encode() + vals.tobytes())
    assert cloud.points.dtype == want and np.array_equal(cloud.points, vals)


def test_mesh_vertex_views_do_not_hold_the_face_bytes(tmp_path):
    """A mesh's vertex columns are copied out, not views pinning the file's face bytes."""
    # a mesh's vertex rows are a small part of its file: they are copied, so the faces' bytes
    # are freed once read (the columns must not pin the whole file)
    side = 60
    x, y = np.meshgrid(
        np.arange(side, dtype=np.float32), np.arange(side, dtype=np.float32), indexing="ij"
    )
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(side * side, np.float32)])
    idx = np.arange(side * side).reshape(side, side)
    a, b, c = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    path = tmp_path / "m.ply"
    write_ply(TriangleMesh(vertices=v, faces=np.column_stack([a, b, c])), path)
    mesh = read_ply(path)
    assert memoryview(_root(mesh.vertices)).nbytes == len(v) * 12 < os.path.getsize(path) / 2
    assert np.array_equal(mesh.vertices, v)


def test_mesh_columns_do_not_hold_the_file_when_rows_are_most_of_it(tmp_path):
    """When vertex rows are most of the file, the columns are copies, not views of it."""
    # Poisson's output: double xyz and an int per vertex, 28 bytes a row against 26 of faces
    # per vertex; the rows are not copied, so the columns are (the file's bytes are freed)
    n = 500
    rows = np.zeros(n, [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("face", "<i4")])
    rows["x"], rows["y"], rows["face"] = np.arange(n), np.arange(n) % 7, np.arange(n) % 3
    tris = np.zeros(2 * n, [("k", "u1"), ("v", "<i4", (3,))])
    tris["k"] = 3
    tris["v"] = (np.arange(2 * n)[:, None] + np.arange(3)) % n
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
        + "".join(f"property double {c}\n" for c in "xyz")
        + f"property int face\nelement face {2 * n}\nproperty list uchar int vertex_indices\n"
        + "end_header\n"
    )
    path = tmp_path / "m.ply"
    path.write_bytes(head.encode() + rows.tobytes() + tris.tobytes())
    assert 2 * rows.nbytes > os.path.getsize(path)
    mesh = read_ply(path)
    assert memoryview(_root(mesh.vertices)).nbytes == n * 24
    assert memoryview(_root(mesh.attributes["face"])).nbytes == n * 4
    assert mesh.vertices.flags.c_contiguous and mesh.vertices.dtype == np.float64
    assert np.array_equal(mesh.vertices, np.column_stack([rows[c] for c in "xyz"]))
    assert np.array_equal(mesh.faces, tris["v"]) and mesh.face_attributes == {}


@pytest.mark.parametrize("big_endian", [False, True])
def test_records_kept_as_they_are_write_the_same_bytes(tmp_path, rng, monkeypatch, big_endian):
    """A read, subset cloud whose rows already are the file's records is written unencoded."""
    import recon_cli.io.ply as ply_mod
    from recon_cli.cli.main import cli

    n = 3000
    cloud = PointCloud(
        points=rng.normal(size=(n, 3)) * 1e3,
        normals=rng.normal(size=(n, 3)),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
    )
    src = tmp_path / "c.ply"
    write_ply(cloud, src)
    if big_endian:
        cli.main(
            ["-q", "convert", str(src), str(tmp_path / "be.ply"), "--big-endian"],
            "recon",
            standalone_mode=False,
        )
        src = tmp_path / "be.ply"
    keep = rng.random(n) < 0.4
    sub = read_ply(src).subset(keep)
    calls = []
    fast = ply_mod._records_as_they_are
    monkeypatch.setattr(
        ply_mod, "_records_as_they_are", lambda el, dt: calls.append(fast(el, dt)) or calls[-1]
    )
    write_ply(sub, tmp_path / "fast.ply")
    assert calls and (calls[0] is None) == big_endian  # written little-endian: re-encoded
    monkeypatch.setattr(ply_mod, "_records_as_they_are", lambda el, dt: None)
    write_ply(sub, tmp_path / "slow.ply")
    assert (tmp_path / "fast.ply").read_bytes() == (tmp_path / "slow.ply").read_bytes()
    back = read_ply(tmp_path / "fast.ply")
    np.testing.assert_array_equal(back.points, cloud.points[keep])
    np.testing.assert_array_equal(back.colors, cloud.colors[keep])
    # columns of another layout (a computed normal in its own array) are encoded as before
    sub.normals = np.ascontiguousarray(sub.normals)
    calls.clear()
    monkeypatch.setattr(
        ply_mod, "_records_as_they_are", lambda el, dt: calls.append(fast(el, dt)) or calls[-1]
    )
    write_ply(sub, tmp_path / "mixed.ply")
    assert calls == [None]
    np.testing.assert_array_equal(read_ply(tmp_path / "mixed.ply").normals, cloud.normals[keep])
