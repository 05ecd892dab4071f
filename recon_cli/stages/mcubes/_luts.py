"""Tables of marching cubes and marching tetrahedra, generated here from first principles.

Conventions (shared with :mod:`recon_cli.stages.mcubes._kernel`)
--------------------------------------------------------
Corner ``c`` of a cell (0..7) sits at offset ``(c & 1, (c >> 1) & 1, (c >> 2) & 1)``:
bit ``i`` of the corner index is the offset along axis ``i``. A corner is *inside* when its
value is below the iso level; the case index has bit ``c`` set when corner ``c`` is inside.

Edges are the segments between two corners on which a vertex can be made. Each edge is
keyed globally by its lower corner's lattice position plus a *type* (0..2: lattice edges
along x, y, z; 3..5: face diagonals in xy, xz, yz; 6: the body diagonal), so neighbouring
cells find the same vertex. Marching cubes uses the 12 cube edges; marching tetrahedra
the 19 edges of the 6-tetrahedron (Kuhn) split of the cube along its 0-7 diagonal, whose
face diagonals always run from a face's lowest to its highest corner, so the split of a
shared face is the same seen from either cell.

How the marching-cubes table is made
------------------------------------
Rather than transcribing a published table, each case is built from the faces: on each
of the 6 faces the iso-line is a set of segments joining the crossed edges (one segment
for two crossings; two for the four crossings of an ambiguous face, chosen by the face
bit: 1 = the inside corners are joined across the face). Every crossed edge lies on two
faces, so the segments chain into closed loops; each loop is oriented so that, seen from
outside the cube, the outside (positive) region is on its left. A neighbouring cell
computes the same segment on a shared face with the opposite direction, so the union of
all cells is closed. The kernel picks the face bit by the asymptotic decider, which both
cells evaluate from the same four values. Loops are never joined through the cube's
interior (no tunnels), which is the consistent choice.

Each loop is triangulated by the shortest-chord triangulation that avoids chords between
two crossings on one face unless that face is the cell's upper (side 1) face: the cell
across the face could otherwise draw the same chord and make an edge with four
triangles. The 12 loops (9-gons, in 12 of the 16384 rows) that admit no such
triangulation get a vertex of their own at the loop's centre (local id ``CENTER`` = 12,
key type 7) and a fan around it.

Tables
------
``MC_START`` (256 * 64 + 1,) int32 and ``MC_TRIS`` (k, 3) int8:
    triangles of case ``i = case * 64 + face_bits`` are ``MC_TRIS[MC_START[i]:MC_START[i+1]]``
    (local edge ids), counter-clockwise seen from outside (the positive side).
``MC_AMBIGUOUS`` (256,) uint8: bit ``f`` set when face ``f`` is ambiguous in that case.
``MC_CENTRE`` (256 * 64, 12) int8: the loop (edge ids, -1 padded) whose centre vertex a row uses.
``FACE_CORNERS`` (6, 4) int8: corners of face ``f = 2 * axis + side`` in cyclic order.
``MT_START`` (257,) int32 and ``MT_TRIS``: the marching-tetrahedra table, by case only.
``MC_EDGES`` (12, 2), ``MT_EDGES`` (19, 2) int8: corners of each local edge.
``MC_EDGE_KEY`` (13, 4), ``MT_EDGE_KEY`` (19, 4) int8: lower-corner offset (dx, dy, dz)
    and key type of each local vertex.
"""

from __future__ import annotations

import functools

import numpy as np

N_TYPES = 8  # key types: edges along x, y, z, xy, xz, yz, xyz; 7 = a cell's centre vertex


# plain-Python vector helpers: numpy per call would make the derivation several times slower
def corner_pos(c: int) -> tuple[float, float, float]:
    return (float(c & 1), float((c >> 1) & 1), float((c >> 2) & 1))


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _edge_key(a: int, b: int) -> tuple[int, int, int, int]:
    lo, hi = (a, b) if a < b else (b, a)
    d = hi ^ lo  # axes along which the edge runs
    types = {1: 0, 2: 1, 4: 2, 3: 3, 5: 4, 6: 5, 7: 6}
    if lo & d:  # diagonals must run from low to high corner along every axis they span
        raise ValueError(f"edge {a}-{b} is not a low-to-high edge")
    return lo & 1, (lo >> 1) & 1, (lo >> 2) & 1, types[d]


