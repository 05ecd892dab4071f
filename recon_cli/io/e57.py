"""E57 (ASTM E2807) through pye57, the optional extra ``recon[e57]``: read only.

Reading takes every scan of the file, each moved by its pose into the file's frame, and
concatenates them (float64 coordinates); ``intensity`` becomes a per-point attribute,
colours are kept (uint8), and the scan each point came from is the attribute ``scan``.
There is no writer: pye57 writes cartesian coordinates as float32, which would round
georeferenced clouds (0.25 m at y = 5e6).
"""

from __future__ import annotations

import os
import tempfile
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud
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
        parts: list[np.ndarray] = []
        inten: list[Any] = []  # None for a scan without intensity
        cols: list[Any] = []  # None for a scan without colours
        scan: list[np.ndarray] = []
        try:
            for k in range(e.scan_count):
                header = e.get_header(k)
                fields = set(header.point_fields)
                has_i = "intensity" in fields
                has_c = {"colorRed", "colorGreen", "colorBlue"} <= fields
                d = e.read_scan(k, intensity=has_i, colors=has_c, ignore_missing_fields=True)
                pts = np.column_stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]]).astype(
                    np.float64
                )
                parts.append(pts)
                inten.append(d["intensity"] if has_i else None)
                cols.append(
                    np.column_stack([d["colorRed"], d["colorGreen"], d["colorBlue"]])
                    if has_c
                    else None
                )
                scan.append(np.full(len(pts), k, np.int32))
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
    if not parts:
        raise InputError("E57 file holds no scan", where)
    pts = np.concatenate(parts)
    text.check_finite(pts, where, "point")
    attributes: dict[str, np.ndarray] = {}
    if all(i is not None for i in inten):
        attributes["intensity"] = np.concatenate(inten)
    if len(parts) > 1:
        attributes["scan"] = np.concatenate(scan)
    colors = np.concatenate(cols).astype(np.uint8) if all(c is not None for c in cols) else None
    cloud = PointCloud(points=pts, colors=colors, attributes=attributes, point_dtype=np.float64)
    return cloud, {"format": "e57", "scans": len(parts)}


def read_e57(path: str | os.PathLike, data=None) -> PointCloud:
    """Every scan of the E57 file ``path`` in the file's frame, as one float64 cloud."""
    from recon_cli.io.ply import read_bytes

    if data is None and str(path) != "-":
        if not os.path.isfile(path):
            raise InputError("no such file", str(path))
        return decode_e57(None, str(path), path=str(path))[0]
    return decode_e57(read_bytes(path) if data is None else data, text.where_of(path))[0]
