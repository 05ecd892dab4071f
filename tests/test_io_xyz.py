"""Text clouds (XYZ/TXT/CSV/PTS): Open3D's and ours read right, headers, errors, fuzz.

Text clouds (XYZ/TXT/CSV/PTS): Open3D's files read right, ours read back identically (by us and
Open3D), header and delimiter detection, errors by line, fuzz.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud
from recon_cli.io.xyz import decode_xyz, xyz_bytes

from shapes import cloud_family

o3d = pytest.importorskip("open3d")


def o3d_cloud(c):
    """An Open3D cloud of ``c``'s points, normals and colours."""
    p = o3d.geometry.PointCloud()
    p.points = o3d.utility.Vector3dVector(c.points)
    p.normals = o3d.utility.Vector3dVector(c.normals)
    p.colors = o3d.utility.Vector3dVector(c.colors / 255.0)
    return p


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("ext", ["xyz", "xyzn", "xyzrgb", "pts"])
def test_open3d_written_files_read_with_right_counts_and_coordinates(seed, ext, tmp_path):
    """Text clouds Open3D wrote read as Open3D reads them: counts, points, normals, colours."""
    c = cloud_family(seed)
    path = tmp_path / f"c.{ext}"
    o3d.io.write_point_cloud(str(path), o3d_cloud(c), print_progress=False)
    ref = o3d.io.read_point_cloud(str(path))
    got, details = decode_xyz(path.read_bytes(), str(path))
    assert len(got.points) == len(c.points)
    assert np.array_equal(
        got.points, np.asarray(ref.points)
    )  # same text, same correctly rounded doubles
    assert np.abs(got.points - c.points).max() <= 1e-9 * max(1.0, np.abs(c.points).max())
    if ext == "xyzn":
        assert np.abs(got.normals - c.normals).max() < 1e-9
    if ext in ("xyzrgb", "pts"):
        # .pts holds 0..255; .xyzrgb k/255 with 10 decimals, recognised as 8-bit colours
        assert got.colors.dtype == np.uint8 and np.array_equal(got.colors, c.colors)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("csv", [False, True])
def test_our_files_read_back_identically_here_and_in_open3d(seed, csv, tmp_path):
    """Our text clouds (spaces or CSV) read back exactly here, with their header and history."""
    c = cloud_family(seed)
    c.history = ["from a test"]
    data = xyz_bytes(c, csv=csv)
    got, details = decode_xyz(data, "o")
    assert details["header"] and details["delimiter"] == ("comma" if csv else "white space")
    assert np.array_equal(got.points, c.points) and np.array_equal(got.normals, c.normals)
    assert np.array_equal(got.colors, c.colors) and got.colors.dtype == np.uint8
    assert all(np.array_equal(got.attributes[k], v) for k, v in c.attributes.items())
    if not csv:
        assert got.history == ["from a test"]
        plain = PointCloud(points=c.points, normals=c.normals, point_dtype=np.float64)
        path = tmp_path / "o.xyzn"
        path.write_bytes(xyz_bytes(plain))
        ref = o3d.io.read_point_cloud(str(path))
        assert np.array_equal(np.asarray(ref.points), c.points) and np.array_equal(
            np.asarray(ref.normals), c.normals
        )


@pytest.mark.parametrize(
    "data, columns",
    [
        (b"1 2 3\n4 5 6\n", ["x", "y", "z"]),
        (b"1;2;3;9\n4;5;6;8\n", ["x", "y", "z", "intensity"]),
        (
            b"X,Y,Z,Intensity,R,G,B\n1,2,3,4,5,6,7\n",
            ["x", "y", "z", "Intensity", "red", "green", "blue"],
        ),
        (b"//X Y Z Nx Ny Nz\n1 2 3 0 0 1\n", ["x", "y", "z", "nx", "ny", "nz"]),
        (
            b"2\n1 2 3 0 10 20 30\n4 5 6 0 40 50 60\n",
            ["x", "y", "z", "intensity", "red", "green", "blue"],
        ),
        (b"1\t2\t3\t0\t0\t1\n", ["x", "y", "z", "nx", "ny", "nz"]),
        (b"1 2 3 10 20 30\n", ["x", "y", "z", "red", "green", "blue"]),
        (b"1 2 3 10 20 300\n", ["x", "y", "z", "column_3", "column_4", "column_5"]),
        (b"# made somewhere\n1 2 3 4 5\n", ["x", "y", "z", "column_3", "column_4"]),
    ],
)
def test_header_delimiter_and_column_detection(data, columns):
    """Headers, delimiters and columns are detected from the text."""
    got, details = decode_xyz(data, "d.txt")
    assert details["columns"] == columns
    assert got.points[0].tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize(
    "data, message",
    [
        (b"1 2 3\n4 5\n", "line 2: 2 columns, the first row has 3"),
        (b"x y z\n1 2 3\n4 5 q\n", "line 3: 'q' is not a number"),
        (b"3\n1 2 3\n4 5 6\n", "line 1 declares 3 points but the file has 2 rows"),
        (b"1,2,3\n4,,6\n", "line 2: a value is missing"),
        (b"", "no data rows"),
        (b"a b\n1 2\n", "rows have 2 columns"),
        (b"x y z w\n1 2 3\n", "the header names 4 columns but the rows have 3"),
        (b"a b c\n1 2 3\n", "has no x, y and z columns"),
    ],
)
def test_malformed_files_name_the_line(data, message):
    """Each malformed text cloud is a one-line InputError naming its line."""
    with pytest.raises(InputError) as exc:
        decode_xyz(data, "bad.xyz")
    assert str(exc.value).startswith("bad.xyz: ") and message in str(exc.value), str(exc.value)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 30),
    cut=st.floats(0, 1),
    junk=st.binary(max_size=20),
    pos=st.floats(0, 1),
    csv=st.booleans(),
)
def test_fuzz_truncated_or_corrupted_text_is_data_or_input_error(seed, cut, junk, pos, csv):
    """A cut or corrupted text cloud reads as data or is a one-line InputError."""
    data = xyz_bytes(cloud_family(seed, 20), csv=csv)
    k = int(cut * len(data))
    p = int(pos * k)
    for variant in (data[:k], data[:p] + junk + data[p:k]):
        try:
            obj = decode_xyz(variant, "f.xyz")[0]
        except InputError as exc:
            assert str(exc).startswith("f.xyz: ") and "\n" not in str(exc)
            continue
        assert np.isfinite(obj.points).all() and obj.points.shape[1] == 3