# the 12 cube edges: 4 along x, 4 along y, 4 along z
MC_EDGES = np.array(
    [[c, c | (1 << ax)] for ax in range(3) for c in range(8) if not c & (1 << ax)], dtype=np.int8
)


def _faces() -> np.ndarray:
    out = []
    for ax in range(3):
        u, v = [a for a in range(3) if a != ax]
        for side in (0, 1):
            base = side << ax
            out.append([base, base | (1 << u), base | (1 << u) | (1 << v), base | (1 << v)])
    return np.array(out, dtype=np.int8)


FACE_CORNERS = _faces()


def _face_normal(f: int) -> tuple[float, float, float]:
    n = [0.0, 0.0, 0.0]
    n[f // 2] = 1.0 if f % 2 else -1.0
    return (n[0], n[1], n[2])


def _edge_index(edges: np.ndarray) -> dict:
    return {frozenset((int(a), int(b))): i for i, (a, b) in enumerate(edges)}


_MC_EDGE_OF = _edge_index(MC_EDGES)


def _mid_of(edges: np.ndarray, e: int) -> tuple[float, float, float]:
    a, b = corner_pos(int(edges[e][0])), corner_pos(int(edges[e][1]))
    return (0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1]), 0.5 * (a[2] + b[2]))


_MC_MIDS = [_mid_of(MC_EDGES, e) for e in range(12)]
_FACE_CORNER_LISTS = [[int(c) for c in FACE_CORNERS[f]] for f in range(6)]


def _mid(e: int) -> tuple[float, float, float]:
    return _MC_MIDS[e]


def ambiguous_faces(case: int) -> int:
    """Bit mask of the faces of ``case`` whose four corners alternate inside/outside."""
    mask = 0
    for f in range(6):
        ins = [(case >> c) & 1 for c in _FACE_CORNER_LISTS[f]]
        if ins[0] == ins[2] and ins[1] == ins[3] and ins[0] != ins[1]:
            mask |= 1 << f
    return mask


def face_segments(case: int, f: int, joined: bool) -> list[tuple[int, int]]:
    """Directed iso-line segments (edge, edge) on face ``f`` of ``case``.

    ``joined`` matters only on an ambiguous face: True when its inside corners are
    connected across the face. Direction: seen from outside the cube, the outside
    region is on the left of each segment.
    """
    cyc = _FACE_CORNER_LISTS[f]
    ins = [(case >> c) & 1 for c in cyc]
    side_edges = [_MC_EDGE_OF[frozenset((cyc[i], cyc[(i + 1) % 4]))] for i in range(4)]
    crossed = [i for i in range(4) if ins[i] != ins[(i + 1) % 4]]
    if not crossed:
        return []
    if len(crossed) == 2:
        pairs = [(side_edges[crossed[0]], side_edges[crossed[1]])]
    else:
        p = 0 if ins[0] else 1  # corners cyc[p], cyc[p + 2] are inside
        cut = [p + 1, p + 3] if joined else [p, p + 2]  # corners cut off by a segment
        # corner k lies between side edges k - 1 and k
        pairs = [(side_edges[(k - 1) % 4], side_edges[k % 4]) for k in cut]
    n = _face_normal(f)
    out = []
    for e1, e2 in pairs:
        m1, m2 = _mid(e1), _mid(e2)
        shared = set(map(int, MC_EDGES[e1])) & set(map(int, MC_EDGES[e2]))
        c = shared.pop() if shared else cyc[0]
        left = _dot(_cross(_sub(m2, m1), _sub(corner_pos(c), m1)), n) > 0
        outside = not (case >> c) & 1
        out.append((e1, e2) if left == outside else (e2, e1))
    return out


def cube_loops(case: int, face_bits: int) -> list[list[int]]:
    """Closed, oriented iso-loops of ``case`` (lists of local edge ids)."""
    nxt: dict[int, int] = {}
    for f in range(6):
        for a, b in face_segments(case, f, bool((face_bits >> f) & 1)):
            if a in nxt:
                raise AssertionError(f"case {case}: edge {a} leaves twice")
            nxt[a] = b
    if sorted(nxt) != sorted(nxt.values()):
        raise AssertionError(f"case {case}: segments do not close into loops")
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop, e = [], start
        while e not in seen:
            seen.add(e)
            loop.append(e)
            e = nxt[e]
        loops.append(loop)
    return loops


