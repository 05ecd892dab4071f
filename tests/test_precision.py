"""Double in, double out: every stage far from the origin (1e6, UTM-like) as at the origin.

Each stage runs on the same generated shape at the origin and moved by an offset; the output
must be double (in memory and once written), keep the input's coordinates where it keeps
them, and be as accurate as at the origin (radius errors, normals, distances, vertices).
The data model's rule for float32 sources (docs/formats.md, "Data model") is checked at the end.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.geometry import PointCloud, TriangleMesh, storage_dtype
from recon_cli.grid import Grid
from recon_cli.io.load import load, save
from recon_cli.io.ply import ply_bytes, read_ply, write_ply
from recon_cli.stages import apply_stage
from recon_cli.tolerances import tol

from shapes import FAR_OFFSETS, icosphere, sphere_cloud

FAR = [k for k in FAR_OFFSETS if k != "origin"]
RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def _offset(where: str) -> np.ndarray:
    return np.asarray(FAR_OFFSETS[where])


def _written(obj, tmp_path, name="out.ply"):
    """``obj`` written to a PLY file and read back."""
    path = tmp_path / name
    save(obj, path)
    return load(path)


def _assert_double(obj, tmp_path):
    """``obj`` is double in memory and in its file, and the file holds exactly its coordinates."""
    assert obj.point_dtype == np.float64
    back = _written(obj, tmp_path)
    assert back.point_dtype == np.float64 and back.points.dtype == np.float64
    np.testing.assert_array_equal(back.points, obj.points)
    return back


def _radius_errors(vertices: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    return np.abs(np.linalg.norm(np.asarray(vertices, np.float64) - centre, axis=1) - radius)


# ------------------------------------------------------------------------------------- stages


@pytest.mark.parametrize("where", FAR)
def test_normals_far_from_origin_as_at_origin(where, tmp_path):
    """Normals of a sphere moved far away equal those at the origin, its points kept exactly.

    Outward, within 1e-6 of the origin's normals, no precision note, written and read back as
    double.
    """
    p0, outward = sphere_cloud(3000, radius=10.0)
    ref = apply_stage("normals", PointCloud(points=p0)).output
    res = apply_stage("normals", PointCloud(points=p0 + _offset(where)))
    out = res.output
    np.testing.assert_array_equal(out.points, p0 + _offset(where))
    assert np.all(np.einsum("ij,ij->i", out.normals, outward) > 0.9)
    # the same normals as at the origin: they do not depend on where the sphere is
    assert np.abs(out.normals - ref.normals).max() < 1e-6
    assert "precision" not in res.report
    back = _assert_double(out, tmp_path)
    np.testing.assert_array_equal(back.normals, out.normals)


@pytest.mark.parametrize("where", FAR)
def test_poisson_far_from_origin_as_at_origin(where, tmp_path):
    """Poisson of a sphere moved far away: as many faces and no larger radius errors than at 0.

    Written as double, read back just as accurate.
    """
    p0, n0 = sphere_cloud(20_000, radius=10.0)
    ref = apply_stage("poisson", PointCloud(points=p0, normals=n0), {"depth": 6}).output
    out = apply_stage(
        "poisson", PointCloud(points=p0 + _offset(where), normals=n0), {"depth": 6}
    ).output
    e0 = _radius_errors(ref.vertices, np.zeros(3), 10.0)
    e = _radius_errors(out.vertices, _offset(where), 10.0)
    assert len(out.faces) == len(ref.faces)
    # at the origin: median ~0.5 %, max ~1.5 % of the radius at depth 6 (float32 at y = 5.1e6 rounds
    # by 0.25)
    assert np.median(e) <= 1.05 * np.median(e0) + 1e-6
    assert e.max() <= 1.05 * e0.max() + 1e-6
    back = _assert_double(out, tmp_path)
    assert (
        np.median(_radius_errors(back.vertices, _offset(where), 10.0))
        <= 1.05 * np.median(e0) + 1e-6
    )


@pytest.mark.parametrize("where", FAR)
def test_ballpivot_far_from_origin_as_at_origin(where, tmp_path):
    """Ball pivoting of a sphere moved far away: the origin's triangles on the exact points."""
    p0, n0 = sphere_cloud(3000, radius=10.0, seed=1)
    ref = apply_stage("ballpivot", PointCloud(points=p0, normals=n0)).output
    out = apply_stage("ballpivot", PointCloud(points=p0 + _offset(where), normals=n0)).output
    np.testing.assert_array_equal(out.vertices, p0 + _offset(where))
    # the same triangles as at the origin (ball centres are computed about a local origin)
    assert np.array_equal(
        np.sort(out.faces, axis=1)[np.lexsort(np.sort(out.faces, axis=1).T)],
        np.sort(ref.faces, axis=1)[np.lexsort(np.sort(ref.faces, axis=1).T)],
    )
    _assert_double(out, tmp_path)


