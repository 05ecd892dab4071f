"""Simulated depth sensors for tests and benches: organized clouds as real cameras write them.

A :class:`DepthCamera` (pinhole, ``width`` x ``height`` pixels) ray-casts a scene given by a
signed distance function (sphere tracing, so unions of the analytic shapes of
:mod:`shapes`, planes and boxes make rooms and tabletops) and returns an *organized*
cloud: an ``(height, width, 3)`` array in world coordinates with NaN where a ray hits nothing
within range, as Kinect/RealSense drivers and PCL write them. Sensor effects, each optional:

- depth noise along the ray growing with the square of the distance (Kinect v1:
  ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)**2`` metres, Nguyen, Izadi & Lovell 2012, scaled
  by ``noise``),
- flying pixels: at depth discontinuities a fraction of the pixels take a depth between
  the foreground and the background (the mixed returns at silhouettes),
- depth quantisation (``disparity_bits``) is not modelled.

:func:`write_organized_pcd` writes such a cloud as a PCD (binary, ASCII or binary_compressed)
with ``WIDTH``/``HEIGHT``, NaN pixels, packed ``rgba`` colour and the ``VIEWPOINT`` of the
camera, as PCL does; :func:`exact_image` and :func:`true_normals` give the noise-free points
and the scene's normals to measure against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shapes import rounded_box_sdf, sphere_sdf, torus_sdf


# ---- scenes: signed distance functions (n, 3) -> (n,) ----------------------------------------
def plane_sdf(p, normal=(0.0, 0.0, 1.0), offset=0.0):
    """Half-space below the plane ``normal . p = offset`` (negative inside)."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    return p @ n - offset


def box_sdf(p, lo, hi):
    """Exact signed distance of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def union(*fns):
    """The union of solids: the minimum of their distances."""
    return lambda p: np.min(np.stack([f(p) for f in fns]), axis=0)


def tabletop_scene():
    """A floor slab (z in [-0.05, 0]), a back wall, a sphere, a torus lying down and a rounded
    box: metres, a room corner 3 m across. Returns the scene's sdf."""
    floor = lambda p: box_sdf(p, (-1.5, -1.5, -0.05), (1.5, 1.5, 0.0))  # noqa: E731
    wall = lambda p: box_sdf(p, (-1.5, 1.45, -0.05), (1.5, 1.5, 1.5))  # noqa: E731
    ball = lambda p: sphere_sdf(p - (-0.5, 0.2, 0.3), 0.3)  # noqa: E731
    ring = lambda p: torus_sdf(p - (0.5, -0.2, 0.12), 0.3, 0.1)  # noqa: E731
    block = lambda p: rounded_box_sdf(p - (0.3, 0.7, 0.25), half=(0.25, 0.2, 0.25), radius=0.04)  # noqa: E731
    return union(floor, wall, ball, ring, block)


