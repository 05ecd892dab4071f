"""Numba kernel of :mod:`recon_cli.stages.poisson.attributes`: the weighted vote per vertex."""

from __future__ import annotations

from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@njit(cache=True)
def weighted_mode(vals, w, out):
    """out[r] = the value of row ``r`` of ``vals`` (m, k) int64 with the largest summed weight.

    The weights are ``w`` (m, k); ties go to the smallest value.
    """
    m, k = vals.shape
    for r in range(m):
        best_v = vals[r, 0]
        best_s = -1.0
        for a in range(k):
            x = vals[r, a]
            seen = False
            for b in range(a):
                if vals[r, b] == x:
                    seen = True
                    break
            if seen:
                continue
            s = 0.0
            for b in range(a, k):
                if vals[r, b] == x:
                    s += w[r, b]
            if s > best_s or (s == best_s and x < best_v):
                best_v = x
                best_s = s
        out[r] = best_v
