"""Disjoint-set forests in int arrays (``parent[x] == x`` at a root), for numba kernels.

References
----------
Tarjan & van Leeuwen, "Worst-case analysis of set union algorithms", J. ACM 31(2), 1984
(path halving).
"""

from __future__ import annotations

from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@njit(cache=True)
def find(parent, x):
    """Root of ``x``, halving the path on the way."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


@njit(cache=True)
def union_min(parent, a, b):
    """Join the sets of ``a`` and ``b``; the smaller root index becomes the root."""
    ra = find(parent, a)
    rb = find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb
