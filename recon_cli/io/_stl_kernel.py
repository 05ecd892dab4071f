"""Kernels of the STL reader: welding corners with identical coordinates, and the ASCII body."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli.io._text_kernel import line_end, parse_float, skip_blank, token_end

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
def _next_word(buf, e, n, w):
    """Whether the token after byte ``e`` is the word ``w``: ``(ok, its start, its end)``."""
    j = skip_blank(buf, e, n)
    k = token_end(buf, j, n)
    return _word(buf, j, k, w), j, k


@njit(cache=True)
def _facet_normal(buf, e, n):
    """Check ``normal nx ny nz`` after ``facet`` (the normal is recomputed, not kept).

    ``(error, byte, end)``: error 1 = not ``normal``, 2 = a malformed number.
    """
    ok, j, e = _next_word(buf, e, n, _NORMAL)
    if not ok:
        return 1, j, e
    for _ in range(3):
        j = skip_blank(buf, e, n)
        k = token_end(buf, j, n)
        _v, st = parse_float(buf, j, k)
        if st == 0:
            return 2, j, e
        e = k
    return 0, 0, e


@njit(cache=True, inline="always")
def _vertex(buf, e, n, corners, slow, nc, ns, fill):
    """Read ``x y z`` after ``vertex`` into ``corners[nc]`` (with ``fill``).

    Numbers the fast parser leaves are NaN, recorded in ``slow[ns:]``. ``(error, byte, end, ns)``:
    error 2 = a malformed number.
    """
    for c in range(3):
        j = skip_blank(buf, e, n)
        k = token_end(buf, j, n)
        v, st = parse_float(buf, j, k)
        if st == 0:
            return 2, j, e, ns
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
    return 0, 0, e, ns


@njit(cache=True)
def ascii_walk(buf, corners, slow, fill):
    """Walk an ASCII STL body.

    With ``fill`` false, count; else fill ``corners`` ((3 m, 3) float64, NaN where slow) and
    ``slow`` ((k, 3): flat index, byte start, byte end).

    The grammar's states: outside a solid (``solid NAME``), in a solid (``facet normal``,
    :func:`_facet_normal`, or ``endsolid``), in a facet (``outer loop``) and in its loop
    (``vertex``, :func:`_vertex`, or ``endloop endfacet``).

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
    err = 0
    at = 0
    while True:
        i = skip_blank(buf, i, n)
        if i >= n:
            break
        e = token_end(buf, i, n)
        if state == 0:
            err, at, state = (0, 0, 1) if _word(buf, i, e, _SOLID) else (1, i, 0)
            e = line_end(buf, e, n)
        elif state == 1 and _word(buf, i, e, _FACET):
            err, at, e = _facet_normal(buf, e, n)
            state = 2
            nvert = 0
        elif state == 1 and _word(buf, i, e, _ENDSOLID):
            e = line_end(buf, e, n)
            state = 0
        elif state == 2 and _word(buf, i, e, _OUTER):
            ok, at, e = _next_word(buf, e, n, _LOOP)
            err = 0 if ok else 1
            state = 3
        elif state == 3 and _word(buf, i, e, _VERTEX):
            if nvert == 3:
                return nfacet, ns, 3, i
            err, at, e, ns = _vertex(buf, e, n, corners, slow, nc, ns, fill)
            nc += 1
            nvert += 1
        elif state == 3 and _word(buf, i, e, _ENDLOOP):
            if nvert != 3:
                return nfacet, ns, 3, i
            ok, at, e = _next_word(buf, e, n, _ENDFACET)
            err = 0 if ok else 1
            nfacet += 1 if ok else 0
            state = 1
        else:
            return nfacet, ns, 1, i
        if err:
            return nfacet, ns, err, at
        i = e
    if state >= 2:
        return nfacet, ns, 4, n
    return nfacet, ns, 0, 0
