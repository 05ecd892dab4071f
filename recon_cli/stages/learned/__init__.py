"""Learned implicit surfaces: a neural signed distance (or occupancy) field fitted to one cloud.

A small MLP s(x) on Fourier features is fitted to the points by gradient descent (Adam):
the zero level passes through the points (L1), its gradient matches the normals when the
cloud has them (||grad s(p) - n_p||), and the eikonal loss on samples near and away from the
surface makes it a distance (IGR, Gropp et al. 2020; with normals its L1 form on extra samples
spread over the band of 5 % of the diagonal around the surface); SIREN's
off-surface term exp(-100 |s|) on the samples away from the points (Sitzmann et al. 2020)
keeps spurious zero levels out of the empty space, which a few CPU minutes of IGR alone
leave (figures in ``bench/calibration.md``). Without
normals it is IGR's zero-level + eikonal form, oriented by the geometric (sphere)
initialisation. ``field="occupancy"`` fits a logistic output instead (Occupancy Networks,
Mescheder et al. 2019) to inside/outside labels taken from the normals of the nearest points.

The field is sampled on a grid (:class:`recon_cli.grid.Grid`, negative inside): evaluated
exactly in the coarse cells that can hold the surface and trilinearly interpolated from a
coarse grid elsewhere. The fitted weights can be kept (:func:`save_model`) and queried later
(:func:`load_model`, :meth:`SdfModel.values`, :meth:`SdfModel.gradients`); meshes extracted
with :func:`recon_cli.stages.mcubes.marching_cubes` take their vertex normals from the network's
gradient (:func:`extract_mesh`).

The framework is PyTorch (the optional extra ``recon[learned]``), imported only when a field
is fitted or queried.

References
----------
.. [1] A. Gropp, L. Yariv, N. Haim, M. Atzmon, Y. Lipman, "Implicit Geometric
   Regularization for Learning Shapes", ICML 2020 (IGR: eikonal loss, zero-level loss).
.. [2] V. Sitzmann, J. Martel, A. Bergman, D. Lindell, G. Wetzstein, "Implicit Neural
   Representations with Periodic Activation Functions", NeurIPS 2020 (SIREN; periodic
   features for detail, normal loss).
.. [3] J. J. Park, P. Florence, J. Straub, R. Newcombe, S. Lovegrove, "DeepSDF: Learning
   Continuous Signed Distance Functions for Shape Representation", CVPR 2019.
.. [4] L. Mescheder, M. Oechsle, M. Niemeyer, S. Nowozin, A. Geiger, "Occupancy Networks:
   Learning 3D Reconstruction in Function Space", CVPR 2019.
.. [5] M. Atzmon, Y. Lipman, "SAL: Sign Agnostic Learning of Shapes from Raw Data", CVPR 2020
   (geometric initialisation); L. Yariv et al., "Multiview Neural Surface Reconstruction by
   Disentangling Geometry and Appearance", NeurIPS 2020 (the same with positional encoding).
"""

from __future__ import annotations

import io
import json
import logging
import os
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from typing import Any

import numpy as np

from recon_cli.errors import BackendError, InputError, ParameterError
from recon_cli.params import Param, StageSpec

FIELDS = ("sdf", "occupancy")
INSTALL_HINT = "fit-sdf needs PyTorch: pip install recon[learned]"
_FORMAT = "recon-fit-sdf-1"
_EXTENT = 0.8  # the cloud's longest half-side maps to this in the network's coordinates
_RADIUS = 0.5  # radius of the initial sphere, network coordinates
_COARSE = 4  # fine samples per coarse cell when sampling the grid
_BAND = 0.05  # band samples for the eikonal term reach this fraction of the diagonal
_OCC_GAIN = 10.0  # occupancy: p(inside) = sigmoid(-gain * s), so the sphere init is a valid field


def _torch():
    """The compute module, importing torch; a one-line error when the extra is missing."""
    os.environ.setdefault(
        "OMP_WAIT_POLICY", "PASSIVE"
    )  # busy-waiting threads crawl on a shared CPU
    try:
        from recon_cli.stages.learned import _torch_net
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] == "torch":
            raise BackendError(INSTALL_HINT) from None
        raise
    return _torch_net


@dataclass
class SdfModel:
    """A fitted field: the network and the map from world to network coordinates.

    Attributes
    ----------
    net : torch module
        s(q) on network coordinates ``q = (x - center) / scale``.
    center : (3,) float64
    scale : float
        World units per network unit; signed distances are ``scale * s``.
    field : {"sdf", "occupancy"}
    config : dict
        ``width``, ``depth``, ``frequencies``.
    """

    net: Any
    center: np.ndarray
    scale: float
    field: str
    config: dict = dataclass_field(default_factory=dict)

    def _q(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return ((x - self.center) / self.scale).astype(np.float32)

    def values(self, points: np.ndarray) -> np.ndarray:
        """Field at (k, 3) world points.

        Signed distance (world units, negative inside) for ``sdf``, ``0.5 - p(inside)`` for
        ``occupancy`` (negative inside, zero at p = 1/2).
        """
        raw = _torch().values(self.net, self._q(points))
        return self._to_field(raw)

    def gradients(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Field (as :meth:`values`) and its gradient in world units (autodiff), (k,) and (k, 3)."""
        raw, g = _torch().gradients(self.net, self._q(points))
        val = self._to_field(raw)
        if self.field == "sdf":
            return val, g.astype(np.float64)
        p = 1.0 / (1.0 + np.exp(_OCC_GAIN * raw.astype(np.float64)))  # p(inside)
        return val, (_OCC_GAIN * p * (1 - p))[:, None] * g / self.scale

    def _to_field(self, raw: np.ndarray) -> np.ndarray:
        raw = raw.astype(np.float64)
        if self.field == "sdf":
            return raw * self.scale
        return 0.5 - 1.0 / (1.0 + np.exp(_OCC_GAIN * raw))


@dataclass
class FitResult:
    """What :func:`fit_sdf` returns.

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
    """

    model: SdfModel
    iterations: int
    seconds: float
    interrupted: bool
    loss: float
    history: list
    eikonal_weight: float = 0.0


SPEC = StageSpec(
    name="fit-sdf",
    keeps_partial=True,
    summary="Fit a neural signed distance field to a cloud (needs recon[learned]).",
    description="""Fit a neural signed distance field to a cloud; write it on a grid (.npz).

    The grid is negative inside. With normals the loss holds the zero level on the points, the
    gradient on the normals and the gradient's norm at 1 (eikonal); without, the zero level and
    the eikonal term (IGR). `recon mcubes OUT.npz mesh.ply` extracts the surface; `recon info
    OUT.npz` reports the eikonal statistics. Needs PyTorch (pip install recon[learned]). Ctrl-C
    stops training and writes the best field so far (exit 130).""",
    takes=("cloud", "mesh"),
    gives=("grid",),
    output_suffix=".npz",
    params=(
        Param(
            "resolution",
            "int",
            128,
            "Grid cells along the longest side of the padded box.",
            unit="cells",
            min=8,
            max=1024,
        ),
        Param(
            "padding",
            "float",
            0.05,
            "Margin around the bounding box.",
            unit="fraction of the longest side",
            min=0.0,
            max=10.0,
        ),
        Param(
            "iterations",
            "int",
            2000,
            "Optimiser steps (the first of --iterations and --max-seconds wins).",
            unit="steps",
            min=1,
        ),
        Param(
            "max_seconds",
            "float",
            None,
            "Stop training after this wall time.",
            unit="seconds",
            min=0.0,
            min_open=True,
        ),
        Param("width", "int", 64, "Hidden units per layer.", unit="units", min=4, max=4096),
        Param("depth", "int", 4, "Hidden layers.", unit="layers", min=1, max=32),
        Param(
            "frequencies",
            "int",
            None,
            "Octaves of the positional encoding (0: raw coordinates; auto: 4 with "
            "normals, 2 without).",
            unit="octaves",
            min=0,
            max=16,
            words={"auto": None},
        ),
        Param(
            "eikonal_weight",
            "float",
            None,
            "Weight of the eikonal loss: the mean of abs(norm(grad s) - 1) with normals "
            "(auto: 3), of (norm(grad s) - 1)^2 without (auto: 0.1).",
            min=0.0,
            words={"auto": None},
        ),
        Param(
            "batch",
            "int",
            1024,
            "Surface points per step (plus 2x as many off-surface samples).",
            unit="points",
            min=16,
        ),
        Param(
            "seed",
            "int",
            0,
            "Seed of the weights and the sampling (same seed: same field).",
            min=0,
            max=2**32 - 1,
        ),
        Param(
            "field",
            "choice",
            "sdf",
            "sdf: signed distance (IGR); occupancy: logistic inside probability, "
            "written as 0.5 - p.",
            choices=FIELDS,
        ),
        Param(
            "threads", "int", None, "CPU threads for training (default: torch's).", min=1, max=1024
        ),
        Param(
            "model",
            "any",
            None,
            "Also write the fitted weights (.npz) to this file.",
            metavar="FILE",
        ),
        Param(
            "mesh",
            "any",
            None,
            "Also write the zero level set (PLY, vertex normals from the network's "
            "gradient) to this file.",
            metavar="FILE",
        ),
    ),
)


def _float(v: Any, name: str, lo: float, hi: float = np.inf) -> float:
    """A keyword of :func:`fit_sdf` that is not a stage parameter, checked."""
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {v!r}") from None
    if not (np.isfinite(x) and lo <= x <= hi):
        raise ParameterError(f"{name} must be in [{lo}, {hi}], got {v!r}")
    return x


def _field(v: Any) -> str:
    f = str(v).lower()
    if f not in FIELDS:
        raise ParameterError(f"field must be one of {', '.join(FIELDS)}, got {v!r}")
    return f


def fit_sdf(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    iterations: int = SPEC.param("iterations").default,
    max_seconds: float | None = SPEC.param("max_seconds").default,
    width: int = SPEC.param("width").default,
    depth: int = SPEC.param("depth").default,
    frequencies: int | None = SPEC.param("frequencies").default,
    eikonal_weight: float | None = SPEC.param("eikonal_weight").default,
    normal_weight: float = 1.0,
    batch: int = SPEC.param("batch").default,
    learning_rate: float = 2e-3,
    field: str = SPEC.param("field").default,
    seed: int = SPEC.param("seed").default,
    threads: int | None = SPEC.param("threads").default,
    progress=None,
) -> FitResult:
    """Fit a neural signed distance (or occupancy) field to a point cloud.

    Parameters
    ----------
    points : (n, 3) float
        The cloud, world units (n >= 10, finite).
    normals : (n, 3) float or None
        Unit outward normals; with them the loss has the normal term.
    iterations : int
        Optimiser steps (the cosine learning-rate schedule spans them).
    max_seconds : float or None
        Stop training after this wall time (the schedule then spans the time); whichever of
        ``iterations`` and ``max_seconds`` comes first ends training.
    width, depth : int
        Hidden units per layer and hidden layers of the MLP.
    frequencies : int or None
        Octaves of the Fourier features (0: the raw coordinates only). None: 4 with normals,
        2 without: high octaves make the gradient's norm ripple off the surface, and IGR's
        form fits them as noise (figures in ``bench/calibration.md``).
    eikonal_weight : float or None
        Weight of the eikonal term (``sdf`` only). With normals it is the L1 form
        E| ||grad s|| - 1 |, on the samples near the points, uniform ones, and as many spread
        over the band of 5 % of the diagonal around the surface (the field's useful part,
        where ``recon info`` judges it); None: 3.0. Without normals it is IGR's squared form
        E(||grad s|| - 1)^2 with IGR's 0.1: nothing but the zero level holds the slope, and
        3.0 slows the fit. The squared penalty barely pulls deviations under 0.1; the L1 one
        pulls every sample to 1 alike (figures in ``bench/calibration.md``).
    normal_weight : float
        Weight of E||grad s(p) - n_p|| (``sdf`` with normals only).
    batch : int
        Surface points per step; as many near-surface samples, half as many wider ones
        (sigma 0.1 of the network box), half as many uniform in the box and, with normals,
        as many band samples (eikonal term only; offsets N(0, (u b)^2), u uniform in [0, 1],
        b 5 % of the diagonal).
    learning_rate : float
        Adam's initial step (cosine decay to 2 % of it).
    field : {"sdf", "occupancy"}
        ``occupancy`` needs normals (they label the training samples inside/outside).
    seed : int
        Seeds the initial weights and the sampling: same seed, same input, same threads:
        same field.
    threads : int or None
        CPU threads for torch (None: torch's default).
    progress : Progress or None
        A bar with the current (smoothed) loss.

    Returns
    -------
    FitResult

    Raises
    ------
    InputError
        Too few points, NaN/inf coordinates, normals of the wrong shape.
    ParameterError
        A parameter out of range; ``occupancy`` without normals.
    BackendError
        PyTorch is not installed (``pip install recon[learned]``).
    """
    from scipy.spatial import cKDTree

    from recon_cli.progress import task

    v = SPEC.check(
        dict(
            iterations=iterations,
            max_seconds=max_seconds,
            width=width,
            depth=depth,
            frequencies=frequencies,
            eikonal_weight=eikonal_weight,
            batch=batch,
            field=field,
            seed=seed,
            threads=threads,
        ),
        complete=False,
    )
    iterations, max_seconds, width, depth = (
        v[k] for k in ("iterations", "max_seconds", "width", "depth")
    )
    batch, field, seed, threads = v["batch"], v["field"], v["seed"], v["threads"]
    normal_weight = _float(normal_weight, "normal_weight", 0.0)
    learning_rate = _float(learning_rate, "learning_rate", 1e-8, 1.0)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be (n, 3), got shape {pts.shape}")
    if len(pts) < 10:
        raise InputError(f"fit-sdf needs at least 10 points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise InputError("points have NaN or infinite coordinates")
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise InputError(f"normals must match the points' shape {pts.shape}, got {nrm.shape}")
        ln = np.linalg.norm(nrm, axis=1)
        if not (np.isfinite(ln).all() and (ln > 0).all()):
            raise InputError("normals have zero length or NaN")
        nrm = nrm / ln[:, None]
    frequencies = v["frequencies"] if v["frequencies"] is not None else 4 if nrm is not None else 2
    eikonal_weight = v["eikonal_weight"]
    if eikonal_weight is None:
        eikonal_weight = 3.0 if nrm is not None else 0.1  # L1 with normals, squared without
    if field == "occupancy" and nrm is None:
        raise ParameterError(
            "field occupancy needs a cloud with normals (they tell inside from outside)"
        )

    T = _torch()
    T.set_threads(threads)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = 0.5 * (lo + hi)
    half = 0.5 * float((hi - lo).max())
    scale = (half if half > 0 else 1.0) / _EXTENT
    q = ((pts - center) / scale).astype(np.float32)
    # IGR's per-point sampling spread: distance to the k-th neighbour
    tree = cKDTree(q)
    k = min(50, len(q) - 1)
    sigma = tree.query(q, k=k + 1)[0][:, -1].astype(np.float32)
    sigma = np.maximum(sigma, 1e-4)
    labels_fn = None
    if field == "occupancy":
        assert nrm is not None  # checked above
        nq = nrm.astype(np.float32)

        def labels_fn(x: np.ndarray) -> np.ndarray:
            # inside (1) when the offsets to the 8 nearest points point against their normals
            _, j = tree.query(x, k=8)
            d = np.einsum("ijk,ijk->ij", x[:, None, :] - q[j], nq[j])
            return (d.mean(axis=1) < 0).astype(np.float32)

    net = T.build(width, depth, frequencies, _RADIUS, seed)
    cfg = T.TrainConfig(
        iterations=iterations,
        max_seconds=max_seconds,
        batch=batch,
        lr=learning_rate,
        eikonal_weight=eikonal_weight,
        normal_weight=normal_weight,
        field=field,
        seed=seed,
        occupancy_gain=_OCC_GAIN,
        # with normals: eikonal samples spread over the band of 5 % of the diagonal around the
        # surface (where the field is used and `recon info` judges it) and the L1 penalty
        band=_BAND * float(np.linalg.norm(q.max(axis=0) - q.min(axis=0))),
        band_share=1.0 if nrm is not None else 0.0,
        eikonal_l1=nrm is not None,
    )
    total = float(iterations) if max_seconds is None else None
    logging.getLogger("recon").info(
        "fit-sdf: training %s (%d points, %s normals, width %d, depth %d)",
        field,
        len(pts),
        "with" if nrm is not None else "without",
        width,
        depth,
    )
    with task(progress, "fitting sdf", total) as t:
        name = getattr(t, "name", None)

        def on_step(it: int, loss: float, elapsed: float) -> None:
            if it == 1:
                logging.getLogger("recon").info("fit-sdf: step 1 done (%.2f s)", elapsed)
            if name is not None:
                t.name = f"fitting {field} loss {loss:.4f}"
            if max_seconds is None:
                t.update(it)
            else:
                t.update(elapsed)

        if max_seconds is not None and hasattr(t, "total"):
            t.total = max_seconds
        out = T.train(
            net, q, None if nrm is None else nrm.astype(np.float32), sigma, labels_fn, cfg, on_step
        )
    model = SdfModel(
        net=net,
        center=center,
        scale=scale,
        field=field,
        config={"width": width, "depth": depth, "frequencies": frequencies},
    )
    return FitResult(
        model,
        out.iterations,
        out.seconds,
        out.interrupted,
        out.best_loss,
        out.history,
        eikonal_weight,
    )


def sample_grid(
    model: SdfModel, origin: np.ndarray, voxel_size: float, shape: tuple[int, int, int]
) -> np.ndarray:
    """The field on a regular grid, (nx, ny, nz) float32 (world units, negative inside).

    ``sdf``: the network is evaluated at every sample of the coarse cells (``4`` samples a
    side) whose corners can be within reach of the surface (|s| below 1.5 coarse-cell
    diagonals or 6 % of the grid's diagonal, or a sign change), elsewhere the coarse grid
    is interpolated trilinearly.
    ``occupancy`` (not a distance: no such bound) is evaluated everywhere.
    """
    from scipy.ndimage import map_coordinates

    nx, ny, nz = (int(s) for s in shape)
    shape = (nx, ny, nz)
    origin = np.asarray(origin, dtype=np.float64)
    h = float(voxel_size)
    axes = [origin[a] + h * np.arange(shape[a]) for a in range(3)]

    def at(ix, iy, iz) -> np.ndarray:
        g = np.stack(np.meshgrid(ix, iy, iz, indexing="ij"), axis=-1).reshape(-1, 3)
        return model.values(g).reshape(len(ix), len(iy), len(iz))

    c = _COARSE
    if model.field != "sdf" or min(shape) < 4 * c:
        return at(*axes).astype(np.float32)
    cshape = [(s - 1 + c - 1) // c + 1 for s in shape]  # coarse nodes cover the grid
    caxes = [origin[a] + h * c * np.arange(cshape[a]) for a in range(3)]
    coarse = at(*caxes)
    # trilinear everywhere (fine sample (i, j, k) sits at coarse index (i/c, j/c, k/c))
    idx = np.indices(shape, dtype=np.float32).reshape(3, -1) / c
    out = map_coordinates(coarse, idx, order=1, mode="nearest").reshape(shape).astype(np.float32)
    # exact values wherever the surface may be within reach, and in a band of 6 % of the
    # grid's diagonal (where the eikonal property is checked: trilinear interpolation of a
    # curved distance field would understate its gradient there)
    reach = max(1.5 * np.sqrt(3.0) * c * h, 0.06 * h * float(np.linalg.norm(np.array(shape) - 1)))
    a = np.abs(coarse)
    near = (
        np.minimum.reduce(
            [
                a[dx : dx + cshape[0] - 1, dy : dy + cshape[1] - 1, dz : dz + cshape[2] - 1]
                for dx in (0, 1)
                for dy in (0, 1)
                for dz in (0, 1)
            ]
        )
        < reach
    )
    neg = coarse < 0
    anyneg = np.logical_or.reduce(
        [
            neg[dx : dx + cshape[0] - 1, dy : dy + cshape[1] - 1, dz : dz + cshape[2] - 1]
            for dx in (0, 1)
            for dy in (0, 1)
            for dz in (0, 1)
        ]
    )
    allneg = np.logical_and.reduce(
        [
            neg[dx : dx + cshape[0] - 1, dy : dy + cshape[1] - 1, dz : dz + cshape[2] - 1]
            for dx in (0, 1)
            for dy in (0, 1)
            for dz in (0, 1)
        ]
    )
    near |= anyneg & ~allneg
    cells = np.argwhere(near)
    if len(cells):
        fine = np.zeros(shape, dtype=bool)
        for dx in range(c + 1):
            for dy in range(c + 1):
                for dz in range(c + 1):
                    i = np.minimum(cells * c + (dx, dy, dz), np.array(shape) - 1)
                    fine[i[:, 0], i[:, 1], i[:, 2]] = True
        where = np.argwhere(fine)
        out[fine] = model.values(origin + where * h).astype(np.float32)
    return out


def extract_mesh(model: SdfModel, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes on ``grid`` (sampled from ``model``) with autodiff vertex normals.

    Returns
    -------
    vertices : (k, 3) float64
    faces : (m, 3) int64
        Counter-clockwise seen from outside.
    normals : (k, 3) float64
        Unit gradients of the network at the vertices (outward).
    """
    from recon_cli.stages.mcubes import marching_cubes

    v, f, _ = marching_cubes(grid.sdf, iso=0.0, spacing=grid.voxel_size, origin=grid.origin)
    if len(v) == 0:
        return v, f, np.zeros((0, 3))
    _, g = model.gradients(v)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return v, f, np.divide(g, n, out=np.zeros_like(g), where=n > 0)


def near_surface_eikonal(grid, distance: float) -> dict:
    """Eikonal statistics (central differences) over grid samples with |s| <= ``distance``.

    Returns
    -------
    dict
        ``cells``, ``fraction_within_0.1`` (share with | ||grad s|| - 1 | <= 0.1), ``median``.
    """
    s = np.asarray(grid.sdf, dtype=np.float64)
    h = grid.voxel_size
    g = np.gradient(s, h)
    norm = np.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2)[1:-1, 1:-1, 1:-1]
    sel = np.abs(s[1:-1, 1:-1, 1:-1]) <= distance
    sel &= np.isfinite(norm)
    vals = norm[sel]
    if not len(vals):
        return {"cells": 0, "fraction_within_0.1": None, "median": None}
    return {
        "cells": int(len(vals)),
        "fraction_within_0.1": float(np.mean(np.abs(vals - 1) <= 0.1)),
        "median": float(np.median(vals)),
    }


def save_model(model: SdfModel, path: str | os.PathLike) -> None:
    """Write the fitted weights and the coordinate map as ``.npz`` (atomically; no pickle)."""
    from recon_cli.io.atomic import write_bytes

    arrays = {f"param:{k}": v for k, v in _torch().state_arrays(model.net).items()}
    meta = {
        "format": _FORMAT,
        "field": model.field,
        "scale": model.scale,
        "center": list(map(float, model.center)),
        **model.config,
    }
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    write_bytes(path, buf.getvalue())


def load_model(path: str | os.PathLike) -> SdfModel:
    """Read weights written by :func:`save_model`.

    Raises
    ------
    InputError
        Not a model file of this format.
    """
    import zipfile

    where = str(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k.split(":", 1)[1]: z[k] for k in z.files if k.startswith("param:")}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise InputError(f"not a fit-sdf model file ({exc})", where) from None
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        raise InputError("not a fit-sdf model file", where)
    T = _torch()
    net = T.build(int(meta["width"]), int(meta["depth"]), int(meta["frequencies"]), _RADIUS, 0)
    try:
        T.load_state(net, arrays)
    except (RuntimeError, KeyError) as exc:
        raise InputError(
            f"model weights do not match its description ({str(exc).splitlines()[0]})", where
        ) from None
    cfg = {k: int(meta[k]) for k in ("width", "depth", "frequencies")}
    return SdfModel(
        net,
        np.asarray(meta["center"], dtype=np.float64),
        float(meta["scale"]),
        _field(meta["field"]),
        cfg,
    )


@SPEC.runner
def run_stage(
    data,
    *,
    resolution: int,
    padding: float,
    iterations: int,
    max_seconds: float | None,
    width: int,
    depth: int,
    frequencies: int | None,
    eikonal_weight: float | None,
    batch: int,
    seed: int,
    field: str,
    threads: int | None,
    model: str | None,
    mesh: str | None,
    progress=None,
):
    """Stage ``fit-sdf``: a cloud (or a mesh's vertices) -> the fitted field on a grid.

    Parameters
    ----------
    data : PointCloud or TriangleMesh
        Its points (and normals when present) are fitted.
    resolution : int
        Cells along the longest side of the padded bounding box (as ``recon sdf``).
    padding : float
        Margin, fraction of the box's longest side.
    iterations, max_seconds, width, depth, frequencies, eikonal_weight, batch, seed, field, threads
        As in :func:`fit_sdf`.
    model : path or None
        Also write the fitted weights here (:func:`save_model`).
    mesh : path or None
        Also write the zero level set here (marching cubes on the grid, vertex normals
        from the network's gradient), as PLY.

    Returns
    -------
    StageResult
        A :class:`~recon_cli.grid.Grid` (``sdf``: signed distance, world units; ``occupancy``:
        ``0.5 - p(inside)``; both negative inside, the surface at 0). Report keys
        ``field``, ``points``, ``normals_used``, ``iterations``, ``train_seconds``,
        ``loss``, ``interrupted``, ``shape``, ``voxel_size``, ``eikonal`` (whole grid,
        :func:`recon_cli.stages.sdf.eikonal_check`), ``eikonal_near`` (samples within 5 % of the
        diagonal of the surface, :func:`near_surface_eikonal`), and with ``mesh``:
        ``mesh_vertices``, ``mesh_faces``.
    """
    from recon_cli.geometry import PointCloud, TriangleMesh, bbox_diagonal, float64
    from recon_cli.grid import Grid
    from recon_cli.stages import StageResult
    from recon_cli.stages.sdf import eikonal_check, grid_frame

    if not isinstance(data, (PointCloud, TriangleMesh)):
        raise InputError(f"fit-sdf needs a point cloud (or mesh), got {type(data).__name__}")
    data = float64(data)  # parameters and the input's kind: checked by SPEC
    model_path = None if model in (None, "") else os.fspath(model)
    mesh_path = None if mesh in (None, "") else os.fspath(mesh)
    pts = data.points
    fit = fit_sdf(
        pts,
        data.normals,
        iterations=iterations,
        max_seconds=max_seconds,
        width=width,
        depth=depth,
        frequencies=frequencies,
        eikonal_weight=eikonal_weight,
        batch=batch,
        field=field,
        seed=seed,
        threads=threads,
        progress=progress,
    )
    origin, h, shape = grid_frame(pts.min(axis=0), pts.max(axis=0), resolution, None, padding)
    from recon_cli.progress import task

    with task(progress, "sampling the field", 1) as t:
        values = sample_grid(fit.model, origin, h, shape)
        t.advance(1)
    grid = Grid(sdf=values, origin=origin, voxel_size=h, history=list(data.history))
    diag = bbox_diagonal(pts)
    report = {
        "field": fit.model.field,
        "points": int(len(pts)),
        "normals_used": data.normals is not None,
        "iterations": fit.iterations,
        "train_seconds": fit.seconds,
        "loss": fit.loss,
        "interrupted": fit.interrupted,
        "shape": list(shape),
        "voxel_size": h,
        "eikonal": eikonal_check(grid) if fit.model.field == "sdf" else None,
        "eikonal_near": near_surface_eikonal(grid, 0.05 * diag)
        if fit.model.field == "sdf"
        else None,
        "provenance": {
            "model": model_path,
            "mesh": mesh_path,
            "iterations_done": fit.iterations,
            "eikonal_weight": fit.eikonal_weight,
            "frequencies": fit.model.config["frequencies"],
        },
    }
    if model_path is not None:
        save_model(fit.model, model_path)
    if mesh_path is not None:
        from recon_cli.io.ply import write_ply

        v, f, n = extract_mesh(fit.model, grid)
        write_ply(
            TriangleMesh(
                vertices=v, faces=f, normals=n, history=list(grid.history), point_dtype=np.float32
            ),
            mesh_path,
        )
        report["mesh_vertices"] = int(len(v))
        report["mesh_faces"] = int(len(f))
    return StageResult(output=grid, report=report)
