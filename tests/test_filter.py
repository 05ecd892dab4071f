"""recon_cli.stages.filter: Open3D's rules exactly, LAS classes as laspy, attributes, refusals.

Open3D's outlier rules and voxel cells exactly, LAS classes and returns against laspy, every
attribute kept, the command's refusals.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.backends import open3d_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.ply import read_ply, write_ply
from recon_cli.stages import apply_stage
from recon_cli.stages.filter import (
    CLASS_NAMES,
    SPEC,
    box_codes,
    class_mask,
    crop_mask,
    filter_cloud,
    radius_outlier_mask,
    return_mask,
    statistical_outlier_mask,
    voxel_downsample,
)

from sensors import DepthCamera, depth_image, look_at, tabletop_scene, write_organized_pcd
from shapes import FAR_OFFSETS, cloud_family, shape_cloud
from shared_data import ROOT, SHARED

AUTZEN = SHARED / "autzen_trim.laz"
RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def _noisy_scan(seed: int, offset: str, n: int = 20_000):
    """A rotated, scaled torus, 0.5 % noise, 2 % uniform outliers in its box, at ``offset``."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-2, 2)
    pts, nrm = shape_cloud("torus", n, rng, scale=scale)
    pts += rng.normal(scale=0.005 * scale, size=pts.shape)
    k = n // 50
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pts[:k] = rng.uniform(lo, hi, size=(k, 3))
    return pts + np.asarray(FAR_OFFSETS[offset]), nrm, scale


FAMILY = [(0, "origin"), (1, "1e6"), (2, "utm")]


# ---- the outlier rules: Open3D's kept points, exactly --------------------------------------------
@pytest.mark.parametrize("seed,offset", FAMILY)
@pytest.mark.parametrize("k,std", [(6, 0.5), (20, 2.0), (30, 1.0)])
def test_statistical_outliers_keep_exactly_open3ds(seed, offset, k, std):
    """Statistical outlier removal keeps exactly Open3D's points, on noisy scans at any offset."""
    pts, _, _ = _noisy_scan(seed, offset)
    keep, fig = statistical_outlier_mask(pts, k, std)
    ref = open3d_backend.statistical_outlier_indices(pts, k, std)
    np.testing.assert_array_equal(np.flatnonzero(keep), ref)
    assert 0 < len(ref) < len(pts)  # the rule did something
    assert fig["threshold"] == pytest.approx(fig["mean"] + std * fig["std"])


@pytest.mark.parametrize("seed,offset", FAMILY)
@pytest.mark.parametrize("spacing,n_min", [(1.0, 1), (2.0, 8), (4.0, 30)])
def test_radius_outliers_keep_exactly_open3ds(seed, offset, spacing, n_min):
    """Radius outlier removal keeps exactly Open3D's points, on noisy scans at any offset."""
    pts, _, scale = _noisy_scan(seed, offset)
    r = spacing * 0.02 * scale  # ~1-4 point spacings of the torus samples
    keep = radius_outlier_mask(pts, r, n_min)
    ref = open3d_backend.radius_outlier_indices(pts, r, n_min)
    np.testing.assert_array_equal(np.flatnonzero(keep), ref)
    assert 0 < len(ref) < len(pts)


def test_outlier_rules_at_their_edges_as_open3d():
    """Duplicates, K=1 and neighbours at exactly R: both rules decide as Open3D does."""
    # duplicates: a point whose K nearest all coincide has mean distance 0 and is dropped
    p = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [1.2, 0, 0], [5, 5, 5.0]])
    keep, _ = statistical_outlier_mask(p, 2, 1.0)
    np.testing.assert_array_equal(
        np.flatnonzero(keep), open3d_backend.statistical_outlier_indices(p, 2, 1.0)
    )
    assert not keep[:3].any()
    # K=1 (only the point itself): every mean is 0, nothing is kept
    assert not statistical_outlier_mask(p, 1, 1.0)[0].any()
    # radius: a neighbour at exactly R does not count (strictly closer), the point itself does
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 0, 0]], float)
    for r in (0.5, 1.0, np.nextafter(1.0, 2.0)):
        for n_min in (1, 2, 3):
            np.testing.assert_array_equal(
                np.flatnonzero(radius_outlier_mask(line, r, n_min)),
                open3d_backend.radius_outlier_indices(line, r, n_min),
            )
    np.testing.assert_array_equal(radius_outlier_mask(line, 1.0, 1), [True, True, False, True])


