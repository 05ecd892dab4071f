"""Normals of one cloud over many processes (a Dask cluster), in slabs.

``recon normals --workers N`` / ``--scheduler ADDRESS``.

The cloud is cut along its longest axis into slabs (as the distributed Poisson solve cuts
it, :mod:`recon_cli.stages.poisson.distributed`); the workers read the file by chunks and
sort its rows per sub-slab, each slab reads its own points and a halo beyond each seam.

- **Neighbourhoods across borders.** Each slab builds its kd-tree over its points and its
  halo, so a point near a seam sees its neighbours on the other side. A point's kNN (or
  radius) neighbourhood is exact when its farthest neighbour is nearer than the halo's far
  edge; a slab with a point whose neighbourhood may reach past it says by how much, and
  the coordinator widens that halo and runs the slabs again. The normals (PCA) of a slab's
  own points are then the single-process ones.
- **Orientation.** ``camera`` (a ``--camera`` point, or each point's own scanner from the
  file's sensors), ``direction``: per point, nothing to join. ``mst`` and
  ``keep``: each slab orients its points and halo with the single-process algorithm
  (:func:`.orient_normals`: the minimum spanning forest, seeds, votes, flux); then each
  slab's graph components are joined across the seams: the points two slabs both hold (the
  halos overlap the neighbours' own points) say whether two components agree, by the sum
  of the products of their oriented normals; a maximum spanning forest of those agreements
  over all the slabs' components gives each component its flip, relative to the largest
  component of its group (Hoppe's propagation, one level up: slabs' graphs, then their
  adjacency). A group that comes out clearly inside-out by its flux (the divergence
  theorem's volume estimate, summed over the slabs about the group's centroid) is flipped,
  as the single-process flux check flips a component.
- **Memory.** Without ``--partitions`` a run takes the fewest slabs (whole rounds of the
  workers) whose one slab fits a share of a worker's memory limit, at
  :func:`slab_bytes_per_point` (a slab's kd-tree neighbourhoods and orientation graph); with
  more slabs than workers each slab's state waits in a file between its steps, so a worker
  holds only the slab it runs (as the Poisson slabs).
- **Output.** Each slab writes its own points' normals by input row; the coordinator
  writes the output file a chunk of the input at a time (every property of the input kept,
  in its order), so it never holds the cloud either.

Differences from the single-process output: a component that lies in one slab only is
oriented as there; a component spread over slabs takes the orientation of its largest
part (for an open surface, whose orientation the single-process run also takes from its
own seed, the two may differ by a sign).

References
----------
Hoppe, H., DeRose, T., Duchamp, T., McDonald, J. & Stuetzle, W. (1992). Surface reconstruction
from unorganized points. SIGGRAPH.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.execution import current
from recon_cli.slabs.runners import map_tasks, register_dask_sizes
from recon_cli.slabs.spill import spill_folder

# the slabs' axis is cut into this many sub-slabs; halos are whole sub-slabs
SUB_SLABS = 256
# the first halo, in sub-slabs (widened where a neighbourhood reaches past it)
HALO = 2
# slabs at most (one seam per plane of a 32-cell lattice, as the Poisson slabs)
MAX_SLABS = 32
# a slab's worker's peak per point of its own, halo included, above the idle worker: a fixed
# part and a part per neighbour of the kNN (bench/calibration.md, SLAB_BYTES_FIXED)
SLAB_BYTES_FIXED = 480
SLAB_BYTES_PER_NEIGHBOUR = 8


def slab_bytes_per_point(knn: int | None) -> float:
    """A normals slab's peak memory per point of its own (bytes), for a kNN of ``knn``.

    A radius neighbourhood (``knn`` None) is counted as 30 neighbours.
    """
    return SLAB_BYTES_FIXED + SLAB_BYTES_PER_NEIGHBOUR * (30 if knn is None else int(knn))


@dataclass
class NSlab:
    """A slab of the distributed normals.

    Its own x range (unit cube of the job), its halo, its points (job frame), their input rows.
    """

    index: int
    count: int
    own: tuple[float, float]
    pad: tuple[float, float]
    origin: np.ndarray
    size: float
    # filled by the steps in order: Any, as a step reads only what an earlier step set
    pts: Any = None
    ref: Any = None
    scan: Any = None  # each point's sensor (orientation towards the sensors)
    rows: Any = None
    own_pt: Any = None
    order: Any = None
    nrm: Any = None  # (n,) in the kd-tree order (``order``)
    curv: Any = None
    sign: Any = None
    comp: Any = None
    info: dict = field(default_factory=dict)


def _timed(fn):
    from recon_cli.slabs.runners import timed

    return timed(fn)


def nload(slab: NSlab, parts: list, nsub: int, has_ref: bool, has_scan: bool = False) -> dict:
    """Read the slab's rows (own and halo) from the chunks' sub-slab files."""
    pa, pb = (int(round(v * nsub)) for v in slab.pad)
    oa, ob = (int(round(v * nsub)) for v in slab.own)
    pts, ref, rows, sub, scan = [], [], [], [], []
    for prefix, off in parts:
        a, b = int(off[pa]), int(off[pb])
        if b <= a:
            continue
        pts.append(np.load(prefix + ".pts.npy", mmap_mode="r")[a:b])
        rows.append(np.load(prefix + ".row.npy", mmap_mode="r")[a:b])
        sub.append(np.repeat(np.arange(pa, pb), np.diff(off[pa : pb + 1])))
        if has_ref:
            ref.append(np.load(prefix + ".nrm.npy", mmap_mode="r")[a:b])
        if has_scan:
            scan.append(np.load(prefix + ".scan.npy", mmap_mode="r")[a:b])
    if has_scan:
        slab.scan = np.concatenate(scan) if scan else np.zeros(0, np.int64)
    slab.pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    slab.rows = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    s = np.concatenate(sub) if sub else np.zeros(0, np.int64)
    slab.own_pt = (s >= oa) & (s < ob)
    slab.ref = (np.concatenate(ref) if ref else np.zeros((0, 3))) if has_ref else None
    return {"points": len(slab.pts), "own_points": int(slab.own_pt.sum())}


def nestimate(slab: NSlab, knn: int | None, radius: float | None) -> dict:
    """Neighbourhoods (kd-tree over the slab and its halo) and PCA normals.

    Returns how far past the halo's edge an own point's neighbourhood may reach (0: every one
    exact).
    """
    from recon_cli.stages.normals import estimate_sorted, neighbourhoods

    n = len(slab.pts)
    if n == 0:
        slab.order = np.zeros(0, np.int64)
        slab.nrm, slab.curv = np.zeros((0, 3)), np.zeros(0)
        return {"reach": 0.0, "degenerate": 0, "neighbours": 0}
    order, ps, indptr, indices = neighbourhoods(slab.pts, knn, radius)
    nrm, curv, deg = estimate_sorted(ps, indptr, indices)
    slab.order, slab.nrm, slab.curv = order, nrm, curv
    slab.info = {"indptr": indptr, "indices": indices}
    own = slab.own_pt[order]
    # the farthest neighbour of each own point against its distance to the halo's edges
    far = ps[indices[np.maximum(indptr[1:] - 1, indptr[:-1])]]
    dk = np.linalg.norm(far - ps, axis=1)
    if radius is not None:
        dk = (
            np.full(n, radius)
            if knn is None
            else np.where(indptr[1:] - indptr[:-1] < knn, radius, dk)
        )
    x = ps[:, 0] / slab.size
    lo_gap = np.inf if slab.pad[0] <= 0.0 else (x - slab.pad[0]) * slab.size
    hi_gap = np.inf if slab.pad[1] >= 1.0 else (slab.pad[1] - x) * slab.size
    short = np.maximum(dk - np.minimum(lo_gap, hi_gap), 0.0)[own]
    return {
        "reach": float(short.max()) if len(short) else 0.0,
        "degenerate": int(deg[own].sum()),
        "neighbours": int((indptr[1:] - indptr[:-1])[own].sum()),
    }


def norient(slab: NSlab, method: str, cam, dirn) -> dict:
    """Orient the slab's normals (points and halo) as the single-process run would.

    Returns its components' figures and, per seam, the oriented normals of the points the neighbour
    holds too (by input row).
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    from recon_cli.stages.normals import GRAPH_K, orient_sorted
    from recon_cli.stages.normals import _kernel as K

    order = slab.order
    n = len(order)
    ps = slab.pts[order]
    if n == 0:
        slab.sign, slab.comp = np.zeros(0, np.int8), np.zeros(0, np.int64)
        return {"comps": np.zeros(0), "left": None, "right": None}
    indptr, indices = slab.info["indptr"], slab.info["indices"]
    ref = None if slab.ref is None else slab.ref[order]
    if slab.scan is not None:  # cam: the sensors (positions, directions, is a direction)
        method, cam = "sensors", (*cam, slab.scan[order])
        slab.scan = None
    sign, _ = orient_sorted(method, ps, slab.nrm, indptr, indices, cam, dirn, ref)
    slab.sign = sign
    if method in ("mst", "keep"):
        eptr, dst = K.graph_edges(indptr, indices, GRAPH_K)
        g = sparse.csr_matrix((np.ones(len(dst)), dst, eptr), shape=(n, n))
        _, comp = connected_components(g, directed=True, connection="weak")
    else:
        comp = np.zeros(n, np.int64)
    slab.comp = comp
    slab.info = {}
    own = slab.own_pt[order]
    o = slab.nrm * sign[:, None]
    ncomp = int(comp.max()) + 1
    msg: dict[str, Any] = {
        "comps": np.bincount(comp[own], minlength=ncomp),
        "sum": np.stack([np.bincount(comp[own], ps[own, a], ncomp) for a in range(3)], axis=1),
    }
    rows = slab.rows[order]
    x = ps[:, 0] / slab.size
    for side, lo, hi in (
        ("left", slab.pad[0], slab.own[0] + (slab.own[0] - slab.pad[0])),
        ("right", slab.own[1] - (slab.pad[1] - slab.own[1]), slab.pad[1]),
    ):
        sel = (x >= lo) & (x < hi)
        msg[side] = (rows[sel], o[sel], comp[sel])
    return msg


