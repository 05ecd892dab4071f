"""recon_cli.eval.render: the software rasteriser, checked by pixels."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon_cli.errors import ParameterError
from recon_cli.eval.render import (
    BACKGROUND,
    BASE_COLOR,
    BOUNDARY_COLOR,
    NON_MANIFOLD_COLOR,
    TURNTABLE,
    VIEWS,
    camera,
    colormap,
    defect_edges,
    png_bytes,
    render,
    resolve_views,
    write_png,
)
from recon_cli.geometry import PointCloud, TriangleMesh

FRAME = (np.zeros(3), 1.0)  # world unit sphere -> 0.46 * side pixels


def _sphere(radius, subdivisions=5, center=(0, 0, 0)):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return TriangleMesh(np.asarray(s.vertices) + np.asarray(center), np.asarray(s.faces))


def _quad(x0, x1, y0, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_sphere_silhouette_area():
    """A sphere's silhouette in three views covers pi r^2 pixels within 1 %, centred."""
    size = 400
    px = 0.46 * size  # pixels per world unit with FRAME
    for r, view in ((0.8, "front"), (0.5, "iso"), (0.3, "top")):
        out = render(_sphere(r), view, (size, size), FRAME)
        expected = np.pi * (r * px) ** 2
        assert out.mask.sum() == pytest.approx(expected, rel=0.01)
        # centred: the centroid of the silhouette is the image centre
        ii, jj = np.nonzero(out.mask)
        assert ii.mean() == pytest.approx(size / 2, abs=0.5) and jj.mean() == pytest.approx(
            size / 2, abs=0.5
        )


def _centres(half_extent_px: float, size: int) -> int:
    """Pixel centres j + 0.5 within size / 2 +- half_extent_px."""
    lo, hi = size / 2 - half_extent_px, size / 2 + half_extent_px
    return int(np.floor(hi - 0.5) - np.ceil(lo - 0.5) + 1)


def test_box_silhouette_and_depth():
    """A box's silhouette is the pixel centres in its rectangle; the depth its front face's."""
    b = trimesh.creation.box(extents=(1.0, 0.5, 0.3))
    mesh = TriangleMesh(np.asarray(b.vertices), np.asarray(b.faces))
    size = 310  # box edges off the pixel centres (a centre on an edge counts as inside)
    px = 0.46 * size
    for view, (w, h) in (("front", (1.0, 0.5)), ("right", (0.3, 0.5)), ("top", (1.0, 0.3))):
        out = render(mesh, view, (size, size), FRAME)
        # exactly the pixel centres inside the projected rectangle, and its area
        assert out.mask.sum() == _centres(w / 2 * px, size) * _centres(h / 2 * px, size), view
        assert out.mask.sum() == pytest.approx(w * h * px * px, rel=0.03), view
    front = render(mesh, "front", (size, size), FRAME)
    # the visible front face is at z = +0.15, i.e. depth -0.15 along the view
    assert np.allclose(front.depth[front.mask], -0.15)
    # everything outside the silhouette is background
    assert (front.image[~front.mask] == np.array(BACKGROUND, dtype=np.uint8)).all()


def test_depth_order_of_overlapping_objects_does_not_depend_on_drawing_order():
    """Two overlapping squares drawn in either order give the same picture, the near one on top."""
    vn, fn = _quad(-0.6, 0.2, -0.6, 0.2, 0.3)  # near (front view looks from +z)
    vf, ff = _quad(-0.2, 0.6, -0.2, 0.6, -0.3)  # far, overlapping the near one
    near_first = TriangleMesh(np.vstack([vn, vf]), np.vstack([fn, ff + 4]))
    far_first = TriangleMesh(np.vstack([vf, vn]), np.vstack([ff, fn + 4]))
    values_nf = np.r_[np.ones(4), np.zeros(4)]  # near = 1 (red end), far = 0 (blue end)
    values_ff = np.r_[np.zeros(4), np.ones(4)]
    a = render(near_first, "front", (200, 200), FRAME, scalars=values_nf, vmax=1.0)
    b = render(far_first, "front", (200, 200), FRAME, scalars=values_ff, vmax=1.0)
    assert np.array_equal(a.image, b.image)
    px = 0.46 * 200
    overlap = (100 + int(0.0 * px), 100 + int(0.0 * px))  # world (0, 0) is inside both
    only_far = (100 - int(0.4 * px), 100 + int(0.4 * px))  # world (0.4, 0.4): row up, column right
    red, blue = colormap(np.array([1.0, 0.0]), 0.0, 1.0).astype(int)
    assert a.depth[overlap] == pytest.approx(-0.3)
    assert a.depth[only_far] == pytest.approx(0.3)
    # heat colours are shaded (0.55 + 0.45 * Lambert), so compare the hue: red dominates over the
    # overlap
    assert int(a.image[overlap][0]) > int(a.image[overlap][2]) and red[0] > red[2]
    assert int(a.image[only_far][2]) > int(a.image[only_far][0]) and blue[2] > blue[0]


