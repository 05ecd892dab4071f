"""Training of :mod:`recon_cli.stages.learned` (inputs already checked).

The cloud in network coordinates, the sampling spread, the loss settings and the
optimisation with its progress.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon_cli.stages.learned.model import OCC_GAIN, RADIUS, SdfModel, compute

EXTENT = 0.8  # the cloud's longest half-side maps to this in the network's coordinates
BAND = 0.05  # band samples for the eikonal term reach this fraction of the diagonal
SPREAD_NEIGHBOURS = 50  # IGR's per-point sampling spread: distance to this neighbour
DISTANCE_WEIGHT = 1.0  # the distance term's weight with normals
DISTANCE_CLAMP = 2.0  # the distance term's clamp, in band widths (the band's edge is reached)
GAP_NEIGHBOURS = 8  # no distance target closer to a point than its 8th neighbour
DISTANCE_EPS = 0.1  # the targets' nearest point may be up to 10 % farther than the nearest
OFFSET_SPREAD = 0.02  # samples p + t n_p, t ~ N(0, 0.02^2) network units (the cloud's side: 1.6)
OFFSET_WEIGHT = 3.0  # the weight of their distance term
EIKONAL_RAMP = 0.25  # with normals the eikonal weight rises over this share of the schedule
EIKONAL_START = 0.1  # from this fraction of it


@dataclass
class FitResult:
    """What :func:`recon_cli.stages.learned.fit_sdf` returns.

    Attributes
    ----------
    model : SdfModel
    iterations : int
        Optimiser steps taken.
    seconds : float
        Training wall time.
    interrupted : bool
        Training stopped by Ctrl-C; ``model`` holds the best parameters seen.
    loss : float
        Best smoothed training loss.
    history : list of (int, float)
        (iteration, smoothed loss) every 10 steps.
    eikonal_weight : float
        The weight used (the default depends on the normals).
    distance_weight : float
        The distance term's weight used (the default depends on the normals).
    """

    model: SdfModel
    iterations: int
    seconds: float
    interrupted: bool
    loss: float
    history: list
    eikonal_weight: float = 0.0
    distance_weight: float = 0.0


@dataclass
class Settings:
    """The checked options of one fit (defaults resolved)."""

    iterations: int
    max_seconds: float | None
    width: int
    depth: int
    frequencies: int
    eikonal_weight: float
    normal_weight: float
    distance_weight: float
    batch: int
    learning_rate: float
    field: str
    seed: int


def network_frame(pts: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Centre, scale (world units per network unit) and the points in network coordinates.

    The points are float32, the bounding box's centre at 0, its longest half-side at
    :data:`EXTENT`.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = 0.5 * (lo + hi)
    half = 0.5 * float((hi - lo).max())
    scale = (half if half > 0 else 1.0) / EXTENT
    return center, scale, ((pts - center) / scale).astype(np.float32)


def sampling_spread(tree, q: np.ndarray) -> np.ndarray:
    """IGR's per-point spread of the near samples: distance to the k-th neighbour, float32."""
    k = min(SPREAD_NEIGHBOURS, len(q) - 1)
    sigma = tree.query(q, k=k + 1)[0][:, -1].astype(np.float32)
    return np.maximum(sigma, 1e-4)


def occupancy_labels(tree, q: np.ndarray, normals: np.ndarray):
    """The labeller of training samples for ``occupancy``.

    A sample is inside (1) when its offsets to the 8 nearest points point against their
    normals.
    """
    nq = normals.astype(np.float32)

    def labels_fn(x: np.ndarray) -> np.ndarray:
        _, j = tree.query(x, k=8)
        d = np.einsum("ijk,ijk->ij", x[:, None, :] - q[j], nq[j])
        return (d.mean(axis=1) < 0).astype(np.float32)

    return labels_fn


