"""The format registry and the commands on every format: convert, info, stages, refusals.

Convert between any two formats, info, stages by suffix, --format for streams, refusals (unknown
suffix, faces to a points-only format).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.load import FORMATS, format_of, load, save, sniff

from shapes import cloud_family, mesh_family

RECON = [sys.executable, "-m", "recon_cli.cli.main"]
MESH_SUFFIXES = [".ply", ".obj", ".off", ".stl", ".OBJ"]
CLOUD_SUFFIXES = [
    ".ply",
    ".obj",
    ".off",
    ".xyz",
    ".txt",
    ".csv",
    ".pts",
    ".pcd",
    ".las",
    ".laz",
    ".PCD",
]


def recon(*args, input: bytes | None = None):
    """Run ``recon`` with ``args`` as a process, its output captured."""
    return subprocess.run([*RECON, *map(str, args)], input=input, capture_output=True, timeout=300)


def _same_mesh(a, b, exact=True):
    ta = a.vertices[a.faces].astype(np.float64)
    tb = b.vertices[b.faces].astype(np.float64)
    return ta.shape == tb.shape and (
        np.array_equal(ta, tb)
        if exact
        else np.allclose(ta, tb, rtol=0, atol=1e-6 * np.abs(ta).max())
    )


@pytest.mark.parametrize("src", MESH_SUFFIXES)
@pytest.mark.parametrize("dst", MESH_SUFFIXES)
def test_meshes_convert_between_any_two_mesh_formats(src, dst, tmp_path):
    """A float32 mesh through any two mesh formats comes back exactly, STL welded again."""
    m = mesh_family(5, np.float32)  # float32: every format holds it exactly
    save(m, tmp_path / f"a{src}")
    got = load(tmp_path / f"a{src}")
    save(got, tmp_path / f"b{dst}")
    again = load(tmp_path / f"b{dst}")
    assert isinstance(again, TriangleMesh) and _same_mesh(again, m)
    assert len(again.vertices) == len(m.vertices)  # STL is welded back to the shared vertices


@pytest.mark.parametrize("dst", CLOUD_SUFFIXES)
def test_clouds_convert_to_every_cloud_format_and_back(dst, tmp_path):
    """A cloud through each cloud format comes back exactly (LAS within its grid), normals too."""
    c = cloud_family(2)
    c.attributes = {}  # a LAS file adds its standard dimensions; checked in test_io_las
    save(c, tmp_path / f"c{dst}")
    got = load(tmp_path / f"c{dst}")
    assert isinstance(got, PointCloud) and len(got.points) == len(c.points)
    tol = 5e-9 * np.ptp(c.points, axis=0).max() if dst.lower() in (".las", ".laz") else 0.0
    assert np.abs(got.points - c.points).max() <= tol
    assert np.array_equal(got.normals, c.normals)


def test_registry_suffixes_case_and_unknown(tmp_path):
    """Suffixes in any case name their format; an unknown one is refused, listing the known."""
    assert (
        format_of("A.LAZ").name == "las"
        and format_of("x.Csv").name == "xyz"
        and format_of("-") is None
    )
    with pytest.raises(ParameterError) as exc:
        format_of("scan.foo")
    assert ".ply" in str(exc.value) and ".laz" in str(exc.value)
    for fmt in FORMATS.values():
        assert format_of(f"f{fmt.suffixes[0]}") is fmt


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".stl", ".xyz", ".csv", ".pcd", ".las"])
def test_sniffing_recognises_our_output(suffix, tmp_path):
    """Each format we write is recognised by its content, and a file without a suffix reads."""
    obj = mesh_family(3, np.float32) if suffix in (".stl", ".off", ".obj") else cloud_family(1)
    save(obj, tmp_path / f"s{suffix}")
    want = format_of(f"s{suffix}")
    assert sniff((tmp_path / f"s{suffix}").read_bytes()) is want
    # a name without a suffix is read by content
    (tmp_path / "nosuffix").write_bytes((tmp_path / f"s{suffix}").read_bytes())
    assert len(load(tmp_path / "nosuffix").points) == len(obj.points)


def test_mesh_to_points_only_format_refused_or_points_only(tmp_path, caplog):
    """A mesh to a points-only format is refused, or written as its vertices with points_only."""
    m = mesh_family(2)
    with pytest.raises(
        ParameterError, match="holds points only; the mesh's .* faces would be dropped"
    ):
        save(m, tmp_path / "m.xyz")
    assert not (tmp_path / "m.xyz").exists()
    with caplog.at_level("WARNING", logger="recon"):
        save(m, tmp_path / "m.pcd", points_only=True)
    assert "dropped" in caplog.text
    assert np.array_equal(load(tmp_path / "m.pcd").points, m.vertices)
    with pytest.raises(ParameterError, match="a point cloud cannot be written as STL"):
        save(cloud_family(0), tmp_path / "c.stl")


def test_missing_extra_names_the_pip_install(tmp_path, monkeypatch):
    """Writing LAS without laspy names the ``pip install 'recon[las]'`` that brings it."""
    monkeypatch.setitem(sys.modules, "laspy", None)
    with pytest.raises(ParameterError, match=r"pip install 'recon\[las\]'"):
        save(cloud_family(0), tmp_path / "c.las")


def test_e57_written_by_pye57_reads_with_right_counts_and_coordinates(tmp_path):
    """An E57 pye57 wrote reads exactly; E57 is not written, and a cut file is refused."""
    pye57 = pytest.importorskip("pye57")
    rng = np.random.default_rng(4)
    # pye57 stores float32 coordinates: values it holds exactly, at UTM-like magnitudes
    pts = (
        (rng.integers(0, 2**20, (200, 3)) * 0.125 + [5e5, 5e6, 0])
        .astype(np.float32)
        .astype(np.float64)
    )
    path = tmp_path / "s.e57"
    e = pye57.E57(str(path), mode="w")
    e.write_scan_raw(
        {
            "cartesianX": pts[:, 0],
            "cartesianY": pts[:, 1],
            "cartesianZ": pts[:, 2],
            "intensity": rng.random(200),
        }
    )
    e.close()
    got = load(path)
    assert np.array_equal(got.points, pts) and len(got.attributes["intensity"]) == 200
    with pytest.raises(ParameterError, match="reads E57 but does not write it"):
        save(got, tmp_path / "o.e57")
    with pytest.raises(InputError, match="not a readable E57 file"):
        path.write_bytes(path.read_bytes()[:1000])
        load(path)


def test_cli_convert_info_and_errors(tmp_path):
    """``recon convert`` and ``info`` across formats; unknown suffixes and faces to XYZ refused."""
    m = mesh_family(1, np.float32)
    save(m, tmp_path / "m.ply")
    r = recon("convert", tmp_path / "m.ply", tmp_path / "m.obj")
    assert r.returncode == 0, r.stderr
    assert _same_mesh(load(tmp_path / "m.obj"), m)
    r = recon("convert", tmp_path / "m.obj", tmp_path / "m.stl")
    assert r.returncode == 0 and _same_mesh(load(tmp_path / "m.stl"), m)
    for name in ("m.obj", "m.stl"):
        r = recon("info", "--json", tmp_path / name)
        rep = json.loads(r.stdout)[0]
        assert r.returncode == 0 and rep["faces"] == len(m.faces) and rep["topology"]["genus"] == 1
    assert (
        json.loads(recon("info", "--json", tmp_path / "m.stl").stdout)[0]["details"][
            "weld_tolerance"
        ]
        == 0.0
    )
    # unknown suffix: exit 2, one line listing what is supported, nothing written
    r = recon("convert", tmp_path / "m.ply", tmp_path / "m.foo")
    err = r.stderr.decode().strip()
    assert (
        r.returncode == 2
        and len(err.splitlines()) == 1
        and ".laz" in err
        and not (tmp_path / "m.foo").exists()
    )
    # faces to a points-only format: refused, then allowed with --points-only
    r = recon("convert", tmp_path / "m.ply", tmp_path / "m.xyz")
    assert (
        r.returncode == 2
        and "--points-only" in r.stderr.decode()
        and not (tmp_path / "m.xyz").exists()
    )
    r = recon("convert", "--points-only", tmp_path / "m.ply", tmp_path / "m.xyz")
    assert r.returncode == 0 and "dropped" in r.stderr.decode()
    # a malformed file: exit 2, one line naming the file and the line
    (tmp_path / "bad.obj").write_bytes(b"v 1 2 3\nv 1 2 oops\n")
    r = recon("info", tmp_path / "bad.obj")
    assert (
        r.returncode == 2
        and r.stderr.decode().strip()
        == f"recon: error: {tmp_path / 'bad.obj'}: line 2: 'oops' is not a number"
    )


def test_cli_streams_with_formats(tmp_path):
    """Streams are sniffed or named by --input-format/--output-format; stages write by suffix."""
    c = cloud_family(3, 200)
    save(c, tmp_path / "c.xyz")
    data = (tmp_path / "c.xyz").read_bytes()
    # '-' is sniffed; --input-format/--output-format name the stream formats
    r = recon("convert", "--output-format", "pcd", "-", "-", input=data)
    assert r.returncode == 0 and r.stdout.startswith(b"# .PCD")
    r2 = recon("convert", "--input-format", "pcd", "-", tmp_path / "c.laz", input=r.stdout)
    assert r2.returncode == 0, r2.stderr
    assert (
        np.abs(load(tmp_path / "c.laz").points - c.points).max()
        <= 5e-9 * np.ptp(c.points, axis=0).max()
    )
    r3 = recon("info", "--format", "pcd", "--json", "-", input=r.stdout)
    assert json.loads(r3.stdout)[0]["format"] == "pcd"
    # a stage reads and writes by suffix
    r4 = recon("normals", "--knn", "10", "--format", "xyz", "-", tmp_path / "n.pcd", input=data)
    assert r4.returncode == 0, r4.stderr
    got = load(tmp_path / "n.pcd")
    assert np.array_equal(got.points, c.points) and got.normals is not None


def test_normals_on_a_mesh_says_it_writes_the_vertices(tmp_path):
    """``recon normals`` of a mesh says it writes the vertices only."""
    save(mesh_family(4), tmp_path / "m.off")
    r = recon("normals", "--knn", "8", tmp_path / "m.off", tmp_path / "n.ply")
    assert r.returncode == 0 and "vertices only are written" in r.stderr.decode()


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".xyz", ".stl", ".pcd", ".las"])
def test_history_of_any_characters_is_written_on_one_line(suffix, tmp_path):
    """Every writer writes any history line as one line of printable ASCII.

    A history line read from a file (an STL's name in latin-1, a glTF string with a newline)
    is written by every writer as one line of printable ASCII (other characters escaped), and the
    file reads back.
    """
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    obj = TriangleMesh(vertices=v, faces=f) if suffix in (".ply", ".obj", ".off", ".stl") else None
    obj = obj or PointCloud(points=v)
    obj.history = ["name \x80\xe9 ü", "two\nlines\r\x00end"]
    path = tmp_path / f"h{suffix}"
    save(obj, str(path))
    back = load(str(path))
    got = np.unique(np.asarray(back.points, dtype=float), axis=0)
    assert np.array_equal(got, np.unique(v, axis=0))
    written = [h for h in back.history if "name" in h or "two" in h]
    if suffix in (".ply", ".obj", ".off", ".xyz"):
        assert written == ["name \\x80\\xe9 \\xfc", "two\\nlines\\r\\x00end"]
