"""STL: binary and ASCII from trimesh read and welded right, ours read back identically, fuzz."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh
from recon_cli.io.stl import decode_stl, float32_rounding, stl_bytes, write_stl
from recon_cli.mesh.topology import report

from shapes import mesh_family

trimesh = pytest.importorskip("trimesh")


def _same_triangles(a, b):
    return np.array_equal(a.vertices[a.faces], b.vertices[b.faces])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("ascii", [False, True])
def test_trimesh_written_stl_reads_welded_with_the_topology_of_the_source(seed, ascii):
    """STL files trimesh wrote weld back to the source's vertices: a closed torus, exact corners."""
    m = mesh_family(seed)
    tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
    data = (
        trimesh.exchange.stl.export_stl_ascii(tm).encode()
        if ascii
        else trimesh.exchange.stl.export_stl(tm)
    )
    got, details = decode_stl(data, "t.stl")
    assert details["encoding"] == ("ascii" if ascii else "binary")
    assert details["triangles"] == len(m.faces) and details["weld_tolerance"] == 0.0
    # welding gives back every vertex of the torus: closed, genus 1
    assert len(got.vertices) == len(m.vertices) == details["vertices"]
    topo = report(got)
    assert topo["watertight"] and topo["genus"] == 1
    want = m.vertices[m.faces].astype(np.float32 if not ascii else np.float64)
    tol = 0 if not ascii else 1e-15 * np.abs(m.vertices).max()
    assert np.abs(got.vertices[got.faces] - want).max() <= tol


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("ascii", [False, True])
def test_our_stl_reads_back_identically_here_and_in_trimesh(seed, ascii):
    """Our STL (binary or ASCII) reads back the same triangles here and in trimesh."""
    m = mesh_family(seed, np.float32)
    data = stl_bytes(m, ascii=ascii)
    got = decode_stl(data, "o.stl")[0]
    assert np.array_equal(got.vertices[got.faces].astype(np.float32), m.vertices[m.faces])
    assert got.history == []
    tm = trimesh.load(io.BytesIO(data), file_type="stl", process=False)
    assert np.array_equal(tm.vertices.reshape(-1, 3, 3).astype(np.float32), m.vertices[m.faces])
    if not ascii:  # facet normals: the triangles' unit normals (from the float64 coordinates)
        ref = trimesh.Trimesh(m.vertices.astype(np.float64), m.faces, process=False).face_normals
        stored = np.frombuffer(data[84:], dtype=[("n", "<f4", 3), ("v", "<f4", 9), ("a", "<u2")])[
            "n"
        ]
        assert np.allclose(stored, ref, atol=1e-6)


def test_float64_to_binary_stl_warns_with_the_rounding(tmp_path, caplog):
    """float64 far off written as binary STL warns of the float32 rounding; ASCII does not."""
    m = mesh_family(1)  # float64, possibly at large offsets
    m.vertices = m.vertices + 5e6
    with caplog.at_level("WARNING", logger="recon"):
        write_stl(m, tmp_path / "m.stl")
    assert float32_rounding(m) > 0 and "binary STL stores float32" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="recon"):
        write_stl(m, tmp_path / "a.stl", ascii=True)
    assert caplog.text == ""
    assert _same_triangles(decode_stl((tmp_path / "a.stl").read_bytes(), "a")[0], m)


def test_negative_zero_welds_with_zero_and_attribute_kept():
    """-0.0 welds with 0.0, and each facet's attribute word is kept."""
    m = TriangleMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-0.0, 0, 0]], np.float32),
        faces=[[0, 1, 2], [3, 2, 1]],
    )
    m.face_attributes["attribute"] = np.array([7, 0], np.uint16)
    got = decode_stl(stl_bytes(m), "z.stl")[0]
    assert len(got.vertices) == 3 and got.face_attributes["attribute"].tolist() == [7, 0]


@pytest.mark.parametrize(
    "data, message",
    [
        (
            b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\n"
            b"endfacet\nendsolid\n",
            "line 6: a facet must have exactly 3 vertices",
        ),
        (
            b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 q 0\n",
            "line 6: 'q' is not a number",
        ),
        (b"solid x\nfacet normal 0 0 1\n outer loop\n", "the file ends inside a facet"),
        (b"solid x\nfacet normal 0 0 1\nouter lop\n", "line 3: unexpected word"),
        (b"x" * 100, "binary STL header declares"),
        (b"x" * 50, "truncated: a binary STL needs at least 84 bytes"),
        (b"", "empty file"),
    ],
)
def test_malformed_files_name_the_line_or_size(data, message):
    """Each malformed STL is a one-line InputError naming its line or its size."""
    with pytest.raises(InputError) as exc:
        decode_stl(data, "bad.stl")
    assert str(exc.value).startswith("bad.stl: ") and message in str(exc.value), str(exc.value)


def test_nan_corner_is_refused():
    """A NaN corner is refused, naming its triangle."""
    m = mesh_family(2, np.float32)
    data = bytearray(stl_bytes(m))
    data[84 + 12 : 84 + 16] = np.float32(np.nan).tobytes()
    with pytest.raises(InputError, match="triangle 0 has a NaN"):
        decode_stl(bytes(data), "n.stl")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 30),
    cut=st.floats(0, 1),
    junk=st.binary(max_size=20),
    pos=st.floats(0, 1),
    ascii=st.booleans(),
)
def test_fuzz_truncated_or_corrupted_stl_is_data_or_input_error(seed, cut, junk, pos, ascii):
    """A cut or corrupted STL reads as data or is a one-line InputError."""
    data = stl_bytes(mesh_family(seed), ascii=ascii)
    k = int(cut * len(data))
    p = int(pos * k)
    for variant in (data[:k], data[:p] + junk + data[p:k]):
        try:
            obj = decode_stl(variant, "f.stl")[0]
        except InputError as exc:
            assert str(exc).startswith("f.stl: ") and "\n" not in str(exc)
            continue
        assert np.isfinite(obj.points).all()
        if len(obj.faces):
            assert obj.faces.min() >= 0 and obj.faces.max() < len(obj.points)
