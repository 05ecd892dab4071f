"""Numba kernels shared by the text readers (OBJ, OFF, STL ascii, XYZ, PCD ascii).

One byte scanner and exact number parsing.

Compute only: the readers validate and raise.

Scanning: :func:`is_space` is white space within a line (space, tab, CR, VT, FF);
:func:`is_blank` adds the newline. :func:`skip_space` / :func:`skip_blank` step over them,
:func:`token_end` finds the end of a token (the next blank byte).

Numbers: :func:`scan_float` reads the longest decimal number starting at byte ``i`` and
returns ``(value, status, stop)``; :func:`parse_float` requires the number to fill
``buf[s:e]`` and returns ``(value, status)``. Status 1: ``value`` is the correctly rounded
double, bit for bit what Python's ``float`` gives for the token; 2: the syntax is valid but
the value needs the slow path (more than 19 significant digits whose rounding the fast
algorithm cannot decide: the caller converts those tokens with Python's ``float``); 0: not
a number. The grammar is ``[+-] digits [. digits] [(e|E) [+-] digits]`` with at least one
digit in the mantissa (``5.``, ``.5``) and in an exponent, or ``nan``, ``inf``,
``infinity`` (any case, optional sign).

The mantissa's digits are read eight at a time (:func:`_digits8`: one 8-byte load, a SWAR
digit test and three multiplications); its first 19 significant digits are kept in a 64-bit
integer ``w`` and the value is ``w * 10**q``. Three ways, fastest first:

* Clinger's fast path when ``w <= 2**53`` and ``|q| <= 22``: ``w`` and ``10**|q|`` are
  exact doubles, so one correctly rounded multiplication or division gives the answer;
* else the Eisel-Lemire algorithm: ``w`` times a 128-bit approximation of ``5**q``
  (:mod:`recon_cli.io._float_luts`) gives the 53 leading bits and the rounding direction,
  with an exactness test for the rare products where the truncation could matter (those go
  to the slow path) and the round-half-to-even case for small ``q``;
* with more than 19 significant digits (the rest dropped, not all zeros) the true value lies
  between ``w`` and ``w + 1`` (times ``10**q``): when both round to the same double that is
  the answer, else the slow path.

References
----------
W. D. Clinger, "How to read floating point numbers accurately", PLDI 1990.
D. Lemire, "Number parsing at a gigabyte per second", Software: Practice and Experience
51(8), 2021 (the algorithm by M. Eisel).
N. Mushtak and D. Lemire, "Fast number parsing without fallback", Software: Practice and
Experience 53(7), 2023.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli._kernels.arrays import borrowed, grow1, grow2
from recon_cli._kernels.bits import clz64, ctz64, f64_from_bits, load_u64le, mulhi64
from recon_cli.io._float_luts import LARGEST_POWER, POW5_128, SMALLEST_POWER

POW10 = np.array([10.0**k for k in range(23)], dtype=np.float64)
POW10_INT = np.array([10**k for k in range(9)], dtype=np.uint64)
_U0 = np.uint64(0)
_U1 = np.uint64(1)
_U9 = np.uint64(9)
_U10 = np.uint64(10)
_TWO53 = np.uint64(1 << 53)
_HIDDEN = np.uint64(1 << 52)
_NOT_HIDDEN = np.uint64(((1 << 64) - 1) ^ (1 << 52))
_NOT_ONE = np.uint64(((1 << 64) - 1) ^ 1)
_LOW9 = np.uint64(0x1FF)
_ALL = np.uint64((1 << 64) - 1)
_INF_BITS = np.uint64(0x7FF << 52)
_SIGN = np.uint64(1 << 63)
_U3 = np.uint64(3)
_U8 = np.uint64(8)
_U16 = np.uint64(16)
_U32 = np.uint64(32)
_LOW32 = np.uint64(0xFFFFFFFF)
_ZEROS8 = np.uint64(0x3030303030303030)  # '0' in every byte
_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_ADD76 = np.uint64(0x7676767676767676)
_HIGH8 = np.uint64(0x8080808080808080)
_PAIRS = np.uint64(0x000000FF000000FF)
_MUL1 = np.uint64(100 + (1000000 << 32))
_MUL2 = np.uint64(1 + (10000 << 32))
_EXP_CAP = 10**12  # exponent digits beyond this only saturate (the value is 0 or inf long before)


# ---------------------------------------------------------------------------------------------
# scanning


@njit(cache=True)
def is_space(c):
    """White space within a line: space, tab, CR, VT, FF (not the newline)."""
    return c == 32 or c == 9 or c == 13 or c == 11 or c == 12


@njit(cache=True)
def is_blank(c):
    """White space or a newline."""
    return c == 10 or is_space(c)


@njit(cache=True)
def skip_space(buf, i, e):
    """The first byte at or after ``i`` (up to ``e``) that is not white space (newlines stop it)."""
    while i < e and is_space(buf[i]):
        i += 1
    return i


@njit(cache=True)
def skip_blank(buf, i, e):
    """The first byte at or after ``i`` (up to ``e``) that is neither white space nor a newline."""
    while i < e and is_blank(buf[i]):
        i += 1
    return i


@njit(cache=True)
def token_end(buf, i, e):
    """The end of the token starting at ``i``: the next white space or newline, or ``e``."""
    while i < e and not is_blank(buf[i]):
        i += 1
    return i


@njit(cache=True)
def line_end(buf, i, e):
    """The position of the next newline at or after ``i``, or ``e``."""
    while i < e and buf[i] != 10:
        i += 1
    return i


# ---------------------------------------------------------------------------------------------
# numbers


@njit(cache=True)
def eisel_lemire(w, q):
    """``(bits, ok)``: the bit pattern of the double nearest to ``w * 10**q``.

    ``w`` is a non-zero uint64; ok is False in the rare case where the 128-bit product cannot
    decide (slow path).
    """
    if q < SMALLEST_POWER:
        return _U0, True  # below half the smallest subnormal even for w = 2**64 - 1
    if q > LARGEST_POWER:
        return _INF_BITS, True
    lz = clz64(w)
    w = w << lz
    k = 2 * (q - SMALLEST_POWER)
    t_hi = POW5_128[k]
    lo = w * t_hi
    hi = mulhi64(w, t_hi)
    if (hi & _LOW9) == _LOW9:  # the low bits may carry: add the next 64 bits of the product
        hi2 = mulhi64(w, POW5_128[k + 1])
        lo = lo + hi2
        if hi2 > lo:
            hi += _U1
    if lo == _ALL and (q < -27 or q > 55):
        return _U0, False
    upper = hi >> np.uint64(63)
    shift = upper + _U9
    mant = hi >> shift
    power2 = ((217706 * q) >> 16) + 63 + np.int64(upper) - np.int64(lz) + 1023
    if power2 <= 0:  # subnormal (or just below the smallest normal before rounding)
        if 1 - power2 >= 64:
            return _U0, True
        mant = mant >> np.uint64(1 - power2)
        mant += mant & _U1
        mant = mant >> _U1
        # mant is at most 2**52: exactly 2**52 is the smallest normal (exponent field 1)
        return mant, True
    if lo <= _U1 and q >= -4 and q <= 23 and (mant & np.uint64(3)) == _U1:
        if (mant << shift) == hi:  # exactly half way: round to even
            mant &= _NOT_ONE
    mant += mant & _U1
    mant = mant >> _U1
    if mant >= (_HIDDEN << _U1):
        mant = _HIDDEN
        power2 += 1
    mant &= _NOT_HIDDEN
    if power2 >= 0x7FF:
        return _INF_BITS, True
    return mant | (np.uint64(power2) << np.uint64(52)), True


@njit(cache=True)
def _lower(c):
    return c + 32 if 65 <= c <= 90 else c


@njit(cache=True)
def _special(buf, i, e, neg):
    """``nan``, ``inf`` or ``infinity`` (any case) at ``i``: (value, status, stop)."""
    if i + 3 > e:
        return 0.0, 0, i
    a, b, c = _lower(buf[i]), _lower(buf[i + 1]), _lower(buf[i + 2])
    if a == 110 and b == 97 and c == 110:  # nan
        return (-np.nan if neg else np.nan), 1, i + 3
    if a == 105 and b == 110 and c == 102:  # inf
        stop = i + 3
        if (
            i + 8 <= e
            and _lower(buf[i + 3]) == 105  # i
            and _lower(buf[i + 4]) == 110  # n
            and _lower(buf[i + 5]) == 105  # i
            and _lower(buf[i + 6]) == 116  # t
            and _lower(buf[i + 7]) == 121  # y
        ):
            stop = i + 8
        return (-np.inf if neg else np.inf), 1, stop
    return 0.0, 0, i


@njit(cache=True)
def _significant_digits(buf, s, e):
    """How many digits of the mantissa ``buf[s:e]`` follow its leading zeros.

    The mantissa is digits and at most one point.
    """
    n = 0
    lead = True
    for i in range(s, e):
        c = buf[i]
        if c != 46:
            lead = lead and c == 48
            n += not lead
    return n


@njit(cache=True)
def _mantissa_long(buf, i, e):
    """The mantissa at ``i`` digit by digit.

    ``(w, q, dropped, ndig, stop)`` with the first 19 significant digits in ``w``, value ``w *
    10**q`` (``dropped``: a non-zero digit was not kept).
    """
    w = _U0
    nd = 0  # significant digits in w (leading zeros are not)
    q = 0
    ndig = 0
    dropped = False
    while i < e:
        c = buf[i]
        if c < 48 or c > 57:
            break
        d = np.uint64(c - 48)
        if nd < 19:
            w = w * _U10 + d
            if w != _U0:
                nd += 1
        else:
            q += 1
            if d != _U0:
                dropped = True
        ndig += 1
        i += 1
    if i < e and buf[i] == 46:  # .
        i += 1
        while i < e:
            c = buf[i]
            if c < 48 or c > 57:
                break
            d = np.uint64(c - 48)
            if nd < 19:
                w = w * _U10 + d
                if w != _U0:
                    nd += 1
                q -= 1
            elif d != _U0:
                dropped = True
            ndig += 1
            i += 1
    return w, q, dropped, ndig, i


@njit(cache=True, inline="always")
def _digits8(buf, i, e):
    """``(value, count)`` of the run of decimal digits at ``i``, at most 8 of them.

    A count of 8: more may follow. Reads no further than ``e``.

    SWAR when the 8 bytes ``buf[i:i + 8]`` lie before ``e``: they are loaded as one integer,
    each byte XOR ``'0'`` (a digit becomes 0..9), the first non-digit found from the high bit
    of ``(b & 0x7f) + 0x76 | b`` per byte (set exactly when ``b`` is not 0..9; no carry
    between bytes), the digits shifted to the top (the bytes after them fall out, zeros enter
    as leading digits) and combined pairwise with three multiplications (as in Lemire's
    fast_float). Near ``e`` the digits are read one by one.
    """
    if i + 8 <= e:
        d = load_u64le(buf, i) ^ _ZEROS8
        nondigit = (((d & _LOW7) + _ADD76) | d) & _HIGH8
        if nondigit == _U0:
            k = 8
        else:
            k = np.int64(ctz64(nondigit) >> _U3)
            if k == 0:
                return _U0, 0
        t = d << np.uint64(64 - 8 * k)
        t = t * _U10 + (t >> _U8)
        t = (((t & _PAIRS) * _MUL1) + (((t >> _U16) & _PAIRS) * _MUL2)) >> _U32
        return t & _LOW32, k
    w = _U0
    k = 0
    while i < e and k < 8 and buf[i] >= 48 and buf[i] <= 57:
        w = w * _U10 + np.uint64(buf[i] - 48)
        i += 1
        k += 1
    return w, k


@njit(cache=True, inline="always")
def _sign(buf, i, e):
    """``(negative, i)``: an optional ``-`` or ``+`` at ``i`` and the byte after it."""
    if i < e:
        c = buf[i]
        if c == 45:  # -
            return True, i + 1
        if c == 43:  # +
            return False, i + 1
    return False, i


@njit(cache=True, inline="always")
def _mantissa(buf, i, e):
    """``(w, q, dropped, ndig, stop)``: the digits at ``i`` with an optional point and fraction.

    The value is ``w * 10**q``; ``ndig`` counts every digit read, ``dropped`` says a non-zero
    digit beyond the 19th significant one was not kept (:func:`_mantissa_long`).
    """
    p0 = i
    # written out and inlined into the callers (a call per number costs more than the digits),
    # eight digits at a time (_digits8). Leading zeros add nothing to w, so w is exact while at
    # most 19 digits follow them (the usual case; w may wrap beyond, unused then); longer
    # mantissas are read again, digit by digit, by _mantissa_long. The loops have their test in
    # the loop condition: numba compiles the equivalent `while True: ... break` form to slower
    # code.
    w, k = _digits8(buf, i, e)
    i += k
    while k == 8:
        v, k = _digits8(buf, i, e)
        w = w * POW10_INT[k] + v
        i += k
    ndig = i - p0
    q = 0
    if i < e and buf[i] == 46:  # .
        i += 1
        f0 = i
        k = 8
        while k == 8:
            v, k = _digits8(buf, i, e)
            w = w * POW10_INT[k] + v
            i += k
        q = f0 - i
        ndig += i - f0
    if ndig > 19 and _significant_digits(buf, p0, i) > 19:
        return _mantissa_long(buf, p0, e)
    return w, q, False, ndig, i


@njit(cache=True, inline="always")
def _exponent(buf, i, e):
    """``(x, ok, stop)``: the exponent ``(e|E) [+-] digits`` at ``i`` (x 0 when there is none).

    Not ok when the marker has no digit; digits beyond ``_EXP_CAP`` only saturate.
    """
    if not (i < e and (buf[i] == 101 or buf[i] == 69)):  # e E
        return 0, True, i
    j = i + 1
    eneg = False
    if j < e and (buf[j] == 45 or buf[j] == 43):
        eneg = buf[j] == 45
        j += 1
    if j >= e or buf[j] < 48 or buf[j] > 57:
        return 0, False, j  # an exponent needs a digit
    x = 0
    while j < e:
        c = buf[j]
        if c < 48 or c > 57:
            break
        if x < _EXP_CAP:
            x = x * 10 + (c - 48)
        j += 1
    return (-x if eneg else x), True, j


@njit(cache=True, inline="always")
def _rounded(w, q, dropped, neg):
    """``(value, status)``: the double nearest to ``±w * 10**q`` (``w`` non-zero).

    Clinger's one exact operation when it applies, else Eisel-Lemire; status 2 when neither can
    decide (the slow path).
    """
    if not dropped and w <= _TWO53 and -22 <= q <= 22:  # Clinger: one exact operation
        v = np.float64(w)
        if q >= 0:
            v = v * POW10[q]
        else:
            v = v / POW10[-q]
        return (-v if neg else v), 1
    bits, ok = eisel_lemire(w, q)
    if ok and dropped:  # the value lies in [w, w + 1) * 10**q: both ends must round alike
        bits2, ok2 = eisel_lemire(w + _U1, q)
        ok = ok2 and bits2 == bits
    if not ok:
        return np.nan, 2
    if neg:
        bits |= _SIGN
    return f64_from_bits(bits), 1


@njit(cache=True, inline="always")
def scan_float(buf, i, e):
    """The decimal number starting at byte ``i`` (reading no further than ``e``).

    ``(value, status, stop)`` with ``stop`` the byte after it; see the module docstring. The caller
    checks that ``buf[stop]`` may follow a number. The steps: sign, mantissa, exponent, rounding.
    """
    neg, i = _sign(buf, i, e)
    p0 = i
    w, q, dropped, ndig, i = _mantissa(buf, i, e)
    if ndig == 0:
        return _special(buf, p0, e, neg)
    x, ok, i = _exponent(buf, i, e)
    if not ok:
        return 0.0, 0, i
    q += x
    if w == _U0:
        return (-0.0 if neg else 0.0), 1, i
    v, status = _rounded(w, q, dropped, neg)
    return v, status, i


@njit(cache=True)
def parse_float(buf, s, e):
    """(value, status) of the number that must fill ``buf[s:e]``; see the module docstring."""
    v, st, stop = scan_float(borrowed(buf), s, e)
    if st == 0 or stop != e:
        return 0.0, 0
    return v, st


@njit(cache=True, inline="always")
def scan_int(buf, i, e):
    """The decimal integer (optional sign, 1 to 18 digits) starting at ``i``.

    ``(value, ok, stop)``.
    """
    neg = False
    if i < e and (buf[i] == 45 or buf[i] == 43):
        neg = buf[i] == 45
        i += 1
    p0 = i
    w, k = _digits8(buf, i, e)
    i += k
    while k == 8:
        v, k = _digits8(buf, i, e)
        w = w * POW10_INT[k] + v
        i += k
    if i == p0 or i - p0 > 18:
        return 0, False, i
    x = np.int64(w)
    return (-x if neg else x), True, i


# ---------------------------------------------------------------------------------------------
# rows of numbers


# state slots of _rows_walk
_NV, _NR, _NS, _NCOL, _LINE = range(5)


@njit(cache=True, inline="always")
def _row(buf, j, end, delim, values, nv, slow, ns):
    """Read the fields of the row starting at byte ``j`` into ``values[nv:]``.

    Tokens left to the slow path are recorded in ``slow[ns:]``. Returns ``(code, where, nv,
    ns, stop)``: code 0 with ``stop`` at the row's newline (or ``end``), -1 / -2 when
    ``values`` / ``slow`` is full, 1 at byte ``where`` when a field is not a number (or empty).
    """
    cap_v = values.shape[0]
    cap_s = slow.shape[0]
    while True:
        v, fs, q = scan_float(buf, j, end)
        if fs == 0:
            return 1, j, nv, ns, j
        if q < end:
            c = buf[q]
            if not (is_blank(c) or (delim != 0 and c == delim)):
                return 1, j, nv, ns, j
        if nv == cap_v:
            return -1, 0, nv, ns, j
        if fs == 2:
            if ns == cap_s:
                return -2, 0, nv, ns, j
            slow[ns, 0] = nv
            slow[ns, 1] = j
            slow[ns, 2] = q
            ns += 1
        values[nv] = v
        nv += 1
        j = skip_space(buf, q, end)
        if j >= end or buf[j] == 10:
            return 0, 0, nv, ns, j
        if delim != 0 and buf[j] == delim:
            j = skip_space(buf, j + 1, end)
            if j >= end or buf[j] == 10:  # a trailing delimiter: an empty last field
                return 1, j, nv, ns, j


@njit(cache=True)
def _rows_walk(buf, i, end, delim, comment, fixed, values, row_start, row_line, slow, st):
    """Rows from byte ``i`` until the end or until an array is full.

    Blank and comment lines are counted and skipped, each row read by :func:`_row`. The arrays
    are fixed here, so the loop keeps their addresses in registers. ``st`` holds the counts,
    updated.
    Returns ``(code, where, bad_count)``: code 0 at the end, -1, -2, -3 when ``values``,
    ``slow`` or the row arrays are full (``where``: the start of the row to parse again), 1 or
    2 as :func:`parse_rows`'s errors.
    """
    buf = borrowed(buf)  # no reference counting around the inlined number scanner
    nv = st[_NV]
    nr = st[_NR]
    ns = st[_NS]
    ncol = st[_NCOL]
    line = st[_LINE]
    code = 0
    where = 0
    bad = 0
    while i < end:
        j = skip_space(buf, i, end)
        if j >= end:
            break
        c = buf[j]
        if c == 10 or (comment != 0 and c == comment):
            i = (j if c == 10 else line_end(buf, j, end)) + 1
            line += 1
            continue
        if not fixed:
            if nr == row_line.shape[0]:
                code = -3
                where = i
                break
            row_start[nr] = nv
            row_line[nr] = line
        r0 = j
        code, where, nv1, ns1, j = _row(buf, j, end, delim, values, nv, slow, ns)
        if code < 0:  # full: the row is parsed again once the array has grown
            where = i
            break
        if code != 0:
            nv, ns = nv1, ns1
            break
        k = nv1 - nv
        nv, ns = nv1, ns1
        if ncol < 0:
            ncol = k
        elif fixed and k != ncol:
            code = 2
            where = r0
            bad = k
            break
        nr += 1
        line += 1
        i = j + 1
    st[_NV] = nv
    st[_NR] = nr
    st[_NS] = ns
    st[_NCOL] = ncol
    st[_LINE] = line
    return code, where, bad


@njit(cache=True)
def parse_rows(buf, start, end, delim, comment, cap, fixed):
    """The rows of numbers in ``buf[start:end]``, in one pass into arrays that grow by doubling.

    Each non-empty line whose first non-blank byte is not ``comment`` (a byte code, 0: none)
    is a row. Fields are separated by white space, and by ``delim`` (a byte code; 0: white
    space only) where given: two delimiters in a row make an empty field, an error.
    ``cap`` is the first capacity of the value array. With ``fixed`` every row must have
    as many fields as the first, and no per-row arrays are kept.

    Returns ``(values, nvals, row_start, row_line, nrows, ncol, slow, nslow, error, where,
    bad_count)``: ``values`` (over-allocated; NaN where slow), ``row_start`` (nrows + 1
    entries) and ``row_line`` (1-based lines counted from ``start``) unless ``fixed``,
    ``ncol`` the first row's field count, ``slow`` ((nslow, 3): value index, byte start and
    end of each token left to the slow path). Error 1: a field is not a number, at byte
    ``where``; 2 (``fixed``): the row at byte ``where`` has ``bad_count`` fields.
    """
    values = np.empty(max(cap, 16), np.float64)
    rcap = 0 if fixed else max(cap // 3, 16)
    row_start = np.empty(rcap + 1, np.int64)
    row_line = np.empty(rcap, np.int64)
    slow = np.empty((16, 3), np.int64)
    st = np.zeros(5, np.int64)
    st[_NCOL] = -1
    st[_LINE] = 1
    i = start
    while True:
        code, where, bad = _rows_walk(
            buf, i, end, delim, comment, fixed, values, row_start, row_line, slow, st
        )
        if code >= 0:
            break
        i = where
        if code == -1:
            values = grow1(values, 2 * values.shape[0])
        elif code == -2:
            slow = grow2(slow, 2 * slow.shape[0])
        else:
            row_line = grow1(row_line, 2 * row_line.shape[0])
            row_start = grow1(row_start, row_line.shape[0] + 1)
    nr = st[_NR]
    if not fixed and code == 0:
        row_start[nr] = st[_NV]
    return values, st[_NV], row_start, row_line, nr, st[_NCOL], slow, st[_NS], code, where, bad
