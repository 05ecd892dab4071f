"""Numba kernels of :mod:`recon_cli.stages.smooth`: Taubin's lambda|mu passes. They only compute."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory)


@njit(cache=True)
def _step(src, dst, ptr, nbr, moves, factor):
    """``dst = src + factor * (mean of the neighbours - src)`` on the moving vertices."""
    for i in range(src.shape[0]):
        s = ptr[i]
        e = ptr[i + 1]
        if not moves[i] or e == s:
            dst[i, 0] = src[i, 0]
            dst[i, 1] = src[i, 1]
            dst[i, 2] = src[i, 2]
            continue
        mx = 0.0
        my = 0.0
        mz = 0.0
        for j in range(s, e):
            w = nbr[j]
            mx += src[w, 0]
            my += src[w, 1]
            mz += src[w, 2]
        inv = 1.0 / (e - s)
        dst[i, 0] = src[i, 0] + factor * (mx * inv - src[i, 0])
        dst[i, 1] = src[i, 1] + factor * (my * inv - src[i, 1])
        dst[i, 2] = src[i, 2] + factor * (mz * inv - src[i, 2])


@njit(cache=True)
def taubin(pos, ptr, nbr, moves, lam, mu, iterations):
    """``iterations`` pairs of a shrinking step ``lam`` and an inflating step ``mu`` (< 0).

    ``pos`` (n, 3) float64 is smoothed in place with the umbrella (uniform) Laplacian over
    the neighbour lists ``nbr[ptr[i]:ptr[i + 1]]``; vertices with ``moves[i]`` False stay.
    """
    tmp = np.empty_like(pos)
    for _ in range(iterations):
        _step(pos, tmp, ptr, nbr, moves, lam)
        _step(tmp, pos, ptr, nbr, moves, mu)
