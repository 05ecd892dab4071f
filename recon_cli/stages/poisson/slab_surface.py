"""A slab's surface: chi at its nodes, the leaves it owns extracted, then its side of the merge.

Each step takes the slab's state (:class:`.slab.Slab`) after the solve and returns a small
message for the coordinator (:mod:`.stitch` holds the coordinator's side of the merge):
chi at the tree's nodes with the neighbours' bands next to each seam (:func:`field`), the
surface of the leaves it owns (:func:`extract`), the input points near its pieces, the
vertices of possible folds, its faces' density for the trim threshold, the trimmed pieces,
the surface normals at the seam vertices, and finally its vertices and faces written to
files (:func:`export`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.errors import StageFailed
from recon_cli.memory import release_free_heap
from recon_cli.slabs.runners import reads_only, timed
from recon_cli.stages.poisson import _bspline_eval as BE
from recon_cli.stages.poisson import _extract_finest as EF
from recon_cli.stages.poisson.octree import (
    Level,
    corner_keys,
    pack_keys,
    set_corners,
    unpack_keys,
)
from recon_cli.stages.poisson.slab import (
    Slab,
    apply_band,
    float_histogram,
    global_table,
    values_in,
)
from recon_cli.stages.poisson.splat import density_table, eval_density


@reads_only
@timed
def island_points(slab: Slab, lo: np.ndarray, hi: np.ndarray) -> dict:
    """How many of the slab's own points lie in each box (k, 3) ``lo``..``hi``."""
    from recon_cli.stages.poisson.octree import points_in_boxes

    own = slab.pts if slab.own_pt is None else slab.pts[slab.own_pt]
    return {"counts": points_in_boxes(own, lo, hi)}