# ---- voxel thinning: Open3D's cells and centroids ------------------------------------------------
@pytest.mark.parametrize("seed,offset", FAMILY)
@pytest.mark.parametrize("cells", [5.0, 40.0])
def test_voxel_centroids_equal_open3ds(seed, offset, cells):
    """Voxel centroids, mean normals and colours equal Open3D's to its rounding at 1e6."""
    pts, nrm, scale = _noisy_scan(seed, offset)
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (len(pts), 3)).astype(np.uint8)
    cloud = PointCloud(points=pts, normals=nrm, colors=colors)
    size = 3.0 * scale / cells
    ours = voxel_downsample(cloud, size)
    ref = open3d_backend.voxel_down_sample(cloud, size)
    assert len(ours) == len(ref["points"]) and 10 < len(ours) < len(pts)
    a, b = np.lexsort(ours.points.T), np.lexsort(ref["points"].T)
    # Open3D sums raw coordinates: its centroids are off by its own rounding at 1e6
    far = float(np.abs(pts).max())
    np.testing.assert_allclose(ours.points[a], ref["points"][b], rtol=0, atol=1e-13 * far + 1e-12)
    # normals: Open3D's mean, made unit; colours: its mean of [0, 1] colours, rounded in uint8
    ref_n = ref["normals"][b] / np.linalg.norm(ref["normals"][b], axis=1, keepdims=True)
    np.testing.assert_allclose(ours.normals[a], ref_n, atol=1e-12)
    assert np.abs(ours.colors[a].astype(float) - ref["colors"][b] * 255).max() <= 0.5 + 1e-9
    assert ours.colors.dtype == np.uint8


def test_voxel_cells_follow_open3ds_anchor_exactly():
    """Points on cell faces fall in Open3D's cells: a point on a face goes to the upper cell."""
    # points on the faces of Open3D's cells (min - S/2 + k S): the same cell as Open3D's floor
    size = 0.1
    g = np.arange(0, 1.0001, size / 2)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    ours = voxel_downsample(PointCloud(points=pts), size).points
    ref = open3d_backend.voxel_down_sample(PointCloud(points=pts), size)["points"]
    assert len(ours) == len(ref) == 11**3  # a point on a face goes to the upper cell
    a, b = np.lexsort(np.round(ours, 9).T), np.lexsort(np.round(ref, 9).T)
    np.testing.assert_allclose(ours[a], ref[b], rtol=0, atol=1e-15)


def test_fine_grids_over_a_wide_box_as_open3d(rng):
    """Cells of 2e-7 over a unit box (over 2^62 cells) match Open3D; 1e-10 is refused."""
    # 5e6 cells a side: more than 2**62 in the box, the three-coordinate table
    pts = rng.uniform(0, 1, (400, 3))
    pts = np.vstack([pts, pts[:100] + rng.normal(scale=1e-7, size=(100, 3)), pts[:50]])
    size = 2e-7
    ours = voxel_downsample(PointCloud(points=pts), size).points
    ref = open3d_backend.voxel_down_sample(PointCloud(points=pts), size)["points"]
    assert 400 < len(ours) == len(ref) < len(pts)
    a, b = np.lexsort(np.round(ours, 12).T), np.lexsort(np.round(ref, 12).T)
    np.testing.assert_allclose(ours[a], ref[b], rtol=0, atol=1e-15)
    for n_min in (1, 2):
        np.testing.assert_array_equal(
            np.flatnonzero(radius_outlier_mask(pts, size, n_min)),
            open3d_backend.radius_outlier_indices(pts, size, n_min),
        )
    with pytest.raises(ParameterError, match="--voxel 1e-10 is too small"):
        voxel_downsample(PointCloud(points=pts), 1e-10)


def test_voxel_attributes_averaged_codes_by_majority():
    """Voxel cells average measures (rounding to even) and take codes by majority, types kept."""
    # two cells of edge 1 anchored at -0.5: x in [-0.5, 0.5) and [0.5, 1.5)
    x = np.array([0.0, 0.1, 0.2, 1.0, 1.1])
    pts = np.column_stack([x, np.zeros(5), np.zeros(5)]).astype(np.float32)
    cloud = PointCloud(
        points=pts,
        normals=np.array([[0, 0, 1], [0, 0, 1], [np.nan, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32),
        colors=np.array(
            [[0, 0, 0], [255, 255, 255], [255, 0, 1], [10, 10, 10], [11, 11, 11]], "u1"
        ),
        attributes={
            "classification": np.array([6, 2, 6, 6, 2], np.uint8),
            "intensity": np.array([10, 11, 13, 10, 11], np.uint16),
            "gps_time": np.array([1.0, 2.0, 4.0, 5.0, 6.0]),
            "withheld": np.array([True, False, False, True, False]),
            "curvature": np.array([0.1, 0.2, 0.3, 0.4, 0.5], np.float32),
        },
    )
    out = voxel_downsample(cloud, 1.0)
    assert len(out) == 2 and out.point_dtype == np.float32
    np.testing.assert_allclose(out.points[:, 0], [0.1, 1.05], atol=1e-7)
    np.testing.assert_allclose(out.normals, [[0, 0, 1], [2**-0.5, 2**-0.5, 0]], atol=1e-7)
    assert out.normals.dtype == np.float32
    np.testing.assert_array_equal(out.colors, [[170, 85, 85], [10, 10, 10]])  # 10.5 -> 10
    a = out.attributes
    np.testing.assert_array_equal(a["classification"], [6, 2])  # majority; a 6/2 tie -> 2
    assert a["classification"].dtype == np.uint8
    np.testing.assert_array_equal(a["intensity"], [11, 10])  # 34/3 -> 11, 10.5 -> 10 (to even)
    assert a["intensity"].dtype == np.uint16
    np.testing.assert_allclose(a["gps_time"], [7 / 3, 5.5])
    np.testing.assert_array_equal(a["withheld"], [False, False])  # 1 of 3; a tie -> False
    assert a["curvature"].dtype == np.float32


# ---- crop, classes, returns ----------------------------------------------------------------------
def test_crop_keeps_points_on_the_faces_as_open3d(rng):
    """Crop keeps the points on the box's faces as Open3D does; malformed boxes are refused."""
    g = np.arange(-2, 3, dtype=float)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = np.vstack([pts, rng.uniform(-2, 2, (500, 3))])
    box = (-1.0, 0.0, -2.0, 1.0, 1.0, 0.5)
    keep = crop_mask(pts, box)
    np.testing.assert_array_equal(np.flatnonzero(keep), open3d_backend.crop_indices(pts, box))
    assert keep[np.all(pts == [1.0, 1.0, -2.0], axis=1)].all()  # a corner of the box
    for bad in ((1, 0, 0, 0, 1, 1), (0, 0, 0, 1, 1), "0,0,0,1,1,1,1"):
        with pytest.raises(ParameterError, match="--crop must be six numbers"):
            crop_mask(pts, bad)


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from([np.float64, np.float32, ">f8"]),
    layout=st.sampled_from(["contiguous", "record", "readonly"]),
    n=st.integers(1, 3 * (1 << 14) + 5),
)
def test_box_codes_equal_the_numpy_expression(seed, dtype, layout, n):
    """``box_codes`` equals the numpy expression for any dtype, layout and non-finite rows."""
    rng = np.random.default_rng(seed)
    g = np.arange(-2, 3, dtype=float)
    faces = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = rng.uniform(-3, 3, (n, 3))
    pts[: min(n, len(faces))] = faces[: min(n, len(faces))]  # on the faces, edges and corners
    for bad in (np.nan, np.inf, -np.inf):
        rows = rng.random(n) < 0.05
        pts[rows, rng.integers(0, 3)] = bad
    pts = pts.astype(dtype)
    if layout == "record":  # a binary PLY's strided view
        rec = np.zeros(n, [("xyz", pts.dtype, (3,)), ("c", "u1", (3,))])
        rec["xyz"] = pts
        pts = rec["xyz"]
    elif layout == "readonly":
        pts.flags.writeable = False
    box = (-1.0, 0.0, -2.0, 1.0, 2.0, 0.5)
    p = pts.astype(np.float64)
    finite = np.isfinite(p).all(axis=1)
    inside = np.all((p >= box[:3]) & (p <= box[3:]), axis=1)
    want = np.where(~finite, 1, np.where(inside, 0, 2))
    got = box_codes(pts, box)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(box_codes(pts), np.where(finite, 0, 1))  # no box: finite only
    np.testing.assert_array_equal(crop_mask(pts, box), want == 0)


def test_invalid_points_and_crop_counted_from_one_pass():
    """Non-finite and cropped points are counted apart; a crop leaving nothing is refused."""
    g = np.arange(-2, 3, dtype=float)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)  # 125 points
    pts[[0, 7, 62]] = [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]]  # 62 was (0, 0, 0)
    box = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)  # 27 grid points on or inside it
    out, rep = filter_cloud(PointCloud(points=pts), crop=box)
    assert rep["invalid_removed"] == 3 and rep["crop_removed"] == 125 - 3 - 26
    assert rep["points_out"] == len(out.points) == 26  # (0, 0, -inf) was the 27th
    _, rep = filter_cloud(PointCloud(points=pts))
    assert rep["invalid_removed"] == 3 and rep["crop_removed"] is None
    with pytest.raises(InputError, match=r"--crop 5,5,5,6,6,6 leaves no point \(of 122\)"):
        filter_cloud(PointCloud(points=pts), crop=(5.0, 5, 5, 6, 6, 6))
    with pytest.raises(InputError, match="every point"):
        filter_cloud(PointCloud(points=np.full((4, 3), np.nan)), crop=box)


def _autzen():
    pytest.importorskip("laspy")
    from recon_cli.io.load import load

    return load(str(AUTZEN))


def test_classes_and_returns_count_as_laspy():
    """Class and return filters on the Autzen tile keep exactly laspy's points and attributes."""
    laspy = pytest.importorskip("laspy")
    las = laspy.read(str(AUTZEN))
    cls = np.asarray(las.classification)
    r, nr = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    cloud = _autzen()
    for classes in ("2", "ground", [2], (1, 2), "unclassified,ground"):
        out, rep = filter_cloud(cloud, classes=classes)
        want = np.isin(cls, SPEC.param("classes").coerce(classes))
        assert len(out) == want.sum() == rep["points_out"]
        assert rep["classes_removed"] == len(cls) - want.sum()
        np.testing.assert_array_equal(out.points, cloud.points[want])  # exact, double kept
        for name, v in cloud.attributes.items():  # every attribute, its type kept
            np.testing.assert_array_equal(out.attributes[name], v[want])
            assert out.attributes[name].dtype == v.dtype
        np.testing.assert_array_equal(out.colors, cloud.colors[want])
        assert out.obj_info == cloud.obj_info  # the LAS header (scale, offset, VLRs) travels
    assert (filter_cloud(cloud, classes=2)[0].attributes["classification"] == 2).sum() == 26107
    rules = {
        "first": r == 1,
        "last": r == nr,
        "single": nr == 1,
        "intermediate": (r > 1) & (r < nr),
    }
    for which, want in rules.items():
        out, rep = filter_cloud(cloud, returns=which)
        assert len(out) == want.sum() and rep["returns_removed"] == len(cls) - want.sum()
        np.testing.assert_array_equal(
            out.attributes["gps_time"], cloud.attributes["gps_time"][want]
        )
        np.testing.assert_array_equal(return_mask(r, nr, which), want)
    out, rep = filter_cloud(cloud, classes="ground", returns="first")  # classes, then returns
    assert len(out) == (rules["first"] & (cls == 2)).sum()
    assert rep["returns_removed"] == (cls == 2).sum() - len(out) > 0


