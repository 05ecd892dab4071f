"""Pictures a person can read.

Panels of rendered meshes laid out with labels, a colour bar with title and unit, and a
quality-versus-time scatter plot.

The meshes are drawn by our own rasteriser (:mod:`recon_cli.eval.render`); text, lines and discs are
set with Pillow (``ImageFont.load_default(size=...)``: the scalable font Pillow ships, no system
font needed; it has no "≥", "—" or arrows, so pictures write ">=" and "·"). Every function here
returns a :class:`Figure`: the image and the named boxes where its parts were put, so that tests
(and callers) can find them.

Layout of :func:`sheet` (one column per view, one row per surface and colouring)::

    title
    view label      view label      ...          colour bar title (unit)
    row label ------------------------------      >= top (x % diag)
    [tile]          [tile]          ...           |bar|  ticks
    row label ------------------------------      max ...
    [tile]          [tile]          ...           legend: boundary / non-manifold edges
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh

TEXT_COLOR = (20, 20, 20)
MARGIN = 12
GAP = 6
TITLE_H = 34
HEADER_H = 26
LABEL_H = 24
BAR_COLUMN_W = 210
BAR_W = 22
FONT_TITLE, FONT_LABEL, FONT_SMALL = 20, 15, 13
MIN_LABEL_W = 560  # row labels get at least this width, even over a single column of tiles

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive ends)


@dataclass
class Figure:
    """A finished picture and where its parts are.

    Attributes
    ----------
    image : (H, W, 3) uint8
    boxes : dict of str -> (x0, y0, x1, y1)
        Pixel boxes (end exclusive) of the named parts: ``"title"``, ``"column k"`` (label of
        column k), ``"row r"`` (label of row r), ``"tile r k"``, ``"colorbar"`` (the
        ramp), ``"colorbar title"``, ``"colorbar top"`` (the ">= max" label),
        ``"colorbar max"``, ``"legend"``; a plot has ``"plot"``, ``"x label"``,
        ``"y label"``, ``"point k"``, ``"point label k"`` and ``"missing"`` (points not drawn).
    """

    image: np.ndarray
    boxes: dict[str, Box] = field(default_factory=dict)


@dataclass
class Row:
    """One row of a :func:`sheet`: a surface seen from every view.

    Attributes
    ----------
    label : str
        Written above the row.
    obj : TriangleMesh or PointCloud
    scalars : (n,) float64, optional
        Per-vertex distances: the row is a heatmap on the sheet's shared scale.
    edges : bool
        Draw the mesh's boundary and non-manifold edges over it
        (:func:`recon_cli.eval.render.defect_edges`).
    """

    label: str
    obj: TriangleMesh | PointCloud
    scalars: np.ndarray | None = None
    edges: bool = False


def sheet(
    rows: Sequence[Row],
    views: Sequence[str | tuple[float, float]] | str | None = None,
    **kwargs,
) -> Figure:
    """Render ``rows`` from every view (one column per view), on one frame and one colour scale.

    Parameters
    ----------
    rows : sequence of Row
        Top to bottom. All rows share the frame (same scale and centre), so surfaces line up.
    views : see :func:`recon_cli.eval.render.resolve_views`
        One column each, labelled with its angles (default: the four-azimuth turntable).
    **kwargs
        ``vmax``, ``unit``, ``diagonal``, ``title``, ``bar_title``, ``panel_size``,
        ``supersample``: see :func:`grid`.

    Returns
    -------
    Figure
    """
    from recon_cli.eval.render import resolve_views

    if not rows:
        raise ParameterError("nothing to draw")
    resolved = resolve_views(views)
    cells = [
        [Cell(row.obj, angles, row.scalars, row.edges) for _, angles in resolved] for row in rows
    ]
    return grid(cells, [row.label for row in rows], [label for label, _ in resolved], **kwargs)


@dataclass
class Cell:
    """One tile of a :func:`grid`: a surface from one view, shaded or as a heatmap."""

    obj: TriangleMesh | PointCloud
    view: str | tuple[float, float]
    scalars: np.ndarray | None = None
    edges: bool = False


def grid(
    cells: Sequence[Sequence[Cell | None]],
    row_labels: Sequence[str],
    column_labels: Sequence[str],
    *,
    vmax: float | None = None,
    unit: str | None = None,
    diagonal: float | None = None,
    title: str | None = None,
    bar_title: str = "distance",
    panel_size: int = 240,
    supersample: int = 2,
) -> Figure:
    """Tiles in rows and columns, labelled, on one frame and one colour scale, with a colour bar.

    Parameters
    ----------
    cells : rows of (Cell or None)
        None leaves a tile blank. Every surface shares one frame (same scale and centre).
    row_labels, column_labels : sequence of str
        A label above each row, and above each column.
    vmax : float, optional
        Distance at the top of the colour scale; larger values are drawn in the top colour
        and the bar's top reads ">= vmax". Default: the largest value of any heatmap.
    unit : str, optional
        Unit of the distances, written in the colour bar's title (default "model units").
    diagonal : float, optional
        The reference's bounding-box diagonal: tick labels then also give % of it.
    title : str, optional
        A line above everything.
    bar_title : str
        Title of the colour bar.
    panel_size : int
        Width and height of a tile in pixels (>= 32).
    supersample : int
        Anti-aliasing factor of the rasteriser.

    Returns
    -------
    Figure
    """
    from recon_cli.eval.metrics import check_vmax
    from recon_cli.eval.render import defect_edges, frame_of, render

    flat = [c for row in cells for c in row if c is not None]
    if not flat:
        raise ParameterError("nothing to draw")
    n_cols = len(column_labels)
    if len(row_labels) != len(cells) or any(len(row) != n_cols for row in cells):
        raise ParameterError("cells, row labels and column labels do not match")
    s = int(panel_size)
    if s < 32:
        raise ParameterError(f"panel size must be at least 32 pixels, got {panel_size}")
    heat = [np.asarray(c.scalars, dtype=np.float64) for c in flat if c.scalars is not None]
    largest = max((float(d.max()) for d in heat if len(d)), default=0.0)
    if heat:
        vmax = check_vmax(vmax if vmax is not None else (largest or 1.0))
    has_edges = any(c.edges for c in flat)
    box = layout(
        len(cells), n_cols, s, title=title is not None, colorbar=bool(heat), legend=has_edges
    )
    width, height = box.pop("size")[2:]
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    texts: list[tuple] = []
    frame = frame_of([c.obj for c in flat])
    edge_cache: dict[int, list] = {}

    if title is not None:
        texts.append((box["title"], title, FONT_TITLE, TEXT_COLOR))
    for k, label in enumerate(column_labels):
        texts.append((box[f"column {k}"], label, FONT_LABEL, TEXT_COLOR))
    for r, row in enumerate(cells):
        texts.append((box[f"row {r}"], row_labels[r], FONT_LABEL, TEXT_COLOR))
        for k, c in enumerate(row):
            if c is None:
                continue
            edges = []
            if c.edges:
                if id(c.obj) not in edge_cache:
                    edge_cache[id(c.obj)] = defect_edges(c.obj)
                edges = edge_cache[id(c.obj)]
            x0, y0, x1, y1 = box[f"tile {r} {k}"]
            img[y0:y1, x0:x1] = render(
                c.obj,
                c.view,
                (s, s),
                frame,
                scalars=c.scalars,
                vmax=vmax,
                supersample=supersample,
                edges=edges,
            ).image
            img[y0 - 1 : y1 + 1, [x0 - 1, x1]] = 225  # a light frame around each tile
            img[[y0 - 1, y1], x0 - 1 : x1 + 1] = 225
    if heat:
        assert vmax is not None  # set with the heatmaps above
        texts += _colorbar(img, box, float(vmax), largest, unit, diagonal, bar_title)
    if has_edges:
        texts += _legend(img, box["legend"])
    return Figure(_draw_texts(img, texts), box)


def layout(
    n_rows: int,
    n_columns: int,
    panel_size: int,
    *,
    title: bool = False,
    colorbar: bool = True,
    legend: bool = False,
) -> dict[str, Box]:
    """Boxes of every part of a :func:`grid` (``"size"`` is ``(0, 0, width, height)``)."""
    s = int(panel_size)
    box: dict[str, Box] = {}
    y = MARGIN
    grid_w = max(n_columns * s + (n_columns - 1) * GAP, MIN_LABEL_W)
    right = MARGIN + grid_w + (BAR_COLUMN_W if colorbar or legend else 0)
    if title:
        box["title"] = (MARGIN, y, right, y + TITLE_H)
        y += TITLE_H
    for k in range(n_columns):
        x = MARGIN + k * (s + GAP)
        box[f"column {k}"] = (x, y, x + s, y + HEADER_H)
    y += HEADER_H
    top = y
    for r in range(n_rows):
        box[f"row {r}"] = (MARGIN, y, MARGIN + grid_w, y + LABEL_H)
        y += LABEL_H
        for k in range(n_columns):
            x = MARGIN + k * (s + GAP)
            box[f"tile {r} {k}"] = (x, y, x + s, y + s)
        y += s + GAP
    bottom = y
    bx = MARGIN + grid_w + 16
    by = top
    if colorbar:
        box["colorbar title"] = (bx, by, right, by + LABEL_H + 40)
        by += LABEL_H + 40 + 12
        bar_h = max(120, min(bottom - by - 120, 2 * s))
        box["colorbar"] = (bx, by, bx + BAR_W, by + bar_h)
        box["colorbar top"] = (bx + BAR_W + 10, by - 10, right, by + 10)
        box["colorbar max"] = (bx, by + bar_h + 14, right, by + bar_h + 14 + 2 * LABEL_H)
        by += bar_h + 14 + 2 * LABEL_H + 10
    if legend:
        box["legend"] = (bx, by, right, by + 2 * LABEL_H)
        by += 2 * LABEL_H
    box["size"] = (0, 0, right + MARGIN, max(bottom, by) + MARGIN)
    return box


def scatter_plot(
    points: Sequence[tuple[str, float, float]],
    *,
    x_label: str,
    y_label: str,
    title: str | None = None,
    size: tuple[int, int] = (760, 480),
    log_x: bool | None = None,
) -> Figure:
    """A labelled scatter plot: one disc and one name per point.

    Parameters
    ----------
    points : sequence of (label, x, y)
        Non-finite points are left out (their label is listed as "not shown" under the plot).
    x_label, y_label : str
        Axis titles (give the unit and which way is better).
    title : str, optional
    size : (width, height)
    log_x : bool, optional
        Logarithmic x axis (default: when the positive x values span more than 20x).

    Returns
    -------
    Figure
    """
    pil = require_pillow()
    Image, ImageDraw = pil.Image, pil.ImageDraw
    w, h = (int(v) for v in size)
    good = [(lab, float(x), float(y)) for lab, x, y in points if np.isfinite(x) and np.isfinite(y)]
    left, right, top, bottom = 90, w - 24, MARGIN + (TITLE_H if title else 0) + 8, h - 70
    box: dict[str, Box] = {"plot": (left, top, right, bottom)}
    xs = np.array([p[1] for p in good]) if good else np.array([1.0])
    ys = np.array([p[2] for p in good]) if good else np.array([1.0])
    if log_x is None:
        log_x = bool(xs.min() > 0 and xs.max() / xs.min() > 20)
    if log_x and not xs.min() > 0:
        log_x = False
    fx = np.log10 if log_x else (lambda v: v)
    x_lo, x_hi = _padded(fx(xs.min()), fx(xs.max()), floor0=not log_x)
    y_lo, y_hi = _padded(ys.min(), ys.max(), floor0=False)
    sx = lambda v: left + (fx(v) - x_lo) / (x_hi - x_lo) * (right - left)  # noqa: E731
    sy = lambda v: bottom - (v - y_lo) / (y_hi - y_lo) * (bottom - top)  # noqa: E731

    im = Image.new("RGB", (w, h), (255, 255, 255))
    dr = ImageDraw.Draw(im)
    small, label = _font(FONT_SMALL), _font(FONT_LABEL)
    xt = _ticks(x_lo, x_hi, log_x)
    for t, text in zip(xt, _tick_labels([10**t for t in xt] if log_x else xt), strict=True):
        x = sx(10**t if log_x else t)
        dr.line([(x, top), (x, bottom)], fill=(232, 232, 232))
        dr.text((x, bottom + 6), text, font=small, fill=TEXT_COLOR, anchor="ma")
    yt = _ticks(y_lo, y_hi, False)
    for t, text in zip(yt, _tick_labels(yt), strict=True):
        y = sy(t)
        dr.line([(left, y), (right, y)], fill=(232, 232, 232))
        dr.text((left - 6, y), text, font=small, fill=TEXT_COLOR, anchor="rm")
    dr.rectangle([left, top, right, bottom], outline=(120, 120, 120))
    if title:
        dr.text((MARGIN, MARGIN), title, font=_font(FONT_TITLE), fill=TEXT_COLOR)
        box["title"] = (MARGIN, MARGIN, w - MARGIN, MARGIN + TITLE_H)
    dr.text(((left + right) / 2, h - 26), x_label, font=label, fill=TEXT_COLOR, anchor="ms")
    box["x label"] = (left, h - 46, right, h - 20)
    ylab = Image.new("RGB", (bottom - top, 22), (255, 255, 255))
    ImageDraw.Draw(ylab).text(
        ((bottom - top) / 2, 11), y_label, font=label, fill=TEXT_COLOR, anchor="mm"
    )
    im.paste(ylab.rotate(90, expand=True), (8, top))
    box["y label"] = (8, top, 30, bottom)
    colors = _point_colors(len(good))
    placed: list[tuple[float, float, float, float]] = []
    for k, ((_lab, x, y), c) in enumerate(zip(good, colors, strict=True)):
        px, py = sx(x), sy(y)
        dr.ellipse([px - 6, py - 6, px + 6, py + 6], fill=c, outline=TEXT_COLOR)
        box[f"point {k}"] = (int(px - 6), int(py - 6), int(px + 7), int(py + 7))
        placed.append((px - 7, py - 7, px + 7, py + 7))
    for k, ((lab, x, y), _c) in enumerate(zip(good, colors, strict=True)):
        px, py = sx(x), sy(y)
        lab = _fit(lab, small, (right - left) * 0.6)
        anchor, tx, ty, bb = _place_label(
            dr, lab, (px, py), small, (left, top, right, bottom), placed
        )
        dr.text((tx, ty), lab, font=small, fill=TEXT_COLOR, anchor=anchor)
        placed.append(bb)
        box[f"point label {k}"] = (int(bb[0]), int(bb[1]), int(bb[2]) + 1, int(bb[3]) + 1)
    missing = [lab for lab, x, y in points if not (np.isfinite(x) and np.isfinite(y))]
    if missing:
        dr.text(
            (left, h - 18),
            _fit("not shown (no figure): " + ", ".join(missing), small, w - left - MARGIN),
            font=small,
            fill=TEXT_COLOR,
        )
        box["missing"] = (left, h - 20, w - MARGIN, h)
    return Figure(np.asarray(im, dtype=np.uint8).copy(), box)


def _place_label(
    dr: Any,
    lab: str,
    at: tuple[float, float],
    font: Any,
    plot: tuple[float, float, float, float],
    placed: list[Any],
) -> tuple[str, float, float, Any]:
    """(anchor, x, y, bounding box) of a point's label: the first place tried that overlaps nothing.

    The places are right, left, above, below and the four corners of the disc at ``at``; the
    first inside the plot when every place overlaps something, the right one when none is inside.
    """
    left, top, right, bottom = plot
    px, py = at
    tries = [
        ("lm", px + 10, py),
        ("rm", px - 10, py),
        ("mb", px, py - 9),
        ("mt", px, py + 9),
        ("lb", px + 8, py - 7),
        ("rt", px - 8, py + 7),
        ("lt", px + 8, py + 7),
        ("rb", px - 8, py - 7),
    ]
    best = None
    for anchor, tx, ty in tries:
        bb = dr.textbbox((tx, ty), lab, font=font, anchor=anchor)
        inside = (
            bb[0] >= left + 2 and bb[2] <= right - 2 and bb[1] >= top + 2 and bb[3] <= bottom - 2
        )
        if inside and not any(_overlap(bb, o) for o in placed):
            return anchor, tx, ty, bb
        if best is None and inside:
            best = (anchor, tx, ty, bb)
    if best is None:
        anchor, tx, ty = tries[0]
        best = (anchor, tx, ty, dr.textbbox((tx, ty), lab, font=font, anchor=anchor))
    return best


# --------------------------------------------------------------------------- internals


def require_pillow():
    """The ``PIL`` package, or :class:`ParameterError` naming the extra to install."""
    try:
        import PIL.Image
        import PIL.ImageDraw
        import PIL.ImageFont
    except ImportError:
        raise ParameterError("drawing pictures needs Pillow: pip install 'recon[render]'") from None
    return PIL


@functools.cache
def _font(size: int):
    """Pillow's own scalable font at ``size`` pixels (Pillow >= 10.1 with FreeType)."""
    return require_pillow().ImageFont.load_default(size=size)