def _fan(loop: list[int]) -> list[tuple[int, int, int]]:
    return [(loop[0], loop[i], loop[i + 1]) for i in range(1, len(loop) - 1)]


def _edge_faces(e: int) -> set[int]:
    a, b = (int(x) for x in MC_EDGES[e])
    return {f for f in range(6) if a in _FACE_CORNER_LISTS[f] and b in _FACE_CORNER_LISTS[f]}


_EDGE_FACES = [_edge_faces(e) for e in range(12)]


@functools.cache
def _chord_ok(a: int, b: int) -> bool:
    """Whether a triangle edge inside a loop may join crossings on cube edges ``a`` and ``b``.

    Two crossings on one face are also both in the neighbour across that face, which
    might join them too (an edge with four triangles). Only the cell below the face (the
    face is its side-1 face) may, so the two cells never both do.
    """
    return all(f % 2 == 1 for f in _EDGE_FACES[a] & _EDGE_FACES[b])


def _triangulate(loop: list[int]) -> list[tuple[int, int, int]] | None:
    """Shortest-chord triangulation of a loop using allowed chords only (None if none)."""
    n = len(loop)
    if n == 3:
        return [(loop[0], loop[1], loop[2])]
    mids = [_mid(e) for e in loop]
    inf = float("inf")
    cost = [[0.0] * n for _ in range(n)]  # cost of the side (i, k); polygon sides are free
    for i in range(n):
        for k in range(i + 2, n):
            if i == 0 and k == n - 1:
                continue
            d = _sub(mids[i], mids[k])
            cost[i][k] = _dot(d, d) ** 0.5 if _chord_ok(loop[i], loop[k]) else inf

    def w(i: int, k: int) -> float:
        return cost[i][k]

    best: dict[tuple[int, int], tuple[float, int]] = {}
    for span in range(2, n):
        for i in range(0, n - span):
            j = i + span
            cand = (inf, -1)
            for k in range(i + 1, j):
                c = (
                    w(i, k)
                    + w(k, j)
                    + (best[(i, k)][0] if k - i > 1 else 0.0)
                    + (best[(k, j)][0] if j - k > 1 else 0.0)
                )
                if c < cand[0]:
                    cand = (c, k)
            best[(i, j)] = cand
    if best[(0, n - 1)][1] < 0:
        return None
    out: list[tuple[int, int, int]] = []
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        k = best[(i, j)][1]
        out.append((loop[i], loop[k], loop[j]))
        if k - i > 1:
            stack.append((i, k))
        if j - k > 1:
            stack.append((k, j))
    return out


CENTER = 12  # local id of a vertex made at the centre of a loop that has no valid triangulation


def _build_mc() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    start = np.zeros(256 * 64 + 1, dtype=np.int32)
    centre = np.full((256 * 64, 12), -1, dtype=np.int8)
    tris: list[tuple[int, int, int]] = []
    amb = np.zeros(256, dtype=np.uint8)
    for case in range(256):
        amb[case] = ambiguous_faces(case)
        for bits in range(64):
            i = case * 64 + bits
            start[i] = len(tris)
            if bits & ~int(amb[case]):
                continue  # the kernel only sets bits of ambiguous faces
            for loop in cube_loops(case, bits):
                t = _triangulate(loop)
                if t is None:  # rare 9-gons: fan around a centre vertex
                    if centre[i, 0] >= 0:
                        raise AssertionError(f"case {case}: two loops need a centre")
                    centre[i, : len(loop)] = loop
                    t = [(CENTER, loop[k], loop[(k + 1) % len(loop)]) for k in range(len(loop))]
                tris.extend(t)
    start[-1] = len(tris)
    return start, np.array(tris, dtype=np.int8).reshape(-1, 3), amb, centre


# the centre vertex (local id 12) belongs to its cell alone: type 7
MC_EDGE_KEY = np.array(
    [*(_edge_key(int(a), int(b)) for a, b in MC_EDGES), (0, 0, 0, 7)], dtype=np.int8
)

# --- marching tetrahedra -------------------------------------------------------------------
# the 6 tetrahedra of the Kuhn split: paths 0 -> 0 + e_i -> 0 + e_i + e_j -> 7
TETS = np.array(
    [[0, 1 << i, (1 << i) | (1 << j), 7] for i in range(3) for j in range(3) if i != j],
    dtype=np.int8,
)
MT_EDGES = np.array(
    sorted(
        {
            tuple(sorted((int(t[a]), int(t[b]))))
            for t in TETS
            for a in range(4)
            for b in range(a + 1, 4)
        }
    ),
    dtype=np.int8,
)
_MT_EDGE_OF = _edge_index(MT_EDGES)
MT_EDGE_KEY = np.array([_edge_key(int(a), int(b)) for a, b in MT_EDGES], dtype=np.int8)


