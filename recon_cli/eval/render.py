"""A small software renderer for ``recon diff --png`` and ``recon compare`` pictures.

Orthographic projection from fixed views, a z-buffer rasteriser (numba kernel in
:mod:`recon_cli.eval._render_kernel`), flat two-sided Lambert shading under a light near the
camera, per-vertex scalars as a colour ramp (heatmaps) with a colour bar, and a tiny
bitmap font for titles and labels. Pillow is used only to encode the PNG.

Image arrays are (H, W, 3) uint8, row 0 at the top.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, float64

# name -> (azimuth, elevation) in degrees; y is up, azimuth 0 looks from +z towards -z
VIEWS: dict[str, tuple[float, float]] = {
    "front": (0.0, 0.0),
    "back": (180.0, 0.0),
    "right": (90.0, 0.0),
    "left": (-90.0, 0.0),
    "top": (0.0, 90.0),
    "bottom": (0.0, -90.0),
    "iso": (35.0, 25.0),
}
# ``--view turntable``: four quarter turns about the up axis, starting at the iso view
TURNTABLE: tuple[tuple[float, float], ...] = tuple((35.0 + 90.0 * k, 25.0) for k in range(4))
DEFAULT_VIEWS = ("turntable",)

BACKGROUND = (255, 255, 255)
BOUNDARY_COLOR = (225, 0, 200)  # magenta: neither on the grey shading nor on the blue-to-red ramp
NON_MANIFOLD_COLOR = (0, 0, 0)
BASE_COLOR = (0.74, 0.76, 0.80)
_AMBIENT = 0.22
# colour ramp of the heatmaps, low (blue) to high (red): (position, r, g, b)
_RAMP = np.array(
    [
        [0.00, 25, 45, 150],
        [0.20, 35, 110, 225],
        [0.40, 45, 195, 215],
        [0.60, 165, 220, 70],
        [0.80, 250, 165, 35],
        [1.00, 200, 25, 25],
    ],
    dtype=np.float64,
)


@dataclass
class Rendering:
    """One rendered panel.

    Attributes
    ----------
    image : (H, W, 3) uint8
    depth : (H, W) float64
        Depth of the visible surface along the view direction (world units, smaller is
        nearer), +inf where nothing is drawn.
    mask : (H, W) bool
        Covered pixels.
    """

    image: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


def camera(view: str | tuple[float, float]) -> np.ndarray:
    """Rows right, up and towards-the-camera of a view, shape (3, 3).

    Parameters
    ----------
    view : str or (azimuth, elevation)
        A name of :data:`VIEWS` or angles in degrees.
    """
    if isinstance(view, str):
        if view not in VIEWS:
            raise ParameterError(f"unknown view {view!r} (views: {', '.join(VIEWS)})")
        view = VIEWS[view]
    az, el = np.radians(np.asarray(view, dtype=np.float64).reshape(2))
    back = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    up_ref = np.array([0.0, 1.0, 0.0])
    right = np.cross(up_ref, back)
    if np.linalg.norm(right) < 1e-9:  # looking straight down or up: keep -z/+z as "up"
        right = np.cross(np.array([0.0, 0.0, -np.sign(back[1])]), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return np.stack([right, up, back])


def frame_of(objects: Sequence[TriangleMesh | PointCloud]) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of a sphere holding every object, to frame them alike."""
    pts = [float64(o).points for o in objects if len(o.points)]
    if not pts:
        raise InputError("nothing to render: every object is empty")
    lo = np.min([p.min(axis=0) for p in pts], axis=0)
    hi = np.max([p.max(axis=0) for p in pts], axis=0)
    center = 0.5 * (lo + hi)
    radius = float(max(np.sqrt(((p - center) ** 2).sum(axis=1).max()) for p in pts))
    return center, radius if radius > 0 else 1.0


