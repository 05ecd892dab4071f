"""Kernel of the OBJ reader: one walk over the lines into arrays that grow by doubling.

The arrays are sized first from a sample of the file (:func:`line_kinds`). Compute only:
:mod:`recon_cli.io.obj` validates and raises.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (the per-user cache, before the first @njit)
from recon_cli._kernels.arrays import borrowed
from recon_cli.io._text_kernel import (
    is_blank,
    line_end,
    scan_float,
    scan_int,
    skip_space,
    token_end,
)

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
NV, NVN, NF, NCORNER, NSLOW, COLOURS, NOCOLOURS, HAS_VN, MAX_V, MAX_VN, NONFINITE, POLYGONS = range(
    12
)


@njit(cache=True, inline="always")
def _corner(buf, p, n):
    """The face corner at ``p`` (``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn``).

    ``(v, vn, ok, stop)`` with the indices as written (``vn`` 0 when absent); not ok when it is not
    one of these forms or an index is 0 (the texture index is read and dropped).
    """
    vi, ok, q = scan_int(buf, p, n)
    ok = ok and vi != 0
    nn = 0
    if ok and q < n and buf[q] == 47:  # /
        q += 1
        ok = q < n
        if ok and buf[q] != 47:  # a texture index: checked, not kept
            _vt, ok, q = scan_int(buf, q, n)
        if ok and q < n and buf[q] == 47:
            nn, ok, q = scan_int(buf, q + 1, n)
            ok = ok and nn != 0
    return vi, nn, ok, q


@njit(cache=True, inline="always")
def _short_vertex(buf, j, n, verts, nv):
    """Read a ``v x y z`` line at byte ``j`` with one space between fields into ``verts[nv]``.

    ``(ok, finite, next line)``: not ok when the line is not of that form, for the general path
    (:func:`_numbers`). ``buf`` is the walk's borrowed view.
    """
    # the three numbers by one loop: one inlined copy of scan_float, not three
    # (each copy costs the compile seconds; written into the row before it counts)
    q = j + 1
    k = 0
    finite = True
    while k < 3:
        val, s0, q = scan_float(buf, q + 1, n)
        if s0 != 1 or not ((q < n and buf[q] == 32) if k < 2 else (q >= n or buf[q] == 10)):
            break
        verts[nv, k] = val
        finite = finite and abs(val) < np.inf
        k += 1
    return k == 3, finite, q + 1


@njit(cache=True, inline="always")
def _short_triangle(buf, j, n, corner_v, corner_n, nc, has_vn):
    """Read an ``f a b c`` line at byte ``j`` with one space between corners into ``corner_v[nc:]``.

    ``(ok, next line)``; not ok when the line is not of that form (or names normals the file
    has none of), for the general path (:func:`_corners`).
    """
    # the three corners by one loop, as the numbers of _short_vertex
    q = j + 1
    k = 0
    named = 0  # corners that name a normal
    while k < 3:
        a, an, ok0, q = _corner(buf, q + 1, n)
        if not (ok0 and a > 0 and an >= 0):
            break
        if not ((q < n and buf[q] == 32) if k < 2 else (q >= n or buf[q] == 10)):
            break
        corner_v[nc + k] = a - 1
        if has_vn:
            corner_n[nc + k] = an - 1
        named += an
        k += 1
    return k == 3 and (has_vn or named == 0), q + 1


@njit(cache=True)
def _numbers(buf, j, n, is_v, row, verts, colours, vnorms, slow, ns, nonfinite):
    """Read the numbers of a ``v`` or ``vn`` line (from byte ``j``) into row ``row``.

    A vertex's first three go to ``verts``, its next three to ``colours``, a normal's to
    ``vnorms``; numbers the fast scanner leaves are recorded in ``slow``. Returns ``(code,
    byte, count, ns, nonfinite, end of line)``, code BAD_NUMBER at a field that is no number.
    """
    t = 0
    p = skip_space(buf, j + (1 if is_v else 2), n)
    while p < n and buf[p] != 10:
        val, fs, q = scan_float(buf, p, n)
        if fs == 0 or (q < n and not is_blank(buf[q])):
            return BAD_NUMBER, p, t, ns, nonfinite, p
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
                    if fs == 1 and nonfinite < 0 and not abs(val) < np.inf:
                        nonfinite = row
                elif arr == 2:
                    vnorms[row, col] = val
                else:
                    colours[row, col] = val
        t += 1
        p = skip_space(buf, q, n)
    return 0, 0, t, ns, nonfinite, p


@njit(cache=True)
def _corners(buf, j, n, nv, nvn, has_vn, corner_v, corner_n, nc, max_v, max_n):
    """Read the corners of an ``f`` line (from byte ``j``) into ``corner_v[nc:]``, ``corner_n``.

    Negative indices count back from the ``nv`` vertices and ``nvn`` normals read so far.
    Returns ``(code, byte, corners, nc, max_v, max_n, end of line)``: code -1 when
    ``corner_v`` is full, else 0 or the error (BAD_INDEX, BEFORE_FIRST, NO_NORMALS) and its byte.
    """
    cap_c = corner_v.shape[0]
    t = 0
    p = skip_space(buf, j + 1, n)
    while p < n and buf[p] != 10:
        if nc == cap_c:
            return -1, p, t, nc, max_v, max_n, p
        vi, nn, ok, q = _corner(buf, p, n)
        if not ok or (q < n and not is_blank(buf[q])):
            return BAD_INDEX, p, t, nc, max_v, max_n, p
        ni = nn - 1 if nn > 0 else (nvn + nn if nn < 0 else -1)
        vi = vi - 1 if vi > 0 else nv + vi
        if vi < 0 or (nn < 0 and ni < 0):
            return BEFORE_FIRST, p, t, nc, max_v, max_n, p
        corner_v[nc] = vi
        max_v = max(max_v, vi)
        if has_vn:
            corner_n[nc] = ni
            max_n = max(max_n, ni)
        elif ni >= 0:
            return NO_NORMALS, p, t, nc, max_v, max_n, p
        nc += 1
        t += 1
        p = skip_space(buf, q, n)
    return 0, 0, t, nc, max_v, max_n, p


@njit(cache=True)
def _vertex_line(buf, i, j, n, is_v, st, verts, colours, vnorms, slow, has_vn):
    """The general path of a ``v`` (``is_v``) or ``vn`` line at byte ``i`` (its key at ``j``).

    Reads it (:func:`_numbers`) and counts it in ``st``. Returns ``(code, byte, next line)``:
    -1 at ``i`` when an array needs more room (or the first ``vn`` line asks for normals),
    else 0 or an error (BAD_NUMBER, BAD_VERTEX, BAD_NORMAL, MIXED_COLOURS) and its byte.
    """
    if not is_v and not has_vn:
        st[HAS_VN] = 2  # ask for the corner normal array
        return -1, i, i
    nv = st[NV]
    nvn = st[NVN]
    full = nv == verts.shape[0] if is_v else nvn == vnorms.shape[0]
    if full or st[NSLOW] + 7 > slow.shape[0]:
        return -1, i, i
    code, at, t, ns, nonfinite, p = _numbers(
        buf,
        j,
        n,
        is_v,
        nv if is_v else nvn,
        verts,
        colours,
        vnorms,
        slow,
        st[NSLOW],
        st[NONFINITE],
    )
    st[NSLOW] = ns
    st[NONFINITE] = nonfinite
    if code != 0:
        return code, at, p
    if not is_v:
        if t != 3:
            return BAD_NORMAL, j, p
        st[NVN] = nvn + 1
        return 0, 0, p + 1
    if not (t == 3 or t == 4 or t == 6):
        return BAD_VERTEX, j, p
    st[COLOURS if t == 6 else NOCOLOURS] += 1
    if st[COLOURS] > 0 and st[NOCOLOURS] > 0:
        return MIXED_COLOURS, j, p
    st[NV] = nv + 1
    return 0, 0, p + 1


@njit(cache=True)
def _face_line(buf, i, j, n, st, corner_v, corner_n, face_len, keep_len, has_vn):
    """The general path of an ``f`` line starting at byte ``i`` (its key at ``j``).

    Reads its corners (:func:`_corners`) and counts it in ``st``. Returns ``(code, byte, next
    line)``: -1 at ``i`` when an array needs more room (or the first polygon asks for face
    lengths; nothing of the line is kept then), else 0 or an error and its byte.
    """
    nf = st[NF]
    if nf == (face_len.shape[0] if keep_len else 1 << 62):
        return -1, i, i
    code, at, t, nc, max_v, max_n, p = _corners(
        buf,
        j,
        n,
        st[NV],
        st[NVN],
        has_vn,
        corner_v,
        corner_n,
        st[NCORNER],
        st[MAX_V],
        st[MAX_VN],
    )
    if code == 0 and t > 3 and not keep_len:  # the first polygon
        st[POLYGONS] = 2  # ask for the face length array
        code = -1
    if code == -1:
        return -1, i, i
    if code != 0:
        return code, at, p
    if t < 3:
        return SHORT_FACE, j, p
    if keep_len:
        face_len[nf] = t
    st[NF] = nf + 1
    st[NCORNER] = nc
    st[MAX_V] = max_v
    st[MAX_VN] = max_n
    return 0, 0, p + 1


@njit(cache=True, inline="always")
def _load(st):
    """The counts the short paths keep in registers, from ``st``."""
    return st[NV], st[NF], st[NCORNER], st[NOCOLOURS], st[MAX_V], st[MAX_VN], st[NONFINITE]


@njit(cache=True, inline="always")
def _store(st, nv, nf, nc, nplain, max_v, max_n, nonfinite):
    """Write the counts of :func:`_load` back into ``st``."""
    st[NV] = nv
    st[NF] = nf
    st[NCORNER] = nc
    st[NOCOLOURS] = nplain
    st[MAX_V] = max_v
    st[MAX_VN] = max_n
    st[NONFINITE] = nonfinite


# one cursor and the counts of the common lines in registers; the other lines through st
@njit(cache=True)
def _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow):
    """Parse lines from byte ``i`` until the end or until an array is full.

    One pass over the bytes: each number is scanned where it starts, and the byte after it must be
    white space or a newline. The common lines, ``v x y z`` and ``f a b c`` (each corner any of the
    four forms) with one space between fields, go through a short path that reads the fields in
    order (:func:`_short_vertex`, :func:`_short_triangle`); any other line (and any such line the
    short path does not take whole) through the general one (:func:`_vertex_line`,
    :func:`_face_line`). ``st`` holds the counts (NV, NVN, NF, NCORNER, NSLOW, COLOURS,
    NOCOLOURS), the largest vertex and normal index named by a corner (MAX_V, MAX_VN, 0-based, -1
    when none) and the first vertex with a NaN or infinite coordinate (NONFINITE, -1 when none;
    numbers left to the slow path are not looked at), updated in place; ``face_len`` is written
    only once POLYGONS is set (a face of more than 3 corners seen, or expected by the caller).
    Returns ``(code, byte)``: 0 at the end, -1 at the start of a line that needs more room, else
    an error code and the offending byte.
    """
    buf = borrowed(buf)  # no reference counting around the inlined number scanners
    n = len(buf)
    keep_len = st[POLYGONS] != 0  # corners per face kept (not while every face is a triangle)
    cap_f = face_len.shape[0] if keep_len else 1 << 62
    has_vn = st[HAS_VN] != 0
    nv, nf, nc, nplain, max_v, max_n, nonfinite = _load(st)
    code = 0
    at = 0
    while i < n:
        j = skip_space(buf, i, n)
        if j >= n:
            break
        c0 = buf[j]
        c1 = buf[j + 1] if j + 1 < n else 10
        if c1 == 32 and c0 == 118 and st[COLOURS] == 0 and nv < verts.shape[0]:
            ok, finite, nxt = _short_vertex(buf, j, n, verts, nv)
            if ok:
                if nonfinite < 0 and not finite:
                    nonfinite = nv
                nv += 1
                nplain += 1
                i = nxt
                continue
        if c1 == 32 and c0 == 102 and nf < cap_f and nc + 3 <= corner_v.shape[0]:
            ok, nxt = _short_triangle(buf, j, n, corner_v, corner_n, nc, has_vn)
            if ok:
                max_v = max(max_v, corner_v[nc], corner_v[nc + 1], corner_v[nc + 2])
                if has_vn:
                    max_n = max(max_n, corner_n[nc], corner_n[nc + 1], corner_n[nc + 2])
                if keep_len:
                    face_len[nf] = 3
                nf += 1
                nc += 3
                i = nxt
                continue
        is_v = is_blank(c1)
        if c0 == 118 and (is_v or (c1 == 110 and (j + 2 >= n or is_blank(buf[j + 2])))):
            _store(st, nv, nf, nc, nplain, max_v, max_n, nonfinite)
            code, at, i = _vertex_line(buf, i, j, n, is_v, st, verts, colours, vnorms, slow, has_vn)
            nv, nf, nc, nplain, max_v, max_n, nonfinite = _load(st)
        elif c0 == 102 and is_v:
            _store(st, nv, nf, nc, nplain, max_v, max_n, nonfinite)
            code, at, i = _face_line(
                buf, i, j, n, st, corner_v, corner_n, face_len, keep_len, has_vn
            )
            nv, nf, nc, nplain, max_v, max_n, nonfinite = _load(st)
        else:
            # anything else (#, vt, vp, o, g, s, l, p, usemtl, mtllib, ...) is skipped
            i = line_end(buf, j, n) + 1
        if code != 0:
            break
    _store(st, nv, nf, nc, nplain, max_v, max_n, nonfinite)
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
def line_kinds(buf, starts, width):
    """``(v, vn, f, corners)`` counted in sample windows of ``buf``.

    How many ``v``, ``vn`` and ``f`` lines start in the windows ``buf[s:s + width]`` (``s`` in
    ``starts``), and how many corners (fields) their ``f`` lines have: a sample from which the
    caller sizes the arrays (they grow when it falls short).
    """
    n = len(buf)
    nv = 0
    nvn = 0
    nf = 0
    nc = 0
    for s in starts:
        e = min(s + width, n)
        p = s if s == 0 else line_end(buf, s - 1, n) + 1  # the first line starting in the window
        while p < e:
            j = skip_space(buf, p, n)
            c1 = buf[j + 1] if j + 1 < n else 10
            if j < n and buf[j] == 118:
                if is_blank(c1):
                    nv += 1
                elif c1 == 110:
                    nvn += 1
            elif j < n and buf[j] == 102 and is_blank(c1):
                nf += 1
                j += 1
                while j < n and buf[j] != 10:
                    j = skip_space(buf, j, n)
                    if j < n and buf[j] != 10:
                        nc += 1
                        j = token_end(buf, j, n)
            p = line_end(buf, j, n) + 1
    return nv, nvn, nf, nc


@njit(cache=True)
def obj_walk(buf, verts, colours, vnorms, corner_v, corner_n, face_len, slow):
    """Walk an OBJ file held in ``buf`` (uint8) once, into the given arrays.

    The caller sizes them from :func:`line_kinds`; they grow when too small. ``corner_n`` empty:
    the caller expects no ``vn`` line; it is made (normals -1 so far) at the first.

    Returns ``(error, byte offset, counts, verts, colours, vnorms, corner_v, corner_n,
    face_len, slow)``, the arrays over-allocated (``counts`` gives their lengths): ``verts``
    (nv, 3), ``colours`` (nv, 3, meaningful when the v lines carry them), ``vnorms``
    (nvn, 3), ``corner_v`` / ``corner_n`` (0-based vertex and normal index of each corner,
    normal -1 when absent; not range-checked; ``corner_n`` stays empty when the file has no
    ``vn`` line), ``face_len`` (corners per face; empty when the caller expects triangles only
    and they are: it is made at the first polygon) and ``slow`` ((k, 4): array 0 verts / 1
    colours / 2 vnorms, flat index, byte start, byte end of each number left to the slow
    path, stored as NaN). ``counts`` also gives the largest vertex and normal index any
    corner names (MAX_V, MAX_VN; -1 when none) and the first vertex with a NaN or infinite
    coordinate (NONFINITE; -1 when none; the slow-path numbers are not looked at).
    """
    st = np.zeros(12, np.int64)
    st[HAS_VN] = 1 if corner_n.shape[0] > 0 else 0
    st[POLYGONS] = 1 if face_len.shape[0] > 0 else 0
    st[MAX_V] = -1
    st[MAX_VN] = -1
    st[NONFINITE] = -1
    i = np.int64(0)  # not a literal 0: _walk (slow to compile) gets one variant, not two
    while True:
        code, at = _walk(buf, i, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow)
        if code != -1:
            return code, at, st, verts, colours, vnorms, corner_v, corner_n, face_len, slow
        i = at
        eol = line_end(buf, i, len(buf))
        verts = _grown(verts, st[NV] + 1)
        if st[COLOURS]:
            colours = _grown(colours, verts.shape[0])
        elif (
            colours.shape[0] < verts.shape[0]
        ):  # nothing in it yet: no copy (its pages stay untouched)
            colours = np.empty_like(verts)
        vnorms = _grown(vnorms, st[NVN] + 1)
        if (
            st[POLYGONS] == 2
        ):  # the first polygon, and the caller expected none: all before are triangles
            face_len = np.full(2 * st[NF] + 1024, 3, np.int64)
            st[POLYGONS] = 1
        elif st[POLYGONS] == 1:
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
    """Fan-triangulate polygons given as runs of ``corner_v``.

    ((m, 3) int64, source face of each).
    """
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