@reads_only
@timed
def fold_vertices(
    slab: Slab, which: np.ndarray, anchor: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> dict:
    """The vertices that decide the folds: :func:`.pieces.reach_vertices` of the slab's mesh."""
    from recon_cli.stages.poisson.pieces import reach_vertices

    return reach_vertices(slab.verts, slab.faces, slab.labels, which, anchor, lo, hi)


def _seam_ranks(slab: Slab) -> tuple[np.ndarray, np.ndarray]:
    """(nv,) rank of each vertex among the left seam's / right seam's vertices (-1 if none).

    The seam vertices sit first (left) and last (right) in the slab's vertices, in the order both
    slabs of a seam give them.
    """
    nv = len(slab.verts)
    nl, nr = slab.seam["left"], slab.seam["right"]
    rl = np.full(nv, -1, np.int64)
    rr = np.full(nv, -1, np.int64)
    rl[:nl] = np.arange(nl)
    rr[nv - nr :] = np.arange(nr)
    return rl, rr


def _links(slab: Slab, faces: np.ndarray, labels: np.ndarray) -> dict:
    """Per seam, the seam edges (both ends on it) of ``faces`` and the faces' pieces.

    A piece goes on across the seam through its edges there (an edge key: the ends' ranks).
    """
    rl, rr = _seam_ranks(slab)
    out = {}
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lab = np.tile(labels, 3)
    for side, rank in (("left", rl), ("right", rr)):
        ra, rb = rank[e[:, 0]], rank[e[:, 1]]
        ok = (ra >= 0) & (rb >= 0)
        key = np.minimum(ra, rb)[ok] * (1 << 31) + np.maximum(ra, rb)[ok]
        out[side] = (key, lab[ok])
    return out


def _seam_use(slab: Slab, faces: np.ndarray) -> dict:
    """Per seam, which of its vertices ``faces`` use."""
    used = np.zeros(len(slab.verts), bool)
    used[faces.reshape(-1)] = True
    nv = len(used)
    nl, nr = slab.seam["left"], slab.seam["right"]
    return {"left": used[:nl], "right": used[nv - nr :]}


def _compact(slab: Slab, keep_faces: np.ndarray, extra: dict | None = None) -> None:
    """Keep the faces flagged and the vertices they use, seam layout kept.

    The left seam's vertices first, the right seam's last, in their order.
    """
    faces = slab.faces[keep_faces]
    used = np.zeros(len(slab.verts), bool)
    used[faces.reshape(-1)] = True
    nv = len(used)
    nl, nr = slab.seam["left"], slab.seam["right"]
    # seam vertices stay when either slab of the seam uses them (extra: the global verdict)
    if extra is not None:
        used[:nl] |= extra["left"]
        used[nv - nr :] |= extra["right"]
    remap = np.cumsum(used) - 1
    slab.faces = remap[faces]
    slab.verts = slab.verts[used]
    if slab.vdens is not None:
        slab.vdens = slab.vdens[used]
    slab.seam = {"left": int(used[:nl].sum()), "right": int(used[nv - nr :].sum())}


@timed
def prepare(
    slab: Slab, drop: np.ndarray, density: tuple | None, at_samples: bool, envelope: Any = None
) -> dict:
    """Drop the pieces the coordinator dropped.

    The density at the vertices (``density``: None, ``(level,)`` the slab's own table, ``(level,
    keys, dens)`` a global one) and, with ``at_samples``, the histogram of the own samples' density
    (the trim's median). ``envelope`` (job axes): the vertices outside it pulled inside first
    (``pulled``: how many of the slab's own).
    """
    job = slab.job
    keep = ~np.isin(slab.labels, drop) if len(drop) else np.ones(len(slab.faces), bool)
    slab.labels = None
    msg: dict[str, Any] = {}
    if envelope is not None:
        from recon_cli.stages.poisson.slab_envelope import pull_vertices

        msg["pulled"] = pull_vertices(slab, envelope, keep)
    if density is not None:
        if len(density) == 1:
            table = slab.tables.get(density[0])
            if table is None:
                table = density_table(slab.smp, density[0])
        else:
            table = global_table(*density)
        slab.tables = {"out": table}
        origin = np.asarray(job.origin)
        v = slab.verts
        slab.vdens = eval_density(table, (v - origin) / job.size) if len(v) else np.zeros(0)
        if at_samples:
            own = slab.smp.pos[slab.own_s]
            slab.at_samples = eval_density(table, own) if len(own) else np.zeros(0)
            msg["hist"] = float_histogram(slab.at_samples)
    _compact(slab, keep)
    msg["seam_use"] = _seam_use(slab, slab.faces)
    return msg


@reads_only
@timed
def density_values(slab: Slab, bins: np.ndarray) -> dict:
    """The density at the own samples in ``bins`` (a median's second round)."""
    return {"values": values_in(slab.at_samples, bins)}


def _unit_gap(slab: Slab, u: np.ndarray) -> np.ndarray:
    """Distance (unit cube) from unit-cube x ``u`` to the nearer end of the slab's points."""
    lo = np.inf if slab.pad[0] <= 0.0 else u - slab.pad[0]
    hi = np.inf if slab.pad[1] >= 1.0 else slab.pad[1] - u
    return np.minimum(lo, hi)


@timed
def auto_spacing(slab: Slab) -> dict:
    """``--trim auto``'s first round: the samples' local spacing (:func:`.trim.local_spacing`).

    Over the slab's samples and its pads'. Returns the histogram of the own samples' spacing (the
    cap's global median) and how many own samples looked past the pad (``inexact``).
    """
    from scipy.spatial import cKDTree

    from recon_cli.stages.poisson.trim import local_spacing

    pos = slab.smp.pos
    if len(pos) < 2:
        slab.spacing = np.full(len(pos), np.inf)
        slab.at_samples = slab.spacing[slab.own_s]
        return {"hist": float_histogram(slab.at_samples), "inexact": 0}
    slab.spacing, reach = local_spacing(cKDTree(pos))
    own = slab.own_s
    slab.at_samples = slab.spacing[own]
    inexact = int(np.count_nonzero(reach[own] >= _unit_gap(slab, pos[own, 0])))
    return {"hist": float_histogram(slab.at_samples), "inexact": inexact}


@timed
def auto_values(slab: Slab, median: float) -> dict:
    """``--trim auto``'s value at the vertices and the own samples nearest each.

    ``median``: the samples' median spacing over all slabs (the cap); the value is minus the
    support ratio (:func:`.trim.spacing_ratio`), cut at minus :data:`.trim.SUPPORT_RATIO`.
    """
    from scipy.spatial import cKDTree

    from recon_cli.stages.poisson.trim import capped_spacing, nearest_counts, spacing_ratio

    job = slab.job
    pos = slab.smp.pos
    v = (slab.verts - np.asarray(job.origin)) / job.size
    slab.at_samples = None
    if not len(v):
        slab.support, slab.mass, slab.spacing = np.zeros(0), np.zeros(0), None
        return {}
    if not len(pos):
        raise StageFailed(
            f"distributed poisson: slab {slab.index} has surface but no sample within its pad "
            "to trim by: use fewer --partitions"
        )
    spacing = capped_spacing(slab.spacing, median)
    slab.spacing = None
    slab.support = -spacing_ratio(cKDTree(pos), spacing, v)
    own = pos[slab.own_s]
    slab.mass = nearest_counts(own, v) if len(own) else np.zeros(len(v))
    return {}


@timed
def trim_cut(slab: Slab, threshold: float) -> dict:
    """The trim's cut (:func:`.trim.cut_by_density`) of the slab's faces.

    By the density at the vertices, or by ``--trim auto``'s value (:func:`auto_values`), the
    density then carried. Returns the areas and the pieces of the low side (small ones are holes
    the trim keeps).
    """
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.stages.poisson.trim import carried_at_cut, cut_by_density

    auto = slab.support is not None
    v, f = slab.verts, slab.faces
    d = slab.support if auto else slab.vdens
    assert d is not None  # the trim runs on the density at the vertices, or auto's value
    high = d > threshold
    nh = high[f].sum(axis=1) if len(f) else np.zeros(0, np.int64)
    nv = len(v)
    nl, nr = slab.seam["left"], slab.seam["right"]
    slab.trim = {"whole_high": int((nh == 3).sum()), "whole_low": int((nh == 0).sum())}
    msg: dict[str, Any] = {"faces": len(f), "cut": bool(len(f) and nh.min() < 3)}
    if len(f):
        verts, faces, side, dens, edges = cut_by_density(v, f, d, threshold, high, nh)
    else:
        verts, faces, side, dens, edges = v, f, np.zeros(0, bool), d, np.zeros((0, 2), np.int64)
    held: np.ndarray | None = None
    carried: np.ndarray | None = dens
    if auto:
        # the cut vertices stand for no sample; the density goes along as the positions do
        assert slab.mass is not None  # set with the support by auto_values
        held = np.concatenate([slab.mass > 0, np.zeros(len(verts) - nv, bool)])
        carried = None if slab.vdens is None else carried_at_cut(slab.vdens, d, edges, threshold)
        slab.support = slab.mass = None
    # the new vertices on a seam's edges belong to the seam: they join its vertices, in the
    # order both slabs give them (by position along the plane)
    sd = np.zeros(len(verts), np.int8)
    sd[:nl] = -1
    sd[nv - nr : nv] = 1
    if len(edges):
        # a new vertex on an edge of two vertices of one seam is on that seam
        a, b = sd[edges[:, 0]], sd[edges[:, 1]]
        sd[nv:] = np.where(a == b, a, 0)
    order = np.concatenate(
        [
            _by_plane_position(verts, np.flatnonzero(sd == -1)),
            np.flatnonzero(sd == 0),
            _by_plane_position(verts, np.flatnonzero(sd == 1)),
        ]
    )
    inv = np.empty(len(order), np.int64)
    inv[order] = np.arange(len(order))
    slab.verts, slab.faces = verts[order], inv[faces]
    slab.vdens = None if carried is None else carried[order]
    slab.seam = {"left": int((sd == -1).sum()), "right": int((sd == 1).sum())}
    area = Connectivity(slab.faces, len(slab.verts), slab.verts).face_areas
    slab.trim.update(side=side, area=area, held=None if held is None else held[order])
    msg["area"] = float(area.sum())
    msg["kept_area"] = float(area[side].sum())
    msg.update(_part(slab, ~side, area))
    return msg


def _by_plane_position(verts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    return idx[np.lexsort((verts[idx, 2], verts[idx, 1]))]


def _part(slab: Slab, part: np.ndarray, area: np.ndarray) -> dict:
    """The pieces of the faces flagged ``part``, their areas and seam links.

    Pieces are joined across edges.
    """
    from recon_cli.mesh.topology import Connectivity

    idx = np.flatnonzero(part)
    faces = slab.faces[idx]
    lab = (
        Connectivity(faces, len(slab.verts)).face_components.astype(np.int64)
        if len(idx)
        else np.zeros(0, np.int64)
    )
    slab.trim["part"], slab.trim["labels"] = idx, lab
    n = int(lab.max()) + 1 if len(lab) else 0
    msg = {
        "areas": np.bincount(lab, weights=area[idx], minlength=n),
        "links": _links(slab, faces, lab),
    }
    held = slab.trim.get("held")
    if held is not None:
        # a piece some sample lies nearest to (--trim auto keeps such islands)
        msg["held"] = np.bincount(lab, weights=held[faces].any(axis=1), minlength=n) > 0
    return msg


@timed
def trim_keep(slab: Slab, flip: np.ndarray) -> dict:
    """Keep the holes the coordinator re-admitted (low pieces ``flip``).

    Returns the pieces of what is kept (small ones are islands the trim drops) and the seams'
    vertices they use per piece.
    """
    t = slab.trim
    keep = t["side"].copy()
    if len(flip):
        keep[t["part"][np.isin(t["labels"], flip)]] = True
    t["keep"] = keep
    msg = _part(slab, keep, t["area"])
    idx = slab.trim["part"]
    faces = slab.faces[idx]
    lab = slab.trim["labels"]
    rl, rr = _seam_ranks(slab)
    fl = faces.reshape(-1)
    lab3 = np.repeat(lab, 3)
    msg["seam_pieces"] = {
        "left": (rl[fl][rl[fl] >= 0], lab3[rl[fl] >= 0]),
        "right": (rr[fl][rr[fl] >= 0], lab3[rr[fl] >= 0]),
    }
    msg["seam_counts"] = dict(slab.seam)
    return msg


@timed
def trim_drop(slab: Slab, drop: np.ndarray, seam_keep: dict) -> dict:
    """Drop the kept side's islands; the report's figures of the trim."""
    t = slab.trim
    keep = t["keep"]
    if len(drop):
        keep[t["part"][np.isin(t["labels"], drop)]] = False
    wh, wl = t["whole_high"], t["whole_low"]
    msg = {
        "removed_area": float(t["area"][~keep].sum()),
        "untouched": int(wh + keep[wh : wh + wl].sum()),
    }
    slab.trim = None
    _compact(slab, keep, seam_keep)
    msg["faces"] = len(slab.faces)
    return msg


@timed
def seam_normals(slab: Slab, seam_keep: dict | None) -> dict:
    """Keep the seam vertices either slab uses (``seam_keep``, as :func:`export`).

    The faces' normals summed at each vertex (the attributes' side test); returns the right seam's
    sums: the next slab owns those vertices and adds them to its own faces'.
    """
    from recon_cli.stages.poisson.attributes import vertex_normal_sums

    if seam_keep is not None:
        _compact(slab, np.ones(len(slab.faces), bool), seam_keep)
    v, f = slab.verts, slab.faces
    slab.vn_sum = vertex_normal_sums(v, f) if len(f) else np.zeros_like(v)
    return {"right": slab.vn_sum[len(v) - slab.seam["right"] :]}


def _pad_gap(slab: Slab, x: np.ndarray) -> np.ndarray:
    """Distance (world units) from job-frame x to the nearer end of the slab's points.

    Inf on the side where the cube ends: no point lies beyond.
    """
    job = slab.job
    u = (x - job.origin[0]) / job.size
    lo = np.inf if slab.pad[0] <= 0.0 else (u - slab.pad[0]) * job.size
    hi = np.inf if slab.pad[1] >= 1.0 else (slab.pad[1] - u) * job.size
    return np.minimum(lo, hi)


def _attributes(slab: Slab, v: np.ndarray, own: np.ndarray, left_sum) -> tuple[dict, Any, dict]:
    """The input's properties at the slab's own vertices ``v``.

    By :func:`.attributes.transfer`, the surface's normal at a seam vertex summed over both slabs'
    faces.
    """
    from recon_cli.stages.poisson.attributes import transfer, unit_rows

    vn = slab.vn_sum
    nl = slab.seam["left"]
    if left_sum is not None and nl:
        vn[:nl] += left_sum
    cell = slab.job.size / (1 << slab.tree_depth)
    if len(v) and not len(slab.pts):
        raise StageFailed(
            f"distributed poisson: slab {slab.index} has surface but no input point within "
            "its pad to carry attributes from: use fewer --partitions or --attributes none"
        )
    moved = transfer(
        slab.pts, slab.unit_nrm, slab.props or {}, slab.colors, v, None, cell, unit_rows(vn[own])
    )
    inexact = 0
    if moved.reach is not None:
        inexact = int(np.count_nonzero(moved.reach >= _pad_gap(slab, v[:, 0])))
    stats = {"fallback": int(moved.fallback), "inexact": inexact}
    return moved.values, moved.colors, stats


@timed
def export(
    slab: Slab,
    seam_keep: dict | None,
    prefix: str | None = None,
    left_sum: np.ndarray | None = None,
) -> dict:
    """The slab's output: its own vertices and its faces.

    The vertices (the left seam's first, then the others; the right seam's belong to the next slab)
    carry the input's properties, colours and density; the faces' references to the right seam's
    vertices are ``-1 - rank``. ``seam_keep``: per seam, the vertices either slab uses (both export
    the same ones; None when :func:`seam_normals` kept them); ``left_sum``: the previous slab's face
    normals summed at the left seam's vertices. With ``prefix`` the arrays go to
    ``prefix.<name>.npy`` (the message names them), else in the message.
    """
    job = slab.job
    if seam_keep is not None:
        _compact(slab, np.ones(len(slab.faces), bool), seam_keep)
    faces, verts = slab.faces, slab.verts
    nv = len(verts)
    nr = slab.seam["right"]
    right = np.zeros(nv, bool)
    right[nv - nr :] = True
    index = np.cumsum(~right) - 1
    rank = np.cumsum(right) - 1
    fl = faces.reshape(-1)
    out_f = np.where(right[fl], -1 - rank[fl], index[fl]).reshape(-1, 3)
    v = verts[~right]
    msg: dict[str, Any] = {"left_seam": slab.seam["left"], "right_seam": nr, "attributes": {}}
    if slab.props or slab.colors is not None:
        values, colors, msg["attribute_stats"] = _attributes(slab, v, ~right, left_sum)
        msg["attributes"] = values
        if colors is not None:
            msg["colors"] = colors
    if job.density:
        assert slab.vdens is not None  # set by extract with the density asked
        msg["attributes"]["density"] = slab.vdens[~right]
    msg["vertices"] = v
    msg["faces"] = out_f
    slab.faces = slab.verts = slab.vdens = slab.vn_sum = None
    slab.props = slab.colors = slab.unit_nrm = None
    msg["counts"] = (len(v), len(out_f))
    msg["box"] = (v.min(axis=0), v.max(axis=0)) if len(v) else None
    if prefix is not None:
        for name in ("vertices", "faces", "colors"):
            if name in msg:
                np.save(f"{prefix}.{name}.npy", msg[name])
                msg[name] = f"{prefix}.{name}.npy"
        files = {}
        for i, (name, arr) in enumerate(msg["attributes"].items()):
            files[name] = f"{prefix}.a{i:03d}.npy"
            np.save(files[name], arr)
        msg["attributes"] = files
    return msg


def plane_values(
    levels: list[Level], gvals: list[np.ndarray], pts: np.ndarray, iso: float, margin: float
) -> np.ndarray:
    """The extraction's value at finest-lattice points ``pts`` (m, 3) of a seam plane.

    The value is negated chi, clamped on the cube's faces as
    :func:`._extract_finest.refine_leaves` clamps, from one leaf whichever slab asks: the leaf
    holding the finest cell whose lower corner the point is (the one below along an axis where
    the point is on the cube's far face). Both slabs of a seam read the same leaves and corner
    values there, so they give the same bits.
    """
    top = len(levels) - 1
    R = 1 << top
    cap = -iso + margin
    out = np.full(len(pts), np.nan)
    cell = np.minimum(pts, R - 1)
    todo = np.arange(len(pts))
    for lev, g in zip(levels[::-1], gvals[::-1], strict=True):
        if not len(todo) or not len(lev.cell_keys):
            continue
        sh = top - lev.depth
        key = pack_keys(cell[todo] >> sh)
        i = np.minimum(np.searchsorted(lev.cell_keys, key), len(lev.cell_keys) - 1)
        hit = lev.cell_keys[i] == key  # the finest cell holding the point's cell: a leaf
        if not hit.any():
            continue
        rows = todo[hit]
        c = i[hit]
        side = float(1 << sh)
        f = (pts[rows] - ((cell[rows] >> sh) << sh)) / side
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        v = np.zeros(len(rows))
        assert lev.cell_nodes is not None  # the tree's levels have their corners set
        for r in range(8):
            w = (
                (fx if r & 1 else 1.0 - fx)
                * (fy if (r >> 1) & 1 else 1.0 - fy)
                * (fz if (r >> 2) & 1 else 1.0 - fz)
            )
            v += w * -g[lev.cell_nodes[c, r & 3] + (r >> 2)]
        face = np.any((pts[rows] == 0) | (pts[rows] == R), axis=1)
        v[face] = np.maximum(v[face], cap)
        out[rows] = v
        todo = todo[~hit]
    if len(todo):
        raise StageFailed("distributed poisson: a seam point lies in no leaf of the tree")
    return out


def _seam_order(lat: np.ndarray, on: np.ndarray) -> np.ndarray:
    """Indices of the vertices flagged ``on``, sorted by their lattice (y, z) then x."""
    idx = np.flatnonzero(on)
    return idx[np.lexsort((lat[idx, 0], lat[idx, 2], lat[idx, 1]))]


@timed
def field(
    slab: Slab,
    iso: float,
    band_left: dict | None,
    band_right: dict | None,
    envelope: Any = None,
) -> dict:
    """Take the neighbours' bands and set chi at every level's nodes.

    The finer side of a coarse leaf's faces is constrained to it, as the single-process solve does.
    Returns whether a leaf coarser than the finest the slab owns holds surface (then every slab
    extracts at the leaves' own size, as :func:`.extract.extract` decides). ``envelope``
    (:class:`.slab_envelope.EnvelopeRun`): chi clipped by it (:func:`.slab_envelope.field_clip`).
    """
    from recon_cli.stages.poisson.extract import FACE_MARGIN

    if band_left is not None:
        apply_band(slab, -1, band_left)
    if band_right is not None:
        apply_band(slab, 1, band_right)
    levels = slab.levels
    top = len(levels) - 1
    chi = slab.chi
    # the extraction reads the tree within two cells of the slab's own range (its leaves,
    # their neighbours across its seams): every level cut to that (the coarse levels are
    # the whole cube's, the finer ones reach into the pad)
    for lev in levels:
        a, b = slab.x_range(slab.own, 1 << lev.depth)
        lo = np.searchsorted(lev.cell_keys, np.int64(max(a - 2, 0)) << 42)
        hi = np.searchsorted(lev.cell_keys, np.int64(b + 2) << 42)
        lev.cell_keys, lev.leaf = lev.cell_keys[lo:hi].copy(), lev.leaf[lo:hi].copy()
        # the corners of those cells: chi at any other node is read by no cell kept
        lev.node_keys = corner_keys(lev.cell_keys, lev.depth)
        lev.n_nodes = len(lev.node_keys)
        lev.cell_parent = None
        set_corners(lev, lev.node_keys)
    release_free_heap()
    if envelope is not None:
        from recon_cli.stages.poisson.slab_envelope import field_clip

        chi.clip = field_clip(slab, envelope, iso)
    gvals = [chi.at_nodes(lev, lev.node_keys) for lev in levels]
    chi.clip = None  # (the state between steps does not hold the envelope; extract sets it again)
    # the extraction interpolates each leaf from its corners: the finer side of a coarse
    # leaf's faces takes its values (bspline.solve)
    for d in range(1, len(levels)):
        up = levels[d - 1]
        BE.constrain_to_coarse_leaves(
            levels[d].node_keys, gvals[d], up.cell_keys, up.cell_nodes, up.leaf, gvals[d - 1]
        )
    chi.drop_neighbours()
    slab.gvals = gvals
    masks = _own_leaves(slab)
    coarse = any(
        EF.straddles(lev.cell_keys, lev.cell_nodes, m, g, lev.depth, top, iso, 1e-9, FACE_MARGIN)
        for lev, m, g in zip(levels[:-1], masks[:-1], gvals[:-1], strict=True)
    )
    release_free_heap()
    return {"coarse": bool(coarse)}


def _own_leaves(slab: Slab) -> list[np.ndarray]:
    """Per level, the leaves the slab owns (lower x in its range)."""
    top = len(slab.levels) - 1
    return _own_leaves_of(slab.levels, *slab.x_range(slab.own, 1 << top))


def _finest(slab: Slab, levels: list, gvals: list, iso: float, a: int, b: int) -> tuple:
    """The finest-lattice extraction of the leaves the slab owns (lattice units).

    The points on its seam planes take :func:`plane_values`.
    """
    from recon_cli.stages.mcubes import marching_cubes_sparse
    from recon_cli.stages.poisson.extract import FACE_MARGIN, finest_cells

    cells, vals, ckeys = finest_cells(levels, gvals, iso, masks=_own_leaves_of(levels, a, b))
    planes = ([a] if slab.index > 0 else []) + ([b] if slab.index < slab.count - 1 else [])
    if planes and len(ckeys):
        on = np.flatnonzero(np.isin(ckeys >> 42, planes))
        pv = plane_values(levels, gvals, unpack_keys(ckeys[on]), iso, FACE_MARGIN)
        vals.reshape(-1)[on] = pv
        del on, pv
    del ckeys, gvals, levels
    release_free_heap()
    lat, faces = marching_cubes_sparse(cells, vals, -iso)
    return lat, faces


def _own_leaves_of(levels: list, a: int, b: int) -> list[np.ndarray]:
    top = len(levels) - 1
    out = []
    for lev in levels:
        cx = (lev.cell_keys >> 42) << (top - lev.depth)
        out.append(lev.leaf & (cx >= a) & (cx < b))
    return out


def _clip_to_domain(
    lat: np.ndarray, faces: np.ndarray, domain: tuple[float, float], res: int
) -> tuple[np.ndarray, np.ndarray]:
    """The faces inside the free boundary's cube and their vertices (:func:`.free.clip_to_cube`).

    ``lat`` (v, 3) the vertices in finest cells of the solve's cube (``res`` a side). A face lies
    in one leaf, whose lattice the domain's faces follow: its centroid says on which side. A seam
    vertex is used on both sides of its seam or on neither (the cells around its edge are
    inside on both sides or on neither): the two slabs keep the same seam vertices.
    """
    from recon_cli.stages.poisson.free import clip_to_cube

    if not len(faces):
        return lat, faces
    lo, hi = domain[0] * res, domain[1] * res
    return clip_to_cube(lat, faces, np.full(3, lo), hi - lo)


@timed
def extract(slab: Slab, iso: float, at_leaves: bool, envelope: Any = None) -> dict:
    """The slab's part of the surface, over the leaves it owns.

    At the leaves' own size (``at_leaves``, :func:`.extract.extract_leaves`), else on the finest
    lattice (:func:`.extract.extract_finest`) with the points on its seams given the values both
    slabs of a seam compute alike (:func:`plane_values`); vertices moved to chi's roots (chi
    clipped by ``envelope``, as :func:`field`). Returns its pieces (faces, boxes) and, per seam,
    its vertices there and their pieces.
    """
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.stages.poisson.extract import extract_leaves
    from recon_cli.stages.poisson.pieces import piece_boxes, vertex_labels

    job = slab.job
    levels, gvals, chi = slab.levels, slab.gvals, slab.chi
    slab.levels = slab.gvals = None
    if job.grid:  # the grid reads chi as the extraction does: trilinear in each leaf
        from recon_cli.stages.poisson.system import chi_levels

        slab.grid_levels = chi_levels(levels, gvals)
    top = len(levels) - 1
    R = 1 << top
    a, b = slab.x_range(slab.own, R)
    if at_leaves:
        lat, faces = extract_leaves(levels, gvals, iso, np.zeros(3), float(R), (a, b))
        del levels, gvals
    else:
        lat, faces = _finest(slab, levels, gvals, iso, a, b)
    if job.domain is not None:
        lat, faces = _clip_to_domain(lat, faces, job.domain, R)
    release_free_heap()
    origin = np.asarray(job.origin)
    verts = lat * np.repeat(job.size / R, 3) + origin
    if envelope is not None:
        from recon_cli.stages.poisson.slab_envelope import field_clip

        chi.clip = field_clip(slab, envelope, iso)
    verts = chi.refine_vertices(verts, iso, origin, job.size, top)
    slab.chi = slab.lfs = slab.arrays = None
    release_free_heap()
    # seam vertices first (left seam, by position), then the others, then the right seam's
    left = lat[:, 0] == a if slab.index > 0 else np.zeros(len(lat), bool)
    right = lat[:, 0] == b if slab.index < slab.count - 1 else np.zeros(len(lat), bool)
    li, ri = _seam_order(lat, left), _seam_order(lat, right)
    mid = np.flatnonzero(~(left | right))
    perm = np.concatenate([li, mid, ri])
    inv = np.empty(len(perm), np.int64)
    inv[perm] = np.arange(len(perm))
    slab.verts = verts[perm]
    slab.faces = inv[faces]
    slab.seam = {"left": len(li), "right": len(ri)}
    lat = lat[perm]
    nv = len(perm)
    del verts, faces, perm, inv
    msg: dict[str, Any] = {"vertices": nv, "faces": len(slab.faces)}
    if len(slab.faces):
        lab = Connectivity(slab.faces, nv).face_components.astype(np.int64)
    else:
        lab = np.zeros(0, np.int64)
    slab.labels = lab
    n = int(lab.max()) + 1 if len(lab) else 0
    msg["pieces"] = piece_boxes(slab.verts, slab.faces, lab, n)
    vlab = vertex_labels(slab.faces, lab, nv)
    nl, nr = slab.seam["left"], slab.seam["right"]
    msg["seam_left"] = (lat[:nl, 1:], slab.verts[:nl], vlab[:nl])
    msg["seam_right"] = (lat[nv - nr :, 1:], slab.verts[nv - nr :], vlab[nv - nr :])
    return msg


def _grid_chi(slab: Slab) -> tuple[Any, int]:
    """Chi at unit-cube positions from the slab's kept levels, and the finest lattice's cells."""
    import functools

    from recon_cli.stages.poisson.system import chi_at

    return functools.partial(chi_at, slab.grid_levels), 1 << (len(slab.grid_levels) - 1)


@reads_only
@timed
def grid_scale(slab: Slab, take: int) -> dict:
    """The slab's part of the grid's extent and scale (``--grid``, :mod:`.field`).

    The box (job frame) of the vertices it keeps, and chi's gradient norms at ``take`` of its
    own vertices (the right seam's are the next slab's) spread evenly along them.
    """
    from recon_cli.stages.poisson.field import gradient_norms

    v = slab.verts
    if not len(v):
        return {"box": None, "norms": np.zeros(0)}
    own = v[: len(v) - slab.seam["right"]]
    if take < len(own):
        own = own[np.unique(np.linspace(0, len(own) - 1, take).round().astype(np.int64))]
    chi, res = _grid_chi(slab)
    norms = gradient_norms(chi, own, np.asarray(slab.job.origin), slab.job.size, res)
    return {"box": (v.min(axis=0), v.max(axis=0)), "norms": norms}


@timed
def grid_block(
    slab: Slab, i0: np.ndarray, shape: tuple[int, int, int], g: float, iso: float
) -> dict:
    """The grid's planes in the slab's own x range (the last slab's takes the cube's far face).

    Returns their first index along the grid's first axis and the planes
    (:func:`.field.field_block`).
    """
    from recon_cli.stages.poisson.field import field_block

    chi, res = _grid_chi(slab)
    a, b = slab.x_range(slab.own, res)
    b += int(slab.index == slab.count - 1)
    lo, hi = max(a - int(i0[0]), 0), min(b - int(i0[0]), shape[0])
    block = field_block(chi, iso, g, i0, shape, res, range(lo, max(lo, hi)))
    slab.grid_levels = None
    return {"x0": lo, "block": block}
