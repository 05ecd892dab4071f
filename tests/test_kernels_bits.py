"""The bit-level intrinsics and the borrowed array view against plain Python on random data.

The bit-level intrinsics (recon_cli/_kernels/bits.py) and the borrowed array view
(recon_cli/_kernels/arrays.py) against plain Python on random data.
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit

from recon_cli._kernels.arrays import borrowed
from recon_cli._kernels.bits import ctz64, load_u64le


@njit
def _loads(buf, at):
    out = np.empty(len(at), np.uint64)
    for k in range(len(at)):
        out[k] = load_u64le(buf, at[k])
    return out


@njit
def _ctz(x):
    out = np.empty(len(x), np.uint64)
    for k in range(len(x)):
        out[k] = ctz64(x[k])
    return out


def test_load_u64le_reads_eight_bytes_at_any_offset_first_byte_lowest():
    """``load_u64le`` reads eight bytes little-endian at any offset, odd addresses too."""
    rng = np.random.default_rng(0)
    buf = rng.integers(0, 256, 4099, dtype=np.uint8)
    at = np.concatenate([np.arange(16), rng.integers(0, len(buf) - 8, 500), [len(buf) - 8]]).astype(
        np.int64
    )
    got = _loads(buf, at)
    raw = buf.tobytes()
    assert got.tolist() == [int.from_bytes(raw[a : a + 8], "little") for a in at.tolist()]
    view = buf[3:]  # a view starting at an odd address
    assert _loads(view, np.array([0, 1], np.int64)).tolist() == [
        int.from_bytes(raw[3 + a : 11 + a], "little") for a in (0, 1)
    ]


def test_ctz64_counts_trailing_zero_bits():
    """``ctz64`` counts the trailing zero bits, 64 for zero."""
    rng = np.random.default_rng(1)
    x = np.concatenate(
        [[0, 1, 2, 1 << 63], rng.integers(1, 1 << 62, 200) << rng.integers(0, 2, 200)]
    ).astype(np.uint64)
    want = [64 if v == 0 else (v & -v).bit_length() - 1 for v in x.tolist()]
    assert _ctz(x).tolist() == want


@njit(inline="always")
def _sum_inline(a, s, e):
    t = 0
    for i in range(s, e):
        t += a[i]
    return t


@njit
def _chunked_sum(a):
    b = borrowed(a)
    t = 0
    for s in range(0, len(b), 7):
        if b[s] % 2 == 0:  # branches around the inlined calls (where numba keeps its refcounting)
            t += _sum_inline(b, s, min(s + 7, len(b)))
        else:
            t += _sum_inline(b, s, min(s + 7, len(b))) + 0
    return t


def test_borrowed_view_reads_the_same_data_and_leaves_the_reference_count_alone():
    """A borrowed view reads the array's data and leaves its reference count as it was."""
    a = np.random.default_rng(2).integers(0, 1000, 10_001).astype(np.int64)
    before = sys.getrefcount(a)
    assert _chunked_sum(a) == int(a.sum())
    assert _chunked_sum(a[5:]) == int(a[5:].sum())
    assert sys.getrefcount(a) == before
