"""PLY scalar type names (the spec's and their sized aliases) and numpy equivalents."""

from __future__ import annotations

import numpy as np

# name in a PLY header -> numpy type code (without byte order)
PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "uchar": "u1",
    "short": "i2",
    "ushort": "u2",
    "int": "i4",
    "uint": "u4",
    "float": "f4",
    "double": "f8",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "float32": "f4",
    "float64": "f8",
}

# numpy type code -> canonical name we write
NUMPY_TO_PLY: dict[str, str] = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}

FORMATS: dict[str, str] = {
    "ascii": "",
    "binary_little_endian": "<",
    "binary_big_endian": ">",
}


def ply_name(dtype: np.dtype) -> str:
    """The PLY type name for a numpy dtype (bool as uchar, int64 as int, ...)."""
    dtype = np.dtype(dtype)
    if dtype.kind == "b":
        return "uchar"
    code = f"{dtype.kind}{dtype.itemsize}"
    if code in NUMPY_TO_PLY:
        return NUMPY_TO_PLY[code]
    if dtype.kind == "i":
        return "int"
    if dtype.kind == "u":
        return "uint"
    if dtype.kind == "f":
        return "double"
    raise TypeError(f"no PLY type for numpy dtype {dtype}")
