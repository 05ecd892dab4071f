"""COPC by region: a window read equals the whole read cropped, bit for bit.

A window (box, octree levels) read equals the whole read cropped, bit for bit; levels and
resolutions give exactly the levels asked; an empty window is refused; the header and the CRS
are kept; ``recon info`` reads no point; the suffix and the content pick the reader; corrupted
files (truncated, bad hierarchy, bad VLRs) are refused in one line, without a hang.

The files are written by copc-lib around chunks lazrs compressed (``copc_files``): the Autzen
tile (US feet, its WKT) and a synthetic terrain whose deeper levels sit in hierarchy pages of
their own.
"""

from __future__ import annotations

import io
import json
import math
import os
import signal
import struct
from contextlib import contextmanager

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError, ParameterError
from recon_cli.io.copc import decode_copc, read_octree
from recon_cli.io.hint import ReadHint
from recon_cli.io.las import decode_las
from recon_cli.io.load import format_of, load, load_detailed

from copc_files import autzen_records, synthetic_records, write_copc
from fuzz_checks import convert_broken_files
from shared_data import SHARED

laspy = pytest.importorskip("laspy")
pytest.importorskip("copclib")

# the COPC info record's data: after the LAS 1.4 header (375 bytes) and the VLR's own (54)
INFO_AT = 375 + 54


@pytest.fixture(scope="module")
def autzen(tmp_path_factory):
    """The Autzen tile as COPC, its whole read, and each point's octree level (from the writer)."""
    path = tmp_path_factory.mktemp("copc") / "autzen.copc.laz"
    rec, scales, offsets, wkt = autzen_records()
    meta = write_copc(path, rec, scales, offsets, 7, wkt, root_cells=32, page_level=3)
    return _case(path, meta, wkt)


@pytest.fixture(scope="module")
def terrain(tmp_path_factory):
    """60k points of synthetic terrain, pages from level 1 down (many pages)."""
    path = tmp_path_factory.mktemp("copc") / "terrain.copc.laz"
    rec, scales, offsets = synthetic_records(60_000, seed=3)
    meta = write_copc(path, rec, scales, offsets, 7, root_cells=16, max_level=6, page_level=1)
    return _case(path, meta, "")


def _case(path, meta, wkt):
    whole, details, fmt = load_detailed(path)
    with open(path, "rb") as f:
        tree = read_octree(f, os.path.getsize(path), str(path))
    # the nodes in file order are the writer's (sorted by level and key): each point's level
    by_offset = tree.nodes[np.argsort(tree.nodes["offset"])]
    got = np.column_stack([by_offset[c] for c in ("level", "x", "y", "z")])
    assert np.array_equal(got, meta["keys"]) and np.array_equal(
        by_offset["point_count"], meta["counts"]
    )
    level = np.repeat(meta["levels"], meta["counts"])
    return {
        "path": path,
        "data": path.read_bytes(),
        "whole": whole,
        "details": details,
        "fmt": fmt,
        "level": level,
        "tree": tree,
        "wkt": wkt,
    }


def _text(box) -> str:
    """A box as the command line takes it (every digit of each float)."""
    return ",".join(repr(float(v)) for v in box)


def _inside(pts, box):
    lo, hi = np.asarray(box[:3]), np.asarray(box[3:])
    return ((pts >= lo) & (pts <= hi)).all(axis=1)


def _assert_same_points(got, whole, keep):
    """``got`` is ``whole`` restricted to ``keep``: points, colours, attributes, bit for bit."""
    assert got.points.dtype == np.float64
    assert np.array_equal(got.points, whole.points[keep])
    assert np.array_equal(got.colors, whole.colors[keep])
    assert sorted(got.attributes) == sorted(whole.attributes)
    for name, v in whole.attributes.items():
        assert got.attributes[name].dtype == v.dtype and np.array_equal(
            got.attributes[name], v[keep]
        ), name


@contextmanager
def _no_hang(seconds=20.0):
    """Fail (instead of waiting for ever) when the body takes more than ``seconds`` of CPU.

    CPU time, not wall time: a loaded machine slows a case down, a loop burns CPU.
    """

    def on_timer(signum, frame):
        raise TimeoutError(f"no answer within {seconds} CPU seconds: a hang")

    old = signal.signal(signal.SIGPROF, on_timer)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)