def render(
    obj: TriangleMesh | PointCloud,
    view: str | tuple[float, float] = "iso",
    size: tuple[int, int] = (320, 320),
    frame: tuple[np.ndarray, float] | None = None,
    scalars: np.ndarray | None = None,
    vmin: float = 0.0,
    vmax: float | None = None,
    color: tuple[float, float, float] = BASE_COLOR,
    supersample: int = 1,
    point_radius: float | None = None,
    edges: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = (),
    edge_width: float = 2.0,
) -> Rendering:
    """Render one mesh or cloud, shaded, or coloured by per-vertex ``scalars``.

    Parameters
    ----------
    obj : TriangleMesh or PointCloud
        A mesh without faces is drawn as its points.
    view : str or (azimuth, elevation)
        See :data:`VIEWS`.
    size : (width, height)
        Pixels.
    frame : (center (3,), radius), optional
        World sphere mapped to 92 % of the smaller image side (default: ``obj``'s own,
        see :func:`frame_of`); pass the same frame to draw several objects at one scale.
    scalars : (n,) float64, optional
        Per-vertex values drawn with :func:`colormap` between ``vmin`` and ``vmax``
        (default max: the largest value).
    color : (r, g, b) in [0, 1]
        Base colour of the shaded surface.
    supersample : int
        Render at this factor and average down (anti-aliasing); 1 for exact pixels.
    point_radius : float, optional
        Disc radius of cloud points in output pixels (default: about width / 250).
    edges : sequence of (edges (k, 2) int, (r, g, b) uint8)
        Mesh edges (vertex index pairs) drawn over the surface in a flat colour where they
        are not hidden by it (depth test with a tolerance of 2 % of the frame radius); a
        later group is drawn over an earlier one. See :func:`defect_edges`.
    edge_width : float
        Pen width of ``edges`` in output pixels.

    Returns
    -------
    Rendering
        ``image``, ``depth`` and ``mask`` at ``size``.
    """
    width, height = (int(v) for v in size)
    ss = int(supersample)
    if width < 1 or height < 1 or ss < 1:
        raise ParameterError(
            f"image size and supersample must be positive, got {size}, {supersample}"
        )
    if not isinstance(obj, (TriangleMesh, PointCloud)):
        raise ParameterError(f"cannot render a {type(obj).__name__}")
    obj = float64(obj)
    if scalars is not None:
        scalars = np.asarray(scalars, dtype=np.float64).reshape(-1)
        if len(scalars) != len(obj.points):
            raise ParameterError(f"{len(scalars)} scalars for {len(obj.points)} vertices")
        if vmax is None:
            vmax = float(scalars.max()) if len(scalars) else 1.0
    center, radius = frame if frame is not None else frame_of([obj])
    rot = camera(view)
    w, h = width * ss, height * ss
    scale = 0.46 * min(w, h) / radius
    p = (obj.points - np.asarray(center, dtype=np.float64)) @ rot.T
    sx = np.ascontiguousarray(w / 2 + p[:, 0] * scale)
    sy = np.ascontiguousarray(h / 2 - p[:, 1] * scale)
    sz = np.ascontiguousarray(-p[:, 2])
    depth = np.full((h, w), np.inf)
    index = np.full((h, w), -1, dtype=np.int64)
    img = np.empty((h, w, 3), dtype=np.float64)
    img[:] = np.asarray(BACKGROUND, dtype=np.float64) / 255.0
    screen = (sx, sy, sz)
    tint = (_light(rot), np.asarray(color, dtype=np.float64), scalars, vmin, vmax)
    if isinstance(obj, TriangleMesh) and len(obj.faces):
        mask = _draw_faces(obj, screen, tint, depth, index, img)
    else:
        r = (point_radius if point_radius is not None else max(1.0, width / 250.0)) * ss
        mask = _draw_points(obj, screen, tint, float(r), depth, index, img)
    if len(edges):
        _draw_edges(screen, edges, 0.02 * radius, 0.5 * edge_width * ss, depth, img)
    if ss > 1:
        img = img.reshape(height, ss, width, ss, 3).mean(axis=(1, 3))
        cover = mask.reshape(height, ss, width, ss).mean(axis=(1, 3))
        d = depth.reshape(height, ss, width, ss).min(axis=(1, 3))
        mask = cover >= 0.5
        depth = np.where(mask, d, np.inf)
    else:
        depth = np.where(mask, depth, np.inf)
    image = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    return Rendering(image=image, depth=depth, mask=mask)


