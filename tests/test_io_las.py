"""LAS/LAZ through laspy: both ways, the real tile bit for bit, UTM precision, errors, fuzz.

LAS/LAZ through laspy: laspy's files read right, ours read back identically in laspy, the real
airborne tile kept bit for bit, precision at UTM coordinates, errors and fuzz.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud
from recon_cli.io.las import decode_las, las_bytes

from shapes import cloud_family
from shared_data import SHARED

laspy = pytest.importorskip("laspy")
AUTZEN = SHARED / "autzen_trim.laz"


def _laspy_file(seed, pf, version, compress, n=300):
    rng = np.random.default_rng(seed)
    h = laspy.LasHeader(point_format=pf, version=version)
    h.scales = np.array([0.001, 0.001, 0.0001])
    h.offsets = np.array([5e5, 5e6, 100.0])
    if pf >= 6:
        h.add_extra_dims(
            [
                laspy.ExtraBytesParams(name="nx", type="f4"),
                laspy.ExtraBytesParams(name="ny", type="f4"),
                laspy.ExtraBytesParams(name="nz", type="f4"),
                laspy.ExtraBytesParams(name="amplitude", type="u2"),
            ]
        )
    las = laspy.LasData(h)
    las.X = rng.integers(-(2**30), 2**30, n)
    las.Y = rng.integers(-(2**30), 2**30, n)
    las.Z = rng.integers(-(2**20), 2**20, n)
    las.intensity = rng.integers(0, 65535, n)
    las.classification = rng.integers(0, 20, n)
    las.return_number = rng.integers(1, 4, n)
    las.number_of_returns = np.maximum(las.return_number, rng.integers(1, 4, n))
    if "red" in las.point_format.dimension_names:
        las.red, las.green, las.blue = (rng.integers(0, 65535, n) for _ in range(3))
    if pf >= 6:
        nrm = rng.normal(size=(n, 3)).astype(np.float32)
        las.nx, las.ny, las.nz = nrm[:, 0], nrm[:, 1], nrm[:, 2]
        las.amplitude = rng.integers(0, 1000, n)
    buf = io.BytesIO()
    las.write(buf, do_compress=compress)
    return las, buf.getvalue()


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("pf, version", [(0, "1.2"), (3, "1.2"), (6, "1.4"), (7, "1.4")])
@pytest.mark.parametrize("compress", [False, True])
def test_laspy_written_files_read_with_coordinates_attributes_and_colours(
    seed, pf, version, compress
):
    """Files laspy wrote (formats 0, 3, 6, 7; LAS, LAZ): exact coordinates, attributes, colours."""
    las, data = _laspy_file(seed, pf, version, compress)
    got, details = decode_las(data, "t.las")
    assert details["point_format"] == pf and details["version"] == version
    assert got.points.dtype == np.float64
    assert np.array_equal(
        got.points, np.column_stack([las.x, las.y, las.z])
    )  # X * scale + offset, in double
    for name in ("intensity", "classification", "return_number", "number_of_returns"):
        assert np.array_equal(got.attributes[name], np.asarray(las[name]))
    if pf in (3, 7):
        assert got.colors.dtype == np.uint16 and np.array_equal(
            got.colors, np.column_stack([las.red, las.green, las.blue])
        )
    if pf >= 6:
        assert np.array_equal(got.normals, np.column_stack([las.nx, las.ny, las.nz]))
        assert np.array_equal(got.attributes["amplitude"], np.asarray(las.amplitude))


@pytest.mark.parametrize("compress", [False, True])
def test_real_airborne_tile_round_trips_bit_for_bit_in_laspy(compress):
    """The real airborne tile read and written again (LAS or LAZ): every point record's bytes."""
    src = laspy.read(AUTZEN)
    cloud, _ = decode_las(None, str(AUTZEN), path=str(AUTZEN))
    data = las_bytes(cloud, compress, "out")
    back = laspy.read(io.BytesIO(data))
    assert back.header.point_format.id == 3 and str(back.header.version) == "1.2"
    assert np.array_equal(back.points.array, src.points.array)  # every byte of every point record
    assert [(v.user_id, v.record_id) for v in back.header.vlrs] == [
        (v.user_id, v.record_id) for v in src.header.vlrs
    ]