# ---- the camera ------------------------------------------------------------------------------
def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotation (columns: right, down, forward), as an optical frame."""
    eye, target, up = (np.asarray(x, float) for x in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f], axis=1)


@dataclass
class DepthCamera:
    """A pinhole depth camera.

    Parameters
    ----------
    eye : (3,) float
        Optical centre in world coordinates.
    rotation : (3, 3) float
        Camera-to-world rotation; column 2 is the viewing direction (:func:`look_at`).
    width, height : int
        Image size in pixels.
    fov : float
        Horizontal field of view, degrees (Kinect v1: 57).
    max_range : float
        Rays hitting nothing closer than this give NaN pixels.
    """

    eye: np.ndarray
    rotation: np.ndarray
    width: int = 160
    height: int = 120
    fov: float = 57.0
    max_range: float = 6.0

    @property
    def focal(self) -> float:
        return 0.5 * self.width / np.tan(np.radians(self.fov) / 2)

    def rays(self) -> np.ndarray:
        """(height, width, 3) unit ray directions in world coordinates."""
        f = self.focal
        u = (np.arange(self.width) + 0.5 - self.width / 2) / f
        v = (np.arange(self.height) + 0.5 - self.height / 2) / f
        uu, vv = np.meshgrid(u, v)
        d = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ self.rotation.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def cast(self, sdf, steps: int = 300, eps: float = 1e-6) -> np.ndarray:
        """(height, width) distance along each ray to the first hit (inf for a miss)."""
        d = self.rays().reshape(-1, 3)
        o = np.asarray(self.eye, float)
        t = np.zeros(len(d))
        live = np.ones(len(d), bool)
        hit = np.zeros(len(d), bool)
        for _ in range(steps):
            idx = np.flatnonzero(live)
            if len(idx) == 0:
                break
            f = sdf(o + t[idx, None] * d[idx])
            close = f < eps
            hit[idx[close]] = True
            t[idx] += np.where(close, 0.0, np.maximum(f, 0.0))
            live[idx[close | (t[idx] > self.max_range)]] = False
        t[~hit | (t > self.max_range)] = np.inf
        return t.reshape(self.height, self.width)


def depth_image(
    camera: DepthCamera,
    sdf,
    rng: np.random.Generator,
    *,
    noise: float = 1.0,
    flying: float = 0.5,
) -> np.ndarray:
    """An organized cloud of ``sdf`` seen by ``camera``: (height, width, 3), NaN where nothing is
    hit.

    Parameters
    ----------
    noise : float
        Scale of the Kinect-like depth noise (0: exact hits).
    flying : float
        Fraction of the pixels at a depth edge (a neighbour more than 5 % farther) that
        become flying pixels, their depth drawn uniformly between the two surfaces.
    """
    t = camera.cast(sdf)
    z = t.copy()
    if flying > 0:
        finite = np.isfinite(t)
        near = np.where(finite, t, 0.0)
        # the farthest finite 4-neighbour (misses make no mixed return)
        pad = np.pad(near, 1)
        nb = np.maximum.reduce([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
        edge = finite & (nb > 1.05 * near)
        pick = edge & (rng.random(t.shape) < flying)
        z[pick] = near[pick] + rng.random(int(pick.sum())) * (nb[pick] - near[pick])
    if noise > 0:
        sigma = noise * (0.0012 + 0.0019 * (np.where(np.isfinite(z), z, 0.4) - 0.4) ** 2)
        z = z + rng.normal(size=z.shape) * sigma
    pts = camera.eye + camera.rays() * z[..., None]
    pts[~np.isfinite(z)] = np.nan
    return pts


def valid_rows(organized: np.ndarray) -> np.ndarray:
    """The finite points of an organized cloud, (n, 3), in row-major pixel order."""
    p = organized.reshape(-1, 3)
    return p[np.isfinite(p).all(axis=1)]


# ---- files as PCL writes them ------------------------------------------------------------------
def write_organized_pcd(
    path,
    organized: np.ndarray,
    camera: DepthCamera | None = None,
    colors=None,
    data: str = "binary",
    dtype: str = "f4",
) -> None:
    """PCD of an organized cloud as PCL writes it: ``WIDTH``/``HEIGHT`` of the image, NaN pixels
    kept, ``rgba`` packed as PCL packs it (0xAARRGGBB in 4 bytes), ``VIEWPOINT`` of the camera
    (position and orientation quaternion w x y z).

    ``data``: ``binary`` (PCL's default), ``ascii`` (NaN written ``nan``) or
    ``binary_compressed`` (column-major, LZF: written as literal runs, which every LZF reader
    decodes); ``dtype``: ``f4`` (as depth cameras give) or ``f8`` coordinates.
    """
    h, w, _ = organized.shape
    n = h * w
    ftype = "<" + dtype
    rows = np.zeros(n, dtype=[("x", ftype), ("y", ftype), ("z", ftype), ("rgba", "<u4")])
    p = organized.reshape(-1, 3)
    rows["x"], rows["y"], rows["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is None:
        colors = np.full((n, 3), 200, np.uint8)
    c = np.asarray(colors, np.uint32).reshape(-1, 3)
    rows["rgba"] = (255 << 24) | (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    view = "0 0 0 1 0 0 0"
    if camera is not None:
        view = " ".join(f"{x:.17g}" for x in (*camera.eye, *quaternion(camera.rotation)))
    size = int(dtype[1])
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgba\n"
        f"SIZE {size} {size} {size} 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH {w}\nHEIGHT {h}\n"
        f"VIEWPOINT {view}\nPOINTS {n}\nDATA {data}\n"
    )
    if data == "binary":
        body = rows.tobytes()
    elif data == "ascii":
        fmt = "%.9g" if size == 4 else "%.17g"
        lines = [
            f"{fmt % x} {fmt % y} {fmt % z} {int(v)}"
            for x, y, z, v in zip(rows["x"], rows["y"], rows["z"], rows["rgba"], strict=True)
        ]
        body = ("\n".join(lines) + "\n").encode("ascii")
    elif data == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(rows[f]).tobytes() for f in rows.dtype.names)
        comp = _lzf_literals(raw)
        body = np.array([len(comp), len(raw)], "<u4").tobytes() + comp
    else:
        raise ValueError(f"unknown PCD data {data!r}")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(body)


def _lzf_literals(raw: bytes) -> bytes:
    """An LZF stream of literal runs only (a control byte ``len - 1`` < 32 before each run)."""
    out = bytearray()
    for i in range(0, len(raw), 32):
        chunk = raw[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def true_normals(sdf, points: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Unit gradients of ``sdf`` at ``points`` (n, 3): the scene's outward normals there."""
    g = np.zeros_like(points, dtype=np.float64)
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        g[:, a] = (sdf(points + d) - sdf(points - d)) / (2 * eps)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def exact_image(camera: DepthCamera, sdf) -> np.ndarray:
    """The noise-free organized cloud of ``sdf`` seen by ``camera`` (NaN where nothing is hit)."""
    t = camera.cast(sdf)
    pts = camera.eye + camera.rays() * t[..., None]
    pts[~np.isfinite(t)] = np.nan
    return pts


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return float(w), float(x), float(y), float(z)
