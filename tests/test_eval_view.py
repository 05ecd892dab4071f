"""``recon view``: the self-contained page, opened in headless Chromium against our rasteriser."""

from __future__ import annotations

import base64
import html
import json
import re

import numpy as np
import pytest

from recon_cli.cli.main import main
from recon_cli.errors import ParameterError
from recon_cli.eval import view as view_module
from recon_cli.eval.diff import diff_files
from recon_cli.eval.figure import colorbar_labels
from recon_cli.eval.render import render
from recon_cli.eval.view import Layer, byte_colors, html_page, make_page, view_files
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import read_ply, write_ply

from browser import chromium, iou, open_page, silhouette
from shapes import torus, transformed
from shared_data import load_shared, sampled_cloud

# the one URL three.js holds: the XHTML namespace it passes to createElementNS (no request)
XHTML_NS = "http://www.w3.org/1999/xhtml"
SIZE = (760, 480)  # the page's viewport; its side panel is 260 CSS pixels wide
CANVAS = (SIZE[0] - 260, SIZE[1])


def run(capsys, *args) -> tuple[int, str, str]:
    """Run the CLI in this process on ``args``: (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def meta_of(doc: bytes) -> dict:
    """The page's recon-meta JSON."""
    text = doc.decode()
    m = re.search(r'<script type="application/json" id="recon-meta">(.*?)</script>', text, re.S)
    assert m is not None
    return json.loads(m.group(1))


def blob(doc: bytes, element: str, dtype) -> np.ndarray:
    """The page's base64 block ``element`` as an array of ``dtype``."""
    m = re.search(
        rf'<script type="application/octet-stream" id="{element}">(.*?)</script>', doc.decode()
    )
    assert m is not None
    return np.frombuffer(base64.b64decode(m.group(1)), dtype=dtype)


def bumped_kitten() -> TriangleMesh:
    """The kitten with a bump on its back (a few % of its size) and a little noise."""
    m = load_shared("kitten")
    v = np.asarray(m.vertices, dtype=np.float64).copy()
    size = float(np.ptp(v, axis=0).max())
    bump = np.exp(-(((v - v[100]) ** 2).sum(axis=1)) / (0.1 * size) ** 2)
    v[:, 1] += 0.03 * size * bump + np.random.default_rng(0).normal(0, 1e-3 * size, len(v))
    return TriangleMesh(v, np.asarray(m.faces), point_dtype=np.float64)


@pytest.fixture(scope="module")
def shapes(tmp_path_factory):
    """The files shown: the kitten, a generated torus (moved far off the origin), a cloud."""
    d = tmp_path_factory.mktemp("view")
    v, f = torus(1.0, 0.35, 48, 20)
    moved = transformed(v, np.random.default_rng(3), scale=2.5, offset=(1e5, -2e5, 3e5))
    files = {
        "kitten": load_shared("kitten"),
        "torus": TriangleMesh(moved, f, point_dtype=np.float64),
        "cloud": sampled_cloud("kitten", 8000, seed=1),
    }
    paths = {}
    for name, obj in files.items():
        paths[name] = d / f"{name}.ply"
        write_ply(obj, paths[name])
        view_files(paths[name], d / f"{name}.html")
    return d, {name: read_ply(p) for name, p in paths.items()}


@pytest.fixture(scope="module")
def browser():
    """A headless Chromium context for the module."""
    with chromium() as context:
        yield context


# ---- the page as a file --------------------------------------------------------------------------


def test_page_holds_everything_and_refers_to_nothing(shapes):
    """The kitten's page refers to no URL or file, holds three.js once, and its data to float32."""
    d, objs = shapes
    doc = (d / "kitten.html").read_bytes()
    text = doc.decode()
    assert re.findall(r"https?://[^\s\"'<>)]*", text.replace(XHTML_NS, "")) == []
    assert not re.search(
        r"<script[^>]*\ssrc=|<link\b|<img\b|@import|\bfetch\(|XMLHttpRequest", text
    )
    assert text.count("/*! three.js 0.187.0 (npm)") == 1
    meta = meta_of(doc)
    kitten = objs["kitten"]
    layer = meta["layers"][0]
    assert layer["index"] == "uint16" and layer["normals"] is None and layer["colors"] is None
    faces = blob(doc, layer["faces"], "<u2").reshape(-1, 3)
    np.testing.assert_array_equal(faces, kitten.faces)
    rel = blob(doc, layer["positions"], "<f4").reshape(-1, 3)
    back = rel.astype(np.float64) + np.asarray(meta["center"])
    # float32 relative to the centre: within float32's rounding of the frame's radius
    assert np.abs(back - kitten.vertices).max() <= 2**-23 * meta["radius"]


