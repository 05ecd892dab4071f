"""Kernel for PLY elements whose list lengths differ between rows (numba: a true loop)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _read_uint(raw, pos, size, big, signed):
    v = 0
    for b in range(size):
        byte = raw[pos + (b if big else size - 1 - b)]
        v = (v << 8) | byte
    if signed and size < 8 and v >= (1 << (8 * size - 1)):
        v -= 1 << (8 * size)
    return v


@njit(cache=True)
def scan_list_rows(raw, offset, count, layout, big):
    """Walk ``count`` rows from ``offset``; layout rows are (is_list, count size, item size, signed).

    Returns (starts (count, nprop), lens (count, nprop), end offset, error code:
    0 ok, 1 truncated, 2 negative length).
    """
    nprop = layout.shape[0]
    starts = np.zeros((count, nprop), np.int64)
    lens = np.zeros((count, nprop), np.int64)
    pos = offset
    n = raw.shape[0]
    for r in range(count):
        for j in range(nprop):
            starts[r, j] = pos
            if layout[j, 0] == 1:
                cs = layout[j, 1]
                if pos + cs > n:
                    return starts, lens, pos, 1
                k = _read_uint(raw, pos, cs, big, layout[j, 3] == 1)
                if k < 0:
                    return starts, lens, pos, 2
                lens[r, j] = k
                pos += cs + k * layout[j, 2]
            else:
                pos += layout[j, 2]
            if pos > n:
                return starts, lens, pos, 1
    return starts, lens, pos, 0


@njit(cache=True)
def gather_fields(flat, stride, offsets, size, big, out):
    """Read field values out of fixed-size rows into ``out`` ((n, k) unsigned ints of ``size`` bytes).

    ``flat`` is the rows' bytes (uint8); field j of row i starts at ``i * stride + offsets[j]``.
    Each value is assembled arithmetically from its bytes in the file's order (``big``),
    so the integer is right on any host; viewing ``out`` as the field's float or signed
    type then gives the value. One pass; unaligned strided numpy casts are far slower.
    """
    n = out.shape[0]
    k = offsets.shape[0]
    if size == 1:
        for i in range(n):
            for j in range(k):
                out[i, j] = flat[i * stride + offsets[j]]
        return
    if size == 4 and not big:  # the common case (float32 on a little-endian file), unrolled
        for i in range(n):
            base = i * stride
            for j in range(k):
                o = base + offsets[j]
                out[i, j] = (
                    np.uint32(flat[o])
                    | (np.uint32(flat[o + 1]) << np.uint32(8))
                    | (np.uint32(flat[o + 2]) << np.uint32(16))
                    | (np.uint32(flat[o + 3]) << np.uint32(24))
                )
        return
    for i in range(n):
        base = i * stride
        for j in range(k):
            o = base + offsets[j]
            v = np.uint64(0)
            for b in range(size):
                shift = 8 * (size - 1 - b) if big else 8 * b
                v |= np.uint64(flat[o + b]) << np.uint64(shift)
            out[i, j] = v