@pytest.mark.parametrize("seed", range(4))
def test_our_files_from_other_clouds_read_back_in_laspy(seed, caplog):
    """Our LAS/LAZ of generated clouds in laspy: coordinates within 5e-9 of the extent, said."""
    c = cloud_family(seed)
    with caplog.at_level("WARNING", logger="recon"):
        data = las_bytes(c, seed % 2 == 1, "o.laz")
    back = laspy.read(io.BytesIO(data))
    pts = np.column_stack([back.x, back.y, back.z])
    # a power-of-ten grid at most 1e-8 of the extent: the rounding is at most half of it, and said
    extent = np.ptp(c.points, axis=0).max()
    assert np.abs(pts - c.points).max() <= 5e-9 * extent
    assert "LAS stores coordinates as integers" in caplog.text
    assert np.array_equal(np.column_stack([back.nx, back.ny, back.nz]), c.normals)
    assert np.array_equal(np.asarray(back.intensity), c.attributes["intensity"])
    assert np.array_equal(np.asarray(back.curvature), c.attributes["curvature"])
    assert np.array_equal(
        np.column_stack([back.red, back.green, back.blue]), c.colors.astype(np.uint16) * 257
    )
    got = decode_las(data, "o")[0]
    assert np.array_equal(got.points, pts) and np.array_equal(got.normals, c.normals)


def test_attribute_that_does_not_fit_is_refused():
    """A fractional classification cannot be written to LAS: refused, naming the attribute."""
    from recon_cli.errors import ParameterError

    c = PointCloud(
        points=np.zeros((2, 3)),
        attributes={"classification": np.array([1.5, 2.0])},
        point_dtype=np.float64,
    )
    with pytest.raises(ParameterError, match="'classification' has values"):
        las_bytes(c, False, "x.las")