def test_lambert_shading_of_a_facing_square():
    """A square facing the camera has the Lambert shade of the light; tilted, another shade."""
    v, f = _quad(-0.5, 0.5, -0.5, 0.5, 0.0)
    out = render(TriangleMesh(v, f), "front", (64, 64), FRAME)
    rot = camera("front")
    light = rot[2] + 0.45 * rot[1] + 0.3 * rot[0]
    cos = light[2] / np.linalg.norm(light)  # the square's normal is +z
    shade = 0.22 + 0.78 * cos
    expected = np.rint(255 * shade * np.asarray(BASE_COLOR)).astype(np.uint8)
    assert (out.image[32, 32] == expected).all()
    # a square turned away from the light is darker
    tilted = TriangleMesh(
        v @ np.array([[np.cos(1.0), 0, np.sin(1.0)], [0, 1, 0], [-np.sin(1.0), 0, np.cos(1.0)]]), f
    )
    t = render(tilted, "front", (64, 64), FRAME)
    assert int(t.image[32, 32].sum()) != int(out.image[32, 32].sum())


def test_point_cloud_is_splatted():
    """Points are drawn as discs of the given pixel radius."""
    pts = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0]])
    out = render(PointCloud(points=pts), "front", (100, 100), FRAME, point_radius=2.0)
    # two discs of radius 2 px: 12 or 13 pixel centres each
    assert 20 <= out.mask.sum() <= 30
    assert out.mask[50, 50] and out.mask[50 - 23, 50 + 23]


def test_cameras_are_orthonormal():
    """Every named view's camera is a rotation; an unknown view is refused."""
    for name in VIEWS:
        r = camera(name)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    with pytest.raises(ParameterError):
        camera("sideways")


def test_colormap():
    """The colour ramp runs blue to red, clipped at its ends; NaN gets the low end's colour."""
    c = colormap(np.array([-1.0, 0.0, 0.5, 1.0, 9.0, np.nan]), 0.0, 1.0)
    assert (c[0] == c[1]).all() and (c[3] == c[4]).all() and (c[5] == c[1]).all()
    assert c[1][2] > c[1][0] and c[3][0] > c[3][2]  # blue low, red high


def test_resolve_views():
    """Views by name or azimuth/elevation get their labels; the default is the 4-view turntable."""
    tt = resolve_views(None)
    assert [a for _, a in tt] == list(TURNTABLE) and len(tt) == 4
    assert (
        len({az for az, _ in TURNTABLE}) == 4 and tt[0][1] == VIEWS["iso"]
    )  # four azimuths, from the iso view
    assert resolve_views(["front", (10, 20)]) == [
        ("front (az 0°, el 0°)", (0.0, 0.0)),
        ("az 10°, el 20°", (10.0, 20.0)),
    ]
    assert resolve_views("-30,45.5") == [("az -30°, el 45.5°", (-30.0, 45.5))]
    for bad in (["sideways"], [], "1,2,3", "a,b", "nan,1"):
        with pytest.raises(ParameterError):
            resolve_views(bad)


def _count(img, rgb, tol=30):
    return int((np.abs(img.astype(int) - np.asarray(rgb)).max(axis=2) < tol).sum())


def test_boundary_and_non_manifold_edges_are_drawn_where_visible():
    """Boundary and non-manifold edges are drawn in their colours where visible, not when hidden."""
    # an open square: four boundary edges along its outline, none inside
    v, f = _quad(-0.5, 0.5, -0.5, 0.5, 0.0)
    sq = TriangleMesh(v, f)
    groups = defect_edges(sq)
    assert len(groups[0][0]) == 4 and len(groups[1][0]) == 0
    out = render(sq, "front", (200, 200), FRAME, edges=groups, edge_width=2.0).image
    px = 0.46 * 200
    lo, hi = int(100 - 0.5 * px), int(100 + 0.5 * px)
    assert _count(out, BOUNDARY_COLOR) > 4 * (hi - lo)  # the outline, about 2 px wide
    assert _count(out[lo + 5 : hi - 5, lo + 5 : hi - 5], BOUNDARY_COLOR) == 0  # not the inside
    assert (out[100, lo] == BOUNDARY_COLOR).all() and (out[lo, 100] == BOUNDARY_COLOR).all()
    # a closed box has none; a box in front of the square hides the square's outline
    bv, bf = _box(1.2)
    box = TriangleMesh(bv + [0, 0, 0.7], bf)  # z from 0.1 to 1.3, wider than the square
    assert all(len(e) == 0 for e, _ in defect_edges(box))
    both = TriangleMesh(np.vstack([v, box.vertices]), np.vstack([f, bf + 4]))
    hidden = render(both, "front", (200, 200), FRAME, edges=defect_edges(both)).image
    assert _count(hidden, BOUNDARY_COLOR) == 0
    # three triangles on one edge: that edge is non-manifold, drawn over the boundary colour
    fan = (
        np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0.5, 0.5, 0.8]], dtype=np.float64)
        * 0.5
    )
    nm = TriangleMesh(fan, np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]]))
    groups = defect_edges(nm)
    assert groups[1][0].tolist() == [[0, 1]]
    img = render(nm, "front", (200, 200), FRAME, edges=groups).image
    assert (img[100 - 20, 100] == NON_MANIFOLD_COLOR).all()  # on the shared edge, x = 0, y = 0.2
    assert _count(img, BOUNDARY_COLOR) > 0


def _box(size):
    h = size / 2
    from shapes import box_mesh

    return box_mesh((-h, -h, -h), (h, h, h))


def test_png_round_trip(tmp_path):
    """A rendered picture written as PNG reads back the same pixels."""
    from PIL import Image

    img = render(_sphere(1.0, 3), "front", (64, 48), FRAME).image
    assert img.shape == (48, 64, 3)
    out = tmp_path / "x.png"
    write_png(img, out)
    back = np.asarray(Image.open(out).convert("RGB"))
    assert np.array_equal(back, img)
    assert png_bytes(img)[:8] == b"\x89PNG\r\n\x1a\n"
