"""A mesh's coordinates in a local east-north-up frame on the globe, and that frame's place (ECEF).

3D Tiles place a tileset on the globe by the root tile's ``transform`` into Earth-centred,
Earth-fixed coordinates (EPSG:4978, metres). Every vertex goes from the mesh's coordinate
system to ECEF through PROJ (pyproj), then into the east-north-up frame at the centre of the
mesh's bounding box: the tiles hold metres in that frame, and the root's transform is the
frame's rotation and origin, exactly (no linearisation of the map projection).

A projected or geographic coordinate system without a vertical axis (LAS files usually give
one) says nothing of heights: they are taken in the unit of the horizontal axes (feet for a
state plane in feet) above the ellipsoid, so a tileset sits off by the geoid's height there
(about -20 m in Oregon) unless the data's heights are ellipsoidal already.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError


def _pyproj():
    try:
        import pyproj
    except ModuleNotFoundError:
        raise ParameterError(
            "placing a tileset on the globe needs pyproj: pip install 'recon[tiles]'"
        ) from None
    return pyproj


def parse_crs(text: str) -> Any:
    """The pyproj CRS of ``text`` (WKT, ``EPSG:<code>``, a PROJ string)."""
    pyproj = _pyproj()
    try:
        return pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as exc:
        first = str(exc).splitlines()[0][:160]
        raise InputError(f"not a coordinate system recon can use ({first})") from None


def enu_rotation(lon: float, lat: float) -> np.ndarray:
    """(3, 3): rows east, north, up at geodetic longitude and latitude (degrees), in ECEF."""
    lo, la = np.radians(lon), np.radians(lat)
    return np.array(
        [
            [-np.sin(lo), np.cos(lo), 0.0],
            [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
            [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
        ]
    )


def geodetic(ecef: np.ndarray) -> tuple[float, float, float]:
    """Longitude, latitude (degrees) and height above the WGS 84 ellipsoid of an ECEF point."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    x, y, z = (float(c) for c in ecef)
    p = float(np.hypot(x, y))
    lat = float(np.arctan2(z, p * (1 - e2)))
    h = 0.0
    for _ in range(8):  # converges to 1e-12 rad in a few steps away from the poles
        n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n if p > 0 else abs(z) - a * np.sqrt(1 - e2)
        lat = float(np.arctan2(z, p * (1 - e2 * n / (n + h))))
    return float(np.degrees(np.arctan2(y, x))), float(np.degrees(lat)), float(h)


def to_local(vertices: np.ndarray, crs: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """``vertices`` ((n, 3), in ``crs``) in the east-north-up frame at their box's centre.

    Returns
    -------
    local : (n, 3) float64
        Metres east, north and up of the centre.
    transform : (4, 4) float64
        That frame to ECEF (rotation columns east, north, up; the centre's ECEF position).
    normals : (3, 3) float64
        What takes a normal of the mesh into the frame: the inverse transpose of the map's
        Jacobian at the centre (the projection's scale and convergence vary across one mesh
        by far less than a float32 normal holds).
    frame : dict
        ``crs`` (its name), ``height_unit`` (metres per unit of the mesh's heights),
        ``longitude``, ``latitude``, ``height`` of the centre.

    Raises
    ------
    InputError
        A vertex PROJ cannot place (outside the coordinate system's area).
    """
    pyproj = _pyproj()
    v = np.asarray(vertices, np.float64)
    height_unit = 1.0
    if len(crs.axis_info) == 2:  # no vertical axis: heights in the horizontal unit
        height_unit = float(crs.axis_info[0].unit_conversion_factor) if crs.is_projected else 1.0
    to_ecef = pyproj.Transformer.from_crs(crs, pyproj.CRS.from_epsg(4978), always_xy=True)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    step = max(float(np.ptp(v, axis=0).max()), 1.0) * 1e-3
    probe = centre + np.vstack([np.zeros(3), np.eye(3) * step])  # the centre, then steps

    def ecef_of(p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.column_stack(to_ecef.transform(p[:, 0], p[:, 1], p[:, 2] * height_unit))

    near = ecef_of(probe)
    origin = near[0]
    ecef = ecef_of(v)
    if not (np.isfinite(near).all() and np.isfinite(ecef).all()):
        bad = int(np.argmin(np.isfinite(ecef).all(axis=1))) if len(ecef) else 0
        raise InputError(
            f"vertex {bad} is outside the area of {crs.name!r}: PROJ cannot place it on the globe"
        )
    lon, lat, h = geodetic(origin)
    rot = enu_rotation(lon, lat)
    local = (ecef - origin) @ rot.T
    jac = ((near[1:] - origin) @ rot.T).T / step
    normals = np.linalg.inv(jac).T
    transform = np.eye(4)
    transform[:3, :3] = rot.T
    transform[:3, 3] = origin
    frame = {
        "crs": crs.name,
        "height_unit": height_unit,
        "longitude": lon,
        "latitude": lat,
        "height": h,
    }
    return local, transform, normals, frame
