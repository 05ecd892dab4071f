"""OFF: trimesh's files read right, ours read back identically (by us and trimesh), fuzz."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.off import decode_off, off_bytes

from shapes import mesh_family

trimesh = pytest.importorskip("trimesh")


@pytest.mark.parametrize("seed", range(6))
def test_trimesh_written_off_reads_with_right_counts_and_coordinates(seed):
    """OFF files trimesh wrote read with their counts, faces and coordinates to 1e-15."""
    m = mesh_family(seed)
    tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
    data = trimesh.exchange.off.export_off(tm, digits=17).encode()
    got, details = decode_off(data, "t.off")
    assert details["declared"] == [len(m.vertices), len(m.faces)]
    assert np.array_equal(got.faces, m.faces)
    assert np.abs(got.vertices - m.vertices).max() <= 1e-15 * np.abs(m.vertices).max()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_our_off_reads_back_identically_here_and_in_trimesh(seed, dtype):
    """Our OFF (float32 or float64) reads back exactly here and in trimesh, history too."""
    m = mesh_family(seed, dtype)
    m.history = ["from a test"]
    data = off_bytes(m)
    got = decode_off(data, "o.off")[0]
    assert np.array_equal(got.vertices.astype(dtype), m.vertices) and np.array_equal(
        got.faces, m.faces
    )
    assert got.history == ["from a test"]
    if m.colors is not None:
        assert data.startswith(b"CNOFF")
        assert np.array_equal(got.colors, m.colors) and np.array_equal(
            got.normals.astype(dtype), m.normals
        )
    else:
        tm = trimesh.load(io.BytesIO(data), file_type="off", process=False)
        assert np.array_equal(tm.faces, m.faces) and np.array_equal(
            tm.vertices.astype(dtype), m.vertices
        )


def test_polygons_face_colours_and_counts_on_the_keyword_line():
    """Polygons are fanned, face colours read, counts on the keyword line; no faces is a cloud."""
    data = (
        b"OFF 5 2 0\n# a comment\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3 255 0 0\n"
        b"3 0 1 4 0 255 0\n"
    )
    m = decode_off(data, "p.off")[0]
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    assert (
        m.face_attributes["red"].tolist() == [255, 255, 0]
        and m.face_attributes["red"].dtype == np.uint8
    )
    cloud = decode_off(b"OFF\n2 0 0\n1 2 3\n4 5 6\n", "c.off")[0]
    assert isinstance(cloud, PointCloud) and cloud.points.tolist() == [[1, 2, 3], [4, 5, 6]]


@pytest.mark.parametrize(
    "data, message",
    [
        (b"OFX\n", "not an OFF file"),
        (
            b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n",
            "truncated: the header declares 3 vertices and 1 faces but the file has 3 rows",
        ),
        (
            b"OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n",
            "line 4: a OFF vertex row holds 3 numbers, not 2",
        ),
        (
            b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
            "line 6: vertex index 7 out of range for 3 vertices",
        ),
        (
            b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n",
            "line 6: a face must start with its number of corners",
        ),
        (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 2\n", "line 7: more rows than"),
        (b"OFF\n99999999999 1 0\n0 0 0\n", "truncated"),
        (b"OFF\n-1 0 0\n", "line 2: the counts must be"),
        (b"OFF\n1 0 0\n0 0 z\n", "line 3: 'z' is not a number"),
        (
            b"OFF\n3 1 0\n0 0 inf\n1 0 0\n0 1 0\n3 0 1 2\n",
            "face 0 uses vertex 0, which has a NaN or infinite coordinate",
        ),
    ],
)
def test_malformed_files_name_the_line(data, message):
    """Each malformed OFF is a one-line InputError naming its line."""
    with pytest.raises(InputError) as exc:
        decode_off(data, "bad.off")
    assert str(exc.value).startswith("bad.off: ") and message in str(exc.value), str(exc.value)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 50), cut=st.floats(0, 1), junk=st.binary(max_size=20), pos=st.floats(0, 1)
)
def test_fuzz_truncated_or_corrupted_off_is_data_or_input_error(seed, cut, junk, pos):
    """A cut or corrupted OFF reads as data or is a one-line InputError."""
    data = off_bytes(mesh_family(seed))
    k = int(cut * len(data))
    p = int(pos * k)
    for variant in (data[:k], data[:p] + junk + data[p:k]):
        try:
            obj = decode_off(variant, "f.off")[0]
        except InputError as exc:
            assert str(exc).startswith("f.off: ") and "\n" not in str(exc)
            continue
        assert np.isfinite(obj.points).all()
        if isinstance(obj, TriangleMesh) and len(obj.faces):
            assert obj.faces.min() >= 0 and obj.faces.max() < len(obj.points)


def test_an_infinite_count_is_refused_in_one_line():
    """``OFF 1e400 0 0`` (the readers' fuzz): int(inf) raised OverflowError, a traceback."""
    with pytest.raises(InputError) as exc:
        decode_off(b"OFF 1e400 0 0\n0 0 0\n", "a.off")
    assert str(exc.value) == "a.off: line 1: the counts must be 2 or 3 non-negative integers"


def test_a_face_count_past_int64_is_refused_in_one_line():
    """A face row with a number past int64 is refused in one line.

    A face row ``18446744073709551616`` (the readers' fuzz): numpy's cast warning, a
    traceback under -W error.
    """
    with pytest.raises(InputError) as exc:
        decode_off(b"OFF 0 1 0\n18446744073709551616\n", "a.off")
    assert str(exc.value) == (
        "a.off: line 2: a face of 18446744073709551616 corners has 0 values after its count"
    )