# ---- reading ------------------------------------------------------------------------------------
def test_whole_read_is_the_las_readers_and_laspys(autzen):
    """The whole COPC read equals the LAS reader's and laspy's points, with the same CRS."""
    las_cloud, las_details = decode_las(None, str(autzen["path"]), path=str(autzen["path"]))
    whole = autzen["whole"]
    assert autzen["fmt"].name == "copc" and autzen["details"]["format"] == "copc"
    assert len(whole.points) == 110_000
    _assert_same_points(whole, las_cloud, slice(None))
    assert whole.obj_info == las_cloud.obj_info
    ref = laspy.read(autzen["path"])
    assert np.array_equal(whole.points, np.column_stack([ref.x, ref.y, ref.z]))
    assert autzen["details"]["crs"] == las_details["crs"] == "NAD_1983_HARN_Lambert_Conformal_Conic"


_BOX = st.tuples(*[st.floats(-0.2, 1.2)] * 6)


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(fractions=_BOX, level=st.one_of(st.none(), st.integers(0, 6)))
def test_window_reads_equal_the_whole_read_cropped(terrain, fractions, level):
    """Random boxes and levels read equal the whole read cropped; an empty window is refused."""
    whole = terrain["whole"]
    lo, hi = whole.points.min(axis=0), whole.points.max(axis=0)
    f = np.asarray(fractions).reshape(2, 3)
    a, b = lo + f.min(axis=0) * (hi - lo), lo + f.max(axis=0) * (hi - lo)
    box = (*a, *b)
    keep = _inside(whole.points, box)
    if level is not None:
        keep &= terrain["level"] <= level
    hint = ReadHint(box=box, level=level, asked="--crop ...")
    if not keep.any():
        with pytest.raises(InputError, match="no point of the file there"):
            load(terrain["path"], hint=hint)
        return
    got, details, _ = load_detailed(terrain["path"], hint=hint)
    _assert_same_points(got, whole, keep)
    window = details["window"]
    assert window["points_in_file"] == 60_000 and window["nodes"] == len(terrain["tree"].nodes)
    assert keep.sum() <= window["points_decoded"] <= 60_000


def test_box_faces_on_points_keep_them_and_only_the_needed_nodes_are_decoded(autzen):
    """Points on a box's faces are kept; a 1 % window decodes a small part of the file."""
    whole = autzen["whole"]
    pts = whole.points
    rng = np.random.default_rng(7)
    for _ in range(4):
        i, j = rng.choice(len(pts), 2, replace=False)
        box = (*np.minimum(pts[i], pts[j]), *np.maximum(pts[i], pts[j]))
        box = (box[0], box[1], pts[:, 2].min(), box[3], box[4], pts[:, 2].max())
        got, details, _ = load_detailed(autzen["path"], hint=ReadHint(box=box))
        keep = _inside(pts, box)
        assert keep[i] and keep[j]  # the points on the faces are inside
        _assert_same_points(got, whole, keep)
    # a 1 % window decodes a small part of the file
    mid, ext = np.median(pts, axis=0), np.ptp(pts, axis=0)
    box = (*(mid - [0.05, 0.05, 1] * ext), *(mid + [0.05, 0.05, 1] * ext))
    _, details, _ = load_detailed(autzen["path"], hint=ReadHint(box=box))
    assert details["window"]["points_decoded"] < 0.15 * len(pts)
    assert details["window"]["nodes_read"] < 0.3 * details["window"]["nodes"]