def _damaged_icosphere(centre):
    """An icosphere (r = 10), vertices duplicated, 32 faces flipped and 2 faces removed (holes)."""
    v, f = icosphere(3, radius=10.0, centre=centre)
    f = f.copy()
    f[::40] = f[::40, ::-1]
    dup = np.arange(0, 200, 7)
    v = np.concatenate([v, v[dup]])
    moved = np.isin(f, dup) & (np.arange(len(f)) % 3 == 0)[:, None]
    f[moved] = len(v) - len(dup) + np.searchsorted(dup, f[moved])
    return v, np.delete(f, [5, 6], axis=0)


@pytest.mark.parametrize("where", FAR)
def test_repair_far_from_origin_as_at_origin(where, tmp_path):
    """Repair of a damaged sphere moved far away: the origin's faces, the input's exact vertices.

    The same merges, fills and volume as at the origin; written as double.
    """
    params = {"fill_holes": 8}
    v0, f0 = _damaged_icosphere(np.zeros(3))
    ref = apply_stage("repair", TriangleMesh(v0, f0), params)
    v, f = _damaged_icosphere(_offset(where))
    res = apply_stage("repair", TriangleMesh(v, f), params)
    out, rep = res.output, res.report
    assert rep["watertight"] and ref.report["watertight"]
    assert rep["vertices_merged"] == ref.report["vertices_merged"] > 0
    assert rep["holes_filled"] == ref.report["holes_filled"] >= 1
    np.testing.assert_array_equal(out.faces, ref.output.faces)
    # every output vertex is an input row, unrounded
    np.testing.assert_array_equal(out.vertices, ref.output.vertices + _offset(where))
    # the volume (cross products) is computed about a local origin: as exact as at the origin
    assert rep["volume"] == pytest.approx(ref.report["volume"], rel=1e-9)
    assert ref.report["volume"] == pytest.approx(4 / 3 * np.pi * 1000, rel=0.02)
    _assert_double(out, tmp_path)


@pytest.mark.parametrize("where", FAR)
@pytest.mark.parametrize("source", ["mesh", "cloud"])
def test_sdf_and_mcubes_far_from_origin_as_at_origin(where, source, tmp_path):
    """The sdf then mcubes of a mesh or cloud moved far: the origin's grid and surface, moved."""
    if source == "mesh":
        v, f = icosphere(3, radius=10.0)
        make = lambda c: TriangleMesh(v + c, f)  # noqa: E731
    else:
        p, n = sphere_cloud(8000, radius=10.0, seed=2)
        make = lambda c: PointCloud(points=p + c, normals=n)  # noqa: E731
    params = {"resolution": 32}
    g0 = apply_stage("sdf", make(np.zeros(3)), params).output
    g = apply_stage("sdf", make(_offset(where)), params).output
    assert g.voxel_size == pytest.approx(g0.voxel_size, rel=1e-12)
    np.testing.assert_allclose(g.origin, g0.origin + _offset(where), rtol=0, atol=1e-9)
    # the same distances as at the origin (float32 values of magnitude ~10: ~1e-6)
    assert np.nanmax(np.abs(g.sdf - g0.sdf)) <= 1e-5 * g0.voxel_size
    assert g.point_dtype == np.float64
    g_back = _written(g, tmp_path, "grid.npz")
    assert g_back.point_dtype == np.float64 and np.array_equal(g_back.origin, g.origin)

    m0 = apply_stage("mcubes", g0).output
    m = apply_stage("mcubes", g_back).output
    assert np.array_equal(m.faces, m0.faces)
    # vertices in world units: the grid's double origin plus the same local positions
    np.testing.assert_allclose(
        m.vertices, m0.vertices + _offset(where), rtol=0, atol=1e-6 * g0.voxel_size
    )
    _assert_double(m, tmp_path)


def test_reference_backends_far_from_origin_as_at_origin():
    """Open3D computes in float32 in places: its calls are made about a local origin too."""
    off = _offset("utm")
    v, f = icosphere(3, radius=10.0)
    params = {"resolution": 24, "backend": "open3d"}
    g0 = apply_stage("sdf", TriangleMesh(v, f), params).output
    g = apply_stage("sdf", TriangleMesh(v + off, f), params).output
    # was a voxel off at UTM coordinates
    assert np.nanmax(np.abs(g.sdf - g0.sdf)) <= 1e-4 * g0.voxel_size
    p, n = sphere_cloud(3000, radius=10.0)
    params = {"depth": 6, "backend": "open3d"}
    m0 = apply_stage("poisson", PointCloud(points=p, normals=n), params).output
    m = apply_stage("poisson", PointCloud(points=p + off, normals=n), params).output
    assert m.point_dtype == np.float64
    e0, e = _radius_errors(m0.vertices, np.zeros(3), 10.0), _radius_errors(m.vertices, off, 10.0)
    # was 0.060 m median, 0.54 m max against 0.0043 / 0.041 at the origin
    assert np.median(e) <= 1.05 * np.median(e0) + 1e-6 and e.max() <= 1.05 * e0.max() + 1e-6


