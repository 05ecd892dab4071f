"""recon_cli.eval.figure: labelled sheets and plots, checked by pixels in their parts' boxes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon_cli.errors import ParameterError
from recon_cli.eval.figure import Row, diff_rows, layout, scatter_plot, sheet
from recon_cli.eval.metrics import vertex_distances
from recon_cli.eval.render import BOUNDARY_COLOR, colormap
from recon_cli.geometry import TriangleMesh

from picture_checks import ink, is_blue, is_red, view_towards
from shapes import cut_sphere


def _sphere(r=1.0, sub=3):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return TriangleMesh(np.asarray(s.vertices), np.asarray(s.faces))


def test_sheet_size_labels_and_colour_bar_are_where_the_layout_says():
    """A sheet's size, labels and colour bar are where ``layout`` says, no ink between tiles."""
    a = _sphere(1.0)
    d = np.linspace(0.0, 0.2, len(a.vertices))
    rows = [Row("shape of a", a, edges=True), Row("a coloured", a, d)]
    fig = sheet(
        rows,
        ("front", "iso", "top"),
        unit="mm",
        diagonal=2.0,
        title="a title",
        panel_size=96,
        supersample=1,
    )
    box = layout(2, 3, 96, title=True, colorbar=True, legend=True)
    assert fig.image.shape == (box["size"][3], box["size"][2], 3)
    assert {k: v for k, v in fig.boxes.items()} == {k: v for k, v in box.items() if k != "size"}
    names = [
        "title",
        "column 0",
        "column 1",
        "column 2",
        "row 0",
        "row 1",
        "colorbar title",
        "colorbar top",
        "colorbar max",
        "legend",
    ]
    for name in names:
        assert ink(fig.image, box[name]) >= 15, name  # text is there
    # and nowhere text should not be: the margins between the tiles and the bar's column
    x0, _, x1, _ = box["tile 0 2"]
    gap = (x1 + 2, box["tile 0 2"][1], box["colorbar"][0] - 2, box["tile 1 2"][3])
    assert ink(fig.image, gap) == 0
    # the colour bar runs from the top colour (red) to the bottom one (blue) of the ramp
    x0, y0, x1, y1 = box["colorbar"]
    top, bottom = colormap(np.array([1.0, 0.0]), 0.0, 1.0)
    assert (fig.image[y0, x0 + 5] == top).all() and (fig.image[y1 - 1, x0 + 5] == bottom).all()
    # a heat tile shows ramp colours, a shape tile does not
    cx = (box["tile 1 0"][0] + box["tile 1 0"][2]) // 2
    cy = (box["tile 1 0"][1] + box["tile 1 0"][3]) // 2
    assert fig.image[cy, cx][2] > fig.image[cy, cx][0]  # d is small at the front: blue end
    with pytest.raises(ParameterError):
        sheet([])
    with pytest.raises(ParameterError):
        sheet(rows, "front", vmax=-1.0)


def test_vmax_fixes_the_scale():
    """``vmax`` fixes the colour scale: above it red, far below it blue; by default the largest."""
    a = _sphere(1.0)
    d = np.full(len(a.vertices), 0.1)
    box = layout(1, 1, 64)

    def centre(vmax):
        fig = sheet([Row("a", a, d)], "front", vmax=vmax, panel_size=64, supersample=1)
        x0, y0, x1, y1 = box["tile 0 0"]
        return fig.image[(y0 + y1) // 2, (x0 + x1) // 2]

    assert is_red(centre(0.05))  # above the top: the top colour
    assert is_blue(centre(10.0))  # far below the top: blue
    assert is_red(centre(None))  # default: the largest value is the top (all values equal it here)


@pytest.mark.parametrize("seed", range(4))
def test_completeness_heatmap_is_red_where_the_candidate_misses_a_part(seed):
    """A sphere missing a cap: completeness red facing the cap, blue elsewhere; the rim drawn."""
    rng = np.random.default_rng(seed)
    ref, cand, direction, center, radius = cut_sphere(rng)
    acc, missed = vertex_distances(cand, ref), vertex_distances(ref, cand)
    assert acc.max() <= 1e-9 * max(1.0, np.abs(center).max())  # what the candidate has is exact
    views = [view_towards(direction), view_towards(-direction)]
    rows = diff_rows([("cut", cand, acc, missed)], ("sphere", ref))
    labels = [r.label for r in rows]
    assert labels[1].startswith("cut · accuracy") and labels[2].startswith("cut · completeness")
    fig = sheet(rows, views, vmax=None, panel_size=120, supersample=1)
    box = fig.boxes

    def centre(name):
        x0, y0, x1, y1 = box[name]
        return fig.image[(y0 + y1) // 2, (x0 + x1) // 2]

    # looking at the missing cap: the completeness tile is red there, the candidate is not there at
    # all
    assert is_red(centre("tile 2 0")), centre("tile 2 0")
    acc_tile = centre("tile 1 0")
    assert not is_red(acc_tile)
    # from the other side everything is there: blue in both directions
    assert is_blue(centre("tile 2 1")) and is_blue(centre("tile 1 1"))
    # the cut's rim is a boundary loop, drawn in the boundary colour on the candidate's shape row
    x0, y0, x1, y1 = box["tile 0 0"]
    assert (
        np.abs(fig.image[y0:y1, x0:x1].astype(int) - BOUNDARY_COLOR).max(axis=2) < 30
    ).sum() > 50
    x0, y0, x1, y1 = box["tile 3 0"]  # the closed reference has none
    assert (
        np.abs(fig.image[y0:y1, x0:x1].astype(int) - BOUNDARY_COLOR).max(axis=2) < 30
    ).sum() == 0


def test_scatter_plot_points_and_labels():
    """The scatter plot draws labelled points on a log x axis, and names the NaN point below."""
    pts = [("fast", 1.0, 0.3), ("slow", 30.0, 0.1), ("broken", float("nan"), 0.2)]
    fig = scatter_plot(
        pts, x_label="time [s], lower is better", y_label="error [mm], lower is better", title="t"
    )
    h, w = fig.image.shape[:2]
    assert (w, h) == (760, 480)
    for name in ("title", "x label", "y label", "point label 0", "point label 1"):
        assert ink(fig.image, fig.boxes[name]) >= 10, name
    assert "point 2" not in fig.boxes  # the NaN point is not drawn ...
    (ax0, ay0, ax1, ay1) = fig.boxes["plot"]
    p0, p1 = fig.boxes["point 0"], fig.boxes["point 1"]
    # ... log x (30x span): "slow" right of "fast", and lower (smaller error)
    assert p1[0] > p0[0] and p1[1] > p0[1]
    for p in (p0, p1):
        assert ax0 <= p[0] and p[2] <= ax1 + 1 and ay0 <= p[1] and p[3] <= ay1 + 1
    # ... and named under the plot
    assert ink(fig.image, fig.boxes["missing"]) >= 10
