"""File input and output: PLY (our own reader/writer), SDF grids (.npz), atomic writes."""

from recon_cli.io.atomic import atomic_open, write_bytes
from recon_cli.io.ply import PlyData, PlyElement, PlyProperty, parse_ply, read_ply, serialize_ply, write_ply

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