def nflux(slab: NSlab, flips: np.ndarray, centre: np.ndarray) -> dict:
    """The flux of the slab's own points about their group's centroid, per component."""
    from recon_cli.stages.normals import _kernel as K  # noqa: F401

    order = slab.order
    if not len(order):
        return {"flux": np.zeros(0), "scale": np.zeros(0)}
    ps = slab.pts[order]
    own = slab.own_pt[order]
    comp = slab.comp
    rel = ps - centre[comp]
    o = slab.nrm * (slab.sign * flips[comp])[:, None]
    ncomp = int(comp.max()) + 1
    flux = np.bincount(comp[own], np.einsum("ij,ij->i", rel, o)[own], ncomp)
    scale = np.bincount(comp[own], np.linalg.norm(rel, axis=1)[own], ncomp)
    return {"flux": flux, "scale": scale}


def nwrite(slab: NSlab, flips: np.ndarray, prefix: str, curvature: bool) -> dict:
    """Write the slab's own points' oriented normals (and curvature) by input row."""
    order = slab.order
    own = slab.own_pt[order]
    sgn = slab.sign * flips[slab.comp] if len(order) else np.zeros(0, np.int8)
    np.save(prefix + ".row.npy", slab.rows[order][own])
    np.save(prefix + ".nrm.npy", (slab.nrm * sgn[:, None])[own])
    if curvature:
        np.save(prefix + ".curv.npy", slab.curv[own])
    flipped = int((sgn[own] < 0).sum())
    slab.pts = slab.nrm = slab.curv = slab.sign = slab.comp = None
    return {"flipped": flipped}