def test_far_coordinates_keep_float32_precision_relative_to_the_centre(shapes):
    """A torus 3.7e5 from the origin comes back within float32 rounding of the frame's radius."""
    d, objs = shapes
    doc = (d / "torus.html").read_bytes()
    meta = meta_of(doc)
    rel = blob(doc, meta["layers"][0]["positions"], "<f4").reshape(-1, 3)
    back = rel.astype(np.float64) + np.asarray(meta["center"])
    # the torus lies 3.7e5 from the origin: absolute float32 would round by ~0.03
    assert np.abs(back - objs["torus"].vertices).max() <= 2**-23 * meta["radius"]


def test_cloud_page_carries_normals_and_colours_as_bytes():
    """A 70k-point cloud's normals within half an int8 step, colours as bytes; big meshes uint32."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(70_000, 3))
    normals = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    colors = rng.random((70_000, 4)).astype(np.float32)
    doc, report = make_page(PointCloud(pts, normals=normals, colors=colors))
    meta = meta_of(doc)["layers"][0]
    assert report["kind"] == "cloud" and report["faces"] == 0 and report["bytes"] == len(doc)
    n = blob(doc, meta["normals"], np.int8).reshape(-1, 3) / 127.0
    assert np.abs(n - normals).max() <= 0.5 / 127 + 1e-12
    c = blob(doc, meta["colors"], np.uint8).reshape(-1, 3)
    np.testing.assert_array_equal(c, np.rint(colors[:, :3] * 255).astype(np.uint8))
    # a mesh of more than 65536 vertices needs 32-bit indices
    mesh = TriangleMesh(pts, rng.integers(0, len(pts), size=(10, 3)))
    assert meta_of(make_page(mesh)[0])["layers"][0]["index"] == "uint32"


def test_z_up_turns_the_data_a_quarter_turn_and_keeps_the_distances():
    """``up="z"`` turns the data a quarter turn (z becomes y), the same diff; "x" is refused."""
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(500, 3)) * (3.0, 2.0, 0.2)  # flat in z, as terrain
    cloud = PointCloud(pts, normals=np.tile([0.0, 0.0, 1.0], (500, 1)))
    shifted = PointCloud(pts + (0.0, 0.0, 0.05))
    doc_y, rep_y = make_page(cloud, shifted, samples=500)
    doc_z, rep_z = make_page(cloud, shifted, samples=500, up="z")
    assert rep_z["up"] == "z" and rep_z["diff"]["accuracy"] == rep_y["diff"]["accuracy"]
    meta = meta_of(doc_z)
    rel = blob(doc_z, meta["layers"][0]["positions"], "<f4").reshape(-1, 3)
    turned = rel.astype(np.float64) + meta["center"]
    np.testing.assert_allclose(turned, pts[:, [0, 2, 1]] * (1, 1, -1), atol=1e-6)
    normals = blob(doc_z, meta["layers"][0]["normals"], np.int8).reshape(-1, 3)
    assert (normals == (0, 127, 0)).all()  # z was up: now y is
    with pytest.raises(ParameterError, match="up must be y or z"):
        make_page(cloud, up="x")


def test_byte_colors_of_each_type():
    """``byte_colors`` of 16-bit, 8-bit-in-16-bit, RGBA and float colours (NaN and out of range)."""
    assert byte_colors(None) is None
    u16 = np.array([[65535, 0, 32768]], dtype=np.uint16)
    np.testing.assert_array_equal(byte_colors(u16), [[255, 0, 128]])
    # 8-bit values in 16-bit fields (autzen_trim.laz)
    np.testing.assert_array_equal(byte_colors(np.array([[40, 236, 0]], np.uint16)), [[40, 236, 0]])
    rgba = np.array([[1, 2, 3, 4]], dtype=np.uint8)
    np.testing.assert_array_equal(byte_colors(rgba), [[1, 2, 3]])
    f = np.array([[0.0, 0.5, 2.0], [np.nan, -1.0, 1.0]])
    np.testing.assert_array_equal(byte_colors(f), [[0, 128, 255], [0, 0, 255]])


def test_text_cannot_break_out_of_the_page():
    """Titles and layer names with ``</script>`` are escaped: no script ends early."""
    cube = TriangleMesh(np.eye(3), np.array([[0, 1, 2]]))
    title = "@@META@@ </script><b>"
    doc = html_page([Layer("a </script>", cube)], title=title).decode()
    assert doc.count("</script>") == doc.count("<script")
    assert f"<title>{html.escape(title)}</title>" in doc
    assert meta_of(doc.encode())["title"] == title


def test_missing_three_bundle_is_one_parameter_error(monkeypatch, tmp_path):
    """A missing three.js bundle is one ParameterError naming ``make viewer``; no page written."""
    monkeypatch.setattr(view_module, "THREE_BUNDLE", "no-such-bundle.js")
    with pytest.raises(ParameterError, match="make viewer"):
        view_files(tmp_path / "x.ply", tmp_path / "x.html")
    assert not (tmp_path / "x.html").exists()


# ---- the page in the browser ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["kitten", "torus", "cloud"])
def test_page_draws_our_rasteriser_silhouette(shapes, browser, name):
    """In Chromium, each page's shaded picture matches our rasteriser's silhouette (IoU >= 0.98)."""
    d, objs = shapes
    opened = open_page(browser, d / f"{name}.html", SIZE)
    try:
        assert opened.value("window.reconError") is None
        assert opened.console_errors() == []
        assert opened.requests == []
        for view in ("iso", "front", "top"):
            if view != "iso":
                opened.value(f"window.recon.setView('{view}')")
            shot = opened.canvas()
            assert shot.shape[:2] == (CANVAS[1], CANVAS[0])
            page_mask = silhouette(shot)
            ours = render(objs[name], view, size=CANVAS).mask
            assert page_mask.mean() > 0.1  # not blank
            # shaded, not flat: many grey levels inside the silhouette
            assert len(np.unique(shot[page_mask].sum(axis=1))) > 30
            score = iou(page_mask, ours)
            assert score >= 0.98, f"{name} {view}: IoU {score:.4f}"
        assert opened.console_errors() == []
    finally:
        opened.close()


def test_page_decodes_without_native_base64(shapes, browser):
    """Browsers without Uint8Array.fromBase64 (it is recent) take the page's atob path."""
    d, objs = shapes
    opened = open_page(browser, d / "torus.html", SIZE, init="delete Uint8Array.fromBase64;")
    try:
        assert opened.value("typeof Uint8Array.fromBase64") == "undefined"
        assert opened.console_errors() == []
        ours = render(objs["torus"], "iso", size=CANVAS).mask
        assert iou(silhouette(opened.canvas()), ours) >= 0.98
    finally:
        opened.close()


