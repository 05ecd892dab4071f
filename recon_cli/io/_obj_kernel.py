"""Kernel of the OBJ reader: one walk over the lines into arrays that grow by doubling.
Compute only; :mod:`recon_cli.io.obj` validates and raises."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli.io._text_kernel import parse_float, parse_int, skip_space, token_end

# error codes (returned with a byte offset)
BAD_NUMBER = 1
BAD_VERTEX = 2  # a v line with other than 3, 4 or 6 numbers
BAD_NORMAL = 3  # a vn line with other than 3 numbers
SHORT_FACE = 4  # a face with fewer than 3 corners
BAD_INDEX = 5  # a face corner that is not an index (or 0)
MIXED_COLOURS = 6  # v lines with and without colours
BEFORE_FIRST = 7  # a negative index reaching before the first vertex or normal

# counts[] slots
NV, NVN, NF, NCORNER, NSLOW, COLOURS, NOCOLOURS = range(7)


@njit(cache=True)
def _index(buf, s, e, sofar):
    """0-based index of the OBJ index ``buf[s:e]`` (1-based, or negative: relative to the
    ``sofar`` items defined before the line); -1 when malformed or 0."""
    v, ok = parse_int(buf, s, e)
    if not ok or v == 0:
        return -1, False
    if v > 0:
        return v - 1, True
    return sofar + v, True


@njit(cache=True)
def _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow):
    """Parse lines from byte ``i`` until the end or until an array might overflow.

    ``st`` holds the counts (NV, NVN, NF, NCORNER, NSLOW, COLOURS, NOCOLOURS), updated in
    place. Returns ``(code, byte)``: 0 at the end, -1 at the start of a line that needs more
    room, else an error code and the offending byte.
    """
    n = len(buf)
    nv = st[NV]
    nvn = st[NVN]
    nf = st[NF]
    nc = st[NCORNER]
    ns = st[NSLOW]
    ncol = st[COLOURS]
    nplain = st[NOCOLOURS]
    code = 0
    at = 0
    while i < n:
        eol = i
        while eol < n and buf[eol] != 10:
            eol += 1
        if (
            nv == verts.shape[0]
            or nvn == vnorms.shape[0]
            or nf == face_len.shape[0]
            or nc + (eol - i) // 2 + 1 > corner_v.shape[0]
            or ns + 7 > slow.shape[0]
        ):
            code = -1
            at = i
            break
        j = skip_space(buf, i, eol)
        if j < eol:
            k = token_end(buf, j, eol)
            c0 = buf[j]
            ln = k - j
            if c0 == 118 and (ln == 1 or (ln == 2 and buf[j + 1] == 110)):  # v, vn
                is_v = ln == 1
                row = nv if is_v else nvn
                t = 0
                p = skip_space(buf, k, eol)
                while p < eol:
                    q = token_end(buf, p, eol)
                    if t < 7:
                        val, fs = parse_float(buf, p, q)
                        if fs == 0:
                            code = BAD_NUMBER
                            at = p
                            break
                        arr = 0 if is_v else 2
                        col = t
                        if is_v and t >= 3:
                            arr = 1
                            col = t - 3
                        if fs == 2:
                            slow[ns, 0] = arr
                            slow[ns, 1] = row * 3 + col
                            slow[ns, 2] = p
                            slow[ns, 3] = q
                            ns += 1
                            val = np.nan
                        if col < 3:
                            if arr == 0:
                                verts[row, col] = val
                            elif arr == 2:
                                vnorms[row, col] = val
                            else:
                                colours[row, col] = val
                    t += 1
                    p = skip_space(buf, q, eol)
                if code != 0:
                    break
                if is_v:
                    if not (t == 3 or t == 4 or t == 6):
                        code = BAD_VERTEX
                        at = j
                        break
                    if t == 6:
                        ncol += 1
                    else:
                        nplain += 1
                    if ncol > 0 and nplain > 0:
                        code = MIXED_COLOURS
                        at = j
                        break
                    nv += 1
                else:
                    if t != 3:
                        code = BAD_NORMAL
                        at = j
                        break
                    nvn += 1
            elif c0 == 102 and ln == 1:  # f
                t = 0
                p = skip_space(buf, k, eol)
                while p < eol:
                    q = token_end(buf, p, eol)
                    # v, v/vt, v/vt/vn, v//vn
                    s1 = p
                    while s1 < q and buf[s1] != 47:
                        s1 += 1
                    vi, ok = _index(buf, p, s1, nv)
                    ni = -1
                    has_n = False
                    if ok and s1 < q:
                        s2 = s1 + 1
                        while s2 < q and buf[s2] != 47:
                            s2 += 1
                        if s2 > s1 + 1:
                            _vt, ok = parse_int(buf, s1 + 1, s2)
                        if ok and s2 < q:
                            ni, ok = _index(buf, s2 + 1, q, nvn)
                            has_n = True
                    if not ok:
                        code = BAD_INDEX
                        at = p
                        break
                    if vi < 0 or ni < -1 or (ni == -1 and has_n):
                        code = BEFORE_FIRST
                        at = p
                        break
                    corner_v[nc] = vi
                    corner_n[nc] = ni
                    nc += 1
                    t += 1
                    p = skip_space(buf, q, eol)
                if code != 0:
                    break
                if t < 3:
                    code = SHORT_FACE
                    at = j
                    break
                face_len[nf] = t
                nf += 1
            # anything else (#, vt, vp, o, g, s, l, p, usemtl, mtllib, ...) is skipped
        i = eol + 1
    st[NV] = nv
    st[NVN] = nvn
    st[NF] = nf
    st[NCORNER] = nc
    st[NSLOW] = ns
    st[COLOURS] = ncol
    st[NOCOLOURS] = nplain
    return code, at


@njit(cache=True)
def _grown(a, need):
    """``a`` with room for at least ``need`` rows (doubling), its content kept."""
    if a.shape[0] >= need:
        return a
    cap = max(2 * a.shape[0], need, 16)
    b = np.empty((cap,) + a.shape[1:], a.dtype)
    b[: a.shape[0]] = a
    return b


@njit(cache=True)
def obj_walk(buf, guess):
    """Walk an OBJ file held in ``buf`` (uint8) once; arrays start at ``guess`` rows and grow.

    Returns ``(error, byte offset, counts, verts, colours, vnorms, corner_v, corner_n,
    face_len, slow)``, the arrays over-allocated (``counts`` gives their lengths): ``verts``
    (nv, 3), ``colours`` (nv, 3, meaningful when the v lines carry them), ``vnorms``
    (nvn, 3), ``corner_v`` / ``corner_n`` (0-based vertex and normal index of each corner,
    normal -1 when absent; not range-checked), ``face_len`` (corners per face) and ``slow``
    ((k, 4): array 0 verts / 1 colours / 2 vnorms, flat index, byte start, byte end of each
    number left to the slow path, stored as NaN).
    """
    st = np.zeros(8, np.int64)
    verts = np.empty((guess, 3), np.float64)
    colours = np.empty((guess, 3), np.float64)
    vnorms = np.empty((16, 3), np.float64)
    corner_v = np.empty(3 * guess, np.int64)
    corner_n = np.empty(3 * guess, np.int64)
    face_len = np.empty(guess, np.int64)
    slow = np.empty((64, 4), np.int64)
    i = 0
    while True:
        code, at = _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow)
        if code != -1:
            return code, at, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow
        i = at
        eol = i
        while eol < len(buf) and buf[eol] != 10:
            eol += 1
        verts = _grown(verts, st[NV] + 1)
        colours = _grown(colours, verts.shape[0])
        vnorms = _grown(vnorms, st[NVN] + 1)
        face_len = _grown(face_len, st[NF] + 1)
        corner_v = _grown(corner_v, st[NCORNER] + (eol - i) // 2 + 1)
        corner_n = _grown(corner_n, corner_v.shape[0])
        slow = _grown(slow, st[NSLOW] + 7)


@njit(cache=True)
def fan(corner_v, face_len):
    """Fan-triangulate polygons given as runs of ``corner_v``: ((m, 3) int64, source face of each)."""
    m = 0
    for f in range(len(face_len)):
        m += face_len[f] - 2
    tri = np.empty((m, 3), np.int64)
    src = np.empty(m, np.int64)
    first = 0
    t = 0
    for f in range(len(face_len)):
        k = face_len[f]
        for a in range(1, k - 1):
            tri[t, 0] = corner_v[first]
            tri[t, 1] = corner_v[first + a]
            tri[t, 2] = corner_v[first + a + 1]
            src[t] = f
            t += 1
        first += k
    return tri, src