def _fit(text: str, font, width: float) -> str:
    """``text`` cut with an ellipsis to ``width`` pixels."""
    if font.getlength(text) <= width:
        return text
    while text and font.getlength(text + "…") > width:
        text = text[:-1]
    return text + "…"


def _draw_texts(img: np.ndarray, texts: list[tuple]) -> np.ndarray:
    """Set each (box, text, size, colour) left-aligned, vertically centred in its box."""
    pil = require_pillow()
    im = pil.Image.fromarray(img)
    ImageDraw = pil.ImageDraw
    dr = ImageDraw.Draw(im)
    for (x0, y0, x1, y1), text, size, color in texts:
        font = _font(size)
        lines = text.split("\n")
        step = (y1 - y0) / len(lines)
        for i, line in enumerate(lines):
            dr.text(
                (x0 + 2, y0 + step * (i + 0.5)),
                _fit(line, font, x1 - x0 - 4),
                font=font,
                fill=color,
                anchor="lm",
            )
    return np.asarray(im, dtype=np.uint8).copy()


def _colorbar(img, box, vmax, largest, unit, diagonal, bar_title) -> list[tuple]:
    from recon_cli.eval.render import colormap

    x0, y0, x1, y1 = box["colorbar"]
    n = y1 - y0
    t = np.linspace(1.0, 0.0, n)
    img[y0:y1, x0:x1] = colormap(t * vmax, 0.0, vmax)[:, None, :]
    img[y0 - 1, x0 - 1 : x1 + 1] = img[y1, x0 - 1 : x1 + 1] = 0
    img[y0 - 1 : y1 + 1, x0 - 1] = img[y0 - 1 : y1 + 1, x1] = 0
    _, _, rx, _ = box["colorbar top"]
    x0t, y0t, x1t, y1t = box["colorbar title"]
    texts = [
        ((x0t, y0t, x1t, y0t + LABEL_H), bar_title, FONT_LABEL, TEXT_COLOR),
        (
            (x0t, y0t + LABEL_H, x1t, y1t),
            f"[{unit or 'model units'}]" + ("\n(% of ref. diagonal)" if diagonal else ""),
            FONT_SMALL,
            TEXT_COLOR,
        ),
    ]
    ticks, note = colorbar_labels(vmax, largest, diagonal)
    for frac, label in ticks:
        y = y0 + int(round((1.0 - frac) * (n - 1)))
        img[y, x1 : x1 + 6] = 0
        texts.append(((x1 + 10, y - 10, rx, y + 10), label, FONT_SMALL, TEXT_COLOR))
    texts.append((box["colorbar max"], note, FONT_SMALL, TEXT_COLOR))
    return texts


