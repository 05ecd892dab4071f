"""Every per-point property of the input carried onto the surface's vertices.

This is ``--attributes`` (PoissonRecon's ``--colors`` and ``--data``), without bleeding across
nearby surfaces.

Each vertex takes its values from the input points near it *on its own side*: among its
:data:`NEIGHBOURS` nearest points, those whose normal agrees with the surface's normal at the
vertex (positive dot product), weighted by a Gaussian of their distance (sigma one finest
cell of the tree, the nearest agreeing point always counting). Points on the other side of a
thin part face the other way and give nothing, so the two faces of a plate coloured
differently keep their colours (PoissonRecon#312: its colours are splatted into the tree
and averaged per node, across the plate). A vertex with no agreeing point among
:data:`FALLBACK_NEIGHBOURS` takes its nearest point's values (counted in the report:
``attribute_fallback_vertices``).

- Numeric properties (floats, colours, and integers whose name says a measurement:
  :data:`MEASURES`, such as ``intensity``) are the weighted mean, rounded and clipped to
  the type for integers.
- Integer codes (LAS ``classification``, ``return_number``, ``point_source_id``, any other
  integer or boolean property) take the value with the largest summed weight (ties: the
  smallest value), so no vertex gets a code no point has.

Every property keeps its dtype.

References
----------
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Kazhdan, M. PoissonRecon issue #312 (colour bleeding through thin parts).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon_cli.errors import ParameterError

# nearest input points read per vertex; more for the vertices none of them agrees with
NEIGHBOURS = 16
FALLBACK_NEIGHBOURS = 64
# vertices per block of the transfer (the neighbours' tables: ~40 bytes a neighbour)
CHUNK = 1 << 16
# integer properties that are measurements (averaged), by lower-case name; the others are codes
MEASURES = frozenset(
    {
        "intensity",
        "amplitude",
        "reflectance",
        "deviation",
        "scan_angle",
        "scan_angle_rank",
        "red",
        "green",
        "blue",
        "alpha",
        "nir",
        "infrared",
        "range",
        "distance",
        "confidence",
        "quality",
        "density",
        "height",
        "elevation",
        "temperature",
    }
)
# the names ``--attributes`` accepts for the colours
COLOR_NAMES = ("colors", "color", "colours", "colour", "rgb")


def is_code(name: str, values: np.ndarray) -> bool:
    """Whether a property is a code (majority) rather than a measurement (mean)."""
    kind = values.dtype.kind
    if kind == "b":
        return True
    return kind in "iu" and name.lower() not in MEASURES


def select(spec, names: list[str], has_colors: bool) -> tuple[list[str], bool]:
    """The properties ``--attributes`` asks for.

    ``all`` (every one, the default), ``none``, or names separated by commas (``colors`` for the
    colours); returns (names, colours).

    Raises
    ------
    ParameterError
        A name the input does not have (the message lists what it has).
    """
    if isinstance(spec, (list, tuple)):  # a pipeline's list of names
        spec = ",".join(str(x) for x in spec) or "none"
    text = "all" if spec is None else str(spec).strip()
    if text.lower() == "all":
        return list(names), has_colors
    if text.lower() == "none":
        return [], False
    asked = [w.strip() for w in text.split(",") if w.strip()]
    if not asked:
        raise ParameterError("--attributes must be all, none or names separated by commas")
    out, colors = [], False
    for w in asked:
        if w.lower() in COLOR_NAMES and has_colors:
            colors = True
        elif w in names:
            if w not in out:
                out.append(w)
        else:
            have = [*names, *(["colors"] if has_colors else [])]
            listed = ", ".join(have) if have else "none"
            raise ParameterError(
                f"--attributes: the input has no property {w!r} (it has: {listed})"
            )
    return out, colors


@dataclass
class Transfer:
    """What :func:`transfer` returns."""

    values: dict[str, np.ndarray] = field(default_factory=dict)
    colors: np.ndarray | None = None
    fallback: int = 0  # vertices with no agreeing point near: their nearest point's values


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit area-weighted normals of the faces around each vertex (0 where none)."""
    t = verts[faces]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    vn = np.zeros_like(verts)
    for c in range(3):
        np.add.at(vn, faces[:, c], fn)
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, ln, out=np.zeros_like(vn), where=ln > 0)


def transfer(
    points: np.ndarray,
    normals: np.ndarray,
    values: dict[str, np.ndarray],
    colors: np.ndarray | None,
    verts: np.ndarray,
    faces: np.ndarray,
    cell: float,
) -> Transfer:
    """Each vertex's properties from the input points near it on its side (module docstring).

    Parameters
    ----------
    points : (n, 3) float
        The input points (world units) the surface was made from.
    normals : (n, 3) float
        Their (outward) normals.
    values : dict of str to (n,) array
        The properties to carry.
    colors : (n, c) array or None
        The points' colours.
    verts, faces
        The surface.
    cell : float
        The Gaussian's sigma (one finest cell of the tree, world units).

    Returns
    -------
    Transfer
        Per-vertex arrays in the properties' dtypes.
    """
    from scipy.spatial import cKDTree

    out = Transfer()
    m = len(verts)
    if m == 0 or (not values and colors is None):
        out.values = {k: v[:0].copy() for k, v in values.items()}
        out.colors = None if colors is None else colors[:0].copy()
        return out
    tree = cKDTree(points)
    vn = vertex_normals(verts, faces)
    res = {k: np.empty(m, v.dtype) for k, v in values.items()}
    col = None if colors is None else np.empty((m, colors.shape[1]), colors.dtype)
    for a in range(0, m, CHUNK):
        b = min(m, a + CHUNK)
        idx, w, fb = _weights(tree, points, normals, verts[a:b], vn[a:b], cell)
        out.fallback += fb
        for k, v in values.items():
            res[k][a:b] = (_majority if is_code(k, v) else _mean)(v, idx, w)
        if colors is not None:
            assert col is not None  # made with the colours
            for c in range(colors.shape[1]):
                col[a:b, c] = _mean(colors[:, c], idx, w)
    out.values, out.colors = res, col
    return out


def _weights(
    tree, points: np.ndarray, normals: np.ndarray, verts: np.ndarray, vn: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """(m, k) neighbour indices and weights (rows sum to 1) and the number of fallbacks."""
    k = min(NEIGHBOURS, len(points))
    dist, idx = tree.query(verts, k=k, workers=-1)
    dist, idx = dist.reshape(len(verts), k), idx.reshape(len(verts), k)
    w, none = _side_weights(points, normals, verts, vn, dist, idx, cell)
    fallback = 0
    if none.any():
        rows = np.flatnonzero(none)
        k2 = min(FALLBACK_NEIGHBOURS, len(points))
        d2, i2 = tree.query(verts[rows], k=k2, workers=-1)
        d2, i2 = d2.reshape(len(rows), k2), i2.reshape(len(rows), k2)
        w2, none2 = _side_weights(points, normals, verts[rows], vn[rows], d2, i2, cell)
        # the nearest point alone where no point agrees (the surface's far sheets)
        w2[none2] = 0.0
        w2[none2, 0] = 1.0
        fallback = int(none2.sum())
        # widen the rows: the fallback rows' k2 neighbours, the others' k padded with 0
        wide_i = np.zeros((len(verts), k2), np.int64)
        wide_w = np.zeros((len(verts), k2))
        wide_i[:, :k], wide_w[:, :k] = idx, w
        wide_i[rows], wide_w[rows] = i2, w2
        idx, w = wide_i, wide_w
    return idx, w, fallback


def _side_weights(points, normals, verts, vn, dist, idx, cell):
    """Gaussian weights of the neighbours on the vertex's side, rows normalised.

    And the rows with no such neighbour.
    """
    agree = np.einsum("mkj,mj->mk", normals[idx], vn) > 0.0
    w = np.exp(-0.5 * (dist / cell) ** 2) * agree
    # the nearest agreeing point always counts (far from the samples every weight underflows)
    first = np.argmax(agree, axis=1)
    rows = np.arange(len(verts))
    has = agree[rows, first]
    w[rows[has], first[has]] = np.maximum(w[rows[has], first[has]], 1e-300)
    s = w.sum(axis=1)
    w[has] /= s[has, None]
    return w, ~has


def _mean(v: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted mean per row, in ``v``'s dtype (integers rounded and clipped)."""
    x = (v[idx].astype(np.float64) * w).sum(axis=1)
    if v.dtype.kind in "iu":
        info = np.iinfo(v.dtype)
        return np.clip(np.round(x), info.min, info.max).astype(v.dtype)
    return x.astype(v.dtype)


def _majority(v: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The value with the largest summed weight per row (ties.

    The smallest): each row's values sorted, equal ones summed, the first largest sum taken.
    """
    vals = v[idx]
    out = vals[:, 0].copy()
    # rows whose neighbours all agree (most, away from class borders) need no vote
    mixed = np.flatnonzero((vals != vals[:, :1]).any(axis=1))
    if len(mixed):
        out[mixed] = _vote(vals[mixed], w[mixed])
    return out


def _vote(vals: np.ndarray, w: np.ndarray) -> np.ndarray:
    """:func:`_majority` on rows of values (m, k) and weights (codes as int64 in the kernel.

    One compiled signature for every dtype).
    """
    from recon_cli.stages.poisson._attributes import weighted_mode

    out = np.empty(len(vals), np.int64)
    weighted_mode(np.ascontiguousarray(vals, np.int64), np.ascontiguousarray(w, np.float64), out)
    return out.astype(vals.dtype)
