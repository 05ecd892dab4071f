"""The slabs' meshes made one: pieces joined across seams, noise pieces and trimming decided.

The coordinator's side of the merge in :mod:`.distributed`: seam vertices each side uses,
pieces joined by union-find over the slabs' pieces (specks, islands and folds decided on the
joined pieces, the largest kept: :func:`.steps.drop_bubbles`' rules), trimming at the global
density threshold with holes and islands decided on the joined pieces, and the parts
assembled into one mesh when the result is returned in memory.
"""

from __future__ import annotations

import numpy as np

from recon_cli.errors import ParameterError, StageFailed
from recon_cli.stages.poisson import slab as S
from recon_cli.stages.poisson import slab_surface as M


def seams_used(uses: list[dict]) -> list[dict]:
    """Per slab, the seam vertices either slab of each of its seams uses.

    The two export the same ones: ``{"left": mask, "right": mask}``.
    """
    n = len(uses)
    out = [{"left": u["left"].copy(), "right": u["right"].copy()} for u in uses]
    for k in range(1, n):
        both = uses[k - 1]["right"] | uses[k]["left"]
        out[k - 1]["right"] = both
        out[k]["left"] = both.copy()
    return out


def _join(parts: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join the slabs' pieces across the seams' edges.

    The pieces are ``{"areas": (n_k,), "links": {side: (edge keys, labels)}}``. Returns the global
    piece of each slab's piece (concatenated, slab offsets) and the pieces' summed areas.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sizes = [len(p["areas"]) for p in parts]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(off[-1])
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for k in range(1, len(parts)):
        rk, rl = parts[k - 1]["links"]["right"]
        lk, ll = parts[k]["links"]["left"]
        _, ia, ib = np.intersect1d(rk, lk, return_indices=True)
        rows.append(rl[ia] + off[k - 1])
        cols.append(ll[ib] + off[k])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r)), (r, c)), shape=(total, total))
    ncomp, comp = connected_components(g, directed=False)
    areas = np.bincount(comp, weights=np.concatenate([p["areas"] for p in parts]), minlength=ncomp)
    return comp, off, areas


def trim_across(
    runner, trim: float, pm: list[dict], seam_keep: list[dict | None]
) -> tuple[list[dict | None], int, float]:
    """The trim over the slabs at ``trim`` times the samples' median density.

    :func:`.trim.trim_by_density`'s steps, its islands and holes joined across seams; returns the
    seam vertices kept, the trimmed faces and the fraction of the area removed.
    """
    med = S.exact_median(runner, "density", M.density_values, [m["hist"] for m in pm], "trim")
    if med is None:  # no sample to measure: nothing is below the threshold
        return seam_keep, 0, 0.0
    return _cut_across(
        runner,
        trim * float(med),
        seam_keep,
        ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value"),
    )


def trim_auto_across(
    runner, seam_keep: list[dict | None]
) -> tuple[list[dict | None], int, float, int]:
    """``--trim auto`` over the slabs (:func:`.trim.trim_auto`'s steps).

    The samples' spacing capped at the global median's multiple, the vertices' support ratio, the
    cut, the holes kept and the islands no sample lies nearest to dropped, joined across seams.
    Returns :func:`trim_across`'s figures and the own samples whose spacing looked past the pad.
    """
    from recon_cli.errors import InputError
    from recon_cli.stages.poisson.trim import SUPPORT_RATIO

    sm = runner.run("trim", M.auto_spacing, lambda k: ())
    inexact = sum(m["inexact"] for m in sm)
    med = S.exact_median(runner, "spacing", M.density_values, [m["hist"] for m in sm], "trim")
    runner.run("trim", M.auto_values, lambda k: (np.inf if med is None else float(med),))
    err = InputError("trim auto removes the whole surface: no part lies near the samples")
    return (*_cut_across(runner, -SUPPORT_RATIO, seam_keep, err), inexact)


def _cut_across(
    runner, threshold: float, seam_keep: list[dict | None], empty: Exception
) -> tuple[list[dict | None], int, float]:
    """Cut every slab's faces at ``threshold``, decide holes and islands on joined pieces.

    Small low pieces are holes (kept), small kept ones islands (dropped unless a sample lies
    nearest to them, when the slabs say so); ``empty`` is raised when nothing is left.
    """
    from recon_cli.stages.poisson.trim import ISLAND_AREA_RATIO

    cm = runner.run("trim", M.trim_cut, lambda k: (threshold,))
    faces_before = sum(m["faces"] for m in cm)
    n = len(cm)
    if not any(m["cut"] for m in cm):
        # nothing below the threshold: the mesh as it is
        return seam_keep, 0, 0.0
    total = sum(m["area"] for m in cm)
    kept_area = sum(m["kept_area"] for m in cm)
    # small low pieces are holes in a sparse patch: kept
    comp, off, areas = _join(cm)
    small = areas < ISLAND_AREA_RATIO * kept_area
    flip = [np.flatnonzero(small[comp[off[k] : off[k + 1]]]) for k in range(n)]
    km = runner.run("trim", M.trim_keep, lambda k: (flip[k],))
    # small kept pieces are islands in the closing sheet: dropped, unless they hold samples
    comp, off, areas = _join(km)
    small = areas < ISLAND_AREA_RATIO * kept_area
    if "held" in km[0]:
        held = np.zeros(len(areas), bool)
        held[comp[np.concatenate([m["held"] for m in km])]] = True
        small &= ~held
    drop = [np.flatnonzero(small[comp[off[k] : off[k + 1]]]) for k in range(n)]
    use = []
    for k, m in enumerate(km):
        u = {}
        for side, (ranks, labels) in m["seam_pieces"].items():
            alive = ~np.isin(labels, drop[k])
            mask = np.zeros(m["seam_counts"][side], bool)
            mask[ranks[alive]] = True
            u[side] = mask
        use.append(u)
    keep = seams_used(use)
    dm = runner.run("trim", M.trim_drop, lambda k: (drop[k], keep[k]))
    removed = sum(m["removed_area"] for m in dm)
    untouched = sum(m["untouched"] for m in dm)
    if sum(m["faces"] for m in dm) == 0:
        raise empty
    return [None] * n, faces_before - untouched, removed / total if total > 0 else 0.0


