"""``recon view``'s page: one self-contained HTML file showing a mesh or a cloud in WebGL.

The page holds everything it needs: three.js (bundled at install from the npm packages pinned in
``tools/viewer``, see ``make viewer``), its own script, and the geometry as base64 of typed arrays
(float32 coordinates relative to the frame's centre, which stays float64 here; uint16 or uint32
face indices; uint8 colours). It opens with no network.

Its first view is the camera of ``recon_cli.eval.render.render`` for the same object and
view: orthographic, y up, the frame's sphere (``recon_cli.eval.render.frame_of``) over 92 %
of the canvas's smaller side, so the page and our rasteriser draw the same silhouette. With a
reference (``recon view A --diff B``) the candidate is coloured by its distance to the reference
on ``recon diff``'s colour scale (``recon_cli.eval.diff.heatmap_distances``), the colour bar
carries ``recon diff --png``'s labels and the panel its numbers.
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError, naming
from recon_cli.geometry import PointCloud, TriangleMesh

#: the folder of the page's template, its script and the three.js bundle (package data)
ASSETS = "viewer"
THREE_BUNDLE = "three.min.js"
# the first line of the bundle, written by `make viewer`: /*! three.js <version> ... */
_BANNER = re.compile(rb"^/\*! three\.js (\S+) ")
_MARK = re.compile(r"@@(\w+)@@")
# multisampling costs software WebGL ~1.7 s per million faces (bench/calibration.md, Viewer):
# pages with more faces than this draw their first frame without it
ANTIALIAS_FACES = 300_000


@dataclass
class Layer:
    """One object of the page.

    Attributes
    ----------
    name : str
        Its label in the page's list of layers.
    obj : TriangleMesh or PointCloud
        A mesh without faces is drawn as its points.
    colors : (n, 3) uint8 or None
        Per-vertex colours (None: the page's grey).
    visible : bool
        Shown when the page opens.
    heat : bool
        ``colors`` are a heatmap: shaded as ``recon_cli.eval.render.render`` shades
        heatmaps (more of the colour kept).
    """

    name: str
    obj: TriangleMesh | PointCloud
    colors: np.ndarray | None = None
    visible: bool = True
    heat: bool = False


def three_bundle() -> tuple[bytes, str]:
    """The bundled three.js script and its version.

    Raises
    ------
    ParameterError
        The bundle is missing (an install without ``make viewer``, which needs npm).
    """
    path = resources.files("recon_cli.eval") / ASSETS / THREE_BUNDLE
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ParameterError(
            f"recon view needs three.js, bundled by `make viewer` (npm): {path} is missing"
        ) from None
    m = _BANNER.match(data)
    return data, m.group(1).decode() if m else "unknown"


def byte_colors(colors: np.ndarray | None) -> np.ndarray | None:
    """Colours as RGB (n, 3) uint8: integers over their type's maximum, floats in [0, 1].

    Integers that all fit in 0-255 are taken as 8-bit values (many LAS files store them so in
    their 16-bit fields). An alpha column is dropped; NaN is 0.
    """
    if colors is None:
        return None
    from recon_cli.io.text import colours_to_unit

    c = np.asarray(colors)
    if c.ndim != 2 or c.shape[1] not in (3, 4):
        raise InputError(f"colours must be (n, 3) or (n, 4), got shape {c.shape}")
    if c.dtype == np.uint8:
        return np.ascontiguousarray(c[:, :3])
    if c.dtype.kind in "ui" and c.size and 0 <= int(c[:, :3].min()) and int(c[:, :3].max()) <= 255:
        # 8-bit values in wider fields, as many LAS writers store them
        return c[:, :3].astype(np.uint8)
    unit = np.nan_to_num(colours_to_unit(c[:, :3]), nan=0.0)
    return np.clip(np.rint(unit * 255.0), 0, 255).astype(np.uint8)


def check_viewable(obj: Any) -> TriangleMesh | PointCloud:
    """``obj`` when a page can show it: a mesh or a cloud with finite points and valid faces.

    Raises
    ------
    InputError
        A grid, no points, a NaN or infinite coordinate, a face index out of range.
    """
    if not isinstance(obj, (TriangleMesh, PointCloud)):
        raise InputError(f"is a {type(obj).__name__.lower()}, not a mesh or point cloud")
    if len(obj.points) == 0:
        raise InputError("is empty: no points to show")
    if not np.isfinite(obj.points).all():
        raise InputError("holds NaN or infinite coordinates")
    if isinstance(obj, TriangleMesh) and len(obj.faces):
        lo, hi = int(obj.faces.min()), int(obj.faces.max())
        if lo < 0 or hi >= len(obj.points):
            raise InputError(f"has face indices outside its {len(obj.points)} vertices")
    return obj


def html_page(
    layers: Sequence[Layer],
    *,
    title: str,
    view: str | tuple[float, float] = "iso",
    panel: str = "",
    frame: tuple[np.ndarray, float] | None = None,
) -> bytes:
    """The HTML page showing ``layers``.

    Parameters
    ----------
    layers : sequence of Layer
        Drawn in this order, all in one frame.
    title : str
        The page's title and heading (plain text).
    view : str or (azimuth, elevation)
        The first view (``recon_cli.eval.render.VIEWS`` or angles in degrees), as
        ``recon_cli.eval.render.render`` sees it.
    panel : str
        HTML put in the side panel under the counts (the diff's numbers and colour bar).
    frame : (center (3,), radius), optional
        The world sphere of the first view (default: ``recon_cli.eval.render.frame_of``
        of every layer).

    Returns
    -------
    bytes
        The page, UTF-8.
    """
    from recon_cli.eval.render import VIEWS, camera, frame_of

    if not layers:
        raise ParameterError("nothing to show")
    center, radius = frame if frame is not None else frame_of([la.obj for la in layers])
    center = np.asarray(center, dtype=np.float64)
    meta_layers, blobs = [], []
    for k, layer in enumerate(layers):
        meta, arrays = _encode(layer, center, f"layer{k}")
        meta_layers.append(meta)
        blobs += arrays
    views = {name: camera(name)[2].tolist() for name in VIEWS}
    meta_all = {
        "title": title,
        "center": center.tolist(),
        "radius": float(radius),
        "view": camera(view)[2].tolist(),
        "views": views,
        "antialias": sum(_face_count(la.obj) for la in layers) <= ANTIALIAS_FACES,
        "layers": meta_layers,
    }
    three, _ = three_bundle()
    data = "".join(
        f'<script type="application/octet-stream" id="{name}">{text}</script>\n'
        for name, text in blobs
    )
    buttons = "".join(f'<button data-view="{name}">{name}</button>' for name in views)
    return _fill(
        _asset("page.html").decode(),
        {
            "TITLE": html.escape(title),
            "COUNTS": _counts(layers),
            "PANEL": panel,
            "VIEWS": buttons,
            "LAYERS": _layer_list(layers),
            # "<" escaped: a file name cannot end the script element
            "META": json.dumps(meta_all).replace("<", "\\u003c"),
            "DATA": data,
            "THREE": three.decode(),
            "VIEWER": _asset("viewer.js").decode(),
        },
    ).encode()


def diff_panel(row: dict[str, Any], vmax: float, largest: float, unit: str | None) -> str:
    """The side panel of a diff: ``recon diff``'s numbers and the labelled colour bar.

    Parameters
    ----------
    row : dict
        ``recon_cli.eval.metrics.compare_meshes``'s result.
    vmax, largest : float
        The top of the colour scale and the largest distance shown.
    unit : str, optional
        The unit of the coordinates (default "model units").
    """
    from recon_cli.eval.figure import colorbar_labels
    from recon_cli.eval.render import colormap

    def g(v: float | None) -> str:
        return "-" if v is None else f"{v:.4g}"

    numbers = [
        ("accuracy", row["accuracy"]),
        ("completeness", row["completeness"]),
        ("chamfer L1", row["chamfer_l1"]),
        ("chamfer L2", row["chamfer_l2"]),
        ("hausdorff", row["hausdorff"]),
        ("hausdorff p95", row["hausdorff_p95"]),
        ("hausdorff p99", row["hausdorff_p99"]),
    ]
    cells = [(name, g(v)) for name, v in numbers]
    cells += [
        (f"F@{rel * 100:.3g}%", f"{f:.4f}")
        for rel, f in zip(row["tau_relative"], row["fscore"], strict=True)
    ]
    nc = row["normal_consistency"]
    cells.append(("normals", "-" if nc is None else f"{nc:.4f}"))
    table = "".join(
        f'<tr><th>{html.escape(k)}</th><td data-metric="{html.escape(k)}">{v}</td></tr>'
        for k, v in cells
    )
    ticks, note = colorbar_labels(vmax, largest, row["reference_diagonal"])
    ramp = colormap(np.linspace(1.0, 0.0, 11), 0.0, 1.0)
    stops = ", ".join(f"rgb({r},{gr},{b})" for r, gr, b in ramp.tolist())
    labels = "".join(
        f'<span class="tick" style="top:{100 * (1 - frac):.4g}%">{html.escape(text)}</span>'
        for frac, text in ticks
    )
    unit_text = html.escape(unit or "model units")
    return (
        f'<h2>distance <span class="small">[{unit_text}] (% of ref. diagonal)</span></h2>'
        f'<div class="colorbar"><div class="ramp" style="background: linear-gradient('
        f'{stops})"></div><div class="ticks">{labels}</div></div>'
        f'<p class="small note">{html.escape(note).replace(chr(10), "<br>")}</p>'
        f'<h2>recon diff</h2><p class="small">{html.escape(row["mode"])}; '
        f"{row['samples']['candidate']} / {row['samples']['reference']} samples, "
        f"seed {row['seed']}</p>"
        f'<table class="metrics">{table}</table>'
    )


def make_page(
    obj: TriangleMesh | PointCloud,
    reference: TriangleMesh | PointCloud | None = None,
    *,
    title: str = "recon view",
    view: str | tuple[float, float] = "iso",
    samples: int = 200_000,
    seed: int = 0,
    taus: Sequence[float | str] | str | None = None,
    vmax: float | None = None,
    unit: str | None = None,
    up: str = "y",
) -> tuple[bytes, dict[str, Any]]:
    """The page of a mesh or cloud, or of a candidate against a reference, and its report.

    Parameters
    ----------
    obj : TriangleMesh or PointCloud
        What to show (with ``reference``: the candidate).
    reference : TriangleMesh or PointCloud, optional
        The ground truth: ``obj`` is then coloured by its distance to it, on ``recon diff``'s
        scale, and a second layer (hidden at first) shows the reference coloured by its distance
        to ``obj`` (red where ``obj`` misses a part).
    title : str
        The page's title.
    view : str or (azimuth, elevation)
        The first view (see :func:`html_page`).
    samples, seed, taus
        As in ``recon_cli.eval.metrics.compare_meshes`` (with ``reference`` only).
    vmax : float, optional
        The top of the colour scale (default: ``recon diff``'s).
    unit : str, optional
        The unit of the coordinates, shown on the colour bar.
    up : {"y", "z"}
        The axis shown upwards: ``"z"`` turns z-up data (LiDAR, maps) a quarter turn about x,
        ``(x, y, z) -> (x, z, -y)``, before anything is drawn (distances do not change), so
        that the views and the orbit are about its z.

    Returns
    -------
    page : bytes
        The HTML page.
    report : dict
        ``kind`` ("mesh" or "cloud"), ``vertices``, ``faces``, ``bytes`` (of the page),
        ``view`` (azimuth, elevation), ``up``, ``frame`` (``center``, ``radius``), ``three``
        (version of three.js), ``diff`` (the ``recon_cli.eval.metrics.compare_meshes`` row,
        None without a reference) and ``scale`` (``vmax``, ``largest``, ``labels``: the colour
        bar's texts top first, then the note; None without a reference).
    """
    from recon_cli.eval.render import frame_of, resolve_views

    angles = resolve_views([view] if isinstance(view, str) else [view])[0][1]
    obj = _upright(check_viewable(obj), up)
    if reference is not None:
        reference = _upright(check_viewable(reference), up)
    report: dict[str, Any] = {
        "kind": "mesh" if _has_faces(obj) else "cloud",
        "vertices": len(obj.points),
        "faces": _face_count(obj),
        "view": list(angles),
        "up": up,
        "diff": None,
        "scale": None,
    }
    if reference is None:
        layers = [Layer("shape", obj, byte_colors(obj.colors))]
        panel = ""
    else:
        layers, panel, report["diff"], report["scale"] = _diff_layers(
            obj, reference, samples, seed, taus, vmax, unit
        )
    center, radius = frame_of([la.obj for la in layers])
    doc = html_page(layers, title=title, view=angles, panel=panel, frame=(center, radius))
    report["frame"] = {"center": center.tolist(), "radius": float(radius)}
    report["three"] = three_bundle()[1]
    report["bytes"] = len(doc)
    return doc, report


def view_files(
    path: str | os.PathLike,
    out: str | os.PathLike,
    diff: str | os.PathLike | None = None,
    **kwargs: Any,
) -> dict[str, Any]:
    """Write the page of the file ``path`` (against ``diff``) to ``out`` atomically (``-``: stdout).

    Parameters
    ----------
    path : path
        A mesh or cloud in any format recon reads (``-``: stdin).
    out : path
        The page; nothing is written when anything fails.
    diff : path, optional
        The reference to colour ``path`` against.
    **kwargs
        See :func:`make_page` (``title`` defaults to the file names).

    Returns
    -------
    dict
        :func:`make_page`'s report, with ``input``, ``output`` and ``reference``.
    """
    from recon_cli.io.atomic import check_output, write_bytes
    from recon_cli.io.load import load

    check_output(out)
    _check_parameters(diff, kwargs)  # before any reading
    three_bundle()
    where = "<stdin>" if str(path) == "-" else os.fspath(path)
    with naming(path):
        obj = check_viewable(load(path))
    reference = None
    if diff is not None:
        with naming(diff):
            reference = check_viewable(load(diff))
    if "title" not in kwargs:
        name = os.path.basename(where)
        kwargs["title"] = name if diff is None else f"{name} against {os.path.basename(diff)}"
    with naming(where if diff is None else f"{where} vs {os.fspath(diff)}"):
        doc, report = make_page(obj, reference, **kwargs)
    write_bytes(out, doc)
    where_out = "<stdout>" if str(out) == "-" else os.fspath(out)
    ref = None if diff is None else os.fspath(diff)
    return {"input": where, "reference": ref, "output": where_out, **report}


# --------------------------------------------------------------------------- internals


def _check_parameters(diff: Any, kwargs: dict[str, Any]) -> None:
    """Refuse a bad view, and with a reference a bad sample count, threshold or scale top."""
    from recon_cli.eval.metrics import check_samples, check_vmax, parse_taus
    from recon_cli.eval.render import resolve_views

    view = kwargs.get("view", "iso")
    resolve_views([view] if isinstance(view, str) else [view])
    _check_up(kwargs.get("up", "y"))
    if diff is None:
        return
    check_samples(kwargs.get("samples", 200_000))
    parse_taus(kwargs.get("taus"), 1.0)
    if kwargs.get("vmax") is not None:
        check_vmax(kwargs["vmax"])


def _check_up(up: Any) -> None:
    if up not in ("y", "z"):
        raise ParameterError(f"up must be y or z, got {up!r}")


def _upright(obj: TriangleMesh | PointCloud, up: str) -> TriangleMesh | PointCloud:
    """``obj`` as drawn with ``up`` upwards: z-up data a quarter turn about x (exact: a swap)."""
    _check_up(up)
    if up == "y":
        return obj
    p = np.asarray(obj.points, dtype=np.float64)
    normals = None
    if obj.normals is not None:
        n = np.asarray(obj.normals, dtype=np.float64)
        normals = np.column_stack([n[:, 0], n[:, 2], -n[:, 1]])
    turned = np.column_stack([p[:, 0], p[:, 2], -p[:, 1]])
    if isinstance(obj, TriangleMesh):
        return TriangleMesh(turned, obj.faces, normals=normals, colors=obj.colors)
    return PointCloud(turned, normals=normals, colors=obj.colors)


def _has_faces(obj: TriangleMesh | PointCloud) -> bool:
    return isinstance(obj, TriangleMesh) and len(obj.faces) > 0


def _face_count(obj: TriangleMesh | PointCloud) -> int:
    return len(obj.faces) if isinstance(obj, TriangleMesh) else 0


def _diff_layers(obj, reference, samples, seed, taus, vmax, unit):
    """The layers, panel, ``recon diff`` row and colour scale of a candidate against a reference."""
    from recon_cli.eval.diff import heatmap_distances
    from recon_cli.eval.figure import colorbar_labels
    from recon_cli.eval.metrics import check_vmax, compare_meshes
    from recon_cli.eval.render import colormap

    if vmax is not None:
        vmax = check_vmax(vmax)
    check_viewable(reference)
    row = compare_meshes(obj, reference, samples=samples, seed=seed, taus=taus)
    (acc,), (missed,), vmax = heatmap_distances([obj], reference, min(row["tau"]), vmax)
    largest = max(float(acc.max()), float(missed.max()))
    layers = [
        Layer(
            "accuracy: coloured by distance to the reference",
            obj,
            colormap(acc, 0.0, vmax),
            heat=True,
        ),
        Layer(
            "completeness: the reference coloured by distance to it (red: missed)",
            reference,
            colormap(missed, 0.0, vmax),
            visible=False,
            heat=True,
        ),
    ]
    ticks, note = colorbar_labels(vmax, largest, row["reference_diagonal"])
    scale = {"vmax": vmax, "largest": largest, "labels": [t for _, t in ticks] + [note]}
    return layers, diff_panel(row, vmax, largest, unit), row, scale


def _encode(layer: Layer, center: np.ndarray, name: str) -> tuple[dict, list[tuple[str, str]]]:
    """A layer's description for the page's script and its arrays as (element id, base64)."""
    obj = layer.obj
    rel = (np.asarray(obj.points, dtype=np.float64) - center).astype("<f4")
    blobs = [(f"{name}-positions", _b64(rel))]
    meta: dict[str, Any] = {
        "name": layer.name,
        "visible": layer.visible,
        "heat": layer.heat,
        "count": len(rel),
        "positions": f"{name}-positions",
        "colors": None,
        "faces": None,
    }
    if _has_faces(obj):
        assert isinstance(obj, TriangleMesh)
        wide = len(rel) > 65536
        faces = np.ascontiguousarray(obj.faces, dtype="<u4" if wide else "<u2")
        blobs.append((f"{name}-faces", _b64(faces)))
        meta["faces"] = f"{name}-faces"
        meta["index"] = "uint32" if wide else "uint16"
    normals = getattr(obj, "normals", None)
    meta["normals"] = None
    if not _has_faces(obj) and normals is not None:
        n = np.asarray(normals, dtype=np.float64)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        unit = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
        blobs.append((f"{name}-normals", _b64(np.rint(unit * 127.0).astype(np.int8))))
        meta["normals"] = f"{name}-normals"
    if layer.colors is not None:
        colors = np.ascontiguousarray(layer.colors, dtype=np.uint8).reshape(-1, 3)
        if len(colors) != len(rel):
            raise ParameterError(f"{len(colors)} colours for {len(rel)} vertices")
        blobs.append((f"{name}-colors", _b64(colors)))
        meta["colors"] = f"{name}-colors"
    return meta, blobs


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _counts(layers: Sequence[Layer]) -> str:
    obj = layers[0].obj
    n = len(obj.points)
    if _has_faces(obj):
        assert isinstance(obj, TriangleMesh)
        return f"{n:,} vertices, {len(obj.faces):,} faces"
    return f"{n:,} points"


def _layer_list(layers: Sequence[Layer]) -> str:
    if len(layers) < 2:
        return ""
    return "".join(
        f'<label><input type="checkbox" data-layer="{k}"{" checked" if la.visible else ""}> '
        f"{html.escape(la.name)}</label>"
        for k, la in enumerate(layers)
    )


def _asset(name: str) -> bytes:
    return (resources.files("recon_cli.eval") / ASSETS / name).read_bytes()


def _fill(template: str, values: dict[str, str]) -> str:
    """``template`` with each ``@@NAME@@`` replaced in one pass (a value is never searched)."""
    parts = _MARK.split(template)
    for k in range(1, len(parts), 2):
        parts[k] = values[parts[k]]
    return "".join(parts)
