"""Real sensor files in: NaN points dropped, depth images' pixels kept, scanner positions read.

NaN points dropped and counted by every reader, organized depth images (PCD WIDTH x HEIGHT, E57
structured scans) keep their pixels, scanner positions (PCD VIEWPOINT, E57 poses, LAS up) read,
reported and written back.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, Sensor, TriangleMesh
from recon_cli.io.load import load, load_detailed, save
from recon_cli.io.pcd import decode_pcd
from recon_cli.io.xyz import decode_xyz

from sensors import (
    DepthCamera,
    depth_image,
    look_at,
    quaternion,
    tabletop_scene,
    write_organized_pcd,
)
from shapes import cloud_family, random_rotation

RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def recon(*args):
    """Run ``recon`` with ``args`` as a process, its output captured."""
    return subprocess.run([*RECON, *map(str, args)], capture_output=True, timeout=300)


def with_nan_rows(cloud: PointCloud, rng, frac=0.2) -> tuple[PointCloud, np.ndarray]:
    """``cloud`` with NaN/inf in one coordinate of about ``frac`` of its rows, and their mask."""
    c = cloud.copy()
    bad = rng.random(len(c.points)) < frac
    bad[0] = True  # the first row too (a reader's first-row special cases)
    col = rng.integers(0, 3, len(c.points))
    c.points[bad, col[bad]] = rng.choice([np.nan, np.inf, -np.inf], int(bad.sum()))
    return c, bad


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".xyz", ".csv", ".pts", ".pcd", ".PCD"])
def test_every_cloud_reader_drops_nan_rows_keeping_the_rest_exactly(suffix, tmp_path):
    """Every cloud reader drops the NaN rows and counts them, the other rows kept exactly."""
    rng = np.random.default_rng(len(suffix))
    src = cloud_family(3)  # rotated, scaled, offset up to 1e6, colours and attributes
    c, bad = with_nan_rows(src, rng)
    path = tmp_path / f"c{suffix}"
    save(c, path)
    got = load(path)
    keep = ~bad
    assert got.invalid_dropped == int(bad.sum()) and len(got.points) == int(keep.sum())
    assert np.array_equal(got.points, src.points[keep])  # double kept
    assert np.array_equal(got.colors, src.colors[keep])
    if suffix not in (".obj", ".off"):  # formats holding per-point attributes
        for k, v in src.attributes.items():
            assert np.array_equal(got.attributes[k], v[keep]), k


def test_ply_ascii_and_big_endian_float32_rows_dropped(tmp_path):
    """ASCII and big-endian float32 PLY drop their NaN rows, their attributes following."""
    rng = np.random.default_rng(5)
    pts = rng.random((300, 3)).astype(np.float32)
    pts[[0, 17, 299], 1] = np.nan
    c = PointCloud(pts, attributes={"i": np.arange(300, dtype=np.int16)})
    save(c, tmp_path / "a.ply", ascii=True)
    assert recon("convert", tmp_path / "a.ply", tmp_path / "b.ply", "--big-endian").returncode == 0
    for name in ("a.ply", "b.ply"):
        got = load(tmp_path / name)
        assert got.points.dtype == np.float32 and got.invalid_dropped == 3
        assert got.attributes["i"].tolist() == [i for i in range(300) if i not in (0, 17, 299)]


def test_las_holds_no_nan_and_says_so(tmp_path):
    """NaN points cannot be written to LAS, said and nothing written; LAS reads as looking up."""
    c, _ = with_nan_rows(cloud_family(1), np.random.default_rng(1))
    with pytest.raises(ParameterError, match="LAS cannot store the .* NaN or infinite"):
        save(c, tmp_path / "c.laz")
    assert not (tmp_path / "c.laz").exists()
    save(cloud_family(1), tmp_path / "c.las")
    got = load(tmp_path / "c.las")
    assert [s.describe() for s in got.sensors] == ["LAS up (airborne) towards (0, 0, 1)"]


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off"])
def test_mesh_with_a_face_on_a_nan_vertex_is_refused_in_one_line(suffix, tmp_path):
    """An unused NaN vertex is dropped; one a face uses refuses the mesh in one line."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [7, 7, 7]], float)
    ok = TriangleMesh(v, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    v_bad = v.copy()
    v_bad[4, 2] = np.nan  # used by no face: dropped, the mesh kept whole
    save(TriangleMesh(v_bad, ok.faces), tmp_path / f"unused{suffix}")
    got = load(tmp_path / f"unused{suffix}")
    assert got.invalid_dropped == 1 and np.array_equal(got.vertices, v[:4])
    assert np.array_equal(got.faces, ok.faces)
    v_bad[1, 0] = np.inf  # used by three faces
    path = tmp_path / f"used{suffix}"
    save(TriangleMesh(v_bad, ok.faces), path)
    with pytest.raises(InputError, match="face 0 uses vertex 1, which has a NaN or infinite"):
        load(path)
    r = recon("repair", path, tmp_path / "out.ply")
    err = r.stderr.decode().strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and str(path) in err
    assert (
        "3 faces use one of the 2 invalid vertices" in err and not (tmp_path / "out.ply").exists()
    )


@settings(max_examples=150, deadline=None)
@given(
    rows=st.lists(
        st.tuples(
            st.sampled_from(["1.5", "-2e3", "nan", "NaN", "inf", "-Infinity", "0", "3.25e-7"]),
            st.sampled_from(["0.5", "nan", "7", "-inf"]),
            st.sampled_from(["2", "1e6", "nan"]),
            st.integers(0, 255),
        ),
        min_size=1,
        max_size=30,
    ),
    sep=st.sampled_from([" ", ",", "\t"]),
)
def test_text_and_pcd_ascii_parsers_drop_exactly_the_nonfinite_rows(rows, sep):
    """Text and ASCII PCD parsers drop exactly the rows with a NaN or infinity."""
    vals = np.array([[float(a), float(b), float(c)] for a, b, c, _ in rows])
    ok = np.isfinite(vals).all(axis=1)
    text = "".join(sep.join([a, b, c, str(i)]) + "\n" for a, b, c, i in rows)
    head = "x,y,z,label\n" if sep == "," else "x y z label\n"
    if ok.any():
        got, _ = decode_xyz((head + text).encode(), "t.xyz")
        assert got.invalid_dropped == int((~ok).sum())
        assert np.array_equal(got.points, vals[ok])
        assert got.attributes["label"].tolist() == [
            r[3] for r, k in zip(rows, ok, strict=True) if k
        ]
    pcd = (
        "VERSION 0.7\nFIELDS x y z label\nSIZE 8 8 8 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(rows)}\nHEIGHT 1\nPOINTS {len(rows)}\nDATA ascii\n" + text.replace(",", " ")
    )
    got, _ = decode_pcd(pcd.encode(), "t.pcd")
    assert got.invalid_dropped == int((~ok).sum()) and got.pixels is None
    assert np.array_equal(got.points, vals[ok])
    assert got.attributes["label"].tolist() == [r[3] for r, k in zip(rows, ok, strict=True) if k]


def _camera(rng, w=64, h=48, offset=0.0):
    """A camera at a random place around the tabletop, looking at it (random roll too)."""
    az = rng.uniform(-2.5, -0.6)
    eye = np.array([2.6 * np.cos(az), 2.6 * np.sin(az), rng.uniform(0.6, 2.0)])
    target = rng.uniform(-0.3, 0.3, 3) + [0, 0.3, 0.2]
    up = random_rotation(rng)[:, 0] * 0.3 + [0, 0, 1]
    rot = look_at(eye, target, up)
    return DepthCamera(eye=eye + offset, rotation=rot, width=w, height=h)


def _scene(offset):
    scene = tabletop_scene()
    return lambda p: scene(p - offset)


@pytest.mark.parametrize(
    "data, dtype, offset",
    [
        ("binary", "f4", 0.0),
        ("ascii", "f4", 0.0),
        ("binary_compressed", "f4", 0.0),
        ("binary", "f8", 1e6),
        ("binary_compressed", "f8", 1e6),
        ("ascii", "f8", 1e6),
    ],
)
def test_organized_pcd_keeps_pixels_colours_and_viewpoint(data, dtype, offset, tmp_path):
    """An organized PCD keeps each point's pixel, its colours and the viewpoint, in any encoding."""
    rng = np.random.default_rng(hash((data, dtype)) % 2**32)
    off = np.array([offset, -offset, 0.5 * offset])
    cam = _camera(rng, offset=off)
    org = depth_image(cam, _scene(off), rng)
    colours = rng.integers(0, 256, (org.shape[0] * org.shape[1], 3))
    path = tmp_path / "depth.pcd"
    write_organized_pcd(path, org, cam, colors=colours, data=data, dtype=dtype)
    got, details, _ = load_detailed(path)
    flat = org.reshape(-1, 3).astype(np.float32 if dtype == "f4" else np.float64)
    valid = np.isfinite(flat).all(axis=1)
    assert 0 < valid.sum() < len(valid)  # the scene has misses
    assert got.invalid_dropped == int((~valid).sum()) and details["height"] == org.shape[0]
    assert got.points.dtype == flat.dtype and np.array_equal(got.points, flat[valid])
    assert got.pixels.shapes == ((48, 64),) and np.array_equal(
        got.pixels.pixel, np.flatnonzero(valid)
    )
    assert np.array_equal(got.colors[:, :3], colours[valid]) and (got.colors[:, 3] == 255).all()
    (sensor,) = got.sensors
    assert sensor.position == tuple(cam.eye) and sensor.source == "PCD VIEWPOINT"
    assert np.allclose(sensor.orientation, quaternion(cam.rotation), atol=1e-15)


def test_info_and_stage_reports_say_what_was_dropped(tmp_path):
    """``recon info``, stage reports and convert say how many points were dropped."""
    rng = np.random.default_rng(3)
    cam = _camera(rng)
    org = depth_image(cam, tabletop_scene(), rng)
    path = tmp_path / "raw.pcd"
    write_organized_pcd(path, org, cam)
    nan = int((~np.isfinite(org).all(axis=2)).sum())
    r = recon("info", "--json", path)
    rep = json.loads(r.stdout)[0]
    assert rep["invalid_dropped"] == nan and rep["organized"] == "64x48"
    assert rep["vertices"] == 64 * 48 - nan and rep["sensors"][0].startswith("PCD VIEWPOINT at (")
    text = recon("info", path).stdout.decode()
    assert f"invalid        {nan} (NaN/inf" in text and "organized      64x48" in text
    r = recon("normals", path, tmp_path / "n.ply", "--orient", "camera", "--json")
    rep = json.loads(r.stdout)
    assert r.returncode == 0 and rep["read"] == {
        "kept": 64 * 48 - nan,
        "invalid_dropped": nan,
        "organized": "64x48",
    }
    assert (
        "invalid_dropped"
        in recon("normals", path, tmp_path / "n.ply", "--orient", "camera").stderr.decode()
    )
    r = recon("convert", path, tmp_path / "c.xyz")
    assert (
        r.returncode == 0
        and f"{nan} points with a NaN or infinite coordinate dropped" in r.stderr.decode()
    )
    # every point invalid: refused in one line, nothing written
    write_organized_pcd(tmp_path / "empty.pcd", np.full((4, 5, 3), np.nan))
    for cmd in (["normals"], ["convert"]):
        r = recon(*cmd, tmp_path / "empty.pcd", tmp_path / "e.ply")
        err = r.stderr.decode().strip()
        assert r.returncode == 2 and err.endswith(
            "all 20 points have a NaN or infinite coordinate: nothing to read"
        )
        assert len(err.splitlines()) == 1 and not (tmp_path / "e.ply").exists()


def test_sensors_written_back_to_ply_and_pcd(tmp_path):
    """Sensors survive PLY and PCD exactly; several sensors are kept in PLY only."""
    rng = np.random.default_rng(9)
    cam = _camera(rng, 32, 24)
    write_organized_pcd(tmp_path / "a.pcd", depth_image(cam, tabletop_scene(), rng), cam)
    a = load(tmp_path / "a.pcd")
    # through PLY (obj_info) and back to PCD (VIEWPOINT): position and orientation exact
    assert recon("normals", tmp_path / "a.pcd", tmp_path / "b.ply", "-q").returncode == 0
    b = load(tmp_path / "b.ply")
    assert b.sensors == a.sensors and b.pixels is None and b.obj_info == []
    save(b, tmp_path / "c.pcd", ascii=True)
    assert load(tmp_path / "c.pcd").sensors == a.sensors
    # several sensors, or one far away: PCD's VIEWPOINT cannot say; PLY keeps them all
    two = PointCloud(
        rng.random((4, 3)),
        sensors=[
            Sensor(position=(1, 2, 3), source="E57 scan 0"),
            Sensor(direction=(0, 0, 1), source="up"),
        ],
        attributes={"scan": np.array([0, 1, 0, 1], np.int32)},
    )
    save(two, tmp_path / "two.ply")
    assert load(tmp_path / "two.ply").sensors == two.sensors
    assert b"VIEWPOINT 0 0 0 1 0 0 0" in (
        save(two, tmp_path / "two.pcd") or (tmp_path / "two.pcd").read_bytes()
    )


def _write_e57(path, scans):
    pye57 = pytest.importorskip("pye57")
    e = pye57.E57(str(path), mode="w")
    for k, (local, valid, rows, cols, quat, trans) in enumerate(scans):
        local = local.copy()
        local[~valid] = np.nan  # flagged invalid: the coordinates of a miss are not a point
        data = {
            "cartesianX": local[:, 0],
            "cartesianY": local[:, 1],
            "cartesianZ": local[:, 2],
            "cartesianInvalidState": np.where(valid, 0, 2).astype(np.int8),
            "intensity": np.linspace(0, 1, len(local)),
        }
        if rows is not None:
            data["rowIndex"], data["columnIndex"] = rows, cols
        e.write_scan_raw(data, name=f"station {k}", rotation=quat, translation=trans)
    e.close()


def test_e57_multi_scan_poses_invalid_points_and_structured_grids(tmp_path):
    """A three-scan E57: poses applied, invalid points dropped, structured grids kept."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    scans, expect = [], []
    for k, (h, w) in enumerate([(6, 9), (5, 7), (4, 4)]):
        local = rng.uniform(-5, 5, (h * w, 3)).astype(np.float32).astype(np.float64)
        valid = rng.random(h * w) > 0.25
        rot = Rotation.random(random_state=k)
        q = rot.as_quat()  # x y z w
        quat = np.array([q[3], q[0], q[1], q[2]])
        trans = rng.uniform(-100, 100, 3) + [5e5, 5e6, 0]
        rows = np.repeat(np.arange(h), w).astype(np.uint16)
        cols = np.tile(np.arange(w), h).astype(np.uint16)
        structured = k < 2
        scans.append(
            (local, valid, rows if structured else None, cols if structured else None, quat, trans)
        )
        expect.append((rot.apply(local[valid]) + trans, trans, valid, structured, h, w))
    _write_e57(tmp_path / "three.e57", scans)
    got, details, _ = load_detailed(tmp_path / "three.e57")
    want = np.concatenate([e[0] for e in expect])
    assert np.abs(got.points - want).max() < 1e-6
    assert (
        got.invalid_dropped == sum(int((~e[2]).sum()) for e in expect) == details["invalid_flagged"]
    )
    assert [s.position for s in got.sensors] == [tuple(e[1]) for e in expect]
    assert [s.source for s in got.sensors] == [f"E57 scan {k} 'station {k}' pose" for k in range(3)]
    assert np.array_equal(
        got.attributes["scan"], np.repeat(np.arange(3), [int(e[2].sum()) for e in expect])
    )
    # not every scan structured: no pixel grid; the two structured alone give one
    assert got.pixels is None and details["structured"] == [True, True, False]
    _write_e57(tmp_path / "two.e57", scans[:2])
    two = load(tmp_path / "two.e57")
    assert two.pixels.shapes == ((6, 9), (5, 7))
    assert np.array_equal(
        two.pixels.pixel,
        np.concatenate([np.flatnonzero(expect[0][2]), 54 + np.flatnonzero(expect[1][2])]),
    )
    assert np.array_equal(
        two.attributes["rowIndex"][: int(expect[0][2].sum())], scans[0][2][expect[0][2]]
    )
    # through PLY: sensors and each point's scan kept
    save(two, tmp_path / "two.ply")
    back = load(tmp_path / "two.ply")
    assert back.sensors == two.sensors and np.array_equal(
        back.attributes["scan"], two.attributes["scan"]
    )
