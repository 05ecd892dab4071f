"""PLY type names, their numpy equivalents, and the classes of a decoded file.

The scalar type names are the spec's and their sized aliases; a file decodes into a
:class:`PlyData` of :class:`PlyElement` rows of :class:`PlyProperty` columns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


@dataclass
class PlyProperty:
    """One property of an element: a scalar, or a list with a count type."""

    name: str
    dtype: str  # numpy type code without byte order, e.g. "f4"
    count_dtype: str | None = None  # set for list properties

    @property
    def is_list(self) -> bool:
        """Whether the property is a list (has a count type)."""
        return self.count_dtype is not None

    def header_line(self) -> str:
        """The property's line of a PLY header."""
        if self.is_list:
            return (
                f"property list {ply_name(np.dtype(self.count_dtype))} "
                f"{ply_name(np.dtype(self.dtype))} {self.name}"
            )
        return f"property {ply_name(np.dtype(self.dtype))} {self.name}"


@dataclass
class PlyElement:
    """An element of a PLY file and its data.

    ``data`` maps each property name to an array: ``(count,)`` for a scalar property;
    for a list property ``(count, k)`` when every row has ``k`` items, otherwise an
    object array of ``count`` 1-d arrays.
    """

    name: str
    count: int
    properties: list[PlyProperty] = field(default_factory=list)
    data: dict[str, np.ndarray] = field(default_factory=dict)
    raw: np.ndarray | None = field(
        default=None, repr=False
    )  # structured rows, when decoded as such


@dataclass
class PlyData:
    """A whole PLY file: format, comments, ``obj_info`` lines and elements in order."""

    format: str = "binary_little_endian"
    comments: list[str] = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)
    elements: list[PlyElement] = field(default_factory=list)
    nbytes: int = 0  # size of the file the elements were decoded from (0: built in memory)

    def element(self, name: str) -> PlyElement | None:
        """The element ``name`` (None when the file has none)."""
        for e in self.elements:
            if e.name == name:
                return e
        return None