def test_first_frame_of_a_200k_face_mesh_is_quick(tmp_path, browser):
    """A 200k-face mesh's page draws its first frame within 3 s."""
    v, f = torus(1.0, 0.3, 500, 200)
    write_ply(TriangleMesh(v, f), tmp_path / "t.ply")
    report = view_files(tmp_path / "t.ply", tmp_path / "t.html")
    assert report["faces"] == 200_000
    opened = open_page(browser, tmp_path / "t.html", SIZE)
    try:
        assert opened.console_errors() == []
        ms = opened.value("window.reconFirstFrameMs")
        # the 1M-face figure (target 3 s) is bench/bench_view.py's
        assert 0 < ms <= 3000
        assert silhouette(opened.canvas()).mean() > 0.1
    finally:
        opened.close()


def test_diff_page_shows_recon_diffs_scale_and_numbers(tmp_path, browser):
    """A diff page has ``recon diff``'s numbers, heatmap colours and scale, hot on the bump."""
    write_ply(bumped_kitten(), tmp_path / "bump.ply")
    write_ply(load_shared("kitten"), tmp_path / "kitten.ply")
    (row,) = diff_files(
        [tmp_path / "bump.ply"],
        tmp_path / "kitten.ply",
        samples=20_000,
        heatmap_path=tmp_path / "heat.ply",
    )
    report = view_files(
        tmp_path / "bump.ply", tmp_path / "diff.html", tmp_path / "kitten.ply", samples=20_000
    )
    for key in ("accuracy", "completeness", "hausdorff", "hausdorff_p99", "fscore"):
        assert report["diff"][key] == row[key]
    # the page's colours are recon diff --heatmap's, so its scale is the same
    doc = (tmp_path / "diff.html").read_bytes()
    meta = meta_of(doc)
    colors = blob(doc, meta["layers"][0]["colors"], np.uint8).reshape(-1, 3)
    np.testing.assert_array_equal(colors, read_ply(tmp_path / "heat.ply").colors[:, :3])
    scale = report["scale"]
    ticks, note = colorbar_labels(scale["vmax"], scale["largest"], row["reference_diagonal"])
    assert scale["labels"] == [t for _, t in ticks] + [note]
    assert scale["largest"] > scale["vmax"] >= row["tau"][0]

    opened = open_page(browser, tmp_path / "diff.html", SIZE)
    try:
        assert opened.console_errors() == []
        shown = opened.value(
            "[...document.querySelectorAll('.colorbar .tick')].map(e => e.textContent)"
        )
        assert shown == [t for _, t in ticks]
        cells = opened.value(
            "Object.fromEntries([...document.querySelectorAll('td[data-metric]')]"
            ".map(e => [e.dataset.metric, e.textContent]))"
        )
        assert cells["accuracy"] == f"{row['accuracy']:.4g}"
        assert cells["hausdorff"] == f"{row['hausdorff']:.4g}"
        assert cells["F@0.5%"] == f"{row['fscore'][0]:.4f}"
        # hot colours on the bump: red pixels in the candidate's picture
        opened.value("window.recon.setView('front')")
        shot = opened.canvas().astype(int)
        red = (shot[..., 0] > 150) & (shot[..., 2] < 80)
        assert red.sum() > 100
        # the second layer: the reference, coloured by its distance to the candidate
        opened.page.check("input[data-layer='1']")
        opened.page.uncheck("input[data-layer='0']")
        after = opened.canvas()
        frame = (np.asarray(report["frame"]["center"]), report["frame"]["radius"])
        ours = render(load_shared("kitten"), "front", size=CANVAS, frame=frame).mask
        assert iou(silhouette(after), ours) > 0.98
        assert opened.console_errors() == []
    finally:
        opened.close()


