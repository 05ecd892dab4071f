"""Kernels for PLY bodies: rows with varying list lengths, and field gathers out of packed rows."""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit
from numba.core import types
from numba.extending import intrinsic

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@intrinsic
def _f32_from_bits(typingctx, bits):
    """The float32 whose bits are the low 32 bits of the integer ``bits`` (no conversion)."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        low = builder.trunc(args[0], ir.IntType(32)) if bits.bitwidth > 32 else args[0]
        return builder.bitcast(low, ir.FloatType())

    return types.float32(bits), codegen


@intrinsic
def _f64_from_bits(typingctx, bits):
    """The float64 whose bits are the 64-bit integer ``bits``."""
    if not isinstance(bits, types.Integer) or bits.bitwidth != 64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(bits), codegen


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
    """Walk ``count`` rows from ``offset``; layout rows: (is_list, count size, item size, signed).

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


@njit(cache=True, nogil=True)
def gather_fields(flat, stride, offsets, size, big, out):
    """Read field values out of fixed-size rows into ``out``: (n, k) unsigned, ``size`` bytes.

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


@njit(cache=True, nogil=True)
def gather_floats(flat, stride, offsets, size, big, out):
    """Read float fields (``size`` 4 or 8 bytes) of fixed-size rows into float64 ``out`` (n, k).

    For float columns that cannot be viewed in place (big-endian files, fields not adjacent,
    mixed float types); each value is decoded by :func:`_load_float`. Rows are unaligned in
    general (a 27-byte xyz+normal+rgb row), which is why this does not view the buffer as
    floats.
    """
    n = out.shape[0]
    k = offsets.shape[0]
    uoff = offsets.astype(np.uint64)
    ustride = np.uint64(stride)
    for i in range(n):
        base = np.uint64(i) * ustride
        for j in range(k):
            out[i, j] = _load_float(flat, base + uoff[j], size, big)


@njit(cache=True, nogil=True)
def gather_bytes(flat, stride, offsets, out):
    """One-byte fields (colours) out of fixed-size rows into ``out`` (n, k) uint8/int8."""
    n = out.shape[0]
    k = offsets.shape[0]
    uoff = offsets.astype(np.uint64)
    ustride = np.uint64(stride)
    for i in range(n):
        base = np.uint64(i) * ustride
        for j in range(k):
            out[i, j] = flat[base + uoff[j]]


@njit(cache=True, inline="always")
def _load_bits32(flat, o, big):
    """The 4 bytes at byte ``o`` (unsigned) of ``flat`` as a uint32, in byte order ``big``.

    Unsigned positions let numba skip its negative-index wraparound, so LLVM combines the
    byte loads into one.
    """
    if big:
        return (
            (np.uint32(flat[o]) << np.uint32(24))
            | (np.uint32(flat[o + np.uint64(1)]) << np.uint32(16))
            | (np.uint32(flat[o + np.uint64(2)]) << np.uint32(8))
            | np.uint32(flat[o + np.uint64(3)])
        )
    return (
        np.uint32(flat[o])
        | (np.uint32(flat[o + np.uint64(1)]) << np.uint32(8))
        | (np.uint32(flat[o + np.uint64(2)]) << np.uint32(16))
        | (np.uint32(flat[o + np.uint64(3)]) << np.uint32(24))
    )


@njit(cache=True, inline="always")
def _load_bits64(flat, o, big):
    """The 8 bytes at byte ``o`` (unsigned) of ``flat`` as a uint64, in byte order ``big``."""
    u = np.uint64(0)
    for b in range(8):
        shift = 8 * (7 - b) if big else 8 * b
        u |= np.uint64(flat[o + np.uint64(b)]) << np.uint64(shift)
    return u


@njit(cache=True, inline="always")
def _load_float(flat, o, size, big):
    """The float (``size`` 4 or 8 bytes, order ``big``) at byte ``o`` of ``flat``, as float64."""
    if size == 4:
        return np.float64(_f32_from_bits(_load_bits32(flat, o, big)))
    return _f64_from_bits(_load_bits64(flat, o, big))


@njit(cache=True, inline="always")
def _is_nonfinite(flat, o, size, big):
    """Whether the float (``size`` 4 or 8 bytes) at byte ``o`` of ``flat`` is NaN or infinite.

    Its exponent bits are all ones (tested on the integer, no float conversion).
    """
    if size == 4:
        return (_load_bits32(flat, o, big) & np.uint32(0x7F800000)) == np.uint32(0x7F800000)
    e = np.uint64(0x7FF0000000000000)
    return (_load_bits64(flat, o, big) & e) == e


@njit(cache=True, nogil=True)
def first_nonfinite_row(flat, stride, first, k, size, big):
    """Index of the first row whose ``k`` floats hold a NaN or infinity; -1 when none does.

    The floats have ``size`` 4 or 8 bytes, from byte ``first`` of each ``stride``-byte row of
    ``flat``.

    Rows are unaligned in general, hence the byte loads. Blocks of rows are tested without
    a branch per row; a block that has a bad value is scanned again for it.
    """
    n = flat.shape[0] // stride
    ustride = np.uint64(stride)
    block = 2048
    for lo in range(0, n, block):
        hi = min(n, lo + block)
        bad = False
        for i in range(lo, hi):
            base = np.uint64(i) * ustride + np.uint64(first)
            for j in range(k):
                bad |= _is_nonfinite(flat, base + np.uint64(j * size), size, big)
        if bad:
            for i in range(lo, hi):
                base = np.uint64(i) * ustride + np.uint64(first)
                for j in range(k):
                    if _is_nonfinite(flat, base + np.uint64(j * size), size, big):
                        return i
    return -1


@njit(cache=True, nogil=True)
def ascii_line_tokens(body):
    r"""Number of whitespace-separated tokens on each line of ``body`` (uint8), one int64 a line.

    Counted as ``bytes.split`` counts them; lines end at ``\n``, ``\r\n`` or a lone ``\r``.
    """
    n = body.shape[0]
    lines = 1
    for i in range(n):
        c = body[i]
        if c == 10 or (c == 13 and (i + 1 >= n or body[i + 1] != 10)):
            lines += 1
    out = np.zeros(lines, np.int64)
    line = 0
    in_token = False
    for i in range(n):
        c = body[i]
        space = c == 32 or (9 <= c <= 13)
        if not space:
            if not in_token:
                out[line] += 1
            in_token = True
        else:
            in_token = False
            if c == 10 or (c == 13 and (i + 1 >= n or body[i + 1] != 10)):
                line += 1
    return out
