"""Open-addressing hash tables of non-negative int64 keys, for numba kernels.

A table is an array ``tk`` of keys (``-1`` = empty slot) of power-of-two capacity
``1 << bits``, usually with a parallel array ``tv`` of int64 values. Keys are placed by
Fibonacci hashing (multiply by 2**64 / golden ratio, keep the top ``bits`` bits) and
linear probing. A table is kept at most half full (:func:`table_bits`).

References
----------
Knuth, *The Art of Computer Programming*, vol. 3, §6.4 (multiplicative hashing, linear probing).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)

MULT = np.uint64(11400714819323198485)  # 2**64 / golden ratio (Fibonacci hashing)


@njit(cache=True, inline="always")
def home_slot(key, bits):
    """The slot where probing for ``key`` starts."""
    return np.int64((np.uint64(key) * MULT) >> np.uint64(64 - bits))


@njit(cache=True, inline="always")
def probe(tk, bits, key):
    """The slot holding ``key``, or the empty slot where it would be inserted."""
    mask = (1 << bits) - 1
    s = home_slot(key, bits)
    while tk[s] != -1 and tk[s] != key:
        s = (s + 1) & mask
    return s


@njit(cache=True)
def table_bits(n):
    """log2 of a capacity that keeps ``n`` keys at most half the table (at least 16 slots)."""
    bits = 4
    while (1 << bits) < 2 * n + 16:
        bits += 1
    return bits


@njit(cache=True)
def build_table(keys):
    """Hash table of unique ``keys`` -> their index: ``(tk, tv, bits)``."""
    bits = table_bits(len(keys))
    cap = 1 << bits
    tk = np.full(cap, -1, np.int64)
    tv = np.empty(cap, np.int64)
    for i in range(len(keys)):
        s = probe(tk, bits, keys[i])
        tk[s] = keys[i]
        tv[s] = i
    return tk, tv, bits


@njit(cache=True, inline="always")
def lookup(tk, tv, bits, key):
    """The value of ``key``, or -1 when absent."""
    s = probe(tk, bits, key)
    return tv[s] if tk[s] == key else -1
