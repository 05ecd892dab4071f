"""The data model: Sensor and its stored line, PixelGrid, drop_invalid, take_rows."""

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
    take_rows,
)

finite = st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    pos=st.tuples(finite, finite, finite),
    quat=st.tuples(finite, finite, finite, finite) | st.none(),
    source=st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=30),
)
def test_sensor_line_round_trip(pos, quat, source):
    """A sensor's line parses back to the same sensor, exactly."""
    s = Sensor(position=pos, orientation=quat, source=source)
    assert s.source == " ".join(source.split())
    back = parse_sensor_line(s.to_line())
    assert back == s  # exact: coordinates are written with repr


def test_sensor_direction_is_unit_and_lines_split_from_others():
    """Directions are made unit; sensor lines split from other records; bad sensors refused."""
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
    """A cloud takes sensors from its records; subsets and copies carry sensors and pixels."""
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
    """``drop_invalid`` drops non-finite rows from every per-point array alike, counting them."""
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
    """An unused invalid vertex is dropped, faces renumbered; one a face uses is refused."""
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


# ---- take_rows: records gathered in one copy, equal to each column's fancy index ----------------
_RECORD = np.dtype(
    [
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("nx", ">f4"),
        ("ny", ">f4"),
        ("nz", ">f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("intensity", "<u2"),
        ("flag", "?"),
        ("label", "<i8"),
        ("gap", "<f2"),
        ("t", "<f8"),
    ],
    align=False,
)


def _interleaved(n: int, rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray]]:
    """A packed record array as a binary PLY's body, and its columns as the reader views them."""
    rec = np.zeros(n, _RECORD)
    for name in _RECORD.names:
        kind = _RECORD[name].kind
        if kind == "f":
            rec[name] = rng.normal(size=n) * 1e3
        elif kind == "b":
            rec[name] = rng.random(n) < 0.5
        else:
            rec[name] = rng.integers(0, np.iinfo(_RECORD[name]).max, n, dtype=np.int64)
    rec["x"][::5] = np.nan  # NaN payloads and signs travel as bytes
    rec["t"][::7] = -0.0
    stride = rec.strides[0]

    def cols3(first: str) -> np.ndarray:
        a = rec[first]
        return np.lib.stride_tricks.as_strided(a, (n, 3), (stride, a.itemsize))

    cols = [cols3("x"), cols3("nx"), cols3("red")]
    cols += [rec[k] for k in ("intensity", "flag", "label", "t")]
    return rec, cols


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 300),
    seed=st.integers(0, 2**32 - 1),
    how=st.sampled_from(["mask", "sorted", "any", "negative", "empty"]),
)
def test_take_rows_equals_each_columns_fancy_index(n, seed, how):
    """``take_rows`` equals indexing each column, for interleaved, separate and mixed columns."""
    rng = np.random.default_rng(seed)
    rec, interleaved = _interleaved(n, rng)
    separate = [np.array(c) for c in interleaved]  # the same values, each its own array
    separate[1] = np.asfortranarray(separate[1])
    mixed = [interleaved[0], None, separate[2], interleaved[3], interleaved[4][::1]]
    rows = {
        "mask": rng.random(n) < 0.4,
        "sorted": np.flatnonzero(rng.random(n) < 0.6),
        "any": rng.integers(0, max(n, 1), 2 * n) if n else np.zeros(0, np.int64),
        "negative": -rng.integers(1, n + 1, n) if n else np.zeros(0, np.int64),
        "empty": np.zeros(0, np.int64) if n % 2 else np.zeros(n, bool),
    }[how]
    for cols in (interleaved, separate, mixed):
        got = take_rows(cols, rows)
        assert len(got) == len(cols)
        for g, c in zip(got, cols, strict=True):
            if c is None:
                assert g is None
                continue
            want = c[rows]
            assert g.dtype == want.dtype and g.shape == want.shape
            # bytes equal: NaN payloads, -0.0 and byte order kept
            assert np.ascontiguousarray(g).tobytes() == np.ascontiguousarray(want).tobytes()
    got = take_rows(interleaved, rows)
    if n > 1 and len(got[0]):  # the interleaved columns came from one copy of the records
        assert all(not np.may_share_memory(g, rec) for g in got)
        assert got[0].base is got[6].base is not None  # one record array holds them
        got[0][...] = 0  # the results are writeable, and each column only its own bytes
        assert np.array_equal(got[2], interleaved[2][rows])


def test_take_rows_refuses_mismatched_rows_and_columns():
    """Columns of other lengths, wrong masks, indices out of range or not integers: refused."""
    a, b = np.zeros((5, 3)), np.zeros(4)
    with pytest.raises(InputError, match="different lengths"):
        take_rows([a, b], [0])
    with pytest.raises(InputError, match="mask of shape"):
        take_rows([a], np.ones(4, bool))
    with pytest.raises(InputError, match="out of range"):
        take_rows([a], [5])
    with pytest.raises(InputError, match="integers"):
        take_rows([a], [0.5])
    assert take_rows([None, None], [0]) == [None, None]


def test_subset_and_drop_invalid_gather_every_column_of_a_read_ply(tmp_path, rng):
    """``subset`` and ``drop_invalid`` of a read PLY gather every column of the kept rows."""
    from recon_cli.io.ply import read_ply, write_ply

    n = 2000
    cloud = PointCloud(
        points=rng.normal(size=(n, 3)),
        normals=rng.normal(size=(n, 3)).astype(np.float32),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        attributes={"intensity": rng.integers(0, 60000, n).astype(np.uint16)},
    )
    write_ply(cloud, tmp_path / "c.ply")
    read = read_ply(tmp_path / "c.ply")
    assert not read.points.flags.c_contiguous  # views into the file's records
    keep = rng.random(n) < 0.3
    sub = read.subset(keep)
    for name in ("points", "normals", "colors"):
        want = getattr(read, name)[keep]
        got = getattr(sub, name)
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert np.array_equal(sub.attributes["intensity"], read.attributes["intensity"][keep])
    bad = read.copy()
    bad.points[~keep] = np.nan
    clean = drop_invalid(bad)
    assert clean.invalid_dropped == n - keep.sum()
    assert np.array_equal(clean.points, read.points[keep])
    assert np.array_equal(clean.colors, read.colors[keep])
