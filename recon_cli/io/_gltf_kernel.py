"""Kernels of the glTF writer: one pass over the coordinates for what numpy needs several for."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)


@njit(cache=True, nogil=True)
def bounds(v, lo, hi):
    """Column bounds of ``v`` ((n, 3) float32 or float64) into ``lo``, ``hi`` (float64 (3,)).

    Returns -1, or the first row with a NaN or infinite value (the bounds are then partial).
    """
    for k in range(3):
        lo[k] = np.inf
        hi[k] = -np.inf
    for i in range(v.shape[0]):
        for k in range(3):
            x = np.float64(v[i, k])
            if not np.isfinite(x):
                return i
            lo[k] = min(lo[k], x)
            hi[k] = max(hi[k], x)
    return -1


@njit(cache=True, nogil=True)
def all_float32(v):
    """Whether every value of the float64 array ``v`` ((n, 3)) is a float32 value."""
    for i in range(v.shape[0]):
        for k in range(3):
            if np.float64(np.float32(v[i, k])) != v[i, k]:
                return False
    return True


@njit(cache=True, nogil=True)
def float32_offsets(v, origin, out, lo, hi):
    """``out = float32(v - origin)`` ((n, 3)); its column bounds into ``lo``, ``hi`` (float32 (3,)).

    Returns the largest ``|float64(out) + origin - v|``: how far a reader that adds the
    origin back in float64 finds any coordinate from ``v`` (inf when ``out`` overflows).
    """
    err = 0.0
    for k in range(3):
        lo[k] = np.inf
        hi[k] = -np.inf
    for i in range(v.shape[0]):
        for k in range(3):
            f = np.float32(v[i, k] - origin[k])
            out[i, k] = f
            e = abs((np.float64(f) + origin[k]) - v[i, k])  # inf when f overflowed
            err = max(err, e)
            lo[k] = min(lo[k], f)
            hi[k] = max(hi[k], f)
    return err


@njit(cache=True, nogil=True)
def unit_vectors(n, out):
    """``out = float32(n / |n|)`` for the rows of ``n`` ((k, 3) float32 or float64).

    Returns ``(first row of zero or non-finite length or -1, largest |length - 1|)``.
    """
    worst = 0.0
    for i in range(n.shape[0]):
        x, y, z = np.float64(n[i, 0]), np.float64(n[i, 1]), np.float64(n[i, 2])
        length = np.sqrt(x * x + y * y + z * z)
        if not (length > 0 and np.isfinite(length)):
            return i, worst
        worst = max(worst, abs(length - 1.0))
        out[i, 0] = np.float32(x / length)
        out[i, 1] = np.float32(y / length)
        out[i, 2] = np.float32(z / length)
    return -1, worst