def test_classes_refusals():
    """Unknown classes or names, no point left, and clouds without LAS fields are refused."""
    cloud = _autzen()
    with pytest.raises(InputError, match=r"--classes 7 leaves no point .*present: 1, 2"):
        filter_cloud(cloud, classes=7)
    for bad, needle in (("grund", "'grund' is neither"), ("300", "300 is not a LAS class")):
        with pytest.raises(ParameterError, match=needle):
            filter_cloud(cloud, classes=bad)
    bare = PointCloud(points=np.zeros((3, 3)))
    with pytest.raises(InputError, match="classification"):
        filter_cloud(bare, classes=2)
    with pytest.raises(InputError, match="return_number"):
        filter_cloud(bare, returns="last")


@given(st.lists(st.one_of(st.integers(0, 255), st.sampled_from(sorted(CLASS_NAMES))), min_size=1))
@settings(max_examples=60, deadline=None)
def test_class_parser_text_and_list_agree(items):
    """Classes given as text or a list, by number or name, parse to the same set."""
    p = SPEC.param("classes")
    want = tuple(sorted({CLASS_NAMES.get(x, x) if isinstance(x, str) else x for x in items}))
    assert p.coerce(items) == want
    assert p.coerce(",".join(str(x).upper() for x in items)) == want
    assert class_mask(np.arange(256), items).sum() == len(want)


@given(st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6))
@settings(max_examples=60, deadline=None)
def test_crop_parser_accepts_exactly_ordered_boxes(v):
    """The crop parser takes six numbers with x0 <= x1 on each axis, and refuses the rest."""
    p = SPEC.param("crop")
    if all(v[i] <= v[i + 3] for i in range(3)):
        assert p.coerce(",".join(repr(x) for x in v)) == tuple(v)
    else:
        with pytest.raises(ParameterError, match="x0 <= x1"):
            p.coerce(v)


# ---- the stage: order, report, attributes, precision ---------------------------------------------
@pytest.mark.parametrize("seed", [0, 3])
def test_subsets_keep_every_attribute_and_the_precision(seed):
    """Invalid, crop and outlier removal keep every field of the rows kept, float32 or float64."""
    cloud = cloud_family(seed, n=3000)
    f32 = PointCloud(
        points=cloud.points.astype(np.float32),
        normals=cloud.normals.astype(np.float32),
        colors=cloud.colors,
        attributes=cloud.attributes,
        point_dtype=np.float32,
    )
    for c in (cloud, f32):
        bad = c.copy()
        bad.points = np.asarray(bad.points).copy()
        bad.points[::7, seed % 3] = [np.nan, np.inf, -np.inf][seed % 3]
        lo, hi = np.percentile(np.asarray(c.points, float), [10, 90], axis=0)
        out, rep = filter_cloud(bad, crop=(*lo, *hi), outliers=(10, 1.0))
        finite = np.isfinite(bad.points).all(axis=1)
        inside = finite & ((bad.points >= lo) & (bad.points <= hi)).all(axis=1)
        assert rep["invalid_removed"] == (~finite).sum() > 0
        assert rep["crop_removed"] == finite.sum() - inside.sum()
        assert rep["outliers_removed"] == inside.sum() - len(out) > 0
        rows = np.flatnonzero(inside)[statistical_outlier_mask(bad.points[inside], 10, 1.0)[0]]
        assert out.points.dtype == c.points.dtype and out.point_dtype == c.point_dtype
        np.testing.assert_array_equal(out.points, bad.points[rows])
        np.testing.assert_array_equal(out.normals, bad.normals[rows])
        np.testing.assert_array_equal(out.colors, bad.colors[rows])
        for k, v in bad.attributes.items():
            np.testing.assert_array_equal(out.attributes[k], v[rows])