def _tinted(shade: np.ndarray, values: np.ndarray | None, tint: tuple) -> np.ndarray:
    """Pixel colours (k, 3) in [0, 1]: the base colour shaded, or the ramp of ``values``."""
    _, color, scalars, vmin, vmax = tint
    if scalars is None:
        return shade[:, None] * color
    assert values is not None, "values come with scalars"
    ramp = colormap(values, vmin, vmax).astype(np.float64) / 255.0
    return ramp * (0.55 + 0.45 * shade[:, None])


def _draw_faces(obj: TriangleMesh, screen: tuple, tint: tuple, depth, index, img) -> np.ndarray:
    """Rasterize the faces into ``depth``/``index``/``img``; returns the covered pixels."""
    from recon_cli.eval._render_kernel import rasterize_triangles

    sx, sy, sz = screen
    light, _, scalars, _, _ = tint
    bary = np.zeros(depth.shape + (3,), dtype=np.float64)
    rasterize_triangles(sx, sy, sz, obj.faces, depth, index, bary)
    mask = index >= 0
    fid = index[mask]
    fn = _face_normals(obj.vertices, obj.faces)
    shade = _AMBIENT + (1 - _AMBIENT) * np.abs(fn[fid] @ light)
    values = None
    if scalars is not None:
        values = np.einsum("ij,ij->i", bary[mask], scalars[obj.faces[fid]])
    img[mask] = _tinted(shade, values, tint)
    return mask


def _draw_points(obj, screen: tuple, tint: tuple, r: float, depth, index, img) -> np.ndarray:
    """Splat the points as discs of radius ``r`` pixels; returns the covered pixels."""
    from recon_cli.eval._render_kernel import splat_points

    sx, sy, sz = screen
    light, _, scalars, _, _ = tint
    splat_points(sx, sy, sz, r, depth, index)
    mask = index >= 0
    pid = index[mask]
    if obj.normals is not None:
        n = obj.normals[pid]
        length = np.linalg.norm(n, axis=1)
        cos = np.abs(n @ light) / np.where(length > 0, length, 1.0)
        shade = np.where(length > 0, _AMBIENT + (1 - _AMBIENT) * cos, 0.8)
    else:
        shade = np.full(len(pid), 0.8)
    img[mask] = _tinted(shade, None if scalars is None else scalars[pid], tint)
    return mask


def _draw_edges(screen: tuple, edges, tolerance: float, half_width: float, depth, img) -> None:
    """Draw each group of ``edges`` in its flat colour where the surface does not hide it."""
    from recon_cli.eval._render_kernel import draw_segments

    sx, sy, sz = screen
    code = np.zeros(depth.shape, dtype=np.int8)
    for k, (e, _) in enumerate(edges):
        e = np.ascontiguousarray(e, dtype=np.int64).reshape(-1, 2)
        if len(e):
            draw_segments(sx, sy, sz, e, tolerance, half_width, depth, code, k + 1)
    for k, (_, rgb) in enumerate(edges):
        img[code == k + 1] = np.asarray(rgb, dtype=np.float64) / 255.0