register_dask_sizes(NSlab)

nload = _timed(nload)
nestimate = _timed(nestimate)
norient = _timed(norient)
nflux = _timed(nflux)
nwrite = _timed(nwrite)


# ---------------------------------------------------------------------------------------------
# the coordinator


def scan_rows(chunk) -> dict:
    """A chunk's box and counts (its points must be finite)."""
    from recon_cli.io.chunks import read_chunk

    cloud = read_chunk(chunk)
    pts = np.asarray(cloud.points, dtype=np.float64)
    if not np.all(np.isfinite(pts)):
        raise InputError("points contain NaN or infinite coordinates", chunk.path)
    out = {
        "rows": len(pts),
        "normals": cloud.normals is not None,
        "sensors": tuple(cloud.sensors),
        "invalid_dropped": int(cloud.invalid_dropped),
    }
    if len(pts):
        out["lo"], out["hi"] = pts.min(axis=0), pts.max(axis=0)
    return out


def bucket_rows(
    chunk, first_row: int, frame: tuple, nsub: int, prefix: str, ref: bool, sensors: int = 0
) -> dict:
    """Write a chunk's points, sorted by sub-slab, to ``prefix.*.npy``.

    The points in the job frame (axes turned, about the cube's corner), their input rows, for
    ``keep`` their input normals and, with ``sensors`` (how many the file gives), each point's
    sensor.
    """
    from recon_cli.geometry import SCAN_ATTRIBUTE
    from recon_cli.io.chunks import read_chunk
    from recon_cli.stages.normals import sensor_views

    cloud = read_chunk(chunk)
    scan = None
    if sensors:
        scan = sensor_views(
            cloud.sensors, cloud.attributes.get(SCAN_ATTRIBUTE), len(cloud.points), np.zeros(3)
        )[3]
    return _bucket_cloud(cloud, first_row, frame, nsub, prefix, ref, scan)


def _plan(counts: np.ndarray, parts: int, halo: int) -> list[tuple]:
    from recon_cli.slabs.plan import choose_seams

    nsub = len(counts)
    per = nsub // MAX_SLABS
    seams = [0] + choose_seams(counts.reshape(-1, per).sum(axis=1), parts) + [MAX_SLABS]
    out = []
    for k in range(parts):
        a, b = seams[k] * per, seams[k + 1] * per
        out.append(((a / nsub, b / nsub), (max(a - halo, 0) / nsub, min(b + halo, nsub) / nsub)))
    return out