def test_depth_camera_frame_invalid_pixels_and_flying_pixels():
    """A depth frame's misses are counted invalid; its flying pixels go as Open3D's rule says."""
    rng = np.random.default_rng(7)
    cam = DepthCamera(eye=np.array([0.0, -2.2, 1.3]), rotation=look_at((0, -2.2, 1.3), (0, 0, 0.2)))
    img = depth_image(cam, tabletop_scene(), rng, noise=1.0, flying=0.6)
    flat = img.reshape(-1, 3)
    nan = ~np.isfinite(flat).all(axis=1)
    assert 0 < nan.sum() < len(flat)  # misses beyond the range
    out, rep = filter_cloud(PointCloud(points=flat), outliers=(20, 2.0))
    assert rep["invalid_removed"] == nan.sum()
    ref = open3d_backend.statistical_outlier_indices(flat[~nan], 20, 2.0)
    np.testing.assert_array_equal(out.points, flat[~nan][ref])
    assert rep["outliers_removed"] > 0


def test_organized_frame_keeps_pixels_and_camera_through_filter(tmp_path):
    """An organized frame keeps its pixels and camera through filter; voxels keep the camera."""
    from recon_cli.io.load import load

    rng = np.random.default_rng(11)
    eye = np.array([0.3, -2.0, 1.2])
    cam = DepthCamera(eye=eye, rotation=look_at(eye, (0, 0, 0.2)), width=96, height=72)
    src = tmp_path / "frame.pcd"
    write_organized_pcd(src, depth_image(cam, tabletop_scene(), rng, flying=0.6), cam)
    cloud = load(src)
    assert cloud.pixels is not None and cloud.sensors and cloud.invalid_dropped > 0
    out, rep = filter_cloud(cloud, outliers=(20, 2.0))
    rows = np.flatnonzero(statistical_outlier_mask(cloud.points, 20, 2.0)[0])
    assert rep["outliers_removed"] == len(cloud) - len(rows) > 0
    np.testing.assert_array_equal(out.pixels.pixel, cloud.pixels.pixel[rows])
    assert out.pixels.shapes == cloud.pixels.shapes and out.sensors == cloud.sensors
    assert out.invalid_dropped == cloud.invalid_dropped
    # the next stage still finds the pixel neighbourhoods and the file's camera
    res = apply_stage("normals", out, {"orient": "camera"})
    assert res.report["neighbours"].startswith("pixels") and res.report["viewpoints"]
    assert (np.einsum("ij,ij->i", res.output.normals, eye - out.points) >= 0).all()
    # a centroid is no pixel: thinned, the cloud is not organized but keeps its camera
    thin = voxel_downsample(out, 0.05)
    assert thin.pixels is None and thin.sensors == cloud.sensors and len(thin) < len(out)


def test_other_ply_elements_travel_unless_they_index_the_points(rng):
    """Other PLY elements travel; one indexing the points is refused when rows merge."""
    from recon_cli.io.ply import PlyElement, PlyProperty

    camera = PlyElement("camera", 1, [PlyProperty("k", "i2")], {"k": np.array([-3], np.int16)})
    edge = PlyElement(
        "edge",
        1,
        [PlyProperty("vertex1", "i4"), PlyProperty("vertex2", "i4")],
        {"vertex1": np.array([0], np.int32), "vertex2": np.array([1], np.int32)},
    )
    pts = rng.uniform(0, 1, (200, 3))
    out, _ = filter_cloud(
        PointCloud(points=pts, extra_elements=[camera]), crop=(0, 0, 0, 1, 1, 0.5)
    )
    assert out.extra_elements == [camera] and len(out) < len(pts)
    linked = PointCloud(points=pts, extra_elements=[camera, edge])
    assert filter_cloud(linked, crop=(0, 0, 0, 1, 1, 1))[0].extra_elements == [camera, edge]
    with pytest.raises(InputError, match="element 'edge' refers to the points by index"):
        filter_cloud(linked, voxel=0.5)