def colormap(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Colours (n, 3) uint8 of ``values`` on the blue-to-red ramp, clipped to [vmin, vmax]."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    span = float(vmax) - float(vmin)
    t = (v - vmin) / span if span > 0 else np.zeros_like(v)
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    out = np.empty((len(v), 3), dtype=np.float64)
    for k in range(3):
        out[:, k] = np.interp(t, _RAMP[:, 0], _RAMP[:, 1 + k])
    return np.rint(out).astype(np.uint8)


def defect_edges(obj: TriangleMesh | PointCloud) -> list[tuple[np.ndarray, tuple[int, int, int]]]:
    """The boundary and non-manifold edges of a mesh, coloured for :func:`render`'s ``edges``.

    Returns
    -------
    list of (edges (k, 2) int64, (r, g, b))
        ``[(boundary, BOUNDARY_COLOR), (non_manifold, NON_MANIFOLD_COLOR)]`` (non-manifold
        drawn last, over boundary); empty for a cloud or a mesh without faces.
    """
    if not isinstance(obj, TriangleMesh) or len(obj.faces) == 0:
        return []
    from recon_cli.mesh.topology import Connectivity

    con = Connectivity(obj.faces, len(obj.vertices))
    return [
        (con.edges[con.boundary_edges], BOUNDARY_COLOR),
        (con.edges[con.non_manifold_edges], NON_MANIFOLD_COLOR),
    ]


def resolve_views(
    views: Sequence[str | tuple[float, float]] | str | None,
) -> list[tuple[str, tuple[float, float]]]:
    """Labelled (azimuth, elevation) views from names, ``"turntable"`` or angle pairs.

    Parameters
    ----------
    views : sequence of str or (azimuth, elevation), or str, optional
        Names of :data:`VIEWS`, ``"turntable"`` (the four azimuths of :data:`TURNTABLE`),
        ``"AZ,EL"`` or (azimuth, elevation) in degrees; a str is one view. Default
        :data:`DEFAULT_VIEWS`.

    Returns
    -------
    list of (label, (azimuth, elevation))
        A label such as ``"front (az 0°, el 0°)"``; turntable views are labelled by angle.

    Raises
    ------
    ParameterError
        An unknown name, malformed angles, or no view.
    """
    if views is None:
        views = DEFAULT_VIEWS
    if isinstance(views, str):
        views = (views,)
    out: list[tuple[str, tuple[float, float]]] = []
    for v in views:
        if isinstance(v, str) and "," in v:  # "AZ,EL" in degrees, as on the command line
            try:
                v = tuple(float(x) for x in v.split(","))  # type: ignore[assignment]  # 2 checked below
            except ValueError:
                raise ParameterError(f"view {v!r} is not AZIMUTH,ELEVATION in degrees") from None
            if len(v) != 2 or not all(np.isfinite(v)):
                raise ParameterError(
                    f"view {','.join(map(str, v))!r} is not AZIMUTH,ELEVATION in degrees"
                )
        if isinstance(v, str):
            if v == "turntable":
                out += [(f"az {a:g}°, el {e:g}°", (a, e)) for a, e in TURNTABLE]
                continue
            camera(v)
            a, e = VIEWS[v]
            out.append((f"{v} (az {a:g}°, el {e:g}°)", (a, e)))
        else:
            a, e = (float(x) for x in v)
            camera((a, e))
            out.append((f"az {a:g}°, el {e:g}°", (a, e)))
    if not out:
        raise ParameterError("no view given")
    return out


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of an (H, W, 3) uint8 image (Pillow)."""
    try:
        from PIL import Image
    except ImportError:
        raise ParameterError("writing PNG needs Pillow: pip install 'recon[render]'") from None
    arr = np.ascontiguousarray(image, dtype=np.uint8)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ParameterError(f"expected an (H, W, 3) image, got shape {arr.shape}")
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def write_png(image: np.ndarray, path: str | os.PathLike) -> None:
    """Write ``image`` ((H, W, 3) uint8) to ``path`` as PNG, atomically."""
    from recon_cli.io.atomic import write_bytes

    write_bytes(path, png_bytes(image))


# --------------------------------------------------------------------------- internals


def _light(rot: np.ndarray) -> np.ndarray:
    # a headlight raised and moved right a little, so facing surfaces are not all equally bright
    d = rot[2] + 0.45 * rot[1] + 0.3 * rot[0]
    return d / np.linalg.norm(d)


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    from recon_cli.mesh.sampling import face_normals

    return face_normals(vertices, faces)[0]