def distance_targets(
    tree, q: np.ndarray, normals: np.ndarray, gap: np.ndarray, reach: float = np.inf
):
    """The signed distance of training samples where the cloud tells it.

    d(x) = |x - p| signed by the side of p's normal, p the nearest point; kept where x is
    off the points by at least the spacing ``gap`` of p (closer, the distance to the points
    is not the surface's), within 60 degrees of p's normal line (beyond, the side is
    ambiguous: x lies beside an edge or a gap) and within ``reach`` of the points (the
    clamped term needs no farther target; the tree's search stops there). p is the nearest
    point up to a factor 1 + ``DISTANCE_EPS`` in distance (an approximate search).
    """
    nq = normals.astype(np.float32)
    last = len(q) - 1

    def distance_fn(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, j = tree.query(x, k=1, eps=DISTANCE_EPS, distance_upper_bound=reach)
        found = j <= last  # none within reach: index len(q), distance inf
        j = np.minimum(j, last)
        d = np.where(found, d, 0.0).astype(np.float32)
        side = np.einsum("ij,ij->i", x - q[j], nq[j])
        keep = found & (d >= gap[j]) & (np.abs(side) >= 0.5 * d)
        return np.where(side < 0, -d, d).astype(np.float32), keep

    return distance_fn


def offset_targets(tree, q: np.ndarray, normals: np.ndarray):
    """The signed distance of samples ``x = p + t n_p`` off the points along their normals.

    d(x) = sign(t) min(|t|, |x - p'|), p' the nearest point: both are at least the distance to
    the surface (the nearest point's, as the surface passes between the points; the offset's,
    as p is on it). Kept where x is on the side of p' that t says (not through a wall thinner
    than |t|) and within 60 degrees of p''s normal line.
    """
    nq = normals.astype(np.float32)

    def offset_fn(x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, j = tree.query(x, k=1)
        side = np.einsum("ij,ij->i", x - q[j], nq[j])
        keep = (np.sign(side) == np.sign(t)) & (np.abs(side) >= 0.5 * d)
        dd = np.minimum(np.abs(t), d)
        return np.where(t < 0, -dd, dd).astype(np.float32), keep

    return offset_fn


def train_config(T, s: Settings, q: np.ndarray, with_normals: bool):
    """The loss and schedule of one fit (see :func:`recon_cli.stages.learned.fit_sdf`)."""
    band = BAND * float(np.linalg.norm(q.max(axis=0) - q.min(axis=0)))
    return T.TrainConfig(
        iterations=s.iterations,
        max_seconds=s.max_seconds,
        batch=s.batch,
        lr=s.learning_rate,
        eikonal_weight=s.eikonal_weight,
        normal_weight=s.normal_weight,
        field=s.field,
        seed=s.seed,
        occupancy_gain=OCC_GAIN,
        # with normals: eikonal samples spread over the band of 5 % of the diagonal around the
        # surface (where the field is used and `recon info` judges it) and the L1 penalty
        band=band,
        band_share=1.0 if with_normals else 0.0,
        eikonal_l1=with_normals,
        # with normals: the value off the points held at the distance to the points,
        # clamped beyond the band so that it does not fill thin cavities from far away
        distance_weight=s.distance_weight if with_normals else 0.0,
        distance_clamp=DISTANCE_CLAMP * band,
        # with normals: samples along the normals, signed by their offset, so that thin walls
        # keep their inside, and the eikonal weight ramped in, so that enclosed air (a cup's
        # inside) opens before the slope is held (figures in docs/design/fit-sdf.md)
        offset_spread=OFFSET_SPREAD if with_normals and s.distance_weight > 0 else 0.0,
        offset_weight=OFFSET_WEIGHT,
        eikonal_ramp=EIKONAL_RAMP if with_normals else 0.0,
        eikonal_start=EIKONAL_START,
    )


def _optimise(T, net, q, nrm, sigma, labels_fn, fns, cfg, s: Settings, progress):
    """Run the optimiser with a progress bar showing the smoothed loss."""
    from recon_cli.progress import task

    total = float(s.iterations) if s.max_seconds is None else None
    with task(progress, "fitting sdf", total) as t:
        name = getattr(t, "name", None)

        def on_step(it: int, loss: float, elapsed: float) -> None:
            if it == 1:
                logging.getLogger("recon").info("fit-sdf: step 1 done (%.2f s)", elapsed)
            if name is not None:
                t.name = f"fitting {s.field} loss {loss:.4f}"
            if s.max_seconds is None:
                t.update(it)
            else:
                t.update(elapsed)

        if s.max_seconds is not None and hasattr(t, "total"):
            t.total = s.max_seconds
        nrm32 = None if nrm is None else nrm.astype(np.float32)
        distance_fn, offset_fn = fns
        return T.train(
            net,
            q,
            nrm32,
            sigma,
            labels_fn,
            cfg,
            on_step,
            distance_fn=distance_fn,
            offset_fn=offset_fn,
        )


def fit(
    pts: np.ndarray, nrm: np.ndarray | None, s: Settings, threads: int | None, progress
) -> FitResult:
    """Fit the field to checked float64 points and unit normals (or None)."""
    from scipy.spatial import cKDTree

    T = compute()
    T.set_threads(threads)
    center, scale, q = network_frame(pts)
    tree = cKDTree(q)
    sigma = sampling_spread(tree, q)
    labels_fn = None
    if s.field == "occupancy":
        assert nrm is not None  # checked by fit_sdf
        labels_fn = occupancy_labels(tree, q, nrm)
    net = T.build(s.width, s.depth, s.frequencies, RADIUS, s.seed)
    cfg = train_config(T, s, q, nrm is not None)
    distance_fn = offset_fn = None
    if s.field == "sdf" and nrm is not None and s.distance_weight > 0:
        k = min(GAP_NEIGHBOURS, len(q) - 1)
        gap = tree.query(q, k=k + 1)[0][:, -1].astype(np.float32)
        distance_fn = distance_targets(tree, q, nrm, gap, cfg.distance_clamp)
        offset_fn = offset_targets(tree, q, nrm)
    logging.getLogger("recon").info(
        "fit-sdf: training %s (%d points, %s normals, width %d, depth %d)",
        s.field,
        len(pts),
        "with" if nrm is not None else "without",
        s.width,
        s.depth,
    )
    out = _optimise(T, net, q, nrm, sigma, labels_fn, (distance_fn, offset_fn), cfg, s, progress)
    config = {"width": s.width, "depth": s.depth, "frequencies": s.frequencies}
    model = SdfModel(net=net, center=center, scale=scale, field=s.field, config=config)
    return FitResult(
        model,
        out.iterations,
        out.seconds,
        out.interrupted,
        out.best_loss,
        out.history,
        s.eikonal_weight,
        s.distance_weight,
    )
