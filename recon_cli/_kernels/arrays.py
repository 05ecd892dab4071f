"""Arrays that grow inside numba kernels (amortised doubling is the caller's choice of ``cap``)."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@njit(cache=True)
def grow1(x, cap):
    """A copy of 1-d ``x`` with capacity ``cap`` (the tail uninitialised)."""
    y = np.empty(cap, x.dtype)
    y[: x.shape[0]] = x
    return y


@njit(cache=True)
def grow2(x, cap):
    """A copy of 2-d ``x`` with ``cap`` rows (the tail uninitialised)."""
    y = np.empty((cap, x.shape[1]), x.dtype)
    y[: x.shape[0]] = x
    return y


@njit(cache=True)
def lower_bound(a, x):
    """First index ``i`` of sorted 1-d ``a`` with ``a[i] >= x`` (``len(a)`` if none): ``np.searchsorted(a, x)``.

    Written out because numba's ``np.searchsorted`` lives in ``numba.np.arraymath``: a kernel
    calling it makes every process that loads the kernel import that module (and scipy.linalg,
    numba's BLAS check), ~0.2 CPU s.
    """
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo
