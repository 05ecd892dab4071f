"""File input and output; :mod:`recon_cli.io.load` picks the format by suffix.

PLY, OBJ, OFF, STL, XYZ/CSV, PCD (our own readers and writers), LAS/LAZ (laspy), E57 (pye57,
read only), SDF grids (.npz), atomic writes.
"""

from recon_cli.io.atomic import atomic_open, write_bytes
from recon_cli.io.ply import (
    PlyData,
    PlyElement,
    PlyProperty,
    parse_ply,
    read_ply,
    serialize_ply,
    write_ply,
)

__all__ = [
    "atomic_open",
    "write_bytes",
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "parse_ply",
    "serialize_ply",
    "read_ply",
    "write_ply",
]