@pytest.mark.parametrize("case", ["autzen", "terrain"])
def test_levels_and_resolutions_give_exactly_the_levels_asked(case, request):
    """``--level`` and ``--resolution`` read exactly the octree levels they name, no more."""
    c = request.getfixturevalue(case)
    whole, level, tree = c["whole"], c["level"], c["tree"]
    deepest = int(level.max())
    for lv in (0, 2, deepest - 1, deepest + 1):
        got, details, _ = load_detailed(c["path"], hint=ReadHint(level=lv))
        _assert_same_points(got, whole, level <= lv)
        assert details["window"]["levels"] == [0, min(lv, deepest)]
        assert got.obj_info[-1] == f"copc_read level {lv}"
        assert details["window"]["points_decoded"] == int((level <= lv).sum())
    # resolution R: down to the first level whose spacing (spacing / 2**level) is at most R
    for lv in (1, 3):
        exact = tree.spacing / 2**lv
        for r, want in ((exact, lv), (exact * 1.000001, lv), (exact * 0.999999, lv + 1)):
            got = load(c["path"], hint=ReadHint(resolution=r))
            assert np.array_equal(got.points, whole.points[level <= want]), (lv, r)
    assert len(load(c["path"], hint=ReadHint(resolution=10 * tree.spacing)).points) == int(
        (level == 0).sum()
    )


def test_an_empty_window_is_refused_not_an_empty_cloud(autzen, tmp_path, capfd):
    """A window holding no point is refused in one line, by the library and the command."""
    pts = autzen["whole"].points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    outside = (*(hi + 10), *(hi + 20))
    above = (lo[0], lo[1], hi[2] + 1, hi[0], hi[1], hi[2] + 2)  # inside the cube, over the points
    for box in (outside, above):
        with pytest.raises(InputError, match="no point of the file there") as exc:
            load(autzen["path"], hint=ReadHint(box=box, asked="--crop x"))
        assert "\n" not in str(exc.value) and str(exc.value).startswith(str(autzen["path"]))
    out = tmp_path / "out.ply"
    code, err = _cli(["filter", autzen["path"], out, "--crop", _text(above)], capfd)
    assert code == 2 and err.count("\n") == 1 and "no point of the file there" in err
    assert not out.exists()


def test_header_and_crs_kept_through_a_window_written_as_laz(autzen, tmp_path):
    """A window written as LAZ keeps each record's bytes, the header's scale and the WKT."""
    whole = autzen["whole"]
    pts = whole.points
    box = (*pts.min(axis=0), *(pts.min(axis=0) + 0.3 * np.ptp(pts, axis=0)))
    got = load(autzen["path"], hint=ReadHint(box=box))
    assert got.obj_info == whole.obj_info  # version, format, scale, offset, the WKT EVLR
    from recon_cli.io.las import coordinate_system
    from recon_cli.io.load import save

    assert not any(line.startswith("las_vlr ") for line in got.obj_info)
    assert coordinate_system(got.obj_info) == autzen["wkt"]  # what tiles georeferences by

    save(got, tmp_path / "w.laz")
    back = laspy.read(tmp_path / "w.laz")
    src = laspy.read(autzen["path"])
    keep = _inside(pts, box)
    assert np.array_equal(back.points.array, src.points.array[keep])  # every byte of each record
    assert np.array_equal(back.header.scales, src.header.scales)
    assert np.array_equal(back.header.offsets, src.header.offsets)
    wkts = [v.string for v in [*back.header.vlrs, *back.header.evlrs] if v.record_id == 2112]
    assert wkts == [autzen["wkt"]] and back.header.global_encoding.wkt
    assert not any(v.user_id == "copc" for v in [*back.header.vlrs, *back.header.evlrs])


def test_info_reports_the_hierarchy_without_decoding_a_point(autzen, monkeypatch, capfd):
    """``recon info`` reports counts per level, box and CRS without decoding a point."""
    import lazrs

    def no(*a, **k):
        raise AssertionError("a point was decoded")

    monkeypatch.setattr(lazrs, "decompress_points_with_chunk_table", no)
    monkeypatch.setattr(laspy, "read", no)
    monkeypatch.setattr(laspy.CopcReader, "query", no)
    code, out = _cli(["info", "--json", autzen["path"]], capfd, stream="out")
    assert code == 0
    rep = json.loads(out)[0]
    level, whole = autzen["level"], autzen["whole"]
    assert rep["format"] == "copc" and rep["vertices"] == 110_000
    d = rep["details"]
    assert d["points_per_level"] == np.bincount(level).tolist()
    assert sum(d["nodes_per_level"]) == d["octree_nodes"] == len(autzen["tree"].nodes)
    assert d["crs"] == "NAD_1983_HARN_Lambert_Conformal_Conic" and d["point_format"] == 7
    assert rep["bbox"]["min"] == whole.points.min(axis=0).tolist()
    assert rep["bbox"]["max"] == whole.points.max(axis=0).tolist()
    assert rep["attributes"] == sorted(whole.attributes) and rep["has_colors"]
    # the properties are those of the cloud a read gives
    props = ["float64 x y z", "uint16 colours x3"]
    props += [f"{v.dtype.name} {k}" for k, v in whole.attributes.items()]
    assert rep["properties"]["vertex"] == props