#: where the colour bar's ticks stand, as fractions of its top value, top first
COLORBAR_TICKS = (1.0, 0.75, 0.5, 0.25, 0.0)


def colorbar_labels(
    vmax: float, largest: float, diagonal: float | None = None
) -> tuple[list[tuple[float, str]], str]:
    """The labels of a distance colour bar, as ``recon diff --png`` writes them.

    Parameters
    ----------
    vmax : float
        Distance at the top of the scale (drawn in the top colour and above).
    largest : float
        The largest distance shown.
    diagonal : float, optional
        The reference's bounding-box diagonal: labels then also give % of it.

    Returns
    -------
    ticks : list of (fraction, str)
        One label per :data:`COLORBAR_TICKS` fraction of ``vmax``, top (``">= vmax"``) first.
    note : str
        Two lines under the bar: the largest distance, and whether any value lies above the top.
    """

    def pct(v: float) -> str:
        return f" ({100 * v / diagonal:.3g}%)" if diagonal else ""

    ticks = [
        (frac, (f">= {_num(frac * vmax)}" if frac == 1.0 else _num(frac * vmax)) + pct(frac * vmax))
        for frac in COLORBAR_TICKS
    ]
    clipped = "higher values: the top colour" if largest > vmax else "no value above the top"
    return ticks, f"max {_num(largest)}{pct(largest)}\n{clipped}"