def merge_pieces(
    runner, em: list[dict], cell: float, speck: float, fold: tuple[float, float] | None
) -> tuple[list[np.ndarray], tuple[int, int, int], float]:
    """Join the slabs' pieces across the seams, decide the specks, islands and folds.

    Pieces join through their seam vertices; the specks (under ``speck`` cells across:
    :func:`.speck_cells` of the noise median), islands and folds (``fold``: :func:`.fold_cells`
    of it) are decided on the joined pieces by :func:`.pieces.noise_pieces`, as in one process,
    the islands' points counted and the folds' vertices sent by the slabs. Returns per slab the
    local labels to drop,
    the counts of specks, islands and folds, and the largest distance between the two slabs'
    positions of a seam vertex (0: the same bits).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from recon_cli.stages.poisson.pieces import noise_pieces, piece_reach

    n = len(em)
    sizes = [len(m["pieces"][0]) for m in em]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(off[-1])
    rows, cols = [], []
    dev = 0.0
    for k in range(1, n):
        lyz, lpos, llab = em[k - 1]["seam_right"]
        ryz, rpos, rlab = em[k]["seam_left"]
        if len(lyz) != len(ryz) or not np.array_equal(lyz, ryz):
            raise StageFailed(
                f"distributed poisson: slabs {k - 1} and {k} disagree on their seam's vertices "
                f"({len(lyz)} against {len(ryz)})"
            )
        if len(lpos):
            dev = max(dev, float(np.abs(lpos - rpos).max()))
        ok = (llab >= 0) & (rlab >= 0)
        rows.append(llab[ok] + off[k - 1])
        cols.append(rlab[ok] + off[k])
    if total == 0:
        return [np.zeros(0, np.int64)] * n, (0, 0, 0), dev
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    g = coo_matrix((np.ones(len(r)), (r, c)), shape=(total, total))
    ncomp, comp = connected_components(g, directed=False)
    faces = np.zeros(ncomp, np.int64)
    lo = np.full((ncomp, 3), np.inf)
    hi = np.full((ncomp, 3), -np.inf)
    for k, m in enumerate(em):
        cnt, plo, phi = m["pieces"]
        gid = comp[off[k] : off[k + 1]]
        np.add.at(faces, gid, cnt)
        for ax in range(3):
            np.minimum.at(lo[:, ax], gid, plo[:, ax])
            np.maximum.at(hi[:, ax], gid, phi[:, ax])
    largest = int(np.argmax(faces))
    local = [comp[off[k] : off[k + 1]] for k in range(n)]

    def count_points(a, b):
        im = runner.run("islands", M.island_points, lambda k: (a, b))
        return np.sum([m["counts"] for m in im], axis=0)

    def farthest(which, anchor, a, b):
        fm = runner.run(
            "folds", M.fold_vertices, lambda k: (which[local[k]], anchor[local[k]], a, b)
        )
        return piece_reach(
            np.concatenate([m["points"] for m in fm]),
            np.concatenate([m["ids"] for m in fm]),
            len(a),
            np.concatenate([m["targets"] for m in fm]),
        )

    specks, islands, folds = noise_pieces(
        lo, hi, largest, cell, speck, fold, count_points, farthest
    )
    gone = specks | islands | folds
    drop = [np.flatnonzero(gone[local[k]]) for k in range(n)]
    counts = (int(specks.sum()), int(islands.sum()), int(folds.sum()))
    return drop, counts, dev


def assemble(out: dict, job: S.Job, perm: tuple, colors: bool):
    """The mesh from the slabs' parts (in memory).

    Vertices concatenated in slab order, face references to a right seam resolved to the next slab's
    vertices, axes turned back.
    """
    from recon_cli.geometry import TriangleMesh

    parts = out["parts"]
    nv = [len(p["vertices"]) for p in parts]
    off = np.concatenate([[0], np.cumsum(nv)]).astype(np.int64)
    faces = []
    for k, p in enumerate(parts):
        f = p["faces"]
        g = np.where(f >= 0, f + off[k], off[min(k + 1, len(parts) - 1)] + (-1 - f))
        faces.append(g)
    inv = np.argsort(perm)
    verts = np.concatenate([p["vertices"] for p in parts])[:, inv] if parts else np.zeros((0, 3))
    mesh = TriangleMesh(
        vertices=np.ascontiguousarray(verts),
        faces=np.concatenate(faces).astype(np.int64) if faces else np.zeros((0, 3), np.int64),
    )
    for name in parts[0]["attributes"] if parts else ():
        mesh.attributes[name] = np.concatenate([p["attributes"][name] for p in parts])
    if colors:
        mesh.colors = np.concatenate([p["colors"] for p in parts if "colors" in p])
    rep = out["report"]
    rep["vertices"] = len(mesh.vertices)
    rep["faces"] = len(mesh.faces)
    rep["distributed"]["phases"] = out.get("phases", {})
    return mesh