def test_truncated_and_garbage_are_one_line_input_errors():
    """Truncated tiles and garbage are one-line InputErrors naming the file."""
    data = AUTZEN.read_bytes()
    for variant in (data[:100], data[: len(data) // 2], b"LASF" + b"\0" * 300, b"not a las file"):
        with pytest.raises(InputError) as exc:
            decode_las(variant, "bad.laz")
        assert str(exc.value).startswith("bad.laz: ") and "\n" not in str(exc.value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
# LAZ too: lazrs aborted the process on a corrupted chunk table ("memory allocation of 52230495040
# bytes failed"), which decode_las now checks before lazrs reads it
@given(
    cut=st.floats(0, 1),
    junk=st.binary(min_size=1, max_size=16),
    pos=st.floats(0, 1),
    compress=st.booleans(),
)
def test_fuzz_truncated_or_corrupted_las_is_data_or_input_error(cut, junk, pos, compress):
    """A cut or corrupted LAS/LAZ reads as finite points or is a one-line InputError."""
    _, data = _laspy_file(1, 3, "1.2", compress, n=50)
    k = int(cut * len(data))
    p = int(pos * k)
    for variant in (data[:k], data[:p] + junk + data[p + len(junk) :]):
        try:
            obj = decode_las(variant, "f.las")[0]
        except InputError as exc:
            assert str(exc).startswith("f.las: ") and "\n" not in str(exc)
            continue
        assert np.isfinite(obj.points).all()


@pytest.mark.parametrize(
    ("at", "field", "what"),
    [
        (100, (2**32 - 1).to_bytes(4, "little"), "VLRs"),  # number of VLRs
        (107, (2**32 - 1).to_bytes(4, "little"), "points"),  # legacy number of points
        (96, (2**32 - 1).to_bytes(4, "little"), "outside the file"),  # offset to the points
        (131, np.float64(1e300).tobytes(), "beyond float64"),  # x scale
    ],
)
@pytest.mark.parametrize("from_path", [False, True])
def test_header_counts_beyond_the_file_refused_before_reading(tmp_path, at, field, what, from_path):
    """Header counts, offsets or scales beyond the file are refused in one line before reading."""
    # a corrupted count made laspy build millions of VLRs or allocate gigabytes (a fuzz case
    # took a test worker to 22 GB): the header is checked against the file's size first
    _, data = _laspy_file(1, 3, "1.2", False, n=50)
    bad = data[:at] + field + data[at + len(field) :]
    f = tmp_path / "bad.las"
    f.write_bytes(bad)
    with pytest.raises(InputError, match=what) as exc:
        decode_las(None, str(f), path=str(f)) if from_path else decode_las(bad, str(f))
    assert str(exc.value).startswith(str(f) + ": ") and "\n" not in str(exc.value)


def test_an_unparsable_coordinate_record_is_read_with_nothing_on_stderr(tmp_path, capfd):
    """An undecodable WKT record is kept as bytes, with nothing on stderr.

    laspy logs a WKT record it cannot decode (and fewer points than declared, which the reader
    refuses in its own line); the record is kept as bytes and nothing reaches stderr.
    """
    from recon_cli.cli.main import main

    h = laspy.LasHeader(point_format=3, version="1.2")
    h.vlrs.append(laspy.VLR("LASF_Projection", 2112, "not WKT", b"\xff\x00garbage"))
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(10)
    src = tmp_path / "a.las"
    las.write(str(src))
    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", "convert", str(src), str(tmp_path / "a.ply")])
    assert ex.value.code == 0 and capfd.readouterr().err == ""
    assert "las_vlr" in " ".join(decode_las(None, str(src), path=str(src))[0].obj_info)


def test_an_extra_dimension_of_three_values_is_three_attributes_through_ply(tmp_path, capfd):
    """An extra-bytes dimension of 3 floats a point is three attributes through PLY.

    An extra-bytes dimension of 3 floats a point (found by the readers' fuzz: convert to PLY
    ended in a numpy traceback) is the attributes ``f_0 f_1 f_2``, one column each.
    """
    from recon_cli.cli.main import main
    from recon_cli.io.load import load

    h = laspy.LasHeader(point_format=0, version="1.4")
    h.add_extra_dims([laspy.ExtraBytesParams(name="f", type="3f4")])
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(7)
    las.f = np.arange(21, dtype=np.float32).reshape(7, 3)
    src = tmp_path / "a.las"
    las.write(str(src))
    cloud, _ = decode_las(None, str(src), path=str(src))
    for k in range(3):
        assert cloud.attributes[f"f_{k}"].shape == (7,)
        np.testing.assert_array_equal(cloud.attributes[f"f_{k}"], np.arange(7) * 3 + k)
    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", "convert", str(src), str(tmp_path / "a.ply")])
    assert ex.value.code == 0 and capfd.readouterr().err == ""
    got = load(str(tmp_path / "a.ply"))
    np.testing.assert_array_equal(got.attributes["f_2"], np.arange(7) * 3 + 2)


def test_a_record_description_that_is_no_text_is_kept_as_its_bytes(tmp_path):
    """A VLR description that is no text is kept byte for byte.

    A VLR description laspy cannot decode comes as bytes (found by the readers' fuzz: an
    AttributeError); it is kept byte for byte in the ``las_vlr`` line.
    """
    import base64

    h = laspy.LasHeader(point_format=3, version="1.2")
    h.vlrs.append(laspy.VLR("LASF_Projection", 2112, "describe", b"GEOGCS[]\0"))
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(5)
    buf = io.BytesIO()
    las.write(buf)
    raw = bytearray(buf.getvalue())
    at = raw.index(b"describe")
    raw[at + 3] = 0x99  # not UTF-8
    cloud, details = decode_las(bytes(raw), "a.las")
    line = next(x for x in cloud.obj_info if x.startswith("las_vlr "))
    desc = base64.b64decode(line.split(" ")[3])
    assert desc.rstrip(b"\0") == b"des\x99ribe"
    assert details["vlrs"] == ["LASF_Projection/2112"]
    back, _ = decode_las(las_bytes(cloud, False, "b.las"), "b.las")  # LAS writes ASCII there
    line = next(x for x in back.obj_info if x.startswith("las_vlr "))
    assert base64.b64decode(line.split(" ")[3]).rstrip(b"\0") == b"des?ribe"
    assert base64.b64decode(line.split(" ")[4]) == b"GEOGCS[]\0"


def test_signalling_nan_normals_are_written_to_ply_without_a_warning(tmp_path, capfd):
    """Signalling-NaN normals are read as quiet NaNs and written to PLY without a warning.

    Normals in float32 extra bytes that hold signalling NaNs (a point format byte set to 0 by
    the readers' fuzz made laspy read colours as them) next to float64 coordinates: numpy's
    cast warning became a traceback. They are read as quiet NaNs; convert ends in exit 0.
    """
    from recon_cli.cli.main import main

    h = laspy.LasHeader(point_format=0, version="1.2")
    h.add_extra_dims([laspy.ExtraBytesParams(name=c, type="f4") for c in ("nx", "ny", "nz")])
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(4)
    las.nx = las.ny = las.nz = np.zeros(4, np.float32)
    buf = io.BytesIO()
    las.write(buf)  # then the normals' bytes set (laspy's writer warns on NaN)
    raw = bytearray(buf.getvalue())
    loud = np.array([0x7FA00000, 0x3F800000, 0xFFC00001, 0x7F800001], np.uint32).view("<f4")
    start = int.from_bytes(raw[96:100], "little")
    for i, v in enumerate(loud):
        raw[start + 32 * i + 20 : start + 32 * i + 32] = v.tobytes() * 3
    src = tmp_path / "a.las"
    src.write_bytes(bytes(raw))
    cloud, _ = decode_las(None, str(src), path=str(src))
    bits = cloud.normals.view(np.uint32)
    assert (bits[[0, 3]] & (1 << 22)).all() and np.isnan(cloud.normals[[0, 2, 3]]).all()
    assert cloud.normals[1, 0] == 1.0
    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", "convert", str(src), str(tmp_path / "a.ply")])
    assert ex.value.code == 0 and capfd.readouterr().err == ""


def test_a_corrupted_laszip_chunk_size_does_not_abort_the_process(tmp_path):
    """A laszip record with a huge chunk size is read or refused, never aborts the process.

    A LAZ whose laszip record gives a chunk of 755 million points (the readers' fuzz) made
    lazrs' parallel decoder abort the process on a 51 GB allocation; it is read (the points are
    whole) or refused in one line. In a child process, as an abort would end this one.
    """
    import struct
    import subprocess
    import sys

    h = laspy.LasHeader(point_format=3, version="1.4")
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(32)
    buf = io.BytesIO()
    las.write(buf, do_compress=True)
    raw = bytearray(buf.getvalue())
    at = raw.index(b"laszip encoded") - 2 + 54 + 12  # the record's chunk size
    assert struct.unpack_from("<I", raw, at)[0] == 50000
    struct.pack_into("<I", raw, at, 755024720)
    src = tmp_path / "a.laz"
    src.write_bytes(bytes(raw))

    def cap_memory():  # were the fix undone, the child fails at once instead of filling memory
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))

    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "recon_cli.cli.main",
            "-q",
            "convert",
            str(src),
            str(tmp_path / "a.ply"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=cap_memory,
    )
    assert run.returncode in (0, 2), run.stderr
    assert run.stderr.count("\n") == (run.returncode == 2), run.stderr


def test_a_zero_scale_is_refused_and_a_bad_kept_grid_is_not_written(tmp_path):
    """A zero x scale is refused in one line; a kept ``las_scale`` with a 0 is not reused.

    A header whose x scale is 0 (the readers' fuzz: read, then written back as LAS, a divide
    by zero) is refused in one line; a cloud whose ``las_scale`` line has a 0 gets a grid of its
    own when written.
    """
    import struct

    _, data = _laspy_file(0, 0, "1.2", False, n=20)
    raw = bytearray(data)
    struct.pack_into("<d", raw, 131, 0.0)
    with pytest.raises(InputError, match=r"^a\.las: header's x scale 0\.0: a scale must not be 0$"):
        decode_las(bytes(raw), "a.las")
    cloud, _ = decode_las(data, "a.las")
    cloud.obj_info = [
        x if not x.startswith("las_scale ") else "las_scale 0 0.001 1e-4" for x in cloud.obj_info
    ]
    back, details = decode_las(las_bytes(cloud, False, "b.las"), "b.las")
    assert all(s > 0 for s in details["scale"])
    np.testing.assert_allclose(back.points, cloud.points, rtol=0, atol=max(details["scale"]))


def _las_extra_named(name: bytes) -> bytes:
    """A LAS of 5 points with one float extra dimension, its name's bytes ``name``."""
    h = laspy.LasHeader(point_format=0, version="1.2")
    h.add_extra_dims([laspy.ExtraBytesParams(name="abc", type="f4")])
    las = laspy.LasData(h)
    las.X = las.Y = las.Z = np.arange(5)
    buf = io.BytesIO()
    las.write(buf)
    return buf.getvalue().replace(b"abc\0", name.ljust(4, b"\0"))


def _convert_extra_named(tmp_path, capfd, name: bytes, suffix: str):
    """``recon convert`` of a LAS with one extra dimension named ``name``: (exit, stderr, OUT)."""
    from recon_cli.cli.main import main

    src = tmp_path / "a.las"
    src.write_bytes(_las_extra_named(name))
    out = tmp_path / ("out" + suffix)
    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", "convert", str(src), str(out)])
    return ex.value.code, capfd.readouterr().err, out


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_an_extra_dimension_named_x_is_refused_by_header_formats(tmp_path, capfd, suffix):
    """An extra dimension named ``x`` is refused by PLY and PCD in one line.

    An extra dimension named ``x`` (make fuzz): the PLY writer built a record with ``x`` twice
    (numpy's ValueError, a traceback); PLY and PCD refuse it in one line naming the output.
    """
    code, err, out = _convert_extra_named(tmp_path, capfd, b"x", suffix)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"recon: error: {out}: attribute 'x' has the name of a "), err
    assert not out.exists()