def _legend(img, legend_box) -> list[tuple]:
    from recon_cli.eval.render import BOUNDARY_COLOR, NON_MANIFOLD_COLOR

    x0, y0, x1, y1 = legend_box
    texts = []
    for i, (color, text) in enumerate(
        ((BOUNDARY_COLOR, "boundary edge"), (NON_MANIFOLD_COLOR, "non-manifold edge"))
    ):
        yc = y0 + i * LABEL_H + LABEL_H // 2
        img[yc - 2 : yc + 2, x0 : x0 + 22] = color
        texts.append(
            ((x0 + 28, yc - LABEL_H // 2, x1, yc + LABEL_H // 2), text, FONT_SMALL, TEXT_COLOR)
        )
    return texts


def _num(v: float) -> str:
    if v == 0:
        return "0"
    a = abs(v)
    if 1e-3 <= a < 1e4:
        return f"{v:.3g}"
    return f"{v:.2e}"


def _tick_labels(ticks: Sequence[float]) -> list[str]:
    """Labels just precise enough to tell neighbouring ticks apart."""
    t = np.asarray(ticks, dtype=np.float64)
    if len(t) == 0:
        return []
    step = float(np.min(np.diff(t))) if len(t) > 1 else abs(float(t[0])) or 1.0
    big = float(np.abs(t).max())
    if 1e-4 <= step and big < 1e5:
        dec = max(0, int(-np.floor(np.log10(step) + 1e-9)))
        return [f"{v:.{dec}f}" for v in t]
    digits = max(1, int(np.ceil(np.log10(big / step) + 1e-9)) if big > 0 else 1)
    return [f"{v:.{digits}e}" for v in t]


def _overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _padded(lo: float, hi: float, floor0: bool) -> tuple[float, float]:
    """Axis range around [lo, hi].

    From 0 when ``floor0`` (and lo >= 0), else 10 % of the span below.
    """
    span = hi - lo
    if not span > 0:
        span = abs(hi) * 0.1 or 1.0
        lo, hi = lo - 0.5 * span, hi + 0.5 * span
    if floor0 and lo >= 0:
        return 0.0, hi + 0.1 * span
    return lo - 0.1 * span, hi + 0.1 * span


def _ticks(lo: float, hi: float, log: bool) -> list[float]:
    if log:
        return [float(t) for t in range(int(np.ceil(lo)), int(np.floor(hi)) + 1)] or [lo, hi]
    raw = (hi - lo) / 5
    mag = 10 ** np.floor(np.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = np.ceil(lo / step) * step
    return [float(t) for t in np.arange(first, hi + 1e-12 * step, step)]


def _point_colors(n: int) -> list[tuple[int, int, int]]:
    palette = [
        (31, 119, 180),
        (214, 39, 40),
        (44, 160, 44),
        (255, 127, 14),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ]
    return [palette[k % len(palette)] for k in range(n)]


def diff_rows(
    candidates: Sequence[
        tuple[str, TriangleMesh | PointCloud, np.ndarray | None, np.ndarray | None]
    ],
    reference: tuple[str, TriangleMesh | PointCloud] | None,
) -> list[Row]:
    """The rows of a comparison sheet.

    Each candidate's shape, accuracy and completeness, then the reference.

    Parameters
    ----------
    candidates : sequence of (name, surface, accuracy distances or None, completeness distances or
    None)
        ``accuracy`` (n_candidate_vertices,): each candidate vertex's distance to the
        reference; ``completeness`` (n_reference_vertices,): each reference vertex's
        distance to the candidate (large where the candidate misses a part).
    reference : (name, surface), optional
    """
    rows = []
    for name, obj, acc, comp in candidates:
        rows.append(Row(f"{name} · shape{_edge_note(obj)}", obj, edges=True))
        if acc is not None:
            rows.append(
                Row(
                    f"{name} · accuracy: its surface coloured by distance to the reference",
                    obj,
                    acc,
                )
            )
        if comp is not None and reference is not None:
            rows.append(
                Row(
                    f"{name} · completeness: the reference coloured by distance to it "
                    "(red: missed)",
                    reference[1],
                    comp,
                )
            )
    if reference is not None:
        rows.append(
            Row(
                f"{reference[0]} (reference) · shape{_edge_note(reference[1])}",
                reference[1],
                edges=True,
            )
        )
    return rows


def overview(
    candidates: Sequence[
        tuple[str, TriangleMesh | PointCloud, np.ndarray | None, np.ndarray | None]
    ],
    reference: tuple[str, TriangleMesh | PointCloud] | None,
    view: str | tuple[float, float] | None = None,
    **kwargs,
) -> Figure:
    """All candidates side by side from one view: shape, accuracy and completeness rows.

    Parameters
    ----------
    candidates, reference
        As in :func:`diff_rows`.
    view : str or (azimuth, elevation), optional
        Default: the first view of the turntable (the iso view).
    **kwargs
        See :func:`grid`.
    """
    from recon_cli.eval.render import resolve_views

    if not candidates:
        raise ParameterError("nothing to draw")
    label, angles = resolve_views(None if view is None else [view])[0]
    ref_name, ref_obj = reference if reference is not None else ("", None)
    has_ref = ref_obj is not None
    cols = [name for name, *_ in candidates] + ([f"{ref_name} (reference)"] if has_ref else [])
    blank: list[Cell | None] = [None] if has_ref else []
    shapes: list[Cell | None] = [Cell(obj, angles, edges=True) for _, obj, _, _ in candidates]
    if ref_obj is not None:
        shapes.append(Cell(ref_obj, angles, edges=True))
    cells = [shapes]
    labels = [f"shape, from {label}"]
    if has_ref and any(a is not None for _, _, a, _ in candidates):
        cells.append(
            [None if a is None else Cell(obj, angles, a) for _, obj, a, _ in candidates] + blank
        )
        labels.append("accuracy: each surface coloured by distance to the reference")
    if has_ref and any(m is not None for *_, m in candidates):
        cells.append(
            [
                None if m is None or ref_obj is None else Cell(ref_obj, angles, m)
                for *_, m in candidates
            ]
            + blank
        )
        labels.append("completeness: the reference coloured by distance to each (red: missed)")
    return grid(cells, labels, cols, **kwargs)


def _edge_note(obj) -> str:
    from recon_cli.eval.render import defect_edges

    if not isinstance(obj, TriangleMesh) or len(obj.faces) == 0:
        return " (point cloud)"
    groups = defect_edges(obj)
    nb, nn = (len(e) for e, _ in groups)
    if not nb and not nn:
        return " (closed, no boundary edge)"
    return f" ({nb} boundary, {nn} non-manifold edges)"
