"""Numba helpers on arrays: growable arrays, borrowed views, a binary search.

Arrays grow inside kernels (amortised doubling is the caller's choice of ``cap``); a borrowed
view of an array serves hot loops that pass it to inlined helpers; the binary search is no numpy
function (see :func:`lower_bound`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

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


@intrinsic
def borrowed(typingctx, arr):
    """The array ``arr`` without its reference count (same data, shape and strides, no owner).

    Every call of an ``inline="always"`` helper with an array argument makes numba take and
    drop a reference to the array (two atomic operations and two calls) where the helper is
    inlined; in a loop with branches numba's pruning keeps them, and they can cost more than
    the helper's work (a number's digits). Helpers given the borrowed view skip them (a null
    owner is a no-op). The view is valid while ``arr`` is alive, so only for use inside the
    kernel that has ``arr`` as an argument: never return it nor store it in a container.
    """
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):
        src = context.make_array(signature.args[0])(context, builder, args[0])
        out = context.make_array(signature.return_type)(context, builder)
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        out.parent = cgutils.get_null_value(out.parent.type)
        out.nitems = src.nitems
        out.itemsize = src.itemsize
        out.data = src.data
        out.shape = src.shape
        out.strides = src.strides
        return out._getvalue()

    return arr(arr), codegen


@njit(cache=True, inline="always")
def lower_bound(a, x, lo, hi):
    """First index ``i`` in ``[lo, hi)`` of sorted 1-d ``a`` with ``a[i] >= x`` (``hi`` if none).

    ``lo + np.searchsorted(a[lo:hi], x)``.
    """
    # written out: numba's np.searchsorted would import numba.np.arraymath (and scipy.linalg)
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo
