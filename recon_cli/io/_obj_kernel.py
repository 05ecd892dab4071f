"""Kernel of the OBJ reader: one walk over the lines into arrays that grow by doubling.
Compute only; :mod:`recon_cli.io.obj` validates and raises."""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli.io._text_kernel import is_blank, line_end, scan_float, scan_int, skip_space

# error codes (returned with a byte offset)
BAD_NUMBER = 1
BAD_VERTEX = 2  # a v line with other than 3, 4 or 6 numbers
BAD_NORMAL = 3  # a vn line with other than 3 numbers
SHORT_FACE = 4  # a face with fewer than 3 corners
BAD_INDEX = 5  # a face corner that is not an index (or 0)
MIXED_COLOURS = 6  # v lines with and without colours
BEFORE_FIRST = 7  # a negative index reaching before the first vertex or normal
NO_NORMALS = 8  # a face corner names a normal and the file has no vn line

# counts[] slots
NV, NVN, NF, NCORNER, NSLOW, COLOURS, NOCOLOURS, HAS_VN = range(8)


@njit(cache=True)
def _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow):
    """Parse lines from byte ``i`` until the end or until an array is full.

    One pass over the bytes: each number is scanned where it starts, and the byte after it
    must be white space or a newline. ``st`` holds the counts (NV, NVN, NF, NCORNER, NSLOW,
    COLOURS, NOCOLOURS), updated in place. Returns ``(code, byte)``: 0 at the end, -1 at the
    start of a line that needs more room, else an error code and the offending byte.
    """
    n = len(buf)
    nv = st[NV]
    nvn = st[NVN]
    nf = st[NF]
    nc = st[NCORNER]
    ns = st[NSLOW]
    ncol = st[COLOURS]
    nplain = st[NOCOLOURS]
    cap_v = verts.shape[0]
    cap_vn = vnorms.shape[0]
    cap_f = face_len.shape[0]
    cap_c = corner_v.shape[0]
    cap_s = slow.shape[0]
    has_vn = st[HAS_VN] != 0
    code = 0
    at = 0
    while i < n:
        j = skip_space(buf, i, n)
        if j >= n:
            break
        c0 = buf[j]
        c1 = buf[j + 1] if j + 1 < n else 10
        if c0 == 118 and (is_blank(c1) or (c1 == 110 and (j + 2 >= n or is_blank(buf[j + 2])))):  # v, vn
            is_v = is_blank(c1)
            if not is_v and not has_vn:
                st[HAS_VN] = 2  # ask for the corner normal array
                code = -1
                at = i
                break
            if (nv == cap_v if is_v else nvn == cap_vn) or ns + 7 > cap_s:
                code = -1
                at = i
                break
            row = nv if is_v else nvn
            t = 0
            p = skip_space(buf, j + (1 if is_v else 2), n)
            while p < n and buf[p] != 10:
                val, fs, q = scan_float(buf, p, n)
                if fs == 0 or (q < n and not is_blank(buf[q])):
                    code = BAD_NUMBER
                    at = p
                    break
                if t < 7:
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
                    if col < 3:
                        if arr == 0:
                            verts[row, col] = val
                        elif arr == 2:
                            vnorms[row, col] = val
                        else:
                            colours[row, col] = val
                t += 1
                p = skip_space(buf, q, n)
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
            i = p + 1
        elif c0 == 102 and is_blank(c1):  # f
            if nf == cap_f:
                code = -1
                at = i
                break
            nc0 = nc
            t = 0
            p = skip_space(buf, j + 1, n)
            while p < n and buf[p] != 10:
                if nc == cap_c:
                    code = -1
                    break
                # v, v/vt, v/vt/vn, v//vn
                vi, ok, q = scan_int(buf, p, n)
                ok = ok and vi != 0
                ni = -1
                before = False
                if ok and q < n and buf[q] == 47:  # /
                    q += 1
                    if q < n and buf[q] != 47:  # a texture index: checked, not kept
                        _vt, ok, q = scan_int(buf, q, n)
                    if ok and q < n and buf[q] == 47:
                        nn, ok, q = scan_int(buf, q + 1, n)
                        ok = ok and nn != 0
                        ni = nn - 1 if nn > 0 else nvn + nn
                        before = ni < 0
                if not ok or (q < n and not is_blank(buf[q])):
                    code = BAD_INDEX
                    at = p
                    break
                vi = vi - 1 if vi > 0 else nv + vi
                if vi < 0 or before:
                    code = BEFORE_FIRST
                    at = p
                    break
                corner_v[nc] = vi
                if has_vn:
                    corner_n[nc] = ni
                elif ni >= 0:
                    code = NO_NORMALS
                    at = p
                    break
                nc += 1
                t += 1
                p = skip_space(buf, q, n)
            if code == -1:
                nc = nc0
                at = i
                break
            if code != 0:
                break
            if t < 3:
                code = SHORT_FACE
                at = j
                break
            face_len[nf] = t
            nf += 1
            i = p + 1
        else:
            # anything else (#, vt, vp, o, g, s, l, p, usemtl, mtllib, ...) is skipped
            i = line_end(buf, j, n) + 1
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
def line_kinds(buf):
    """``(v, vn, f)``: about how many lines are ``v``, ``vn`` and ``f`` lines (those starting
    with the word and a space or tab; no branch per byte, so the loop vectorises): sizes for
    the arrays, which grow when lines with leading white space were missed."""
    n = len(buf)
    nv = 0
    nvn = 0
    nf = 0
    for i in range(n - 2):
        a = np.int64(buf[i] == 10)
        b = buf[i + 1]
        c = buf[i + 2]
        sp = np.int64((c == 32) | (c == 9))
        nv += a & np.int64(b == 118) & sp
        nf += a & np.int64(b == 102) & sp
        nvn += a & np.int64(b == 118) & np.int64(c == 110)
    if n >= 2:  # the first line
        nv += buf[0] == 118 and (buf[1] == 32 or buf[1] == 9)
        nvn += buf[0] == 118 and buf[1] == 110
        nf += buf[0] == 102 and (buf[1] == 32 or buf[1] == 9)
    return nv, nvn, nf


@njit(cache=True)
def obj_walk(buf, verts, colours, vnorms, corner_v, corner_n, face_len, slow):
    """Walk an OBJ file held in ``buf`` (uint8) once, into the given arrays (sized by the
    caller from :func:`line_kinds`), which grow when they are too small. ``corner_n`` empty:
    the caller expects no ``vn`` line; it is made (normals -1 so far) at the first.

    Returns ``(error, byte offset, counts, verts, colours, vnorms, corner_v, corner_n,
    face_len, slow)``, the arrays over-allocated (``counts`` gives their lengths): ``verts``
    (nv, 3), ``colours`` (nv, 3, meaningful when the v lines carry them), ``vnorms``
    (nvn, 3), ``corner_v`` / ``corner_n`` (0-based vertex and normal index of each corner,
    normal -1 when absent; not range-checked; ``corner_n`` stays empty when the file has no
    ``vn`` line), ``face_len`` (corners per face) and ``slow`` ((k, 4): array 0 verts / 1
    colours / 2 vnorms, flat index, byte start, byte end of each number left to the slow
    path, stored as NaN).
    """
    st = np.zeros(8, np.int64)
    st[HAS_VN] = 1 if corner_n.shape[0] > 0 else 0
    i = 0
    while True:
        code, at = _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow)
        if code != -1:
            return code, at, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow
        i = at
        eol = line_end(buf, i, len(buf))
        verts = _grown(verts, st[NV] + 1)
        colours = _grown(colours, verts.shape[0])
        vnorms = _grown(vnorms, st[NVN] + 1)
        face_len = _grown(face_len, st[NF] + 1)
        corner_v = _grown(corner_v, st[NCORNER] + (eol - i) // 2 + 1)
        if st[HAS_VN] == 2:  # the first vn line, and the caller expected none
            corner_n = np.full(corner_v.shape[0], -1, np.int64)
            st[HAS_VN] = 1
        elif st[HAS_VN] == 1:
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
