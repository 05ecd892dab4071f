"""E57 (ASTM E2807) through pye57, the optional extra ``recon[e57]``: read only.

Reading takes every scan of the file, each moved by its pose into the file's frame, and
concatenates them (float64 coordinates); ``intensity`` becomes a per-point attribute,
colours are kept (uint8), and the scan each point came from is the attribute ``scan``.
Each scan's pose gives a sensor (its translation is the scanner's position; a scan without
a pose was taken at the file's origin). Points flagged invalid (``cartesianInvalidState``)
or with a NaN coordinate are dropped and counted; a structured scan (``rowIndex`` and
``columnIndex``) keeps them as attributes and each point's pixel
(:class:`~recon_cli.geometry.PixelGrid`).
There is no writer: pye57 writes cartesian coordinates as float32, which would round
georeferenced clouds (0.25 m at y = 5e6).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import SCAN_ATTRIBUTE, PixelGrid, PointCloud, Sensor, drop_invalid
from recon_cli.io import text


def _pye57():
    try:
        import pye57
    except ModuleNotFoundError:
        raise ParameterError("E57 needs pye57: pip install 'recon[e57]'") from None
    return pye57


def decode_e57(data, where: str, path=None) -> tuple[PointCloud, dict]:
    """Decode an E57 file (pye57 reads from a path: bytes are put in a temporary file)."""
    pye57 = _pye57()
    tmp = None
    if path is None:
        fd, tmp = tempfile.mkstemp(suffix=".e57")
        with os.fdopen(fd, "wb") as f:
            f.write(text.as_uint8(data).data)
        path = tmp
    try:
        try:
            e = pye57.E57(str(path))
        except Exception as exc:  # libE57Format raises its own exception types
            raise InputError(
                "not a readable E57 file "
                f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})",
                where,
            ) from None
        try:
            scans = [_read_scan(e, k) for k in range(e.scan_count)]
        except InputError as exc:
            raise InputError(exc.message, where) from None
        except Exception as exc:
            raise InputError(
                "E57 scan could not be read "
                f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})",
                where,
            ) from None
        finally:
            e.close()
    finally:
        if tmp is not None:
            os.unlink(tmp)
    if not scans:
        raise InputError("E57 file holds no scan", where)
    pts = np.concatenate([sc["points"] for sc in scans])
    attributes = {}
    for key in ("intensity", "rowIndex", "columnIndex"):
        if all(sc[key] is not None for sc in scans):
            attributes[key] = np.concatenate([sc[key] for sc in scans])
    if len(scans) > 1:
        attributes[SCAN_ATTRIBUTE] = np.concatenate(
            [np.full(len(sc["points"]), k, np.int32) for k, sc in enumerate(scans)]
        )
    colors = (
        np.concatenate([sc["colors"] for sc in scans]).astype(np.uint8)
        if all(sc["colors"] is not None for sc in scans)
        else None
    )
    pixels = None
    if all(sc["grid"] is not None for sc in scans):
        shapes = tuple(sc["grid"][0] for sc in scans)
        starts = np.concatenate([[0], np.cumsum([h * w for h, w in shapes])])
        pixels = PixelGrid(
            shapes, np.concatenate([sc["grid"][1] + starts[k] for k, sc in enumerate(scans)])
        )
    cloud = PointCloud(
        points=pts,
        colors=colors,
        attributes=attributes,
        point_dtype=np.float64,
        sensors=[sc["sensor"] for sc in scans],
        pixels=pixels,
    )
    flagged = sum(sc["flagged"] for sc in scans)
    cloud = drop_invalid(cloud, where)
    cloud.invalid_dropped += flagged
    details = {
        "format": "e57",
        "scans": len(scans),
        "structured": [sc["grid"] is not None for sc in scans],
        "invalid_flagged": flagged,
    }
    return cloud, details


def _read_scan(e, k: int) -> dict:
    """One scan: points in the file's frame, its sensor, attributes, pixel grid, invalid count.

    The pixel grid may be None; the count is of the points its ``cartesianInvalidState`` (or
    spherical) flags as invalid.
    """
    header = e.get_header(k)
    fields = set(header.point_fields)
    has_i = "intensity" in fields
    has_c = {"colorRed", "colorGreen", "colorBlue"} <= fields
    has_rc = {"rowIndex", "columnIndex"} <= fields
    d = e.read_scan(k, intensity=has_i, colors=has_c, row_column=has_rc, ignore_missing_fields=True)
    pts = np.column_stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]]).astype(np.float64)
    # pye57 leaves out the points flagged invalid (no return, direction only): count them
    flagged = int(header.point_count) - len(pts)
    name = _scan_name(header)
    if header.has_pose():
        sensor = Sensor(
            position=tuple(np.asarray(header.translation, np.float64)),
            orientation=tuple(np.asarray(header.rotation, np.float64)),
            source=f"E57 scan {k}{name} pose",
        )
    else:  # no pose: the scan's own frame is the file's, its origin the scanner's
        sensor = Sensor(position=(0.0, 0.0, 0.0), source=f"E57 scan {k}{name} origin")
    grid = None
    if has_rc and len(pts):
        grid = _scan_grid(header, d["rowIndex"], d["columnIndex"])
    return {
        "points": pts,
        "intensity": d["intensity"] if has_i else None,
        "colors": np.column_stack([d["colorRed"], d["colorGreen"], d["colorBlue"]])
        if has_c
        else None,
        "rowIndex": d["rowIndex"] if has_rc else None,
        "columnIndex": d["columnIndex"] if has_rc else None,
        "sensor": sensor,
        "grid": grid,
        "flagged": flagged,
    }


def _scan_name(header) -> str:
    from pye57 import libe57

    try:
        name = str(header["name"].value())
    except libe57.E57Exception:  # the name is optional in E57
        return ""
    return f" {name!r}" if name else ""


def _scan_grid(header, rows: np.ndarray, cols: np.ndarray):
    """``((height, width), pixel)`` of a structured scan, or None when it is not a grid.

    Not a grid: one row or column, or two returns in one pixel.
    """
    from pye57 import libe57

    try:
        r0, r1 = int(header.rowMinimum), int(header.rowMaximum)
        c0, c1 = int(header.columnMinimum), int(header.columnMaximum)
    except libe57.E57Exception:  # the index bounds are optional: take the data's
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())
    r = rows.astype(np.int64) - r0
    c = cols.astype(np.int64) - c0
    h, w = r1 - r0 + 1, c1 - c0 + 1
    if h < 2 or w < 2 or r.min() < 0 or c.min() < 0 or r.max() >= h or c.max() >= w:
        return None
    pixel = r * w + c
    if len(np.unique(pixel)) != len(pixel):
        return None
    return (h, w), pixel


def read_e57(path: str | os.PathLike, data=None) -> PointCloud:
    """Every scan of the E57 file ``path`` in the file's frame, as one float64 cloud."""
    from recon_cli.io.ply import read_bytes

    if data is None and str(path) != "-":
        if not os.path.isfile(path):
            raise InputError("no such file", str(path))
        return decode_e57(None, str(path), path=str(path))[0]
    return decode_e57(read_bytes(path) if data is None else data, text.where_of(path))[0]