def test_suffix_and_content_choose_the_reader(autzen, tmp_path, monkeypatch):
    """.copc.laz or COPC content picks the COPC reader; a plain LAZ so named is refused."""
    assert format_of("a.COPC.LAZ").name == "copc" and format_of("a.laz").name == "las"
    named_laz = tmp_path / "tile.laz"
    named_laz.write_bytes(autzen["data"])
    box = (*autzen["whole"].points.min(axis=0), *autzen["whole"].points.mean(axis=0))
    _, details, fmt = load_detailed(named_laz, hint=ReadHint(box=box))
    assert fmt.name == "copc" and "window" in details  # a .laz holding COPC: read in part
    _, details, fmt = load_detailed(named_laz, format="las", hint=ReadHint(box=box))
    assert fmt.name == "las" and "window" not in details  # --input-format las: whole, as LAS
    # a plain LAZ named .copc.laz is refused, pointing at the way to read it
    plain = tmp_path / "plain.copc.laz"
    plain.write_bytes((SHARED / "autzen_trim.laz").read_bytes())
    with pytest.raises(InputError, match="not a COPC file.*--input-format las"):
        load(plain)
    # octree levels of a file that has none: refused before reading it
    monkeypatch.setattr(laspy, "read", lambda *a, **k: pytest.fail("read"))
    with pytest.raises(ParameterError, match="--level 2 chooses the octree levels of a COPC"):
        load(SHARED / "autzen_trim.laz", hint=ReadHint(level=2, asked="--level 2"))


def test_stdin_bytes_of_a_copc_file_read_in_part(autzen):
    """A COPC file's bytes (as from stdin) are read in part, as the file is."""
    from recon_cli.io.load import decode

    box = (*autzen["whole"].points.min(axis=0), *autzen["whole"].points.mean(axis=0))
    got, details, fmt = decode(autzen["data"], "-", None, hint=ReadHint(box=box, level=2))
    keep = _inside(autzen["whole"].points, box) & (autzen["level"] <= 2)
    assert fmt.name == "copc" and details["window"]["levels"] == [0, 2]
    _assert_same_points(got, autzen["whole"], keep)


# ---- the commands -------------------------------------------------------------------------------
def _cli(args, capfd, stream="err"):
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as ex:
        main(["-q", *map(str, args)])
    out, err = capfd.readouterr()
    return ex.value.code, (err if stream == "err" else out)


def test_filter_pipeline_and_library_read_the_same_window(autzen, tmp_path, capfd):
    """``recon filter``, a pipeline and the library read the same window of the file."""
    import recon_cli

    pts = autzen["whole"].points
    box = (*pts.min(axis=0), *(pts.min(axis=0) + 0.5 * np.ptp(pts, axis=0)))
    crop = _text(box)
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    assert _cli(["filter", autzen["path"], a, "--crop", crop, "--level", "3"], capfd)[0] == 0
    keep = _inside(pts, box) & (autzen["level"] <= 3)
    got = load(a)
    _assert_same_points(got, autzen["whole"], keep)
    toml = tmp_path / "p.toml"
    toml.write_text(
        f'[[stage]]\nname = "filter"\ncrop = [{crop}]\nlevel = 3\n\n'
        '[[stage]]\nname = "filter"\nclasses = "ground"\n'
    )
    code, out = _cli(["run", "--json", toml, autzen["path"], b], capfd, stream="out")
    assert code == 0
    rep = json.loads(out)
    assert rep["read"]["window"]["levels"] == [0, 3] and rep["read"]["kept"] == keep.sum()
    ground = autzen["whole"].attributes["classification"] == 2
    assert np.array_equal(load(b).points, pts[keep & ground])
    lib = recon_cli.filter(str(autzen["path"]), crop=box, level=3)
    assert np.array_equal(lib.points, pts[keep])
    # the same levels asked of a cloud in memory: it holds no octree
    with pytest.raises(InputError, match="this cloud was not read so"):
        recon_cli.filter(autzen["whole"], level=3)
    with pytest.raises(ParameterError, match="exclude each other"):
        recon_cli.filter(str(autzen["path"]), level=3, resolution=1.0)


# ---- corrupted files ----------------------------------------------------------------------------
def _root_page(data: bytes) -> tuple[int, int]:
    return struct.unpack_from("<2Q", data, INFO_AT + 40)


def _entries(data: bytes, offset: int, size: int) -> np.ndarray:
    dt = np.dtype([("key", "<i4", 4), ("offset", "<u8"), ("size", "<i4"), ("count", "<i4")])
    return np.frombuffer(data[offset : offset + size], dt)


def _entry_at(data, offset, size, pick) -> int:
    """The byte offset of the first entry of the page at ``offset`` for which ``pick(e)``."""
    for i, e in enumerate(_entries(data, offset, size)):
        if pick(e):
            return offset + 32 * i
    raise AssertionError("no such entry")


def _set(data: bytes, at: int, fmt: str, *values) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, at, *values)
    return bytes(out)


def _child_page(data):
    root, size = _root_page(data)
    at = _entry_at(data, root, size, lambda e: e["count"] == -1)
    off, n = struct.unpack_from("<Qi", data, at + 16)
    return at, off, n


def _corruptions(data: bytes, tree) -> list[tuple[str, bytes, str]]:
    """(label, corrupted file, what the message says)."""
    root, size = _root_page(data)
    node_at = _entry_at(data, root, size, lambda e: e["count"] > 0)
    child_at, child, child_size = _child_page(data)
    own = _entry_at(data, child, child_size, lambda e: e["count"] > 0)
    keys = {tuple(map(int, k)) for k in tree.nodes[["level", "x", "y", "z"]].tolist()}
    # the root node's chunk: its raw first point (36 bytes), its count, its 10 layer sizes
    first = tree.nodes[(tree.nodes["level"] == 0)][0]
    chunk = int(first["offset"])
    orphan = next(
        (lv, x, y, z)
        for lv in range(3, 8)
        for x in range(2**lv)
        for y, z in ((0, 0), (2**lv - 1, 2**lv - 1))
        if (lv - 1, x >> 1, y >> 1, z >> 1) not in keys and (lv, x, y, z) not in keys
    )
    return [
        (
            "root page past the end",
            _set(data, INFO_AT + 40, "<Q", len(data) + 64),
            "hierarchy page",
        ),
        ("root page of 33 bytes", _set(data, INFO_AT + 48, "<Q", 33), "multiple of 32"),
        (
            "child page is the root",
            _set(data, child_at + 16, "<Q", root),
            "does not hold that node",
        ),
        (
            "a page's own node points at the page (laspy loops)",
            _set(data, own + 16, "<Qii", child, child_size, -1),
            "does not hold that node",
        ),
        ("a chunk past the end", _set(data, node_at + 16, "<Q", len(data)), "lies outside"),
        ("a chunk inside the header", _set(data, node_at + 16, "<Q", 100), "lies outside"),
        (
            "a count one too many",
            _set(data, node_at + 28, "<i", 1 + struct.unpack_from("<i", data, node_at + 28)[0]),
            "header declares",
        ),
        ("a key off the grid", _set(data, node_at, "<4i", 1, 2, 0, 0), "outside the octree"),
        ("a negative level", _set(data, node_at, "<i", -3), "outside the octree"),
        ("a count below -1", _set(data, node_at + 28, "<i", -7), "outside the octree"),
        (
            "a node twice",
            _set(data, node_at + 32, "<4i", *struct.unpack_from("<4i", data, node_at)),
            "twice",
        ),
        ("an orphan node", _set(data, own, "<4i", *orphan), ""),
        ("half size 0", _set(data, INFO_AT + 24, "<d", 0.0), "not finite and positive"),
        ("y scale 0", _set(data, 139, "<d", 0.0), "scale positive"),
        ("x offset NaN", _set(data, 155, "<d", math.nan), "not finite"),
        ("spacing NaN", _set(data, INFO_AT + 32, "<d", math.nan), "not finite and positive"),
        ("centre infinite", _set(data, INFO_AT, "<d", math.inf), "not finite and positive"),
        ("a chunk's count", _set(data, chunk + 36, "<I", 1 + first["point_count"]), "declares"),
        ("a chunk's layer size", _set(data, chunk + 40, "<I", 2**31), "bytes of layers"),
        ("info VLR renamed", _set(data, 375 + 2, "4s", b"cope"), "not a COPC file"),
        ("info VLR shortened", _set(data, 375 + 20, "<H", 40), "cut short"),
        ("point format 3", _set(data, 104, "B", 0x83), ""),
        ("point count huge", _set(data, 247, "<Q", 2**40), "points"),
    ]


