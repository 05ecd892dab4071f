"""Geometric comparison of a reconstruction against a reference (``recon diff``).

Definitions (``d(p, S)`` is the exact Euclidean distance from point ``p`` to the set ``S``:
the nearest triangle for a mesh, the nearest point for a cloud):

* ``C`` are ``samples`` area-uniform samples of the candidate (a cloud: its points, at
  most ``samples`` of them drawn without replacement), ``R`` the same for the reference;
* ``accuracy``      = mean over ``c`` in ``C`` of ``d(c, reference)``;
* ``completeness``  = mean over ``r`` in ``R`` of ``d(r, candidate)``;
* ``chamfer_l1``    = (accuracy + completeness) / 2;
* ``chamfer_l2``    = (mean ``d(c, reference)**2`` + mean ``d(r, candidate)**2``) / 2 (squared
  units);
* ``hausdorff``     = max of the two directional maxima; ``hausdorff_p95`` / ``_p99`` = max of the
  two directional 95th / 99th percentiles;
* ``precision(τ)``  = fraction of ``C`` with ``d < τ``; ``recall(τ)`` = fraction of ``R`` with
  ``d < τ``; ``fscore(τ)`` = 2 P R / (P + R) (0 when both are 0);
* ``normal_consistency`` = mean over both directions of ``|n(p) · n(q)|`` where ``q`` is the
  closest point of ``p`` and the normals are the face normals (cloud: the point normals);
  ``normal_consistency_oriented`` is the same without the absolute value (detects flipped
  orientation). ``None`` when a side has no normals.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any, TypeGuard

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, bbox_diagonal, float64

DEFAULT_TAUS = ("0.5%", "1%")

# a candidate whose bounding box is this many times larger or smaller than the reference's
# is most likely in other units (mm against m)
_UNITS_RATIO = 5.0


def compare_meshes(
    candidate: TriangleMesh | PointCloud,
    reference: TriangleMesh | PointCloud,
    samples: int = 200_000,
    seed: int = 0,
    taus: Sequence[float | str] | str | None = None,
) -> dict[str, Any]:
    """Distances, F-scores, normal consistency and topology of ``candidate`` against ``reference``.

    Parameters
    ----------
    candidate, reference : TriangleMesh or PointCloud
        The reconstruction and the ground truth, in the same units and frame. A mesh is
        sampled area-uniformly and measured point-to-surface; a cloud gives its points
        and is measured point-to-point (stated in ``mode``).
    samples : int
        Number of samples drawn on each side (a cloud with more points is subsampled).
    seed : int
        Seed of the sampling (the candidate uses ``seed``, the reference ``seed + 1``).
    taus : sequence of float or str, or str, optional
        F-score thresholds: a float is an absolute distance, a string ``"0.5%"`` is a
        percentage of the reference's bounding-box diagonal; a comma-separated string
        (``"0.5%,1%"``) is accepted. Default ``0.5%`` and ``1%``.

    Returns
    -------
    dict
        Stable keys: ``mode``, ``mode_accuracy``, ``mode_completeness``, ``samples``,
        ``seed``, ``reference_diagonal``, ``accuracy``, ``completeness``, ``chamfer_l1``,
        ``chamfer_l2``, ``hausdorff``, ``hausdorff_p95``, ``hausdorff_p99``, ``tau``
        (absolute, list), ``tau_relative`` (fraction of the diagonal, list), ``precision``,
        ``recall``, ``fscore`` (lists aligned with ``tau``), ``normal_consistency``,
        ``normal_consistency_oriented``, ``directions`` (per direction: ``mean``, ``rms``,
        ``max``, ``p50``, ``p95``, ``p99``), ``area`` and ``volume`` (``candidate`` /
        ``reference``; None for a cloud, volume None unless the mesh is closed and
        consistently oriented), ``topology`` (``candidate`` / ``reference``: the
        :func:`recon_cli.mesh.topology.report` dict, None for a cloud) and ``warnings`` (list of
        str: units or frames that look different, point-to-point fallback, no normals).
        Distances are in the units of the inputs.

    Raises
    ------
    InputError
        An empty side (no points, or a mesh of zero area), or non-finite coordinates.
    ParameterError
        ``samples`` < 1 or an unusable ``tau``.
    """
    samples = check_samples(samples)
    seed = int(seed)
    _check_input(candidate, "candidate")
    _check_input(reference, "reference")
    candidate, reference = float64(candidate), float64(reference)
    diag = bbox_diagonal(reference.points)
    if not diag > 0:
        raise InputError("reference has a zero-size bounding box")
    tau_abs = parse_taus(taus, diag)
    warnings = _units_warnings(candidate, reference)

    cand_pts, cand_nrm = samples_of(candidate, samples, seed)
    ref_pts, ref_nrm = samples_of(reference, samples, seed + 1)
    d_acc, n_acc = surface_distances(cand_pts, reference)
    d_comp, n_comp = surface_distances(ref_pts, candidate)
    mode_acc = _mode(reference)
    mode_comp = _mode(candidate)
    if mode_acc == mode_comp:
        mode = mode_acc
    else:
        mode = f"accuracy {mode_acc}, completeness {mode_comp}"
    if isinstance(reference, PointCloud):
        warnings.append(
            "reference has no faces: distances to it are point-to-point (nearest reference point)"
        )

    acc_stats = _stats(d_acc)
    comp_stats = _stats(d_comp)
    precision = [float(np.mean(d_acc < t)) for t in tau_abs]
    recall = [float(np.mean(d_comp < t)) for t in tau_abs]
    fscore = [
        2 * p * r / (p + r) if p + r > 0 else 0.0 for p, r in zip(precision, recall, strict=True)
    ]
    nc, nc_oriented = _normal_consistency([(cand_nrm, n_acc), (ref_nrm, n_comp)])
    if nc is None:
        warnings.append("normal consistency not computed: a point cloud side has no normals")

    topo_c, topo_r = topology_of(candidate), topology_of(reference)
    return {
        "mode": mode,
        "mode_accuracy": mode_acc,
        "mode_completeness": mode_comp,
        "samples": {"candidate": int(len(cand_pts)), "reference": int(len(ref_pts))},
        "seed": seed,
        "reference_diagonal": diag,
        "accuracy": acc_stats["mean"],
        "completeness": comp_stats["mean"],
        "chamfer_l1": 0.5 * (acc_stats["mean"] + comp_stats["mean"]),
        "chamfer_l2": 0.5 * (acc_stats["rms"] ** 2 + comp_stats["rms"] ** 2),
        "hausdorff": max(acc_stats["max"], comp_stats["max"]),
        "hausdorff_p95": max(acc_stats["p95"], comp_stats["p95"]),
        "hausdorff_p99": max(acc_stats["p99"], comp_stats["p99"]),
        "tau": [float(t) for t in tau_abs],
        "tau_relative": [float(t / diag) for t in tau_abs],
        "precision": precision,
        "recall": recall,
        "fscore": fscore,
        "normal_consistency": nc,
        "normal_consistency_oriented": nc_oriented,
        "directions": {"accuracy": acc_stats, "completeness": comp_stats},
        "area": {"candidate": _area(candidate, topo_c), "reference": _area(reference, topo_r)},
        "volume": {
            "candidate": _volume(candidate, topo_c),
            "reference": _volume(reference, topo_r),
        },
        "topology": {"candidate": topo_c, "reference": topo_r},
        "warnings": warnings,
    }


def point_distances(query: np.ndarray, target: TriangleMesh | PointCloud) -> np.ndarray:
    """Exact distance from each query point to ``target``.

    Parameters
    ----------
    query : (k, 3) float64
        Points.
    target : TriangleMesh or PointCloud
        A mesh with faces (point-to-triangle distance) or a cloud (nearest point).

    Returns
    -------
    (k,) float64
        Distances, in the units of the inputs.
    """
    query = np.ascontiguousarray(query, dtype=np.float64).reshape(-1, 3)
    _check_input(target, "target")
    target = float64(target)
    if not np.isfinite(query).all():
        raise InputError("query points hold NaN or infinite coordinates")
    return surface_distances(query, target)[0]


def vertex_distances(
    candidate: TriangleMesh | PointCloud, reference: TriangleMesh | PointCloud
) -> np.ndarray:
    """Distance from each vertex (point) of ``candidate`` to ``reference``: (n,), for heatmaps."""
    _check_input(candidate, "candidate")
    return point_distances(candidate.points, reference)


def heatmap(
    candidate: TriangleMesh | PointCloud,
    distances: np.ndarray,
    vmax: float | None = None,
) -> TriangleMesh | PointCloud:
    """A copy of ``candidate`` with per-vertex ``distance`` as a scalar property and as colours.

    Parameters
    ----------
    candidate : TriangleMesh or PointCloud
    distances : (n,) float64
        One distance per vertex (see :func:`vertex_distances`).
    vmax : float, optional
        Distance shown in the hottest colour (default: the 99th percentile of ``distances``).

    Returns
    -------
    TriangleMesh or PointCloud
        With ``attributes["distance"]`` (float32) and ``colors`` (n, 3) uint8 (see
        :func:`recon_cli.eval.render.colormap`); everything else copied.
    """
    from recon_cli.eval.render import colormap

    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    if len(d) != len(candidate.points):
        raise ParameterError(f"{len(d)} distances for {len(candidate.points)} vertices")
    if vmax is None:
        vmax = default_vmax([d])
    out = candidate.copy()
    out.attributes["distance"] = d.astype(np.float32)
    out.colors = colormap(d, 0.0, float(vmax))
    return out


def shared_vmax(distance_arrays: Sequence[np.ndarray], tau: float | None = None) -> float:
    """Top of a colour scale shared by several heatmaps: :func:`default_vmax`, at least ``tau``.

    Reaching the smallest F-score threshold keeps sub-threshold noise blue.
    """
    v = default_vmax(distance_arrays)
    return max(v, float(tau)) if tau is not None else v


def check_vmax(vmax: Any) -> float:
    """``vmax`` as a positive finite float, or :class:`ParameterError`."""
    try:
        v = float(vmax)
    except (TypeError, ValueError):
        raise ParameterError(f"vmax must be a number, got {vmax!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ParameterError(f"vmax must be positive, got {vmax!r}")
    return v


def default_vmax(distance_arrays: Sequence[np.ndarray]) -> float:
    """Shared colour-scale maximum: the largest 99th percentile of the arrays (1 if all are 0)."""
    v = 0.0
    for d in distance_arrays:
        if len(d):
            v = max(v, float(np.percentile(d, 99)))
    return v if v > 0 else 1.0


def parse_taus(taus: Sequence[float | str] | str | None, diagonal: float) -> list[float]:
    """Absolute F-score thresholds from ``taus`` (floats absolute, ``"x%"`` of ``diagonal``)."""
    if taus is None:
        taus = DEFAULT_TAUS
    if isinstance(taus, str):
        taus = [t for t in taus.split(",") if t.strip()]
    out = []
    for t in taus:
        try:
            if isinstance(t, str) and t.strip().endswith("%"):
                v = float(t.strip()[:-1]) / 100.0 * diagonal
            else:
                v = float(t)
        except ValueError:
            raise ParameterError(f"tau {t!r} is not a number or a percentage like '0.5%'") from None
        if not (math.isfinite(v) and v > 0):
            raise ParameterError(f"tau must be positive, got {t!r}")
        out.append(v)
    if not out:
        raise ParameterError("at least one tau is needed")
    return out


def topology_of(obj: TriangleMesh | PointCloud) -> dict[str, Any] | None:
    """The topology report of a mesh (:func:`recon_cli.mesh.topology.report`), None for a cloud."""
    if not isinstance(obj, TriangleMesh):
        return None
    from recon_cli.mesh.topology import report

    return report(obj)


def load_geometry(path: str | os.PathLike, role: str | None = None) -> TriangleMesh | PointCloud:
    """Read a mesh or cloud from ``path`` (a grid ``.npz`` is refused with :class:`InputError`).

    With ``role`` ("candidate", "reference") it is also checked as :func:`compare_meshes`
    would, and the errors name ``path``.
    """
    from recon_cli.errors import naming
    from recon_cli.io.load import load

    obj = load(path)
    if not isinstance(obj, (TriangleMesh, PointCloud)):
        raise InputError("is a grid, not a mesh or point cloud", str(path))
    if role is not None:
        with naming(path):
            _check_input(obj, role)
    return obj


# --------------------------------------------------------------------------- internals


def check_samples(samples: Any) -> int:
    """``samples`` as a positive integer, or a :class:`~recon_cli.errors.ParameterError`."""
    try:
        n = int(samples)
    except (TypeError, ValueError):
        raise ParameterError(f"samples must be an integer, got {samples!r}") from None
    if n < 1 or n != float(samples):
        raise ParameterError(f"samples must be a positive integer, got {samples!r}")
    return n


def _check_input(obj: Any, name: str) -> None:
    if not isinstance(obj, (TriangleMesh, PointCloud)):
        raise ParameterError(f"{name} must be a mesh or a point cloud, got {type(obj).__name__}")
    if len(obj.points) == 0:
        raise InputError(f"{name} is empty (no vertices)")
    if not np.isfinite(obj.points).all():
        raise InputError(f"{name} holds NaN or infinite coordinates")
    if isinstance(obj, TriangleMesh) and len(obj.faces):
        f = obj.faces
        if f.min() < 0 or f.max() >= len(obj.vertices):
            raise InputError(f"{name} has face indices outside its {len(obj.vertices)} vertices")
        if not (_area(obj) or 0.0) > 0:
            raise InputError(f"{name} has faces but zero surface area")


def _is_surface(obj: TriangleMesh | PointCloud) -> TypeGuard[TriangleMesh]:
    return isinstance(obj, TriangleMesh) and len(obj.faces) > 0


def _mode(target: TriangleMesh | PointCloud) -> str:
    return "point-to-surface" if _is_surface(target) else "point-to-point"


def _as_target(obj: TriangleMesh | PointCloud) -> TriangleMesh | PointCloud:
    # a mesh without faces is a cloud of its vertices
    if isinstance(obj, TriangleMesh) and len(obj.faces) == 0:
        return obj.to_point_cloud()
    return obj


def samples_of(
    obj: TriangleMesh | PointCloud, n: int, seed: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """Sample points and their unit normals (None when unknown)."""
    from recon_cli.mesh.sampling import sample_surface

    if _is_surface(obj):
        s = sample_surface(obj, n, seed=seed)
        return s.points, s.normals
    pts = obj.points
    nrm = _unit(obj.normals) if obj.normals is not None else None
    if len(pts) > n:
        idx = np.sort(np.random.default_rng(seed).choice(len(pts), size=n, replace=False))
        pts = pts[idx]
        nrm = None if nrm is None else nrm[idx]
    return pts, nrm


def surface_distances(
    query: np.ndarray, target: TriangleMesh | PointCloud
) -> tuple[np.ndarray, np.ndarray | None]:
    """Distances from ``query`` to ``target`` and the target's unit normal at each closest point."""
    target = _as_target(target)
    if isinstance(target, TriangleMesh):
        from recon_cli.mesh.distance import closest_points
        from recon_cli.mesh.sampling import face_normals

        # queries in Morton order: neighbours in a run reuse each other's nearest triangle
        # (3x faster than area-sampled points in random order)
        order = _morton_order(query)
        d_sorted, f_sorted, _ = closest_points(target.vertices, target.faces, query[order])
        d = np.empty(len(query))
        face = np.empty(len(query), dtype=np.int64)
        d[order], face[order] = d_sorted, f_sorted
        fn, _ = face_normals(target.vertices, target.faces)
        return d, fn[face]
    from scipy.spatial import cKDTree

    d, idx = cKDTree(target.points).query(query, k=1)
    nrm = None if target.normals is None else _unit(target.normals)[idx]
    return np.asarray(d, dtype=np.float64), nrm


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 21 bits of ``x`` (uint64)."""
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation sorting ``points`` (k, 3) along a Z-order curve of their bounding cube."""
    if len(points) < 2:
        return np.arange(len(points))
    lo = points.min(axis=0)
    span = float((points.max(axis=0) - lo).max()) or 1.0
    q = np.clip(((points - lo) * ((2**21 - 1) / span)).astype(np.int64), 0, 2**21 - 1)
    code = (
        _spread_bits(q[:, 0])
        | (_spread_bits(q[:, 1]) << np.uint64(1))
        | (_spread_bits(q[:, 2]) << np.uint64(2))
    )
    return np.argsort(code, kind="stable")


