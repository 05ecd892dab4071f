"""The table of the decimal-to-binary conversion in :mod:`recon_cli.io._text_kernel`.

``POW5_128[2 * (q + 342)]`` and ``[... + 1]`` are the high and low 64 bits of 5**q for
q in -342..308, normalised so that bit 127 is set: truncated for q >= 0 and for q < 0 the
reciprocal 2**b // 5**-q plus one (so never below the true value), truncated to 128 bits,
as in Lemire's fast_float (computed here with Python integers, not transcribed).
"""

from __future__ import annotations

import numpy as np

SMALLEST_POWER = -342
LARGEST_POWER = 308


def _pow5_128() -> np.ndarray:
    out = []
    for q in range(SMALLEST_POWER, LARGEST_POWER + 1):
        if q < 0:
            p5 = 5**-q
            z = p5.bit_length()  # the smallest z with 2**z >= p5 (p5 is odd, never a power of two)
            c = (1 << (z + 127 if q >= -27 else 2 * z + 128)) // p5 + 1
            while c >= 1 << 128:
                c >>= 1
        else:
            c = 5**q
            while c < 1 << 127:
                c <<= 1
            while c >= 1 << 128:
                c >>= 1
        out += [c >> 64, c & ((1 << 64) - 1)]
    return np.array(out, dtype=np.uint64)


POW5_128 = _pow5_128()
