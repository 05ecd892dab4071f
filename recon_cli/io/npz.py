"""The grid file format (``.npz``): :class:`recon_cli.grid.Grid` on disk.

Format (``numpy.savez``, uncompressed):

``sdf``
    float32, shape (nx, ny, nz); negative inside, NaN where unknown.
``origin``
    float64 (3,): xyz of sample [0, 0, 0].
``voxel_size``
    float64 scalar: spacing of samples along every axis.
``provenance``
    str: history lines joined by newlines (oldest first).
``point_dtype`` (optional)
    str, ``float32`` or ``float64``: the float type of the source's coordinates, which
    meshes extracted from the grid are written with (float32 when absent).
"""

from __future__ import annotations

import io
import os
import zipfile

import numpy as np

from recon_cli.errors import InputError
from recon_cli.grid import Grid
from recon_cli.io.atomic import write_bytes
from recon_cli.io.ply import read_bytes

# the date of every member of a grid file (zip's earliest): no clock in the bytes
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def is_npz(data: bytes | np.ndarray) -> bool:
    """True when ``data`` starts like a zip archive (``.npz``)."""
    return bytes(data[:4]) == b"PK\x03\x04"


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """The bytes of ``numpy.savez(**arrays)``, but the same arrays give the same bytes.

    numpy dates each member with the clock; here every member is dated 1980-01-01 (zip's
    earliest date), so two runs' files are equal.
    """
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)
    return buf.getvalue()


def grid_bytes(grid: Grid) -> bytes:
    """``grid`` as the bytes of its ``.npz`` file."""
    return npz_bytes(
        {
            "sdf": grid.sdf.astype(np.float32),
            "origin": np.asarray(grid.origin),
            "voxel_size": np.float64(grid.voxel_size),
            "provenance": np.array("\n".join(grid.history)),
            "point_dtype": np.array(np.dtype(grid.point_dtype).name),
        }
    )


def read_grid(path: str | os.PathLike, data: bytes | np.ndarray | None = None) -> Grid:
    """Read a grid ``.npz`` (``-``: standard input).

    Every array's header is checked before its data is read: ``sdf`` a 3-d float array
    with at least one sample and no more than the file holds or memory can take,
    ``origin`` three finite numbers, ``voxel_size`` one finite positive number. The CRC of
    every member read is checked (as ``numpy.load`` does).

    A regular file whose ``sdf`` member is stored uncompressed (what :func:`write_grid` and
    ``numpy.savez`` write) is read straight from the file into the array (one copy, no
    whole-file buffer); a compressed member, standard input and ``data`` go through
    ``numpy.load``.

    Raises
    ------
    InputError
        Not an npz, missing arrays, wrong shapes or types, non-finite frame, a claimed
        size the file does not hold or the memory cannot take, a CRC mismatch.
    """
    where = "<stdin>" if str(path) == "-" else str(path)
    if data is None and str(path) != "-" and os.path.isfile(path):
        try:
            with open(path, "rb") as fh:
                if fh.read(4) != b"PK\x03\x04":
                    raise InputError("not a grid .npz file", where)
                fh.seek(0)
                return _read_grid(fh, where, fh)
        except PermissionError:
            raise InputError("permission denied", where) from None
    buf = read_bytes(path) if data is None else data
    if not is_npz(buf):
        raise InputError("not a grid .npz file", where)
    return _read_grid(io.BytesIO(buf if isinstance(buf, bytes) else buf.data), where, None)


def _read_grid(source, where: str, fh) -> Grid:
    """The grid in the zip archive ``source`` (a binary file object).

    ``fh``: the same object when it is a real file whose stored ``sdf`` member can be read into the
    array directly.
    """
    from recon_cli.grid import allocation_problem

    try:
        with zipfile.ZipFile(source) as zf:
            members = {n[:-4]: n for n in zf.namelist() if n.endswith(".npy")}
            missing = [k for k in ("sdf", "origin", "voxel_size") if k not in members]
            if missing:
                raise InputError(f"grid file lacks {missing[0]!r}", where)
            heads = {k: _npy_header(zf, members[k]) for k in ("sdf", "origin", "voxel_size")}
            shape, dtype, room = heads["sdf"]
            if len(shape) != 3 or dtype.kind != "f":
                dims = " x ".join(map(str, shape))
                raise InputError(
                    f"'sdf' must be a 3-d float array, got {dtype} of shape ({dims})", where
                )
            if min(shape) == 0:
                raise InputError(
                    f"the grid has no samples (shape {' x '.join(map(str, shape))})", where
                )
            for k, (shp, dt, rm) in heads.items():
                if dt.kind not in "fiu" or dt.hasobject:
                    raise InputError(f"{k!r} must be numeric, got {dt}", where)
                if _count(shp) * dt.itemsize > rm:
                    raise InputError(
                        f"{k!r} claims {' x '.join(map(str, shp))} values but the file is shorter",
                        where,
                    )
            if heads["origin"][0] != (3,) or heads["voxel_size"][0] not in ((), (1,)):
                raise InputError("'origin' must have 3 values and 'voxel_size' one", where)
            problem = allocation_problem(
                shape, dtype.itemsize + 8
            )  # the array, its float32 copy, a mask
            if problem:
                raise InputError(f"{problem}: not read", where)
            sdf = None
            if fh is not None and zf.getinfo(members["sdf"]).compress_type == zipfile.ZIP_STORED:
                sdf = _read_stored(fh, zf.getinfo(members["sdf"]), where)
            source.seek(0)
            with np.load(source, allow_pickle=False) as z:
                if sdf is None:
                    sdf = z["sdf"]
                origin = z["origin"].astype(np.float64)
                voxel = float(z["voxel_size"].reshape(-1)[0])
                prov = str(z["provenance"]) if "provenance" in z.files else ""
                pdt = str(z["point_dtype"]) if "point_dtype" in z.files else "float32"
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        raise InputError(f"corrupt grid file ({exc})", where) from None
    if not np.isfinite(origin).all():
        raise InputError(f"'origin' must be finite, got {origin.tolist()}", where)
    if not (np.isfinite(voxel) and voxel > 0):
        raise InputError(f"'voxel_size' must be a finite positive number, got {voxel}", where)
    if pdt not in ("float32", "float64"):
        raise InputError(f"'point_dtype' must be float32 or float64, got {pdt[:40]!r}", where)
    return Grid(
        sdf=sdf,
        origin=origin,
        voxel_size=voxel,
        history=[s for s in prov.split("\n") if s],
        point_dtype=pdt,
    )


def _read_stored(fh, info: zipfile.ZipInfo, where: str) -> np.ndarray:
    """The array of the uncompressed ``.npy`` member ``info`` of the zip file ``fh``.

    It is read into its own (aligned, writable) memory with ``readinto``; CRC checked.
    """
    import struct
    import zlib

    from numpy.lib import format as npy

    fh.seek(info.header_offset)
    local = fh.read(30)  # the local file header; the name and an extra field follow
    if len(local) != 30 or local[:4] != b"PK\x03\x04":
        raise InputError("corrupt grid file (bad local header of 'sdf')", where)
    name_len, extra_len = struct.unpack("<HH", local[26:30])
    start = info.header_offset + 30 + name_len + extra_len
    fh.seek(start)
    version = npy.read_magic(fh)
    shape, fortran, dtype = (
        npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
    )(fh)
    head_len = fh.tell() - start
    fh.seek(start)
    crc = zlib.crc32(fh.read(head_len))
    arr = np.empty(shape, dtype=dtype, order="F" if fortran else "C")
    raw = arr.reshape(-1, order="A").data.cast("B") if arr.size else memoryview(b"")
    got = 0
    while got < raw.nbytes:
        k = fh.readinto(raw[got:])
        if not k:
            raise InputError("corrupt grid file ('sdf' is shorter than its header says)", where)
        got += k
    crc = zlib.crc32(raw, crc)
    if head_len + raw.nbytes != info.file_size or crc != info.CRC:
        raise InputError("corrupt grid file (CRC check of 'sdf' failed)", where)
    return arr


def _count(shape: tuple) -> int:
    n = 1
    for s in shape:
        n *= int(s)
    return n


def _npy_header(zf: zipfile.ZipFile, name: str) -> tuple[tuple, np.dtype, int]:
    """(shape, dtype, data bytes the member holds) of one ``.npy`` member, from its header only."""
    from numpy.lib import format as npy

    size = zf.getinfo(name).file_size
    with zf.open(name) as fh:
        version = npy.read_magic(fh)
        read = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, _, dtype = read(fh)
        return tuple(shape), dtype, size - fh.tell()


def grid_shape(path: str | os.PathLike) -> tuple[int, ...]:
    """The shape of a grid file's ``sdf`` array, from its header alone (the values not read).

    Raises
    ------
    InputError
        The header claims more values than the file holds (as :func:`read_grid` says it).
    """
    with zipfile.ZipFile(path) as zf:
        name = next(n for n in zf.namelist() if n == "sdf.npy")
        shape, dtype, left = _npy_header(zf, name)
    if _count(shape) * dtype.itemsize > left:
        dims = " x ".join(map(str, shape))
        raise InputError(f"'sdf' claims {dims} values but the file is shorter", os.fspath(path))
    return tuple(int(k) for k in shape)


def write_grid(grid: Grid, path: str | os.PathLike) -> None:
    """Write ``grid`` atomically (``-``: standard output)."""
    write_bytes(path, grid_bytes(grid))
