"""The data model's sensor pieces: Sensor and its stored line, PixelGrid, drop_invalid."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import (
    PixelGrid,
    PointCloud,
    Sensor,
    TriangleMesh,
    drop_invalid,
    parse_sensor_line,
    split_sensor_lines,
)

finite = st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    pos=st.tuples(finite, finite, finite),
    quat=st.tuples(finite, finite, finite, finite) | st.none(),
    source=st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=30),
)
def test_sensor_line_round_trip(pos, quat, source):
    s = Sensor(position=pos, orientation=quat, source=source)
    assert s.source == " ".join(source.split())
    back = parse_sensor_line(s.to_line())
    assert back == s  # exact: coordinates are written with repr


def test_sensor_direction_is_unit_and_lines_split_from_others():
    up = Sensor(direction=(0, 0, 5), source="LAS up")
    assert up.direction == (0.0, 0.0, 1.0) and "towards (0, 0, 1)" in up.describe()
    lines = ["las_version 1.4", up.to_line(), "pcd_viewpoint 1 2 3 1 0 0 0", "sensor position x"]
    sensors, rest = split_sensor_lines(lines)
    # an older recon's pcd_viewpoint line is a sensor; a malformed sensor line is kept as text
    assert sensors == [
        up,
        Sensor(position=(1, 2, 3), orientation=(1, 0, 0, 0), source="PCD VIEWPOINT"),
    ]
    assert rest == ["las_version 1.4", "sensor position x"]
    for bad in ({}, {"position": (0, 0, 0), "direction": (0, 0, 1)}, {"direction": (0, 0, 0)}):
        with pytest.raises(InputError):
            Sensor(**bad)
    with pytest.raises(InputError, match="finite"):
        Sensor(position=(0, np.nan, 0))


def test_cloud_parses_sensor_lines_and_carries_sensors_and_pixels():
    s = Sensor(position=(1.5, 0, 2), source="PCD VIEWPOINT")
    c = PointCloud(np.arange(12.0).reshape(4, 3), obj_info=["x", s.to_line()])
    assert c.sensors == [s] and c.obj_info == ["x"]
    c.pixels = PixelGrid(((2, 3),), [0, 2, 4, 5])
    c.invalid_dropped = 2
    sub = c.subset(np.array([True, False, True, True]))
    assert sub.pixels.pixel.tolist() == [0, 4, 5] and sub.sensors == [s]
    assert sub.invalid_dropped == 2 and sub.pixels.describe() == "3x2"
    cp = c.copy()
    cp.pixels.pixel[0] = 1
    assert c.pixels.pixel[0] == 0 and cp.sensors == c.sensors
    two = PixelGrid(((2, 3), (4, 5)), [0, 7])
    assert two.offsets().tolist() == [0, 6, 26] and two.describe() == "3x2, 5x4"
    with pytest.raises(InputError, match="pixels has 2 rows"):
        PointCloud(np.zeros((3, 3)), pixels=two)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 60),
    seed=st.integers(0, 2**31 - 1),
    frac=st.floats(0, 1),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_drop_invalid_keeps_every_per_point_array_aligned(n, seed, frac, dtype):
    rng = np.random.default_rng(seed)
    pts = (rng.normal(size=(n, 3)) * 1e3 + 1e6).astype(dtype)
    bad = rng.random(n) < frac
    cols = rng.integers(0, 3, n)
    pts[bad, cols[bad]] = rng.choice([np.nan, np.inf, -np.inf], int(bad.sum()))
    cloud = PointCloud(
        pts,
        normals=rng.normal(size=(n, 3)).astype(dtype),
        colors=rng.integers(0, 255, (n, 4)).astype(np.uint8),
        attributes={"label": np.arange(n, dtype=np.int32), "t": rng.random(n)},
        point_dtype=dtype,
        pixels=PixelGrid(((n, 2),), np.arange(n) * 2),
        history=["h"],
        invalid_dropped=3,
    )
    out = drop_invalid(cloud, "f.pcd")
    keep = ~bad
    assert out.invalid_dropped == 3 + int(bad.sum())
    assert out.points.dtype == dtype and np.array_equal(out.points, pts[keep])
    assert np.array_equal(out.normals, cloud.normals[keep])
    assert np.array_equal(out.colors, cloud.colors[keep])
    assert np.array_equal(out.attributes["label"], np.flatnonzero(keep))
    assert np.array_equal(out.attributes["t"], cloud.attributes["t"][keep])
    assert np.array_equal(out.pixels.pixel, 2 * np.flatnonzero(keep))
    assert out.history == ["h"] and out.point_dtype == dtype
    assert (out is cloud) == (not bad.any())


def test_drop_invalid_on_meshes_refuses_a_face_using_a_bad_vertex():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0], [0, 0, 1]], float)
    # an invalid vertex no face uses: dropped, faces renumbered
    m = TriangleMesh(v, [[0, 1, 2], [0, 2, 4]], attributes={"a": np.arange(5.0)})
    out = drop_invalid(m, "m.ply")
    assert out.invalid_dropped == 1 and out.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert np.array_equal(out.vertices, v[[0, 1, 2, 4]]) and out.attributes["a"].tolist() == [
        0,
        1,
        2,
        4,
    ]
    with pytest.raises(InputError, match=r"^m\.ply: face 1 uses vertex 3, which has a NaN"):
        drop_invalid(TriangleMesh(v, [[0, 1, 2], [1, 3, 2], [3, 4, 0]]), "m.ply")