@pytest.mark.parametrize("ascii_", [False, True])
def test_convert_keeps_doubles(ascii_, tmp_path):
    """``recon convert`` (binary or ASCII) keeps double coordinates and normals at UTM offsets."""
    p, n = sphere_cloud(500, radius=10.0, centre=FAR_OFFSETS["utm"])
    src = tmp_path / "in.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    args = [*RECON, "convert", src, tmp_path / "out.ply"] + (["--ascii"] if ascii_ else [])
    subprocess.run(list(map(str, args)), check=True, capture_output=True, timeout=300)
    back = read_ply(tmp_path / "out.ply")
    assert back.point_dtype == np.float64
    np.testing.assert_array_equal(back.points, p)
    np.testing.assert_array_equal(back.normals, n)


def test_utm_normals_then_poisson_on_the_command_line_as_at_origin(tmp_path):
    """The issue's case: `recon normals | recon poisson --depth 7` at UTM-like coordinates.

    A double cloud, meshed as at the origin.
    """
    env = dict(os.environ)
    errors = {}
    for where in ("origin", "utm"):
        p, _ = sphere_cloud(20_000, radius=10.0, centre=FAR_OFFSETS[where])
        write_ply(PointCloud(points=p), tmp_path / f"{where}.ply")
        normals = subprocess.run(
            [*RECON, "-q", "normals", str(tmp_path / f"{where}.ply"), "-"],
            capture_output=True,
            check=True,
            env=env,
            timeout=300,
        ).stdout
        subprocess.run(
            [*RECON, "-q", "poisson", "--depth", "7", "-", str(tmp_path / f"{where}.mesh.ply")],
            input=normals,
            capture_output=True,
            check=True,
            env=env,
            timeout=300,
        )
        mesh = read_ply(tmp_path / f"{where}.mesh.ply")
        assert mesh.point_dtype == np.float64 and mesh.vertices.dtype == np.float64
        errors[where] = _radius_errors(mesh.vertices, _offset(where), 10.0)
    # was 0.048 m median / 0.25 m max at UTM (float32 output) against ~0.0015 / 0.016 at the origin
    assert np.median(errors["utm"]) <= 1.05 * np.median(errors["origin"]) + 1e-6
    assert errors["utm"].max() <= 1.05 * errors["origin"].max() + 1e-6


# ------------------------------------------------------------------- the data model's rule


def test_library_float64_cloud_is_written_as_double(tmp_path):
    """A float64 cloud or mesh from the library is written as double, its values exactly."""
    p, n = sphere_cloud(100, radius=1.0, centre=(0.1, 0.2, 0.3))
    back = read_ply(_file_of(PointCloud(points=p, normals=n), tmp_path))
    assert back.point_dtype == np.float64
    np.testing.assert_array_equal(back.points, p)
    np.testing.assert_array_equal(back.normals, n)
    mesh = TriangleMesh(*icosphere(1))
    assert read_ply(_file_of(mesh, tmp_path)).point_dtype == np.float64


def _file_of(obj, tmp_path):
    path = tmp_path / "lib.ply"
    path.write_bytes(ply_bytes(obj))
    return path


def test_float32_source_stays_float32_near_the_origin(tmp_path):
    """A float32 source near the origin stays float32, computed coordinates included."""
    p, _ = sphere_cloud(100, radius=10.0, centre=(3.0, -2.0, 1.0))
    cloud = PointCloud(points=p.astype(np.float32))
    assert cloud.point_dtype == np.float32
    assert read_ply(_file_of(cloud, tmp_path)).point_dtype == np.float32
    # computed float64 coordinates of a float32 source near the origin: float32 rounds them
    # by ~1e-8 of the diagonal, within tol.precision, so the file stays float32
    computed = PointCloud(points=p, point_dtype=np.float32)
    assert storage_dtype(computed) == np.float32
    assert read_ply(_file_of(computed, tmp_path)).point_dtype == np.float32