def test_library_function_drops_nan_rows_of_arrays(rng):
    """``recon_cli.filter`` on arrays drops their NaN rows, then thins as Open3D does."""
    import recon_cli

    pts = rng.normal(size=(500, 3)) + 1e6
    pts[::9] = np.nan
    out = recon_cli.filter(pts, voxel=0.5)
    assert out.report["invalid_removed"] == len(pts[::9])
    assert np.isfinite(out.points).all() and out.history[-1].split()[2] == "filter"
    ref = open3d_backend.voxel_down_sample(PointCloud(points=pts[np.isfinite(pts[:, 0])]), 0.5)
    assert len(out.points) == len(ref["points"]) == out.report["points_out"]


def test_stage_order_report_and_pipeline_kinds(tmp_path):
    """The stage's counts add up in order; it keeps normals, so Poisson may follow it."""
    from recon_cli.pipeline import check_pipeline, parse_pipeline

    pts, nrm, scale = _noisy_scan(4, "1e6", n=8000)
    cloud = PointCloud(points=pts, normals=nrm)
    res = apply_stage(
        "filter",
        cloud,
        {"radius_outliers": "%r,4" % (0.04 * scale), "outliers": "20,2", "voxel": scale / 20},
    )
    rep = res.report
    counts = [rep[k] for k in ("invalid_removed", "radius_outliers_removed", "outliers_removed")]
    assert (
        rep["points_in"] - sum(counts) - rep["voxel_merged"] == rep["points_out"] == len(res.output)
    )
    assert rep["crop_removed"] is None and rep["classes_removed"] is None
    assert res.output.normals is not None and res.output.history[-1].startswith("recon ")
    assert "outliers=20,2" in res.output.history[-1] and cloud.history == []
    # filter keeps normals: a pipeline may go on to poisson; without normals poisson refuses at run
    text = '[[stage]]\nname = "filter"\nvoxel = 0.1\n[[stage]]\nname = "poisson"\n'
    check_pipeline(parse_pipeline(text, "p.toml", check=False))
    with pytest.raises(InputError, match="needs points with normals"):
        apply_stage("poisson", apply_stage("filter", PointCloud(points=pts)).output)
    with pytest.raises(InputError, match="needs a point cloud, got a triangle mesh"):
        apply_stage("filter", TriangleMesh(vertices=pts[:3], faces=[[0, 1, 2]]))


# ---- the command: refusals are one line, exit 2, no output ---------------------------------------
@pytest.mark.parametrize(
    "args,needle",
    [
        (["--classes", "grund"], "'grund' is neither"),
        (["--crop", "0,0,0,-1,1,1"], "--crop must be six numbers"),
        (["--voxel", "0"], "--voxel must be a number with 0 < x"),
        (["--classes", "6"], "--classes 6 leaves no point"),
        (["--outliers", "0,2"], "--outliers must be K,STD: an integer K >= 1"),
        (["--crop", "5,5,5,6,6,6"], "--crop 5,5,5,6,6,6 leaves no point"),
    ],
)
def test_command_refusals(tmp_path, args, needle):
    """Bad classes, crops, voxels, outliers, or nothing left: exit 2, one line, no output."""
    src = tmp_path / "in.ply"
    write_ply(
        PointCloud(
            points=np.random.default_rng(0).random((50, 3)),
            attributes={"classification": np.full(50, 2, np.uint8)},
        ),
        src,
    )
    out = tmp_path / "out.ply"
    r = subprocess.run(
        [*RECON, "filter", src, out, *args], capture_output=True, text=True, cwd=ROOT
    )
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err and not out.exists()


def test_command_ground_of_the_airborne_tile(tmp_path):
    """``recon filter --classes 2`` of the tile writes its 26107 ground points in float64."""
    pytest.importorskip("laspy")
    out = tmp_path / "ground.ply"
    r = subprocess.run(
        [*RECON, "filter", AUTZEN, out, "--classes", "2", "--json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["points_out"] == 26107 and rep["classes_removed"] == 83893
    back = read_ply(out)
    assert len(back) == 26107 and (back.attributes["classification"] == 2).all()
    assert back.points.dtype == np.float64 and os.path.getsize(out) > 0