def _join(msgs: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each slab component's flip and group, components joined across seams.

    Components are joined by the agreement of the normals their shared points have (a maximum
    spanning forest, Kruskal, parity union-find); the largest component of a group keeps its
    orientation.
    """
    sizes = [len(m["comps"]) for m in msgs]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(off[-1])
    counts = np.concatenate([m["comps"] for m in msgs]) if total else np.zeros(0)
    edges = []
    for k in range(1, len(msgs)):
        a, b = msgs[k - 1]["right"], msgs[k]["left"]
        if a is None or b is None:
            continue
        _, ia, ib = np.intersect1d(a[0], b[0], return_indices=True)
        if not len(ia):
            continue
        dots = np.einsum("ij,ij->i", a[1][ia], b[1][ib])
        ca, cb = a[2][ia] + off[k - 1], b[2][ib] + off[k]
        key = ca * total + cb
        uk, inv = np.unique(key, return_inverse=True)
        score = np.bincount(inv.reshape(-1), dots, len(uk))
        edges += [
            (abs(sc), int(u // total), int(u % total), 1 if sc >= 0 else -1)
            for u, sc in zip(uk, score, strict=True)
        ]
    parent = list(range(total))
    parity = [1] * total  # the node's flip relative to its parent

    def find(x):
        p = 1
        path = []
        while parent[x] != x:
            path.append(x)
            p *= parity[x]
            x = parent[x]
        # compress: every node on the path points at the root with its parity to it
        acc = p
        for y in path:
            py = parity[y]
            parent[y], parity[y] = x, acc
            acc *= py
        return x, p

    for _w, u, v, sg in sorted(edges, reverse=True):
        ru, pu = find(u)
        rv, pv = find(v)
        if ru == rv:
            continue
        # flip(v) = flip(u) * sg  ->  parity of rv under ru
        parent[rv] = ru
        parity[rv] = pu * pv * sg
    root = np.empty(total, np.int64)
    flip = np.empty(total, np.int8)
    for x in range(total):
        r, p = find(x)
        root[x], flip[x] = r, p
    # the largest component of each group keeps its own orientation
    groups, gid = np.unique(root, return_inverse=True)
    big = np.full(len(groups), -1)
    best = np.full(len(groups), -1.0)
    for x in range(total):
        if counts[x] > best[gid[x]]:
            best[gid[x]], big[gid[x]] = counts[x], x
    flip = (flip * flip[big[gid]]).astype(np.int8)
    return flip, gid, off


def _core(client, files, counts, frame, n_rows: int, p: dict, tmp: str, progress=None) -> tuple:
    """The slabs' steps on bucketed rows, on one progress bar over them all.

    ``files``: per chunk its file prefix and sub-slab offsets. Returns each slab's output file
    prefix and the report's figures.
    """
    from recon_cli.progress import task
    from recon_cli.slabs.runners import Overall

    weights = {k: w for k, w in PHASE_WEIGHTS.items() if k != "flux" or p["orient"] == "mst"}
    with task(progress, "normals: the whole job", sum(weights.values())) as bar:
        return _core_steps(
            client, files, counts, frame, n_rows, p, tmp, progress, Overall(bar, weights)
        )


# each phase's share of a run's wall time (the progress bar over the whole job)
PHASE_WEIGHTS = {"load": 10.0, "neighbourhoods": 45.0, "orient": 30.0, "flux": 5.0, "write": 10.0}


def make_runner(
    client: Any, slabs: list, progress: Any, overall: Any, spill_dir: str | None = None
) -> Any:
    """The runner of the slabs' steps on ``client``, or in this process without one.

    ``spill_dir``: where the slabs' states wait between their steps (None: in memory).
    """
    from recon_cli.slabs.runners import DaskRunner, LocalRunner

    if client is None:
        return LocalRunner(slabs, progress, "normals", overall, spill_dir)
    return DaskRunner(client, slabs, progress, "normals", overall, spill_dir)


def _core_steps(client, files, counts, frame, n_rows, p, tmp, progress, overall) -> tuple:
    from recon_cli.stages.normals import FLUX_MIN

    origin, size, perm = frame
    nsub = len(counts)
    parts = p["partitions"]
    method = p["orient"]
    cam = None if p["camera"] is None else np.asarray(p["camera"], float)[list(perm)] - origin
    dirn = None if p["direction"] is None else np.asarray(p["direction"], float)[list(perm)]
    sensors = p.get("sensors")
    if sensors is not None:  # each point towards its own sensor, in the job's frame
        pos, dirs, is_dir = (np.asarray(a) for a in sensors[:3])
        cam = (
            np.where(is_dir[:, None], 0.0, pos[:, list(perm)] - origin),
            dirs[:, list(perm)],
            is_dir,
        )
    halo = HALO
    sub_w = size / nsub
    phases: dict = {}
    for _attempt in range(4):
        plan = _plan(counts, parts, halo)
        slabs = [NSlab(k, parts, plan[k][0], plan[k][1], origin, size) for k in range(parts)]
        # more slabs than workers: a worker keeps only the slab it runs in memory
        spill = None
        if parts > max(p["workers"], 1):
            spill = os.path.join(tmp, f"states{_attempt}")
            os.makedirs(spill, exist_ok=True)
        runner = make_runner(client, slabs, progress, overall, spill)
        try:
            lm = runner.run(
                "load", nload, lambda k: (files, nsub, method == "keep", sensors is not None)
            )
            em = runner.run("neighbourhoods", nestimate, lambda k: (p["knn"], p["radius"]))
            reach = max(m["reach"] for m in em)
            if reach > 0 and halo < nsub:
                runner.close()
                halo = min(nsub, halo + int(np.ceil(reach / sub_w)) + 1)
                continue
            om = runner.run("orient", norient, lambda k: (method, cam, dirn))
            flip, gid, off = _join(om)
            ngroups = int(gid.max()) + 1 if len(gid) else 0
            if method == "mst" and ngroups:
                cnt = np.concatenate([m["comps"] for m in om]).astype(np.float64)
                sums = np.concatenate([m["sum"] for m in om])
                gc: np.ndarray = np.stack(
                    [np.bincount(gid, sums[:, a], ngroups) for a in range(3)], axis=1
                )
                gc /= np.maximum(np.bincount(gid, cnt, ngroups), 1.0)[:, None]
                centre = gc[gid]

                def flux_args(
                    k: int, flip: np.ndarray = flip, off: np.ndarray = off, c: np.ndarray = centre
                ) -> tuple:
                    return flip[off[k] : off[k + 1]], c[off[k] : off[k + 1]]

                fm = runner.run("flux", nflux, flux_args)
                flux = np.bincount(gid, np.concatenate([m["flux"] for m in fm]), ngroups)
                scale = np.bincount(gid, np.concatenate([m["scale"] for m in fm]), ngroups)
                inside_out = flux < -FLUX_MIN * scale
                flip = (flip * np.where(inside_out[gid], -1, 1)).astype(np.int8)

            def write_args(k: int, flip: np.ndarray = flip, off: np.ndarray = off) -> tuple:
                return (
                    flip[off[k] : off[k + 1]],
                    os.path.join(tmp, f"n{k:03d}"),
                    p["curvature"],
                )

            wm = runner.run("write", nwrite, write_args)
            for name, ph in runner.phases.items():
                phases[name] = ph
        finally:
            runner.close()
        break
    own = sum(m["own_points"] for m in lm)
    report = {
        "points": n_rows,
        "knn": p["knn"],
        "radius": p["radius"],
        "neighbourhood_size": sum(m["neighbours"] for m in em) / max(own, 1),
        "degenerate": sum(m["degenerate"] for m in em),
        "components": ngroups if method in ("mst", "keep") else None,
        "flipped": sum(m["flipped"] for m in wm),
        "orient": method,
        "distributed": {
            "slabs": parts,
            "halo": halo / nsub,
            "slab_points": [m["own_points"] for m in lm],
            "phases": phases,
        },
    }
    return [os.path.join(tmp, f"n{k:03d}") for k in range(parts)], report


def _gather(prefixes: list[str], n_rows: int, curvature: bool, tmp: str):
    """The slabs' normals (and curvature) by input row, in memory-mapped arrays in ``tmp``."""
    nrm = np.lib.format.open_memmap(os.path.join(tmp, "normals.npy"), "w+", np.float64, (n_rows, 3))
    curv = (
        np.lib.format.open_memmap(os.path.join(tmp, "curv.npy"), "w+", np.float64, (n_rows,))
        if curvature
        else None
    )
    for pre in prefixes:
        rows = np.load(pre + ".row.npy")
        nrm[rows] = np.load(pre + ".nrm.npy")
        if curv is not None:
            curv[rows] = np.load(pre + ".curv.npy")
    return nrm, curv


def slab_count(
    partitions: int | None,
    npoints: int,
    client: Any,
    knn: int | None,
    budget: int | None = None,
) -> tuple:
    """The normals' slabs of a run and why (:func:`recon_cli.slabs.plan.slab_count`)."""
    from recon_cli.slabs import plan

    bpp = slab_bytes_per_point(knn)
    return plan.slab_count(
        partitions, npoints, client, bpp, MAX_SLABS, "normals", "the most slabs", budget
    )


def _steps_params(
    ex: Any,
    client: Any,
    npoints: int,
    neighbourhood: tuple,
    orientation: tuple,
    curvature: bool,
    sensors: tuple | None,
) -> tuple[dict, dict]:
    """The slabs' steps' parameters and the report's entry on their count.

    The count is the execution's ``partitions``, else as many as the cluster's workers' memory
    (or, in this process, the execution's budget) needs (:func:`slab_count`).
    ``neighbourhood``: (knn, radius); ``orientation``: (method, camera, direction);
    ``sensors``: the sensors' positions, directions and is-direction flags, or None.
    """
    knn, radius = neighbourhood
    method, cam, dirn = orientation
    budget = ex.budget() if client is None else None
    parts, why = slab_count(ex.partitions, npoints, client, knn, budget)
    p = dict(
        knn=knn,
        radius=radius,
        orient=method,
        camera=cam,
        direction=dirn,
        curvature=bool(curvature),
        partitions=parts,
        workers=why["workers"],
        sensors=sensors,
    )
    return p, why


def _frame(lo, hi, perm_axis_longest=True):
    size = float((hi - lo).max()) * 1.01 or 1.0
    origin = 0.5 * (lo + hi) - 0.5 * size
    axis = int(np.argmax(hi - lo))
    perm = (axis, (axis + 1) % 3, (axis + 2) % 3)
    return origin[list(perm)], size, perm


def distributed_normals(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    knn: int | None = 30,
    radius: float | None = None,
    orient: str = "mst",
    camera=None,
    direction=None,
    curvature: bool = False,
    sensors: tuple | None = None,
    progress: Any = None,
) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Normals of a cloud given in memory, in slabs (module docstring).

    Where it runs is the :func:`recon_cli.execution.current` execution's (:func:`recon_cli.run_on`):
    on its Dask cluster, or else all in this process; in its ``partitions`` slabs, or else the
    fewest whose one slab fits a share of a worker's memory limit, or without a cluster of its
    memory budget (:func:`slab_count`); the slabs' files in a folder in its temporary folder
    (default: the system's). ``sensors``: for ``orient="camera"`` without ``camera``,
    ``(positions, directions, is_direction, which)`` as :func:`.sensor_views` gives them (about
    the origin: world coordinates). Returns the oriented normals, the curvature (or None) and
    the report.
    """
    from recon_cli.geometry import PointCloud
    from recon_cli.stages.normals import SPEC, check_knn, check_orient, check_points

    ex = current()
    knn, radius = check_knn(knn, radius)
    method, cam, dirn = check_orient(orient, camera, direction)
    SPEC.check({"curvature": curvature}, complete=False)
    if ex.partitions is not None and not 1 <= int(ex.partitions) <= MAX_SLABS:
        raise ParameterError(
            f"--partitions must be 1..{MAX_SLABS} for normals, got {ex.partitions}"
        )
    pts = check_points(points)
    if method == "keep" and normals is None:
        raise ParameterError("--orient keep needs input normals")
    if len(pts) == 0:
        raise InputError("the input has no points")
    if method == "camera" and cam is None and sensors is None:
        raise ParameterError("--orient camera needs --camera X,Y,Z (or the data's sensors)")
    frame = _frame(pts.min(axis=0), pts.max(axis=0))
    with spill_folder(ex.spill_parent(), "normals") as tmp, ex.cluster() as (client, info):
        p, why = _steps_params(
            ex,
            client,
            len(pts),
            (knn, radius),
            (method, cam, dirn),
            curvature,
            None if sensors is None else tuple(sensors[:3]),
        )
        cloud = PointCloud(
            points=pts, normals=None if normals is None else np.asarray(normals, float)
        )
        scan = None if sensors is None else sensors[3]
        b = _bucket_cloud(
            cloud, 0, frame, SUB_SLABS, os.path.join(tmp, "c00000"), method == "keep", scan
        )
        prefixes, report = _core(
            client,
            [(os.path.join(tmp, "c00000"), b["offsets"])],
            b["counts"],
            frame,
            len(pts),
            p,
            tmp,
            progress,
        )
        report["distributed"]["partitions"] = why
        report["distributed"]["cluster"] = info
        nrm, curv = _gather(prefixes, len(pts), p["curvature"], tmp)
        nrm_out = np.array(nrm)
        inv = np.argsort(frame[2])
        nrm_out = nrm_out[:, inv]
        curv_out = None if curv is None else np.array(curv)
        del nrm, curv
    return nrm_out, curv_out, report


def _bucket_cloud(cloud, first_row, frame, nsub, prefix, ref, scan=None):
    origin, size, perm = frame
    pts = np.asarray(cloud.points, dtype=np.float64)[:, list(perm)] - origin
    sub = np.clip(np.floor(pts[:, 0] / size * nsub), 0, nsub - 1).astype(np.int64)
    order = np.argsort(sub, kind="stable")
    np.save(prefix + ".pts.npy", pts[order])
    np.save(prefix + ".row.npy", first_row + order.astype(np.int64))
    if ref:
        nrm = np.asarray(cloud.normals, dtype=np.float64)[:, list(perm)]
        np.save(prefix + ".nrm.npy", nrm[order])
    if scan is not None:
        np.save(prefix + ".scan.npy", np.asarray(scan, np.int64)[order])
    sub = sub[order]
    return {
        "offsets": np.searchsorted(sub, np.arange(nsub + 1)),
        "counts": np.bincount(sub, minlength=nsub),
    }


def run_from_files(
    input: str,
    output: str,
    params: dict,
    *,
    load_kw: dict,
    save_kw: dict,
    ascii: bool = False,
    progress: Any = None,
) -> dict | None:
    """``recon normals IN OUT`` in slabs from IN's chunks (the stage's ``from_files``).

    On the execution's cluster (``--workers``, ``--scheduler``), or in this process when IN is too
    large for the memory in one piece (:func:`recon_cli.execution.current`); None otherwise (the
    command loads IN). OUT is written a chunk of IN at a time (binary PLY; other formats
    assembled here); returns the report.
    """
    from recon_cli.io.chunks import plan_chunks
    from recon_cli.stages import provenance_line
    from recon_cli.stages.normals import SPEC

    ex = current()
    chunks = None
    if not ex.distributed:
        if input == "-" or load_kw.get("format") or params.get("backend", "native") != "native":
            return None
        chunks = plan_chunks(input)
        if any(c.kind == "whole" for c in chunks):
            return None  # rows not known before reading: loaded whole
        knn0 = SPEC.check(params, complete=True)["knn"] or None
        rows = sum(c.stop - c.start for c in chunks)
        if (ex.partitions or slab_count(None, rows, None, knn0, ex.budget())[0]) == 1:
            return None
    v, knn, radius, (method, cam, dirn) = _checked(params, input, load_kw)
    t0 = time.perf_counter()
    chunks = chunks or plan_chunks(input)
    with spill_folder(ex.spill_parent(output), "normals") as tmp, ex.cluster() as (client, info):
        scans, n_rows, sensors, views = _scan(client, chunks, method, cam)
        lo = np.min([s["lo"] for s in scans if "lo" in s], axis=0)
        hi = np.max([s["hi"] for s in scans if "lo" in s], axis=0)
        frame = _frame(lo, hi)
        first = np.concatenate([[0], np.cumsum([s["rows"] for s in scans])]).astype(np.int64)
        keep_ref, nscan = method == "keep", len(sensors or ())
        buckets = map_tasks(
            client,
            bucket_rows,
            [
                (
                    c,
                    int(first[i]),
                    frame,
                    SUB_SLABS,
                    os.path.join(tmp, f"c{i:05d}"),
                    keep_ref,
                    nscan,
                )
                for i, c in enumerate(chunks)
            ],
            progress,
            "normals: sorting the chunks into slabs",
        )
        counts = np.sum([b["counts"] for b in buckets], axis=0)
        files = [(os.path.join(tmp, f"c{i:05d}"), b["offsets"]) for i, b in enumerate(buckets)]
        p, why = _steps_params(
            ex,
            client,
            n_rows,
            (knn, radius),
            (method, cam, dirn),
            v["curvature"],
            None if sensors is None else views[:3],
        )
        prefixes, report = _core(client, files, counts, frame, n_rows, p, tmp, progress)
        report["distributed"]["partitions"] = why
        t1 = time.perf_counter()
        nrm, curv = _gather(prefixes, n_rows, p["curvature"], tmp)
        prov = provenance_line("normals", {**SPEC.defaults(), **params})
        _write(chunks, first, nrm, curv, frame[2], output, save_kw, ascii, prov, method, report)
        t2 = time.perf_counter()
    _finish_report(report, scans, chunks, info, method, cam, sensors, (t1 - t0, t2 - t1))
    report["output"] = "<stdout>" if output == "-" else output
    return report


def _checked(params: dict, input: str, load_kw: dict) -> tuple[dict, Any, Any, tuple]:
    """The options of a distributed run, checked.

    Returns (values, knn, radius, (orientation method, camera, direction)).
    """
    from recon_cli.stages.normals import (
        SPEC,
        check_distributed_neighbours,
        check_knn,
        check_orient,
    )

    v = SPEC.check(params, complete=True)
    check_distributed_neighbours(v["neighbours"])
    if v["backend"] != "native":
        raise ParameterError("--workers/--scheduler run the native normals: leave out --backend")
    if input == "-":
        raise ParameterError("--workers/--scheduler read IN by chunks: give a file, not '-'")
    if load_kw.get("format"):
        raise ParameterError(
            "--workers/--scheduler read IN by its suffix: leave out --input-format"
        )
    knn, radius = check_knn(v["knn"], v["radius"])
    return v, knn, radius, check_orient(v["orient"], v["camera"], v["direction"])


def _scan(client: Any, chunks: list, method: str, cam: Any) -> tuple[list, int, Any, Any]:
    """Each chunk's rows, bounds and scanner positions: (scans, rows, sensors, their views).

    ``sensors`` is None unless each point is oriented towards its own scanner.
    """
    from recon_cli.stages.normals import sensor_views

    scans = map_tasks(client, scan_rows, [(c,) for c in chunks])
    n_rows = sum(s["rows"] for s in scans)
    if n_rows == 0:
        raise InputError("the input has no points")
    if method == "keep" and not all(s["normals"] for s in scans):
        raise ParameterError("--orient keep needs input normals")
    sensors = views = None
    if method == "camera" and cam is None:  # each point towards its own scanner
        if len({s["sensors"] for s in scans}) > 1:
            raise InputError("the tiles do not all give the same scanner positions")
        sensors = list(scans[0]["sensors"])
        # the sensors' positions and directions (no point: their checks come per chunk)
        views = sensor_views(sensors, np.zeros(0, np.int64), 0, np.zeros(3))
    return scans, n_rows, sensors, views


def _finish_report(report, scans, chunks, info, method, cam, sensors, seconds) -> None:
    """The command's report: viewpoints, the readers' drops, the cluster, the timings."""
    report["backend"] = "native"
    if method == "camera":
        report["viewpoints"] = (
            [f"--camera ({', '.join(f'{float(x):.9g}' for x in cam)})"]
            if sensors is None
            else [s.describe() for s in sensors]
        )
    dropped = sum(s["invalid_dropped"] for s in scans)
    if dropped:  # as the command's report of a reader's drops
        report["read"] = {"kept": sum(s["rows"] for s in scans), "invalid_dropped": dropped}
    report["distributed"]["cluster"] = info
    report["distributed"]["chunks"] = len(chunks)
    report["timings"] = {"stage": seconds[0], "write": seconds[1]}
    report["stage"] = "normals"


def _write(chunks, first, nrm, curv, perm, output, save_kw, ascii, prov, method, report) -> None:
    """OUT: the input's rows, chunk by chunk, with their normals (axes turned back) and curvature.

    A binary PLY streamed, any other format assembled in memory.
    """
    from recon_cli.io.chunks import read_chunk
    from recon_cli.io.load import save

    inv = list(np.argsort(perm))

    def part(i, c):
        cloud = read_chunk(c)
        a, b = int(first[i]), int(first[i]) + len(cloud.points)
        had = cloud.normals is not None
        cloud.normals = np.asarray(nrm[a:b])[:, inv]
        if curv is not None:
            cloud.attributes["curvature"] = np.asarray(curv[a:b])
        return cloud, had

    report["input_normals"] = "none"
    fmt = save_kw.get("format")
    stream = (
        output != "-"
        and not ascii
        and not save_kw.get("points_only")
        and (fmt == "ply" or (fmt is None and output.lower().endswith(".ply")))
    )
    if not stream:
        clouds = [part(i, c) for i, c in enumerate(chunks)]
        had = clouds[0][1]
        allc = _concat([c for c, _ in clouds])
        allc.history.append(prov)
        save(allc, output, ascii=ascii, **save_kw)
        report["input_normals"] = (
            "none" if not had else ("sign kept" if method == "keep" else "replaced")
        )
        return
    from recon_cli.io.atomic import atomic_open
    from recon_cli.io.ply import emit_body, geometry_to_ply

    with atomic_open(output) as f:
        for i, c in enumerate(chunks):
            cloud, had = part(i, c)
            ply = geometry_to_ply(cloud)
            if i == 0:
                report["input_normals"] = (
                    "none" if not had else ("sign kept" if method == "keep" else "replaced")
                )
                ply.comments.append(prov)
                head = PlyHead(ply, int(first[-1]))
                f.write(head.bytes)
                fields = [(p.name, p.dtype) for p in ply.elements[0].properties]
            elif [(p.name, p.dtype) for p in ply.elements[0].properties] != fields:
                raise InputError("the tiles do not all have the same properties", c.path)
            emit_body(ply, f.write)  # the header is the first chunk's, with every row


class PlyHead:
    """The output's header: the first chunk's, with the whole row count."""

    def __init__(self, ply, rows: int):
        from recon_cli.io.ply import header_bytes

        count = ply.elements[0].count
        ply.elements[0].count = rows
        self.bytes = header_bytes(ply)
        ply.elements[0].count = count


def _concat(clouds):
    from recon_cli.geometry import PointCloud

    if len(clouds) == 1:
        return clouds[0]
    first = clouds[0]
    return PointCloud(
        points=np.concatenate([c.points for c in clouds]),
        normals=np.concatenate([c.normals for c in clouds]),
        colors=None if first.colors is None else np.concatenate([c.colors for c in clouds]),
        attributes={k: np.concatenate([c.attributes[k] for c in clouds]) for k in first.attributes},
        history=list(first.history),
        point_dtype=first.point_dtype,
        obj_info=list(first.obj_info),
    )