@pytest.mark.parametrize("where", FAR)
def test_float32_source_far_away_is_written_double_with_a_note(where, tmp_path):
    """A far float32 source: its coordinates stay float32, new ones are written double, noted."""
    p32 = sphere_cloud(4000, radius=10.0, centre=FAR_OFFSETS[where])[0].astype(np.float32)
    n = sphere_cloud(4000, radius=10.0)[1].astype(np.float32)
    cloud = PointCloud(points=p32, normals=n)
    assert cloud.point_dtype == np.float32
    # float32 coordinates kept as they are: float32 loses nothing, the file stays float32
    res = apply_stage("normals", cloud)
    assert "precision" not in res.report
    assert read_ply(_file_of(res.output, tmp_path)).point_dtype == np.float32
    # new coordinates (Poisson's vertices) would be rounded by ~0.03-0.25: written as double, said
    # so
    res = apply_stage("poisson", cloud, {"depth": 5})
    mesh = res.output
    assert mesh.point_dtype == np.float32 and storage_dtype(mesh) == np.float64
    bound = float(np.spacing(np.float32(np.abs(mesh.vertices).max()))) / 2  # half a float32 ulp
    assert bound > tol.precision * 35
    assert res.report["precision"].startswith(
        f"coordinates kept as double: float32 would round them by up to {bound:.3g}"
    )
    back = read_ply(_file_of(mesh, tmp_path))
    assert back.point_dtype == np.float64
    np.testing.assert_array_equal(back.vertices, mesh.vertices)


def test_float32_values_in_a_float64_array_stay_float32(tmp_path):
    """Float64 arrays holding float32 values lose nothing as float32.

    As a stage that converted and kept them would hold them.
    """
    p = (
        sphere_cloud(100, radius=10.0, centre=FAR_OFFSETS["utm"])[0]
        .astype(np.float32)
        .astype(np.float64)
    )
    cloud = PointCloud(points=p, point_dtype=np.float32)
    assert storage_dtype(cloud) == np.float32
    back = read_ply(_file_of(cloud, tmp_path))
    np.testing.assert_array_equal(back.points, p)


def test_grid_point_dtype_defaults_and_checks(tmp_path):
    """A grid's point dtype defaults to float32, old files read as float32, a bad one refused."""
    g = Grid(sdf=np.zeros((2, 2, 2)), origin=(0, 0, 0), voxel_size=1.0)
    assert g.point_dtype == np.float32
    path = tmp_path / "g.npz"
    save(g, path)
    assert load(path).point_dtype == np.float32
    # grid files written before point_dtype existed read as float32 sources
    with np.load(path) as z:
        old = {k: z[k] for k in z.files if k != "point_dtype"}
    np.savez(tmp_path / "old.npz", **old)
    assert load(tmp_path / "old.npz").point_dtype == np.float32
    np.savez(tmp_path / "bad.npz", **old, point_dtype=np.array("float16"))
    from recon_cli.errors import InputError

    with pytest.raises(InputError, match="point_dtype"):
        load(tmp_path / "bad.npz")


@pytest.mark.parametrize(
    "types, double",
    [
        (("float", "float", "float"), False),
        (("short", "uchar", "float"), False),
        (("double", "float", "float"), True),
        (("int", "int", "int"), True),
        (("uint", "float", "float"), True),
    ],
)
def test_ply_source_type(types, double, tmp_path):
    """A file's coordinates are a float32 source only when float32 holds every column exactly."""
    header = "ply\nformat ascii 1.0\nelement vertex 2\n" + "".join(
        f"property {t} {c}\n" for t, c in zip(types, "xyz", strict=True)
    )
    path = tmp_path / "t.ply"
    big = types[0] in ("double", "int", "uint")
    path.write_text(header + "end_header\n" + ("16777217" if big else "7") + " 3 1\n1 2 3\n")
    cloud = read_ply(path)
    assert cloud.point_dtype == (np.float64 if double else np.float32)
    back = read_ply(_file_of(cloud, tmp_path))
    np.testing.assert_array_equal(back.points, cloud.points)
    if big:
        assert back.points[0, 0] == 16777217  # 2**24 + 1: not a float32


def test_coordinates_beyond_float32_range_are_written_double(tmp_path):
    """Coordinates beyond float32's range are written as double, with the report's note."""
    mesh = TriangleMesh(
        np.array([[0.0, 0.0, 0.0], [1e39, 0.0, 0.0], [0.0, 1e39, 0.0]]),
        [[0, 1, 2]],
        point_dtype=np.float32,
    )
    assert storage_dtype(mesh) == np.float64
    res = apply_stage("repair", mesh)
    assert res.report["precision"] == "coordinates kept as double: they exceed the float32 range"
    np.testing.assert_array_equal(read_ply(_file_of(res.output, tmp_path)).vertices, mesh.vertices)
