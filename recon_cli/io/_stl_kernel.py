"""Kernels of the STL reader: welding corners with identical coordinates, and the ASCII body."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli.io._text_kernel import parse_float, skip_blank, token_end

_MULT = np.uint64(11400714819323198485)


@njit(cache=True)
def weld_exact(bits):
    """Merge the equal rows of ``bits``, the coordinates' bit patterns ((n, 3) uint32 or uint64).

    Returns ``(unique row of each input row, index of
    the first input row of each unique row)``, unique rows numbered in order of first appearance.
    """
    n = bits.shape[0]
    cap = 16
    while cap < 2 * n + 16:
        cap *= 2
    mask = cap - 1
    table = np.full(cap, -1, np.int64)
    inverse = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    nu = 0
    for i in range(n):
        h = np.uint64(bits[i, 0])
        h = (h * _MULT) ^ np.uint64(bits[i, 1])
        h = (h * _MULT) ^ np.uint64(bits[i, 2])
        h = h * _MULT
        s = np.int64(h >> np.uint64(40)) & mask
        while True:
            j = table[s]
            if j == -1:
                table[s] = nu
                first[nu] = i
                inverse[i] = nu
                nu += 1
                break
            r = first[j]
            if bits[r, 0] == bits[i, 0] and bits[r, 1] == bits[i, 1] and bits[r, 2] == bits[i, 2]:
                inverse[i] = j
                break
            s = (s + 1) & mask
    return inverse, first[:nu].copy()


_FACET = np.frombuffer(b"facet", np.uint8).copy()
_NORMAL = np.frombuffer(b"normal", np.uint8).copy()
_OUTER = np.frombuffer(b"outer", np.uint8).copy()
_LOOP = np.frombuffer(b"loop", np.uint8).copy()
_VERTEX = np.frombuffer(b"vertex", np.uint8).copy()
_ENDLOOP = np.frombuffer(b"endloop", np.uint8).copy()
_ENDFACET = np.frombuffer(b"endfacet", np.uint8).copy()
_SOLID = np.frombuffer(b"solid", np.uint8).copy()
_ENDSOLID = np.frombuffer(b"endsolid", np.uint8).copy()


@njit(cache=True)
def _word(buf, s, e, w):
    if e - s != len(w):
        return False
    for k in range(e - s):
        if buf[s + k] != w[k]:
            return False
    return True


@njit(cache=True)
def ascii_walk(buf, corners, slow, fill):
    """Walk an ASCII STL body.

    With ``fill`` false, count; else fill ``corners`` ((3 m, 3) float64, NaN where slow) and
    ``slow`` ((k, 3): flat index, byte start, byte end).

    Returns ``(facets, slow count, error, byte)``; error 1 = unexpected word, 2 = a number is
    malformed, 3 = a facet without three vertices, 4 = the file ends inside a facet.
    """
    n = len(buf)
    i = 0
    state = 0  # 0 outside a solid, 1 in a solid, 2 in a facet (expecting outer loop), 3 in a loop
    nfacet = 0
    nvert = 0  # vertices of the current facet
    nc = 0
    ns = 0
    while True:
        i = skip_blank(buf, i, n)
        if i >= n:
            break
        e = token_end(buf, i, n)
        if state == 0:
            if not _word(buf, i, e, _SOLID):
                return nfacet, ns, 1, i
            # the solid's name: the rest of the line
            while e < n and buf[e] != 10:
                e += 1
            state = 1
        elif state == 1:
            if _word(buf, i, e, _FACET):
                j = skip_blank(buf, e, n)
                k = token_end(buf, j, n)
                if not _word(buf, j, k, _NORMAL):
                    return nfacet, ns, 1, j
                e = k
                for _ in range(3):
                    j = skip_blank(buf, e, n)
                    k = token_end(buf, j, n)
                    _v, st = parse_float(buf, j, k)
                    if st == 0:
                        return nfacet, ns, 2, j
                    e = k
                state = 2
                nvert = 0
            elif _word(buf, i, e, _ENDSOLID):
                while e < n and buf[e] != 10:
                    e += 1
                state = 0
            else:
                return nfacet, ns, 1, i
        elif state == 2:
            if not _word(buf, i, e, _OUTER):
                return nfacet, ns, 1, i
            j = skip_blank(buf, e, n)
            k = token_end(buf, j, n)
            if not _word(buf, j, k, _LOOP):
                return nfacet, ns, 1, j
            e = k
            state = 3
        else:
            if _word(buf, i, e, _VERTEX):
                if nvert == 3:
                    return nfacet, ns, 3, i
                for c in range(3):
                    j = skip_blank(buf, e, n)
                    k = token_end(buf, j, n)
                    v, st = parse_float(buf, j, k)
                    if st == 0:
                        return nfacet, ns, 2, j
                    if fill:
                        if st == 2:
                            slow[ns, 0] = nc * 3 + c
                            slow[ns, 1] = j
                            slow[ns, 2] = k
                            v = np.nan
                        corners[nc, c] = v
                    if st == 2:
                        ns += 1
                    e = k
                nc += 1
                nvert += 1
            elif _word(buf, i, e, _ENDLOOP):
                if nvert != 3:
                    return nfacet, ns, 3, i
                j = skip_blank(buf, e, n)
                k = token_end(buf, j, n)
                if not _word(buf, j, k, _ENDFACET):
                    return nfacet, ns, 1, j
                e = k
                nfacet += 1
                state = 1
            else:
                return nfacet, ns, 1, i
        i = e
    if state >= 2:
        return nfacet, ns, 4, n
    return nfacet, ns, 0, 0
