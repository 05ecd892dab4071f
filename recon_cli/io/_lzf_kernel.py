"""LZF compression (as in PCD ``binary_compressed``): a bounds-checked decoder and an encoder.

A stream is a sequence of runs, each starting with a control byte ``c``: ``c < 32`` is a
literal run of ``c + 1`` bytes; otherwise a back-reference of length ``(c >> 5) + 2`` (when
``c >> 5 == 7`` the next byte adds to the length) to ``((c & 31) << 8 | next byte) + 1``
bytes back in the output.

References
----------
M. Lehmann, liblzf 3.6 (``lzf_c.c`` / ``lzf_d.c``): the format; this is our own code.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)


@njit(cache=True)
def lzf_decompress(src, out):
    """Decode ``src`` (uint8) into ``out`` (uint8, of the expected size).

    Returns the number of bytes written, or ``-1 - i`` when the stream is malformed at input
    byte ``i`` (a run that overruns the input or the output, or reaches before its start).
    """
    i = 0
    o = 0
    n = len(src)
    m = len(out)
    while i < n:
        c = np.int64(src[i])
        start = i
        i += 1
        if c < 32:
            k = c + 1
            if i + k > n or o + k > m:
                return -1 - start
            out[o : o + k] = src[i : i + k]
            i += k
            o += k
        else:
            k = c >> 5
            if k == 7:
                if i >= n:
                    return -1 - start
                k += np.int64(src[i])
                i += 1
            if i >= n:
                return -1 - start
            ref = o - ((c & 31) << 8) - np.int64(src[i]) - 1
            i += 1
            k += 2
            if ref < 0 or o + k > m:
                return -1 - start
            for t in range(k):  # may overlap: byte by byte
                out[o + t] = out[ref + t]
            o += k
    return o


@njit(cache=True)
def lzf_compress(src):
    """Encode ``src`` (uint8); returns the compressed bytes (uint8)."""
    n = len(src)
    out = np.empty(n + n // 32 + 16, np.uint8)
    hbits = 16
    table = np.full(1 << hbits, -1, np.int64)
    o = 0
    lit_start = 0  # first byte of the pending literal run
    i = 0
    while i + 2 < n:
        h = (
            (np.int64(src[i]) << 16) | (np.int64(src[i + 1]) << 8) | np.int64(src[i + 2])
        ) * 2654435761
        h = (h >> 8) & ((1 << hbits) - 1)
        ref = table[h]
        table[h] = i
        off = i - ref - 1
        if (
            ref >= 0
            and off < 8192
            and src[ref] == src[i]
            and src[ref + 1] == src[i + 1]
            and src[ref + 2] == src[i + 2]
        ):
            k = 3
            maxk = min(264, n - i)
            while k < maxk and src[ref + k] == src[i + k]:
                k += 1
            # flush the literal run, 32 bytes at most per control byte
            p = lit_start
            while p < i:
                r = min(32, i - p)
                out[o] = r - 1
                out[o + 1 : o + 1 + r] = src[p : p + r]
                o += 1 + r
                p += r
            L = k - 2
            if L < 7:
                out[o] = (L << 5) | (off >> 8)
                o += 1
            else:
                out[o] = (7 << 5) | (off >> 8)
                out[o + 1] = L - 7
                o += 2
            out[o] = off & 255
            o += 1
            i += k
            lit_start = i
        else:
            i += 1
    p = lit_start
    while p < n:
        r = min(32, n - p)
        out[o] = r - 1
        out[o + 1 : o + 1 + r] = src[p : p + r]
        o += 1 + r
        p += r
    return out[:o].copy()
