"""PCD: Open3D's files read right, ours read back identically, LZF, errors, fuzz.

PCD: Open3D's ascii/binary/compressed files read right, ours read back identically (by us and
Open3D), LZF round trips, errors, fuzz.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_io_xyz import o3d_cloud

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud
from recon_cli.io._lzf_kernel import lzf_compress, lzf_decompress
from recon_cli.io.pcd import decode_pcd, pcd_bytes
from recon_cli.io.text import as_uint8

from shapes import cloud_family

o3d = pytest.importorskip("open3d")
DATA = ["ascii", "binary", "binary_compressed"]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("data", DATA)
def test_open3d_written_pcd_reads_with_right_counts_and_coordinates(seed, data, tmp_path):
    """PCD files Open3D wrote (ASCII, binary, compressed) read with its counts, points, colours."""
    c = cloud_family(seed)
    path = tmp_path / "c.pcd"
    o3d.io.write_point_cloud(
        str(path), o3d_cloud(c), write_ascii=data == "ascii", compressed=data == "binary_compressed"
    )
    ref = o3d.io.read_point_cloud(str(path))
    got, details = decode_pcd(path.read_bytes(), str(path))
    assert details["data"] == data and len(got.points) == len(c.points)
    assert got.colors.dtype == np.uint8 and np.array_equal(got.colors, c.colors)
    if data == "ascii":  # Open3D keeps the printed decimals as doubles; TYPE F SIZE 4 says float32
        assert np.array_equal(got.points, np.asarray(ref.points).astype(got.points.dtype))
    else:
        assert np.array_equal(got.points.astype(np.float64), np.asarray(ref.points))
        assert np.array_equal(got.normals.astype(np.float64), np.asarray(ref.normals))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("data", DATA)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_our_pcd_reads_back_identically_here_and_in_open3d(seed, data, dtype, tmp_path):
    """Our PCD in each encoding and precision reads back exactly here, and in Open3D."""
    c = cloud_family(seed)
    c.points = c.points.astype(dtype)
    c.point_dtype = dtype
    raw = pcd_bytes(c, data)
    got, details = decode_pcd(raw, "o.pcd")
    assert got.points.dtype == dtype and np.array_equal(got.points, c.points)
    assert np.array_equal(got.colors, c.colors) and np.array_equal(got.normals, c.normals)
    assert all(np.array_equal(got.attributes[k], v) for k, v in c.attributes.items())
    if dtype == np.float64 and data != "ascii":
        # Open3D 0.20's PCD reader returns zeros for binary F 8 fields (PCL reads them): not
        # comparable
        return
    path = tmp_path / "o.pcd"
    path.write_bytes(raw)
    ref = o3d.io.read_point_cloud(str(path))
    if (
        data == "ascii" and dtype == np.float32
    ):  # printed with %.9g: Open3D reads the decimals as doubles
        assert np.array_equal(np.asarray(ref.points).astype(np.float32), c.points)
    else:
        assert np.array_equal(np.asarray(ref.points), c.points.astype(np.float64))
    assert np.array_equal(np.round(np.asarray(ref.colors) * 255).astype(np.uint8), c.colors)


def test_fields_with_counts_padding_and_viewpoint_kept():
    """Fields with counts and padding become attributes; the viewpoint becomes a sensor, kept."""
    head = (
        b"VERSION .7\nFIELDS x y z _ label hist\nSIZE 4 4 4 1 2 4\nTYPE F F F U U F\n"
        b"COUNT 1 1 1 1 1 2\n"
        b"WIDTH 2\nHEIGHT 1\nVIEWPOINT 1 2 3 1 0 0 0\nPOINTS 2\nDATA binary\n"
    )
    rows = np.zeros(
        2,
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("_", "u1"),
            ("label", "<u2"),
            ("hist", "<f4", 2),
        ],
    )
    rows["x"] = [1, 2]
    rows["label"] = [7, 9]
    rows["hist"] = [[0.5, 1.5], [2.5, 3.5]]
    got = decode_pcd(head + rows.tobytes(), "f.pcd")[0]
    assert got.attributes["label"].tolist() == [7, 9] and got.attributes["hist_1"].tolist() == [
        1.5,
        3.5,
    ]
    assert [(s.position, s.orientation) for s in got.sensors] == [((1, 2, 3), (1, 0, 0, 0))]
    again = decode_pcd(pcd_bytes(got), "g.pcd")[0]
    assert again.sensors == got.sensors and again.attributes["label"].tolist() == [7, 9]


@settings(max_examples=200, deadline=None)
@given(
    data=st.one_of(
        st.binary(max_size=3000),
        st.lists(st.sampled_from([b"ab", b"abc", b"\0\0\0\0", b"xyz1"]), max_size=400).map(
            b"".join
        ),
    )
)
def test_lzf_round_trip(data):
    """LZF compression then decompression gives back the bytes."""
    src = as_uint8(data)
    comp = lzf_compress(src)
    out = np.empty(len(src), np.uint8)
    assert lzf_decompress(comp, out) == len(src) and np.array_equal(out, src)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=200), size=st.integers(0, 400))
def test_lzf_decoder_never_overruns(data, size):
    """The LZF decoder on random bytes never writes past its output."""
    out = np.zeros(size, np.uint8)
    got = lzf_decompress(as_uint8(data), out)
    assert -len(data) - 1 <= got <= size


@pytest.mark.parametrize(
    "head, message",
    [
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100\nHEIGHT 1\n"
            "POINTS 100\nDATA binary\n",
            "truncated: POINTS 100 need 1200 bytes",
        ),
        (
            "FIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA binary\n",
            "FIELDS, SIZE, TYPE and COUNT differ",
        ),
        ("FIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nPOINTS 1\nDATA binary\n", "no 'z' field"),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 2\nPOINTS 1\nDATA binary\n",
            "WIDTH 2 x HEIGHT 2 is not POINTS 1",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA zip\n",
            "unknown DATA 'zip'",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n1 2 3\n4 5\n",
            "line 9: 2 values, the fields need 3",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n1 2 3\n",
            "POINTS 2 declared but the data has 1 rows",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA binary_compressed\n",
            "truncated: no compressed sizes",
        ),
        (
            "FIELDS x y z\nSIZE 3 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA binary\n",
            "unsupported field type F3",
        ),
        ("FIELDS x y z\nSIZE 4 4 4\n", "truncated header"),
        (  # found by the fuzz (tests/test_io_readers_fuzz.py): numpy's ValueError, a traceback
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 2147483648 1 1\nWIDTH 1\nPOINTS 1\n"
            "DATA ascii\n1 2 3\n",
            "line 5: a point of 8589934600 bytes (SIZE x COUNT) is longer than the file",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH -1\nHEIGHT -2\nPOINTS 2\nDATA ascii\n",
            "a negative POINTS, WIDTH or HEIGHT",
        ),
        (  # the fuzz: a byte 0x80 in a field name made the PLY and PCD writers' tracebacks
            "FIELDS x y z n\x80\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n"
            "1 2 3 4\n",
            "line 2: field name 'n\\xc2\\x80' is not printable ASCII",
        ),
    ],
)
def test_malformed_files_are_one_line_errors(head, message):
    """Each malformed PCD header is a one-line InputError naming the fault."""
    with pytest.raises(InputError) as exc:
        decode_pcd(("VERSION 0.7\n" + head).encode(), "bad.pcd")
    assert str(exc.value).startswith("bad.pcd: ") and message in str(exc.value), str(exc.value)


def test_compressed_sizes_checked_before_allocation():
    """Compressed sizes that disagree with the header are refused before allocating."""
    head = (
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 300000000\nPOINTS 300000000\n"
        b"DATA binary_compressed\n"
    )
    with pytest.raises(InputError, match="truncated: 10 compressed bytes declared"):
        decode_pcd(head + np.array([10, 3_600_000_000], "<u4").tobytes(), "big.pcd")
    with pytest.raises(InputError, match="uncompressed size 12 is not POINTS"):
        decode_pcd(head + np.array([0, 12], "<u4").tobytes(), "big.pcd")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 30),
    cut=st.floats(0, 1),
    junk=st.binary(max_size=20),
    pos=st.floats(0, 1),
    data=st.sampled_from(DATA),
)
def test_fuzz_truncated_or_corrupted_pcd_is_data_or_input_error(seed, cut, junk, pos, data):
    """A cut or corrupted PCD reads as data or is a one-line InputError."""
    raw = pcd_bytes(cloud_family(seed, 30), data)
    k = int(cut * len(raw))
    p = int(pos * k)
    for variant in (raw[:k], raw[:p] + junk + raw[p:k]):
        try:
            obj = decode_pcd(variant, "f.pcd")[0]
        except InputError as exc:
            assert str(exc).startswith("f.pcd: ") and "\n" not in str(exc)
            continue
        assert isinstance(obj, PointCloud) and np.isfinite(obj.points).all()


def test_signalling_nan_normals_beside_double_coordinates_convert_without_a_warning(
    tmp_path, capfd
):
    """Signalling-NaN float32 normals beside float64 points convert without a warning.

    Float32 normals holding signalling NaNs beside float64 coordinates (the readers' fuzz): the
    cast to the output's doubles raised numpy's warning; they are read as quiet NaNs.
    """
    from recon_cli.cli.main import main

    head = (
        "VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 8 8 8 4 4 4\n"
        "TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n"
    )
    loud = np.array([0x7FA00000, 0x3F800000, 0], np.uint32).view("<f4").tobytes()
    body = b"".join(np.arange(3, dtype="<f8").tobytes() + loud for _ in range(2))
    src = tmp_path / "a.pcd"
    src.write_bytes(head.encode() + body)
    cloud, _ = decode_pcd(src.read_bytes(), str(src))
    assert np.isnan(cloud.normals[:, 0]).all() and (cloud.normals[:, 1] == 1).all()
    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", "convert", str(src), str(tmp_path / "a.ply")])
    assert ex.value.code == 0 and capfd.readouterr().err == ""
