"""Numba kernels of the extraction.

The level set over the leaves of the tree at their own size (:func:`leaf_polygons`, Kazhdan, Klein,
Dalal & Hoppe 2007; see :mod:`.extract`) and the roots on edges; the finest-lattice variant is
in :mod:`._extract_finest`.

They only compute; conventions in :mod:`recon_cli.stages.poisson._octree`.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)
from recon_cli._kernels.arrays import lower_bound
from recon_cli._kernels.hashtable import probe, table_bits
from recon_cli.stages.poisson._octree import MASK21, lattice_key

# ---------------------------------------------------------------------------------------------
# extraction at the leaves' own resolution (Kazhdan, Klein, Dalal & Hoppe 2007)
#
# The levels but the finest are concatenated: level l's cells are ``keys[coff[l]:coff[l + 1]]``
# (sorted lattice keys, see :mod:`._octree`) with ``leaf`` flags and ``nodes`` (corner nodes,
# indices local to the level), its nodes' chi ``g[goff[l]:goff[l + 1]]``; the finest level D
# (the largest, all leaves) is passed as it is, ``fkeys``, ``fnodes``, ``fg``, its cells
# numbered from ``coff[D]`` on (not copied: no second copy of the tree at the peak).
# chi at corner q of cell c of level l is ``fg[fnodes[c - coff[D], q & 3] + (q >> 2)]`` at the
# finest level, ``g[goff[l] + nodes[c, q & 3] + (q >> 2)]`` above it: written out where it is
# read, not as a helper taking the five arrays (inlined by numba, such a helper kept their
# reference counting in the loops: 1.5x slower, see docs/design/poisson.md).
# ``_state`` gives -1 for a cell that is not in the tree, its index for a leaf and -2 - index
# for a cell with children. Points are in finest-lattice units (``R = 2**depth``). A minimal
# edge is keyed by its lower end and axis (:func:`edge_key`).


@njit(cache=True, inline="always")
def _state(keys, leaf, coff, fkeys, D, lev, x, y, z):
    n = np.int64(1) << lev
    if x < 0 or y < 0 or z < 0 or x >= n or y >= n or z >= n:
        return -1
    key = lattice_key(x, y, z)
    if lev == D:
        i = lower_bound(fkeys, key, 0, len(fkeys))
        if i == len(fkeys) or fkeys[i] != key:
            return -1
        return coff[D] + i  # the finest cells are all leaves
    i = lower_bound(keys, key, coff[lev], coff[lev + 1])
    if i == coff[lev + 1] or keys[i] != key:
        return -1
    return i if leaf[i] else -2 - i


@njit(cache=True, inline="always")
def clamp_faces(v, x, y, z, R, cap):
    if x == 0 or y == 0 or z == 0 or x == R or y == R or z == R:
        return min(v, cap)
    return v


@njit(cache=True, inline="always")
def edge_key(x, y, z, axis, R):
    """Key of the minimal edge from finest-lattice point (x, y, z) along ``axis``."""
    return ((np.int64(x) * (R + 1) + y) * (R + 1) + z) * 4 + axis


# what _minimal_edges reads of the tree (the levels' arrays and the lattice's size) ...
TreeView = namedtuple("TreeView", "keys leaf nodes g coff goff fkeys fnodes fg D R cap")
# ... and the scratch it writes: its stack, a cell, and the edges found (start, length, values)
EdgeScratch = namedtuple("EdgeScratch", "stack cell buf_p buf_len buf_v")


@njit(cache=True)
def _minimal_edges(tree, scratch, l0, e0, axis, hint, hxyz, m):
    """Append the minimal edges of a level-``l0`` lattice edge to the buffers, in order.

    The edge starts at ``e0`` (3,) along ``axis``; an edge is split when one of the 4 cells of its
    level around it has children. Values come from a leaf of the edge's level that holds it (every
    leaf with a corner at a point gives the same value: finer corrections vanish there and the
    prolongation copies coincident nodes exactly). ``hint``: index of a leaf of level ``l0`` holding
    the edge, lower corner ``hxyz`` (3,), or -1. ``tree`` is a :data:`TreeView`, ``scratch`` an
    :data:`EdgeScratch` whose buffers hold ``m`` edges. Returns the new count.

    Written out in one loop: each pop is a few lookups, and a helper per pop taking the tree's
    arrays costs more than they do (``docs/design/poisson.md``).
    """
    keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D, R, cap = tree
    stack, cell, buf_p, buf_len, buf_v = scratch
    b = (axis + 1) % 3
    c = (axis + 2) % 3
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = l0, e0[0], e0[1], e0[2]
    top = 1
    while top > 0:
        top -= 1
        lev, x, y, z = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        split = False
        found = -1
        fq = 0
        use_hint = hint >= 0 and lev == l0
        if use_hint:
            found = hint
            fq = (x - hxyz[0]) | ((y - hxyz[1]) << 1) | ((z - hxyz[2]) << 2)
        # the 4 cells of the level around the edge (the finest cells have no children: with the
        # hint, nothing to look up)
        for t in range(0 if use_hint and lev == D else 4):
            db, dc = t >> 1, t & 1
            cell[0], cell[1], cell[2] = x, y, z
            cell[b] -= db
            cell[c] -= dc
            if use_hint and cell[0] == hxyz[0] and cell[1] == hxyz[1] and cell[2] == hxyz[2]:
                continue
            s = _state(keys, leaf, coff, fkeys, D, lev, cell[0], cell[1], cell[2])
            if s <= -2:
                split = True
            elif s >= 0 and found < 0:
                found = s
                fq = (db << b) | (dc << c)
        if split:
            # upper half pushed first: the lower one comes out first
            for h in range(2):
                stack[top + h, 0], stack[top + h, 1] = lev + 1, 2 * x
                stack[top + h, 2], stack[top + h, 3] = 2 * y, 2 * z
            stack[top, 1 + axis] += 1
            top += 2
            continue
        sh = D - lev
        px, py, pz = x << sh, y << sh, z << sh
        ln = np.int64(1) << sh
        q1 = fq | (1 << axis)
        if lev == D:
            v0 = fg[fnodes[found - coff[D], fq & 3] + (fq >> 2)]
            v1 = fg[fnodes[found - coff[D], q1 & 3] + (q1 >> 2)]
        else:
            v0 = g[goff[lev] + nodes[found, fq & 3] + (fq >> 2)]
            v1 = g[goff[lev] + nodes[found, q1 & 3] + (q1 >> 2)]
        buf_p[m, 0], buf_p[m, 1], buf_p[m, 2] = px, py, pz
        buf_len[m] = ln
        buf_v[m, 0] = clamp_faces(v0, px, py, pz, R, cap)
        # the far end along the axis
        ex, ey, ez = (ln if axis == 0 else 0), (ln if axis == 1 else 0), (ln if axis == 2 else 0)
        buf_v[m, 1] = clamp_faces(v1, px + ex, py + ey, pz + ez, R, cap)
        m += 1
    return m


@njit(cache=True)
def _grow2(a, n):
    out = np.empty((max(n, 2 * a.shape[0]), a.shape[1]), a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _grow1(a, n):
    out = np.empty(max(n, 2 * a.shape[0]), a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _rehash(tk, tv, bits):
    """The hash table (``tk`` keys, ``tv`` values, capacity ``1 << bits``) at twice the capacity."""
    nb = bits + 1
    nk = np.full(1 << nb, -1, np.int64)
    nv = np.empty(1 << nb, np.int64)
    for i in range(tk.shape[0]):
        if tk[i] != -1:
            s = probe(nk, nb, tk[i])
            nk[s] = tk[i]
            nv[s] = tv[i]
    return nk, nv, nb


@njit(cache=True, inline="always")
def _tri_area(p, i, j, k):
    ax = p[j, 0] - p[i, 0]
    ay = p[j, 1] - p[i, 1]
    az = p[j, 2] - p[i, 2]
    bx = p[k, 0] - p[i, 0]
    by = p[k, 1] - p[i, 1]
    bz = p[k, 2] - p[i, 2]
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return np.sqrt(cx * cx + cy * cy + cz * cz)


MAX_DP = 12  # loops up to this size get a minimal-area triangulation, larger ones a fan


@njit(cache=True, inline="always")
def _triangulate(n, lp, lm, cost, split, st, tris):
    """Minimal-area triangulation of the loop ``lp`` (n, 3) with allowed diagonals only.

    A diagonal may join only roots on no common face of the leaf (``lm``: bit masks of the leaf's
    faces each root lies on; two roots on one face may be joined by the leaf across it too, so such
    a diagonal could be used twice). Writes (n - 2, 3) loop indices into ``tris`` and returns True,
    or returns False when no such triangulation exists.
    """
    inf = 1e300
    for i in range(n):
        for j in range(n):
            cost[i, j] = inf
    for i in range(n - 1):
        cost[i, i + 1] = 0.0
    for gap in range(2, n):
        for i in range(n - gap):
            j = i + gap
            if not (j - i == 1 or (i == 0 and j == n - 1) or (lm[i] & lm[j]) == 0):
                continue
            best = inf
            bk = -1
            for k in range(i + 1, j):
                cc = cost[i, k] + cost[k, j]
                if cc >= inf:
                    continue
                cc += _tri_area(lp, i, k, j)
                if cc < best:
                    best = cc
                    bk = k
            cost[i, j] = best
            split[i, j] = bk
    if cost[0, n - 1] >= inf:
        return False
    # unwind the splits (``st``: (n, 2) scratch)
    st[0, 0] = 0
    st[0, 1] = n - 1
    top = 1
    t = 0
    while top > 0:
        top -= 1
        i = st[top, 0]
        j = st[top, 1]
        if j - i < 2:
            continue
        k = split[i, j]
        tris[t, 0] = i
        tris[t, 1] = k
        tris[t, 2] = j
        t += 1
        st[top, 0] = i
        st[top, 1] = k
        st[top + 1, 0] = k
        st[top + 1, 1] = j
        top += 2
    return True


# the per-leaf scratch of leaf_polygons (fixed sizes): the minimal-face stack, the corner values
# (raw and clamped), the leaf's bounds, a minimal face's hint corner and edge start, and where
# each of its four sides' edges start in the edge buffer
FaceWork = namedtuple("FaceWork", "qstack raw clv lo3 hi3 hxyz e0 starts")
# the level set: the iso-value, the straddle tolerance, the roots' distance from edge ends
Level = namedtuple("Level", "iso eps clamp")
# growing buffers: a face's roots (edge key, whether the walk enters the inside, position), a
# leaf's segments (root keys from/to, end points) and one loop (root keys, positions, the leaf
# faces each root lies on, vertex ids, the segments visited)
Roots = namedtuple("Roots", "key up pos")
Segments = namedtuple("Segments", "key pos")
Loop = namedtuple("Loop", "key pos mask vid visited")
# the mesh so far: triangles, vertices, each vertex's edge key (-1: a fan centre) and the roots'
# hash table (edge key -> vertex); the counts (triangles, vertices, roots, hash bits) live in
# an int64 (4,) array beside it
Out = namedtuple("Out", "tri vpos vkey tk tv")
# the minimal-area triangulation's tables (MAX_DP loops)
Triangulation = namedtuple("Triangulation", "cost split stack tris")


@njit(cache=True)
def _leaf_range(tree, ci, lev, cx, cy, cz, side, work):
    """The corner values of a leaf into ``work.raw`` and ``work.clv`` (clamped); (min clv, max)."""
    keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D, R, cap = tree
    lo = 1e300
    hi = -1e300
    for q in range(8):
        v = (
            fg[fnodes[ci - coff[D], q & 3] + (q >> 2)]
            if lev == D
            else g[goff[lev] + nodes[ci, q & 3] + (q >> 2)]
        )
        work.raw[q] = v
        work.clv[q] = clamp_faces(
            v,
            (cx + (q & 1)) * side,
            (cy + ((q >> 1) & 1)) * side,
            (cz + (q >> 2)) * side,
            R,
            cap,
        )
        lo = min(lo, work.clv[q])
        hi = max(hi, v)
    return lo, hi


@njit(cache=True)
def _face_edges(tree, scratch, work, ll, a, wl, u, vv, hint):
    """The minimal edges around the level-``ll`` face at ``wl`` on axis ``a``, corner (u, vv).

    Its boundary counter-clockwise about +a: side 0 from (u, vv) along +b, 1 from (u+1, vv) along
    +c, 2 from (u, vv+1) along +b and 3 from (u, vv) along +c (the caller walks 2 and 3
    backwards). The edges go to ``scratch``'s buffers, each side's first index to
    ``work.starts`` (and the end to ``starts[4]``). ``hint``: the leaf holding the face, lower
    corner ``work.hxyz``.
    """
    keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D, R, cap = tree
    ebuf_p, ebuf_len, ebuf_v = scratch.buf_p, scratch.buf_len, scratch.buf_v
    e0, hxyz, starts = work.e0, work.hxyz, work.starts
    b = (a + 1) % 3
    c = (a + 2) % 3
    m = 0
    for sd in range(4):
        e0[a] = wl
        e0[b] = u + (1 if sd == 1 else 0)
        e0[c] = vv + (1 if sd == 2 else 0)
        ax = b if sd % 2 == 0 else c
        starts[sd] = m
        if ll == D:
            # a finest edge: never split, its values are the hint leaf's corners (what
            # _minimal_edges does, without the call)
            fq = (e0[0] - hxyz[0]) | ((e0[1] - hxyz[1]) << 1) | ((e0[2] - hxyz[2]) << 2)
            hf = hint - coff[D]  # a finest leaf
            v0 = clamp_faces(fg[fnodes[hf, fq & 3] + (fq >> 2)], e0[0], e0[1], e0[2], R, cap)
            qq = fq | (1 << ax)
            v1 = clamp_faces(
                fg[fnodes[hf, qq & 3] + (qq >> 2)],
                e0[0] + (qq & 1) - (fq & 1),
                e0[1] + ((qq >> 1) & 1) - ((fq >> 1) & 1),
                e0[2] + (qq >> 2) - (fq >> 2),
                R,
                cap,
            )
            ebuf_p[m, 0] = e0[0]
            ebuf_p[m, 1] = e0[1]
            ebuf_p[m, 2] = e0[2]
            ebuf_len[m] = 1
            ebuf_v[m, 0] = v0
            ebuf_v[m, 1] = v1
            m += 1
        else:
            m = _minimal_edges(tree, scratch, ll, e0, ax, hint, hxyz, m)
    starts[4] = m


@njit(cache=True)
def _face_roots(scratch, work, lim, R, a, roots):
    """The roots on the edges :func:`_face_edges` found, in walk order.

    Returns ``(n, centre_in, roots)``: their number, whether chi at the face's centre (bilinear
    on it) is inside, and the buffers (grown when needed) holding each root's edge key, whether
    the walk enters the inside there, and its position (linear interpolation, kept
    ``lim.clamp`` of the edge away from its ends: no two roots at one point).
    """
    ebuf_p, ebuf_len, ebuf_v = scratch.buf_p, scratch.buf_len, scratch.buf_v
    starts = work.starts
    iso = lim.iso
    b = (a + 1) % 3
    c = (a + 2) % 3
    corner_sum = 0.0
    nroots = 0
    for sd in range(4):
        elo = starts[sd]
        ehi = starts[sd + 1]
        first = elo if sd < 2 else ehi - 1
        corner_sum += ebuf_v[first, 0] if sd < 2 else ebuf_v[first, 1]
        for i in range(elo, ehi):
            if (ebuf_v[i, 0] > iso) != (ebuf_v[i, 1] > iso):
                nroots += 1
    if nroots == 0:
        return 0, False, roots
    centre_in = corner_sum * 0.25 > iso
    if roots.key.shape[0] < nroots:
        roots = Roots(
            np.empty(2 * nroots, np.int64),
            np.empty(2 * nroots, np.bool_),
            np.empty((2 * nroots, 3)),
        )
    kr = 0
    for sd in range(4):
        elo = starts[sd]
        ehi = starts[sd + 1]
        ax = b if sd % 2 == 0 else c
        for jj in range(ehi - elo):
            i = elo + jj if sd < 2 else ehi - 1 - jj
            va = ebuf_v[i, 0]
            vb = ebuf_v[i, 1]
            if (va > iso) == (vb > iso):
                continue
            roots.key[kr] = edge_key(ebuf_p[i, 0], ebuf_p[i, 1], ebuf_p[i, 2], ax, R)
            # walked from its start (sides 0, 1) or its end (sides 2, 3)
            roots.up[kr] = (vb > iso) if sd < 2 else (va > iso)
            t = (iso - va) / (vb - va)
            t = min(max(t, lim.clamp), 1.0 - lim.clamp)
            roots.pos[kr, 0] = ebuf_p[i, 0]
            roots.pos[kr, 1] = ebuf_p[i, 1]
            roots.pos[kr, 2] = ebuf_p[i, 2]
            roots.pos[kr, ax] += t * ebuf_len[i]
            kr += 1
    return nroots, centre_in, roots


@njit(cache=True)
def _pair_roots(roots, nroots, centre_in, s, segs, ns):
    """Append a face's iso-segments to ``segs`` (``ns`` held); returns ``(ns, segs)``.

    Consecutive roots are paired without crossings by the centre's side: inside, the inside
    arcs are joined. Each segment runs from the root where the walk leaves the inside to the one
    where it enters, reversed when the leaf lies above the face (``s`` 1).
    """
    if ns + nroots > segs.key.shape[0]:
        segs = Segments(_grow2(segs.key, ns + nroots), _grow2(segs.pos, ns + nroots))
    rup = roots.up
    for i in range(nroots):
        j = (i + 1) % nroots
        # down -> next up joins an outside arc (centre inside); up -> next down an inside arc
        if centre_in and not rup[i] and rup[j]:
            fr, to = i, j
        elif (not centre_in) and rup[i] and not rup[j]:
            fr, to = j, i
        else:
            continue
        if s == 1:
            fr, to = to, fr
        segs.key[ns, 0] = roots.key[fr]
        segs.key[ns, 1] = roots.key[to]
        for q in range(3):
            segs.pos[ns, q] = roots.pos[fr, q]
            segs.pos[ns, 3 + q] = roots.pos[to, q]
        ns += 1
    return ns, segs


@njit(cache=True, inline="always")
def _face_range(work, a, s):
    """The range of a leaf's face across axis ``a`` (``s`` 0 low, 1 high): (min clamped, max).

    Chi is bilinear on it; clamped points only lower it (``work.clv``, ``work.raw``).
    """
    flo = 1e300
    fhi = -1e300
    for q in range(8):
        if ((q >> a) & 1) == s:
            flo = min(flo, work.clv[q])
            fhi = max(fhi, work.raw[q])
    return flo, fhi


@njit(cache=True)
def _leaf_segments(tree, scratch, work, lim, ci, lev, cell, roots, segs):
    """The iso-segments of the minimal faces covering a leaf's boundary (:func:`leaf_polygons`).

    ``cell``: the leaf's (x, y, z) at its level; its corner values are in ``work`` and its bounds
    in ``work.lo3`` / ``hi3``. Returns ``(ns, roots, segs)``: the segments' count and the
    buffers, grown when needed.
    """
    keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D, R, cap = tree
    qstack, hxyz = work.qstack, work.hxyz
    cx, cy, cz = cell
    ns = 0
    for a in range(3):
        b = (a + 1) % 3
        c = (a + 2) % 3
        ca = cell[a]
        for s in range(2):
            w = ca + s
            if w == 0 or w == (np.int64(1) << lev):
                continue  # on the cube's faces: outside
            flo, fhi = _face_range(work, a, s)
            if flo > lim.iso + lim.eps or fhi < lim.iso - lim.eps:
                continue
            # minimal faces: the leaves' faces on the far side where it is finer
            qstack[0, 0] = lev
            qstack[0, 1] = cell[b]
            qstack[0, 2] = cell[c]
            top = 1
            while top > 0:
                top -= 1
                ll, u, vv = qstack[top, 0], qstack[top, 1], qstack[top, 2]
                wl = w << (ll - lev)
                na = wl if s == 1 else wl - 1
                # the cell across (a finest leaf: the far side is no finer, and no lookup)
                ix, iy, iz = (na, u, vv) if a == 0 else ((vv, na, u) if a == 1 else (u, vv, na))
                st = (
                    -1
                    if ll == D and ll == lev
                    else _state(keys, leaf, coff, fkeys, D, ll, ix, iy, iz)
                )
                if st <= -2:
                    for o in range(4):
                        qstack[top, 0] = ll + 1
                        qstack[top, 1] = 2 * u + (o & 1)
                        qstack[top, 2] = 2 * vv + (o >> 1)
                        top += 1
                    continue
                # the leaf whose face this is: the far one when it is a leaf of this level,
                # else this one (then the face is the whole of its own)
                if st >= 0:
                    hint = st
                    hxyz[a] = na
                    hxyz[b] = u
                    hxyz[c] = vv
                else:
                    hint = ci
                    hxyz[0] = cx
                    hxyz[1] = cy
                    hxyz[2] = cz
                _face_edges(tree, scratch, work, ll, a, wl, u, vv, hint)
                nroots, centre_in, roots = _face_roots(scratch, work, lim, R, a, roots)
                if nroots:
                    ns, segs = _pair_roots(roots, nroots, centre_in, s, segs, ns)
    return ns, roots, segs


@njit(cache=True)
def _chain_loop(segs, ns, i0, order, sfrom, loop, work, R):
    """Chain the segments from ``i0`` into a loop; its roots go to ``loop``.

    Each root ends one segment and starts the next. Returns ``(n, ok)``: the loop's length and
    whether it closed. ``order`` / ``sfrom``: the segments sorted by their first root (unused for
    16 or fewer: then a linear search). A root's mask has bit 2q (2q + 1) when its edge lies on
    the leaf's lower (upper) face across axis q.
    """
    small = ns <= 16
    n = 0
    cur = i0
    while True:
        loop.visited[cur] = True
        rk = segs.key[cur, 0]
        loop.key[n] = rk
        loop.pos[n, 0] = segs.pos[cur, 0]
        loop.pos[n, 1] = segs.pos[cur, 1]
        loop.pos[n, 2] = segs.pos[cur, 2]
        ax = rk & 3
        rest = rk >> 2
        pz = rest % (R + 1)
        rest //= R + 1
        py = rest % (R + 1)
        px = rest // (R + 1)
        mk = 0
        for q in range(3):
            pq = px if q == 0 else (py if q == 1 else pz)
            if q != ax:
                if pq == work.lo3[q]:
                    mk |= 1 << (2 * q)
                if pq == work.hi3[q]:
                    mk |= 1 << (2 * q + 1)
        loop.mask[n] = mk
        n += 1
        nxt = -1
        if small:
            for i in range(ns):
                if segs.key[i, 0] == segs.key[cur, 1]:
                    nxt = i
                    break
        else:
            idx = lower_bound(sfrom, segs.key[cur, 1], 0, ns)
            if idx < ns and sfrom[idx] == segs.key[cur, 1]:
                nxt = order[idx]
        if nxt < 0:
            return n, False
        cur = nxt
        if cur == i0:
            return n, True
        if loop.visited[cur]:
            return n, False


@njit(cache=True)
def _emit_loop(out, counts, loop, n, tr):
    """Weld a loop's roots and triangulate it; returns ``out``, grown when needed.

    One vertex per minimal edge, whichever leaf meets it first; a minimal-area triangulation,
    or a fan about a new vertex at the loop's centroid (its edges are its own).
    """
    tri, vpos, vkey, tk, tv = out
    nt, nv, nroot, bits = counts[0], counts[1], counts[2], counts[3]
    lp, lid = loop.pos, loop.vid
    if nt + n > tri.shape[0]:
        tri = _grow2(tri, nt + n)
    if nv + n + 1 > vpos.shape[0]:
        vpos = _grow2(vpos, nv + n + 1)
        vkey = _grow1(vkey, nv + n + 1)
    if 2 * (nroot + n) > tk.shape[0]:
        tk, tv, bits = _rehash(tk, tv, bits)
    for i in range(n):
        sl = probe(tk, bits, loop.key[i])
        if tk[sl] == -1:
            tk[sl] = loop.key[i]
            tv[sl] = nv
            vpos[nv, 0] = lp[i, 0]
            vpos[nv, 1] = lp[i, 1]
            vpos[nv, 2] = lp[i, 2]
            vkey[nv] = loop.key[i]
            nv += 1
            nroot += 1
        lid[i] = tv[sl]
    if n == 3:
        tri[nt, 0] = lid[0]
        tri[nt, 1] = lid[1]
        tri[nt, 2] = lid[2]
        nt += 1
    elif n <= MAX_DP and _triangulate(n, lp, loop.mask, tr.cost, tr.split, tr.stack, tr.tris):
        for t in range(n - 2):
            for q in range(3):
                tri[nt, q] = lid[tr.tris[t, q]]
            nt += 1
    else:
        for q in range(3):
            sm = 0.0
            for i in range(n):
                sm += lp[i, q]
            vpos[nv, q] = sm / n
        vkey[nv] = -1
        for i in range(n):
            tri[nt, 0] = nv
            tri[nt, 1] = lid[i]
            tri[nt, 2] = lid[(i + 1) % n]
            nt += 1
        nv += 1
    counts[0], counts[1], counts[2], counts[3] = nt, nv, nroot, bits
    return Out(tri, vpos, vkey, tk, tv)


@njit(cache=True, nogil=True)  # chunks of cells run in threads of their own (.extract)
def leaf_polygons(tree, surface, xlo, xhi, c0, c1):
    """Iso-surface triangles of the leaves numbered ``c0`` to ``c1 - 1`` at the leaf's own size.

    The leaves are those cells in [``c0``, ``c1``) (the levels' numbering below) whose lower x
    (finest-lattice units) is in [``xlo``, ``xhi``): a slab's part of the mesh. A chunk's
    vertices are its own; :func:`weld_chunks` joins the chunks' meshes.

    ``tree`` is ``(keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D)``: the levels'
    sorted cell keys, leaf flags, the cells' corner nodes and chi at the nodes, concatenated, and
    the finest level D's as they are (see above). ``surface`` is ``(iso, eps, margin, clamp)``.
    Each leaf whose corner range reaches ``iso`` (within ``eps``) gathers the iso-segments of
    the minimal faces covering its boundary (:func:`_leaf_segments`), chains them into loops
    and triangulates each loop (:func:`_emit_loops`). Points on the cube's faces count as
    outside (chi clamped to ``iso - margin``); a root is kept ``clamp`` of its edge away from
    the edge's ends.

    Returns ``tri`` (t, 3) int64 vertex indices, ``vpos`` (v, 3) the vertices (finest-lattice
    units): one per minimal edge crossing the level set, shared by every leaf around it (welded
    through a hash table of edge keys), and the fan centres; ``vkey`` (v,) each vertex's edge
    key (-1 for a fan centre); and the number of segment chains that did not close into a loop
    (0 unless something is wrong).
    """
    keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D = tree
    iso, eps, margin, clamp = surface
    R = np.int64(1) << D
    view = TreeView(keys, leaf, nodes, g, coff, goff, fkeys, fnodes, fg, D, R, iso - margin)
    lim = Level(iso, eps, clamp)
    scratch, work, roots, segs, loop, out, tr = _buffers(D)
    counts = np.array([0, 0, 0, 12], np.int64)
    none = np.empty(0, np.int64)
    broken = 0
    for lev in range(D + 1):
        side = np.int64(1) << (D - lev)
        end = min(c1, coff[lev + 1] if lev < D else coff[D] + len(fkeys))
        for ci in range(max(c0, coff[lev]), end):
            if lev < D:
                if not leaf[ci]:
                    continue
                k = keys[ci]
            else:
                k = fkeys[ci - coff[D]]
            cx = (k >> 42) & MASK21
            if cx * side < xlo or cx * side >= xhi:
                continue
            cy = (k >> 21) & MASK21
            cz = k & MASK21
            lo, hi = _leaf_range(view, ci, lev, cx, cy, cz, side, work)
            if lo > iso + eps or hi < iso - eps:
                continue
            work.lo3[0] = cx * side
            work.lo3[1] = cy * side
            work.lo3[2] = cz * side
            for q in range(3):
                work.hi3[q] = work.lo3[q] + side
            ns, roots, segs = _leaf_segments(
                view, scratch, work, lim, ci, lev, (cx, cy, cz), roots, segs
            )
            if ns == 0:
                continue
            loop, out, nb = _emit_loops(segs, ns, loop, work, R, out, counts, tr, none, none)
            broken += nb
    return out.tri[: counts[0]], out.vpos[: counts[1]], out.vkey[: counts[1]], broken


@njit(cache=True)
def _buffers(D):
    """The buffers of :func:`leaf_polygons` at their first sizes, for a tree of depth ``D``.

    ``(scratch, work, roots, segs, loop, out, tr)``: an :data:`EdgeScratch`, a :data:`FaceWork`,
    :data:`Roots`, :data:`Segments`, a :data:`Loop`, the mesh :data:`Out` and the
    :data:`Triangulation`'s tables.
    """
    ne = 4 * (np.int64(1) << D) + 8
    scratch = EdgeScratch(
        np.empty((2 * (D + 3), 4), np.int64),
        np.empty(3, np.int64),
        np.empty((ne, 3), np.int64),
        np.empty(ne, np.int64),
        np.empty((ne, 2)),
    )
    i3 = np.empty(3, np.int64)
    work = FaceWork(
        np.empty((4 * (D + 3), 3), np.int64),
        np.empty(8),
        np.empty(8),
        i3.copy(),
        i3.copy(),
        i3.copy(),
        i3.copy(),
        np.empty(5, np.int64),
    )
    roots = Roots(np.empty(64, np.int64), np.empty(64, np.bool_), np.empty((64, 3)))
    segs = Segments(np.empty((64, 2), np.int64), np.empty((64, 6)))
    out = Out(
        np.empty((1024, 3), np.int64),
        np.empty((1024, 3)),
        np.empty(1024, np.int64),
        np.full(1 << 12, -1, np.int64),
        np.empty(1 << 12, np.int64),
    )
    tr = Triangulation(
        np.empty((MAX_DP, MAX_DP)),
        np.empty((MAX_DP, MAX_DP), np.int64),
        np.empty((MAX_DP, 2), np.int64),
        np.empty((MAX_DP, 3), np.int64),
    )
    return scratch, work, roots, segs, _loop_buffer(64), out, tr


@njit(cache=True)
def _loop_buffer(size):
    """A :data:`Loop` of ``size`` roots, none visited."""
    return Loop(
        np.empty(size, np.int64),
        np.empty((size, 3)),
        np.empty(size, np.int64),
        np.empty(size, np.int64),
        np.zeros(size, np.bool_),
    )


@njit(cache=True, inline="always")
def _emit_loops(segs, ns, loop, work, R, out, counts, tr, order, sfrom):
    """Chain a leaf's ``ns`` segments into loops (:func:`_chain_loop`) and triangulate each.

    (:func:`_emit_loop`.) Returns ``(loop, out, broken)``: the buffers, grown when needed, and
    the number of chains that did not close into a loop. ``order``, ``sfrom``: empty arrays,
    :func:`_chain_loop`'s (made here for more than 16 segments).
    """
    if loop.visited.shape[0] < ns:
        loop = _loop_buffer(segs.key.shape[0])
    if ns > 16:
        order = np.argsort(segs.key[:ns, 0])
        sfrom = segs.key[:ns, 0][order]
    loop.visited[:ns] = False
    broken = 0
    for i0 in range(ns):
        if loop.visited[i0]:
            continue
        n, ok = _chain_loop(segs, ns, i0, order, sfrom, loop, work, R)
        if ok and n == 2:
            # two roots on one edge of the leaf joined on both its faces there (chi clamped at
            # the cube's faces is not linear along such an edge): a loop of no area, left out,
            # which glues the leaves across those faces directly
            continue
        if not ok or n < 3:
            broken += 1
            continue
        out = _emit_loop(out, counts, loop, n, tr)
    return loop, out, broken


@njit(cache=True)
def weld_chunks(vkey, voff, tri, toff):
    """One mesh from the chunks' meshes of :func:`leaf_polygons`, concatenated in chunk order.

    Chunk ``c``'s vertices are ``vkey[voff[c]:voff[c + 1]]`` (edge keys, -1 a fan centre), its
    triangles ``tri[toff[c]:toff[c + 1]]`` (indices local to the chunk). Vertices with one edge
    key become one, numbered in order of first appearance, so the mesh is the one a single
    chunk of every leaf gives, whatever the chunks. Returns the triangles (global indices) and,
    per global vertex, the index of its first appearance in ``vkey``.
    """
    n = vkey.shape[0]
    bits = table_bits(n)
    tk = np.full(np.int64(1) << bits, -1, np.int64)
    tv = np.empty(np.int64(1) << bits, np.int64)
    gid = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    nv = 0
    for i in range(n):
        k = vkey[i]
        if k == -1:
            gid[i] = nv
            first[nv] = i
            nv += 1
            continue
        s = probe(tk, bits, k)
        if tk[s] == -1:
            tk[s] = k
            tv[s] = nv
            gid[i] = nv
            first[nv] = i
            nv += 1
        else:
            gid[i] = tv[s]
    out = np.empty_like(tri)
    for c in range(toff.shape[0] - 1):
        for t in range(toff[c], toff[c + 1]):
            for q in range(3):
                out[t, q] = gid[voff[c] + tri[t, q]]
    return out, first[:nv]


@njit(cache=True)
def fit_roots(fm, f0, f1, f2, iso, clamp):
    """Per edge, the root of a quadratic fit of chi through the ends' values, or -1.

    The quadratic's slopes at the ends are in the ratio of chi's central differences there (values
    ``fm``, ``f0``, ``f1``, ``f2`` at lattice steps -1, 0, 1, 2), as a fraction of the edge in
    [clamp, 1 - clamp]: the cubic Hermite interpolant with its end slopes scaled so that their mean
    is the secant's (its cubic term then vanishes), as PoissonRecon's non-linear fit; the root
    nearest the linear one when there are two; -1 where the ends do not straddle ``iso``.
    """
    n = len(f0)
    out = np.full(n, -1.0)
    for i in range(n):
        g0 = f0[i] - iso
        g1 = f1[i] - iso
        if not (g0 * g1 < 0.0):
            continue
        lin = g0 / (g0 - g1)
        m0 = 0.5 * (f1[i] - fm[i])
        m1 = 0.5 * (f2[i] - f0[i])
        t = lin
        if (m0 + m1) * (g1 - g0) > 0.0:
            # p(t) = g0 + b t + a t^2 with p(1) = g1 and p'(0) / p'(1) = m0 / m1
            b = m0 * (g1 - g0) / (0.5 * (m0 + m1))
            a = g1 - g0 - b
            if abs(a) <= 1e-12 * abs(b):
                t = -g0 / b
            else:
                disc = b * b - 4.0 * a * g0
                if disc >= 0.0:
                    sq = np.sqrt(disc)
                    # the two roots, computed without cancellation
                    q = -0.5 * (b + sq if b >= 0.0 else b - sq)
                    r1 = q / a
                    r2 = g0 / q if q != 0.0 else r1
                    best = -1.0
                    for r in (r1, r2):
                        if 0.0 <= r <= 1.0 and (best < 0.0 or abs(r - lin) < abs(best - lin)):
                            best = r
                    if best >= 0.0:
                        t = best
        out[i] = min(max(t, clamp), 1.0 - clamp)
    return out
