"""Numba kernels shared by the text readers (OBJ, OFF, XYZ, PCD ascii): numbers out of bytes.

Compute only: the readers validate and raise. A number is parsed from ``buf[s:e]`` (uint8):

* :func:`parse_float` returns ``(value, status)``: status 1 when the value is exact (the
  decimal mantissa fits 53 bits and the power of ten is at most 22, so one correctly
  rounded multiplication or division gives the nearest double: Clinger's fast path),
  2 when the syntax is valid but the value needs a correctly rounded slow path (more
  digits, large exponents, ``nan``/``inf``: the caller converts those tokens with Python's
  ``float``), 0 when the token is not a number;
* :func:`parse_int` returns ``(value, ok)``.

References
----------
W. D. Clinger, "How to read floating point numbers accurately", PLDI 1990.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)

POW10 = np.array([10.0**k for k in range(23)], dtype=np.float64)
_TWO53 = 1 << 53


@njit(cache=True, inline="always")
def is_space(c):
    return c == 32 or c == 9 or c == 13 or c == 11 or c == 12


@njit(cache=True)
def _is_word(buf, s, e, word):
    """``buf[s:e]``, case-insensitively, equals ``word`` (lower-case ASCII codes)."""
    if e - s != len(word):
        return False
    for k in range(e - s):
        c = buf[s + k]
        if 65 <= c <= 90:
            c += 32
        if c != word[k]:
            return False
    return True


_NAN = np.frombuffer(b"nan", np.uint8).copy()
_INF = np.frombuffer(b"inf", np.uint8).copy()
_INFINITY = np.frombuffer(b"infinity", np.uint8).copy()


@njit(cache=True)
def parse_float(buf, s, e):
    """(value, status) of the decimal number ``buf[s:e]``; see the module docstring."""
    i = s
    neg = False
    if i < e and (buf[i] == 45 or buf[i] == 43):  # - +
        neg = buf[i] == 45
        i += 1
    if i < e and (buf[i] == 110 or buf[i] == 78 or buf[i] == 105 or buf[i] == 73):  # n N i I
        if _is_word(buf, i, e, _NAN) or _is_word(buf, i, e, _INF) or _is_word(buf, i, e, _INFINITY):
            return 0.0, 2
        return 0.0, 0
    m = np.uint64(0)
    nd = 0  # significant digits kept in m
    extra = 0  # significant digits beyond 19 (slow path)
    exp10 = 0
    digits = 0
    # value = m * 10**exp10; zeros after the last non-zero digit are kept pending (zi in the
    # integer part, zf in the fraction) and only enter m when a non-zero digit follows, so
    # trailing zeros ("0.5000", "1200") cost no digits of the 19 m can hold
    zi = 0
    zf = 0
    frac = False
    while i < e:
        c = buf[i]
        if c == 46 and not frac:  # .
            frac = True
            i += 1
            continue
        if c < 48 or c > 57:
            break
        d = c - 48
        digits += 1
        if d == 0:
            if nd == 0:
                if frac:
                    exp10 -= 1  # leading zeros of a fraction
            elif frac:
                zf += 1
            else:
                zi += 1
        elif nd + zi + zf + 1 > 19:
            extra += 1  # beyond 19 significant digits: the slow path decides
        else:
            for _ in range(zi + zf):
                m = m * np.uint64(10)
            nd += zi + zf + 1
            exp10 -= zf
            m = m * np.uint64(10) + np.uint64(d)
            if frac:
                exp10 -= 1
            zi = 0
            zf = 0
        i += 1
    exp10 += zi  # integer zeros never followed by a non-zero digit scale the value
    if digits == 0:
        return 0.0, 0
    if i < e and (buf[i] == 101 or buf[i] == 69):  # e E
        i += 1
        eneg = False
        if i < e and (buf[i] == 45 or buf[i] == 43):
            eneg = buf[i] == 45
            i += 1
        if i >= e:
            return 0.0, 0
        x = 0
        while i < e and 48 <= buf[i] <= 57:
            if x < 100000:
                x = x * 10 + (buf[i] - 48)
            i += 1
        exp10 += -x if eneg else x
    if i != e:
        return 0.0, 0
    if m == 0:
        return (-0.0 if neg else 0.0), 1
    if extra > 0 or m > np.uint64(_TWO53) or exp10 < -22 or exp10 > 22:
        return 0.0, 2
    v = np.float64(m)
    if exp10 >= 0:
        v = v * POW10[exp10]
    else:
        v = v / POW10[-exp10]
    return (-v if neg else v), 1


@njit(cache=True)
def parse_int(buf, s, e):
    """(value, ok) of the decimal integer ``buf[s:e]`` (optional sign, at most 18 digits)."""
    i = s
    neg = False
    if i < e and (buf[i] == 45 or buf[i] == 43):
        neg = buf[i] == 45
        i += 1
    if i >= e or e - i > 18:
        return 0, False
    v = 0
    while i < e:
        c = buf[i]
        if c < 48 or c > 57:
            return 0, False
        v = v * 10 + (c - 48)
        i += 1
    return (-v if neg else v), True




@njit(cache=True)
def skip_space(buf, i, e):
    while i < e and is_space(buf[i]):
        i += 1
    return i


@njit(cache=True)
def token_end(buf, i, e):
    while i < e and not is_space(buf[i]):
        i += 1
    return i


@njit(cache=True)
def _field_end(buf, i, e, delim):
    """End of the field starting at ``i``: the next space, ``delim`` or ``e``."""
    while i < e:
        c = buf[i]
        if is_space(c) or c == delim:
            break
        i += 1
    return i


@njit(cache=True)
def parse_rows(buf, start, end, delim, comment, mode, values, row_start, row_line, slow):
    """Walk the lines of ``buf[start:end]``: each non-empty, non-comment line is a row of numbers.

    Fields are separated by white space, and by ``delim`` (a byte code; 0: white space
    only) where given: two delimiters in a row make an empty field, which is an error. A
    line whose first non-blank byte is ``comment`` (a byte code, 0: none) is skipped.

    ``mode`` 0 counts: returns ``(rows, values, slow, 0, 0)``; ``mode`` 1 fills ``values``
    (float64, NaN where slow), ``row_start`` (rows + 1) and ``row_line`` (1-based line
    numbers counted from ``start``); ``mode`` 2 fills ``slow`` ((k, 3): value index, byte
    start, byte end of each slow token). Returns ``(rows, values, slow, error, where)``:
    error 1 = a field is not a number, at byte ``where``.
    """
    i = start
    line = 0
    nrows = 0
    nvals = 0
    nslow = 0
    while i < end:
        line += 1
        eol = i
        while eol < end and buf[eol] != 10:
            eol += 1
        j = skip_space(buf, i, eol)
        if j < eol and not (comment != 0 and buf[j] == comment):
            if mode == 1:
                row_start[nrows] = nvals
                row_line[nrows] = line
            while True:
                k = _field_end(buf, j, eol, delim)
                if mode != 0 or k == j:
                    v, st = parse_float(buf, j, k)
                    if st == 0:
                        return nrows, nvals, nslow, 1, j
                    if st == 2:
                        if mode == 2:
                            slow[nslow, 0] = nvals
                            slow[nslow, 1] = j
                            slow[nslow, 2] = k
                        nslow += 1
                        v = np.nan
                    if mode == 1:
                        values[nvals] = v
                nvals += 1
                j = skip_space(buf, k, eol)
                if j >= eol:
                    break
                if delim != 0 and buf[j] == delim:
                    j = skip_space(buf, j + 1, eol)
                    if j >= eol:  # a trailing delimiter: an empty last field
                        return nrows, nvals, nslow, 1, eol
            nrows += 1
        i = eol + 1
    if mode == 1:
        row_start[nrows] = nvals
    return nrows, nvals, nslow, 0, 0


@njit(cache=True)
def gather_tokens(buf, spans):
    """The tokens ``buf[s:e]`` for the rows ``(s, e)`` of ``spans`` as a zero-padded ``(k, width)``
    uint8 array (viewed as numpy bytes strings by the caller)."""
    width = 1
    for r in range(spans.shape[0]):
        width = max(width, spans[r, 1] - spans[r, 0])
    out = np.zeros((spans.shape[0], width), np.uint8)
    for r in range(spans.shape[0]):
        s = spans[r, 0]
        for k in range(spans[r, 1] - s):
            out[r, k] = buf[s + k]
    return out