def _refused(data, hint, label, what, name="bad.copc.laz"):
    with _no_hang():
        with pytest.raises(InputError) as exc:
            decode_copc(data, name, hint=hint)
    msg = str(exc.value)
    assert msg.startswith(f"{name}: ") and "\n" not in msg, (label, msg)
    assert what in msg, (label, msg)


@pytest.mark.parametrize("hint", [None, ReadHint(level=2), ReadHint(box=(0, 0, 0, 1e9, 1e9, 1e9))])
def test_corrupted_hierarchy_and_vlrs_refused_in_one_line(autzen, hint, monkeypatch):
    """Corrupted hierarchy pages and VLRs are refused in one line before lazrs decodes."""
    import lazrs

    def decoded(*a, **k):
        raise AssertionError("refused only after lazrs decoded")

    monkeypatch.setattr(lazrs, "decompress_points_with_chunk_table", decoded)
    for label, bad, what in _corruptions(autzen["data"], autzen["tree"]):
        _refused(bad, hint, label, what)


def test_truncated_files_refused(terrain):
    """A file cut anywhere, header to chunks, is refused in one line."""
    data = terrain["data"]
    root, size = _root_page(data)
    last_page = max(root + size, *(int(o) + int(n) for o, n in _page_ranges(data)))
    cuts = [0, 10, 200, 374, 400, 600, 2000, len(data) // 3, root + 16, last_page - 1]
    for cut in cuts:
        for hint in (None, ReadHint(level=1)):
            _refused(data[:cut], hint, f"cut at {cut}", "")
    # the point data cut but the hierarchy whole: its chunks lie outside the file
    tree = terrain["tree"]
    end = int(tree.nodes["offset"].max())
    _refused(data[:end], ReadHint(level=6), "cut in the chunks", "")


def _page_ranges(data):
    root, size = _root_page(data)
    todo, out = [(root, size)], []
    while todo:
        off, n = todo.pop()
        out.append((off, n))
        todo += [
            (int(e["offset"]), int(e["size"])) for e in _entries(data, off, n) if e["count"] == -1
        ]
    return out


def test_evlrs_read_from_a_corrupted_start_are_data_not_a_traceback(terrain):
    """EVLRs read from a corrupted start are kept as data; the points read whole."""
    # the start of the EVLRs moved: laspy reads records whose text is not text (found by the fuzz)
    bad = terrain["data"][:234] + b"\0\0\1" + terrain["data"][237:]
    cloud, _ = decode_copc(bad, "f.copc.laz")
    assert np.array_equal(cloud.points, terrain["whole"].points)
    assert any(line.startswith("las_evlr ") for line in cloud.obj_info)


def test_cli_refuses_corrupted_files_in_one_line_and_writes_nothing(autzen, tmp_path, capfd):
    """Commands on corrupted files exit 2 with one line; the output keeps its bytes."""
    bad = tmp_path / "bad.copc.laz"
    out = tmp_path / "out.ply"
    out.write_bytes(b"before\n")
    for label, data, _ in _corruptions(autzen["data"], autzen["tree"])[::3]:
        bad.write_bytes(data)
        for args in (["filter", bad, out, "--level", "2"], ["info", bad], ["convert", bad, out]):
            code, err = _cli(args, capfd)
            assert code == 2 and err.count("\n") == 1, (label, args, err)
            assert err.startswith(f"recon: error: {bad}: "), (label, err)
            assert out.read_bytes() == b"before\n"
    assert sorted(os.listdir(tmp_path)) == ["bad.copc.laz", "out.ply"]


def _fuzz_case(data, tree, mutation, hint):
    """Read a mutated file: a cloud of finite points, or one InputError line; never a hang."""
    with _no_hang():
        try:
            cloud, _ = decode_copc(mutation(data), "f.copc.laz", hint=hint)
        except InputError as exc:
            assert str(exc).startswith("f.copc.laz: ") and "\n" not in str(exc)
            return
    assert np.isfinite(cloud.points).all() and 0 < len(cloud.points) <= tree.point_count


_HINTS = st.sampled_from(
    [None, ReadHint(level=1), ReadHint(box=(-1e12, -1e12, -1e12, 1e12, 1e12, 1e12), level=4)]
)


def _fuzz(terrain, draw_data, hint):
    data = terrain["data"]
    root, size = _root_page(data)
    regions = [(0, 375), (375, 700), (700, root), (root, len(data))]
    a, b = draw_data.draw(st.sampled_from(regions))
    at = draw_data.draw(st.integers(a, max(a, b - 1)))
    if draw_data.draw(st.booleans()):
        _fuzz_case(data, terrain["tree"], lambda d: d[:at], hint)
        return
    junk = draw_data.draw(st.binary(min_size=1, max_size=8))
    _fuzz_case(data, terrain["tree"], lambda d: d[:at] + junk + d[at + len(junk) :], hint)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(draw_data=st.data(), hint=_HINTS)
def test_fuzz_corrupted_copc_is_data_or_one_line(terrain, draw_data, hint):
    """Generated corruptions of the terrain file read as data or are refused in one line."""
    _fuzz(terrain, draw_data, hint)


@pytest.mark.fuzz
@settings(
    max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(draw_data=st.data(), hint=_HINTS)
def test_fuzz_long_corrupted_copc_is_data_or_one_line(terrain, draw_data, hint):
    """The same fuzz at 3000 examples (make fuzz)."""
    _fuzz(terrain, draw_data, hint)


def test_cli_on_randomly_broken_files_one_line_and_output_untouched(terrain, tmp_path, capfd):
    """``recon convert`` of seeded cuts and junk: one line and the output untouched."""
    # as the PLY and glTF fuzzes check the command: seeded cuts and junk in each part of the file
    data = terrain["data"]
    root, _ = _root_page(data)
    rng = np.random.default_rng(5)
    cases = []
    for a, b in [(0, 375), (375, 700), (700, root), (root, len(data))]:
        for at in rng.integers(a, b, 1):
            junk = rng.bytes(int(rng.integers(1, 9)))
            cases.append((f"cut {at}", "t.copc.laz", data[:at]))
            cases.append((f"junk at {at}", "t.copc.laz", data[:at] + junk + data[at + len(junk) :]))
    codes = convert_broken_files(cases, tmp_path, capfd)
    assert codes[2] >= len(cases) // 2  # the cuts at least are refused


def test_window_of_bytes_equals_window_of_file(autzen):
    """A window read from bytes equals the same window read from the file."""
    box = (*autzen["whole"].points.min(axis=0), *autzen["whole"].points.mean(axis=0))
    a, _ = decode_copc(None, "f", path=str(autzen["path"]), hint=ReadHint(box=box))
    b, _ = decode_copc(io.BytesIO(autzen["data"]).getvalue(), "f", hint=ReadHint(box=box))
    assert np.array_equal(a.points, b.points) and a.obj_info == b.obj_info