@pytest.mark.parametrize("suffix, code", [(".ply", 2), (".pcd", 2), (".las", 0)])
def test_an_extra_dimension_named_with_a_space_is_refused_by_header_formats(
    tmp_path, capfd, suffix, code
):
    """An extra dimension named ``a c`` is refused by PLY and PCD, written by LAS.

    An extra dimension ``a c`` was written as the PLY property ``a c``, a file no reader takes
    (exit 0 then); PLY and PCD refuse it in one line naming the output, LAS writes it.
    """
    got, err, out = _convert_extra_named(tmp_path, capfd, b"a c", suffix)
    assert got == code, err
    if code:
        fmt = suffix[1:].upper()
        assert err == (
            f"recon: error: {out}: attribute 'a c' cannot be a {fmt} field name (one word of "
            "printable ASCII); write another format\n"
        )
        assert not out.exists()
    else:
        assert "a c" in decode_las(None, str(out), path=str(out))[0].attributes


def test_an_extra_dimension_without_a_name_is_refused_in_one_line():
    """An extra dimension with an empty name is refused in one line.

    An Extra Bytes record whose name's first byte is 0 (the readers' fuzz): laspy lists a
    dimension ``''`` it cannot give the values of (a ValueError traceback); refused in one line.
    """
    with pytest.raises(InputError) as exc:
        decode_las(_las_extra_named(b"\0bc"), "a.las")
    assert str(exc.value) == "a.las: an extra-bytes dimension's name is empty or repeated: ''"