def _unit(n: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def _stats(d: np.ndarray) -> dict[str, float]:
    p50, p95, p99 = np.percentile(d, [50, 95, 99])
    return {
        "mean": float(d.mean()),
        "rms": float(np.sqrt(np.mean(d * d))),
        "max": float(d.max()),
        "p50": float(p50),
        "p95": float(p95),
        "p99": float(p99),
    }


def _normal_consistency(pairs) -> tuple[float | None, float | None]:
    absolute, oriented = [], []
    for a, b in pairs:
        if a is None or b is None:
            return None, None
        dot = np.einsum("ij,ij->i", a, b)
        # zero normals (degenerate faces, unoriented points) carry no direction
        valid = (np.einsum("ij,ij->i", a, a) > 0.5) & (np.einsum("ij,ij->i", b, b) > 0.5)
        if not valid.any():
            return None, None
        absolute.append(float(np.abs(dot[valid]).mean()))
        oriented.append(float(dot[valid].mean()))
    return float(np.mean(absolute)), float(np.mean(oriented))


def _area(obj: TriangleMesh | PointCloud, topo: dict | None = None) -> float | None:
    if not _is_surface(obj):
        return None
    if topo and topo.get("area") is not None:
        return float(topo["area"])
    tri = obj.vertices[obj.faces]
    return float(
        0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    )


def _volume(obj: TriangleMesh | PointCloud, topo: dict | None = None) -> float | None:
    """Enclosed volume: the topology report's (None unless closed and oriented) when it has one."""
    if not _is_surface(obj):
        return None
    if topo is not None and "volume" in topo:
        return None if topo["volume"] is None else float(topo["volume"])
    tri = obj.vertices[obj.faces]
    c = tri.mean(axis=(0, 1))  # about the centroid, for less cancellation far from the origin
    a, b, d = tri[:, 0] - c, tri[:, 1] - c, tri[:, 2] - c
    return float(np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0)


def _units_warnings(
    candidate: TriangleMesh | PointCloud, reference: TriangleMesh | PointCloud
) -> list[str]:
    out = []
    dc, dr = bbox_diagonal(candidate.points), bbox_diagonal(reference.points)
    if dc > 0 and dr > 0:
        ratio = dc / dr
        if ratio > _UNITS_RATIO or ratio < 1 / _UNITS_RATIO:
            out.append(
                f"candidate's bounding box is {ratio:.3g} times the reference's: different units "
                f"(mm against m)? distances are taken as given"
            )
    lo = np.maximum(candidate.points.min(axis=0), reference.points.min(axis=0))
    hi = np.minimum(candidate.points.max(axis=0), reference.points.max(axis=0))
    if (lo > hi).any():
        out.append("bounding boxes do not overlap: different frames? distances are taken as given")
    return out