def test_cloud_against_mesh_diff_page_draws_heat_points(shapes, browser, tmp_path):
    """A cloud diffed against its mesh draws its silhouette, nearly all blue (near zero)."""
    d, objs = shapes
    report = view_files(d / "cloud.ply", tmp_path / "c.html", d / "kitten.ply", samples=5000)
    assert report["kind"] == "cloud" and report["diff"]["mode_accuracy"] == "point-to-surface"
    opened = open_page(browser, tmp_path / "c.html", SIZE)
    try:
        assert opened.console_errors() == []
        shot = opened.canvas()
        # framed with the reference, as recon diff --png frames both
        frame = (np.asarray(report["frame"]["center"]), report["frame"]["radius"])
        ours = render(objs["cloud"], "iso", size=CANVAS, frame=frame).mask
        assert iou(silhouette(shot), ours) > 0.98
        # a sampled cloud lies on the kitten: all of it near the bottom (blue) of the scale
        inside = shot[silhouette(shot)].astype(int)
        assert (inside[:, 2] > inside[:, 0]).mean() > 0.95
    finally:
        opened.close()


# ---- the command ---------------------------------------------------------------------------------


def test_cli_writes_the_page_and_reports(tmp_path, capsysbinary):
    """``recon view`` writes the page and its JSON report, or the page to stdout with -o -."""
    src = tmp_path / "k.ply"
    write_ply(load_shared("kitten"), src)
    code, out, err = run(capsysbinary, "view", src, "-o", tmp_path / "k.html", "--json")
    assert code == 0 and err == b""
    report = json.loads(out)
    assert report["kind"] == "mesh" and report["faces"] == 12100 and report["vertices"] == 6050
    assert report["bytes"] == (tmp_path / "k.html").stat().st_size
    assert report["three"] == "0.187.0" and report["diff"] is None and report["view"] == [35, 25]
    code, page, err = run(capsysbinary, "view", src, "-o", "-", "--view", "front", "--title", "K")
    assert code == 0 and page.startswith(b"<!DOCTYPE html>") and b"<title>K</title>" in page
    assert meta_of(page)["view"] == pytest.approx([0, 0, 1])
    assert err.decode().startswith("wrote <stdout> (0.")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.ply"], "missing.ply"),
        (["garbage.ply"], "garbage.ply"),
        (["empty.ply"], "empty.ply: is empty"),
        (["k.ply", "--view", "sideways"], "unknown view"),
        (["k.ply", "--samples", "5"], "--samples need --diff"),
        (["k.ply", "--diff", "empty.ply"], "empty.ply: is empty"),
        (["k.ply", "--json", "-o", "-"], "--json and -o -"),
    ],
)
def test_cli_bad_input_is_one_line_and_nothing_written(tmp_path, capsys, args, message):
    """Missing, broken or empty inputs and bad options: exit 2, one line, nothing written."""
    write_ply(load_shared("kitten"), tmp_path / "k.ply")
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat nonsense\n")
    write_ply(PointCloud(np.zeros((0, 3))), tmp_path / "empty.ply")
    out_path = tmp_path / "page.html"
    full = [tmp_path / a if a.endswith(".ply") else a for a in args]
    if "-o" not in args:
        full += ["-o", out_path]
    code, out, err = run(capsys, "view", *full)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("recon: error: ") and message in err
    assert not out_path.exists() and out == ""