def _normals_then_poisson(cloud):
    """``recon normals IN - | recon poisson - OUT.ply`` in process, through PLY bytes."""
    from recon_cli.io.ply import parse_ply, ply_bytes, ply_to_geometry
    from recon_cli.stages import apply_stage

    def through_ply(obj):
        return ply_to_geometry(parse_ply(ply_bytes(obj)))

    oriented = through_ply(apply_stage("normals", cloud, {}).output)
    return oriented, through_ply(apply_stage("poisson", oriented, {"depth": 7}).output)


@pytest.mark.slow
def test_airborne_tile_at_state_plane_coordinates_keeps_its_coordinates_through_normals():
    """The tile at state-plane coordinates keeps its float64 points through normals and PLY."""
    cloud, _ = decode_las(None, str(AUTZEN), path=str(AUTZEN))
    from recon_cli.io.ply import parse_ply, ply_bytes, ply_to_geometry
    from recon_cli.stages import apply_stage

    oriented = apply_stage("normals", cloud, {}).output
    # through a PLY pipe, as `recon normals tile.laz - | recon poisson - ...` does
    again = ply_to_geometry(parse_ply(ply_bytes(oriented)))
    assert again.points.dtype == np.float64 and np.array_equal(again.points, cloud.points)
    assert any(s.startswith("las_scale") for s in again.obj_info)