def _tet_triangles(case: int, tet: np.ndarray) -> list[tuple[int, int, int]]:
    ins = [int(c) for c in tet if (case >> int(c)) & 1]
    out = [int(c) for c in tet if not (case >> int(c)) & 1]
    if not ins or not out:
        return []
    if len(ins) == 1:
        poly = [_MT_EDGE_OF[frozenset((ins[0], o))] for o in out]
    elif len(out) == 1:
        poly = [_MT_EDGE_OF[frozenset((i, out[0]))] for i in ins]
    else:
        (a, b), (c, d) = ins, out
        poly = [_MT_EDGE_OF[frozenset(p)] for p in ((a, c), (a, d), (b, d), (b, c))]  # a cycle
    # orient by geometry: the normal must point from the inside corners to the outside ones
    mids = [_mid_of(MT_EDGES, e) for e in poly]
    normal = (0.0, 0.0, 0.0)
    for k in range(1, len(poly) - 1):
        c = _cross(_sub(mids[k], mids[0]), _sub(mids[k + 1], mids[0]))
        normal = (normal[0] + c[0], normal[1] + c[1], normal[2] + c[2])
    po = [corner_pos(c) for c in out]
    pi = [corner_pos(c) for c in ins]
    direction = tuple(
        sum(p[a] for p in po) / len(po) - sum(p[a] for p in pi) / len(pi) for a in range(3)
    )
    if _dot(normal, direction) < 0:
        poly = poly[::-1]
    return _fan(poly)


def _build_mt() -> tuple[np.ndarray, np.ndarray]:
    start = np.zeros(257, dtype=np.int32)
    tris: list[tuple[int, int, int]] = []
    for case in range(256):
        start[case] = len(tris)
        for tet in TETS:
            tris.extend(_tet_triangles(case, tet))
    start[-1] = len(tris)
    return start, np.array(tris, dtype=np.int8).reshape(-1, 3)


# --- the stored tables ------------------------------------------------------------------
# Deriving the marching-cubes table takes ~0.4 s, too long for every command: the result is
# stored beside the code in _lut_data.npz (read by recon_cli.stages.mcubes._lut_data) and a test
# derives it again and compares. After changing the derivation, regenerate it with
#     python -m recon_cli.stages.mcubes._luts
TABLES_FILE = "_lut_data.npz"
_DERIVED = ("MC_START", "MC_TRIS", "MC_AMBIGUOUS", "MC_CENTRE", "MT_START", "MT_TRIS")


@functools.cache
def build_tables() -> dict[str, np.ndarray]:
    """Every table the kernels use, derived here: the names of the module docstring's ``Tables``."""
    mc_start, mc_tris, mc_amb, mc_centre = _build_mc()
    mt_start, mt_tris = _build_mt()
    return {
        "MC_START": mc_start,
        "MC_TRIS": mc_tris,
        "MC_AMBIGUOUS": mc_amb,
        "MC_CENTRE": mc_centre,
        "MT_START": mt_start,
        "MT_TRIS": mt_tris,
        "MC_EDGES": MC_EDGES,
        "MC_EDGE_KEY": MC_EDGE_KEY,
        "FACE_CORNERS": FACE_CORNERS,
        "MT_EDGES": MT_EDGES,
        "MT_EDGE_KEY": MT_EDGE_KEY,
        "CENTER": np.array(CENTER, dtype=np.int8),
    }


def __getattr__(name: str):
    if name in _DERIVED:  # derived on first use, not at import
        return build_tables()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def write_tables(path: str | None = None) -> str:
    """Store :func:`build_tables` as ``_lut_data.npz`` beside this module (or at ``path``).

    Returns the path.
    """
    import os

    path = path or os.path.join(os.path.dirname(os.path.abspath(__file__)), TABLES_FILE)
    with open(path, "wb") as fh:
        # numpy's stub types **kwds as its keyword allow_pickle
        np.savez_compressed(fh, **build_tables())  # type: ignore[arg-type]
    return path


if __name__ == "__main__":  # pragma: no cover
    print(write_tables())