@pytest.mark.slow
def test_airborne_tile_at_utm_like_coordinates_meshes_like_the_same_tile_at_the_origin():
    """60k tile points far off and at the origin give the same Poisson mesh, 99 % within 1e-4 ft."""
    cloud, _ = decode_las(None, str(AUTZEN), path=str(AUTZEN))
    cloud = cloud.subset(np.arange(60_000))
    shift = np.floor(cloud.points.min(axis=0))
    near = cloud.copy()
    near.points = cloud.points - shift
    _, far_mesh = _normals_then_poisson(cloud)
    _, near_mesh = _normals_then_poisson(near)
    assert len(far_mesh.faces) == len(near_mesh.faces)
    assert far_mesh.vertices.dtype == np.float64  # double through normals -> PLY -> poisson -> PLY
    diff = np.abs(far_mesh.vertices - shift - near_mesh.vertices.astype(np.float64)).max(axis=1)
    # the same surface: almost every vertex equal to 1e-6 ft; the solve's rounding differs with the
    # offset, which moves a few crossings by millimetres (measured max 0.0066 ft; float32 output
    # rounded to 1/16 ft)
    assert np.quantile(diff, 0.99) < 1e-4 and diff.max() < 0.02


@pytest.mark.parametrize(
    ("where", "value", "what"),
    [
        ("table count", 3264405940, "declares 3264405940 chunks"),  # lazrs allocated 52 GB
        ("table offset", 2**40, "chunk table at byte"),
        ("table offset", 0, "chunk table at byte 0"),
    ],
)
def test_a_corrupted_laz_chunk_table_is_refused_before_lazrs_decodes(where, value, what):
    """A corrupted LAZ chunk table is refused in one line before lazrs reads it.

    The chunk table's offset (the points' first 8 bytes) or its count of chunks (after its
    version, at the offset) corrupted: lazrs allocated by them and aborted the process; the
    reader refuses them in one line first.
    """
    import struct

    _, data = _laspy_file(1, 3, "1.2", True, n=50)
    raw = bytearray(data)
    points = struct.unpack_from("<I", raw, 96)[0]
    table = struct.unpack_from("<q", raw, points)[0]
    if where == "table count":
        struct.pack_into("<I", raw, table + 4, value)
    else:
        struct.pack_into("<q", raw, points, value)
    with pytest.raises(InputError, match=what) as exc:
        decode_las(bytes(raw), "bad.laz")
    assert str(exc.value).startswith("bad.laz: ") and "\n" not in str(exc.value)
