"""Learned implicit surfaces: a neural signed distance (or occupancy) field fitted to one cloud.

A small MLP s(x) on Fourier features is fitted to the points by gradient descent (Adam):
the zero level passes through the points (L1), its gradient matches the normals when the
cloud has them (||grad s(p) - n_p||), and the eikonal loss on samples near and away from the
surface makes it a distance (IGR, Gropp et al. 2020; with normals its L1 form on extra samples
spread over the band of 5 % of the diagonal around the surface); SIREN's
off-surface term exp(-100 |s|) on the samples away from the points (Sitzmann et al. 2020)
keeps spurious zero levels out of the empty space, which a few CPU minutes of IGR alone
leave; and with normals the value on the samples away from the points is held at the distance
to the nearest point, signed by its normal and clamped beyond the band (DeepSDF's clamped L1),
so that the field rises at the true slope in thin walls and enclosed air, where the eikonal
term alone lets it sag (figures in ``bench/calibration.md``); samples off the points along
their normals, signed by their offset, hold the inside of walls thinner than the band, and the
eikonal weight is ramped in over the first quarter of the schedule, so that enclosed air (a
cup's inside) opens before the slope is held (``docs/design/fit-sdf.md``). Without normals it
is IGR's zero-level + eikonal form, oriented by the geometric (sphere) initialisation.
``field="occupancy"`` fits a logistic output instead (Occupancy Networks,
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

import os
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError, StageFailed
from recon_cli.params import Param, StageSpec
from recon_cli.stages.learned.meshing import extract_mesh, sample_grid
from recon_cli.stages.learned.model import (
    FIELDS,
    INSTALL_HINT,
    SdfModel,
    load_model,
    save_model,
)
from recon_cli.stages.learned.training import DISTANCE_WEIGHT, FitResult, Settings, fit

__all__ = [
    "FIELDS",
    "INSTALL_HINT",
    "SPEC",
    "FitResult",
    "SdfModel",
    "extract_mesh",
    "fit_sdf",
    "load_model",
    "run_stage",
    "sample_grid",
    "save_model",
]

SPEC = StageSpec(
    name="fit-sdf",
    keeps_partial=True,
    summary="Fit a neural signed distance field to a cloud (needs recon[learned]).",
    description="""Fit a neural signed distance field to a cloud; write it on a grid (.npz).

    The grid is negative inside. With normals the loss holds the zero level on the points, the
    gradient on the normals, the gradient's norm at 1 (eikonal) and the value near the surface
    at the signed distance to the points; without, the zero level and the eikonal term (IGR).
    Beyond two cells of the grid's zero level the grid holds the exact distance to it (the
    network extrapolates there; --model keeps the network). `recon mcubes OUT.npz mesh.ply`
    extracts the surface; `recon info OUT.npz` reports the eikonal statistics. Needs PyTorch
    (pip install recon[learned]). Ctrl-C stops training and writes the best field so far
    (exit 130).""",
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


def _checked_points(points: Any, normals: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The cloud as float64 (n, 3) and its normals as unit vectors (or None), checked."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be (n, 3), got shape {pts.shape}")
    if len(pts) < 10:
        raise InputError(f"fit-sdf needs at least 10 points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise InputError("points have NaN or infinite coordinates")
    if normals is None:
        return pts, None
    nrm = np.asarray(normals, dtype=np.float64)
    if nrm.shape != pts.shape:
        raise InputError(f"normals must match the points' shape {pts.shape}, got {nrm.shape}")
    ln = np.linalg.norm(nrm, axis=1)
    if not (np.isfinite(ln).all() and (ln > 0).all()):
        raise InputError("normals have zero length or NaN")
    return pts, nrm / ln[:, None]


#: the stage's declared parameters that are :func:`fit_sdf`'s options (the others: the grid's
#: and the extra outputs')
FIT_PARAMS = (
    "iterations",
    "max_seconds",
    "width",
    "depth",
    "frequencies",
    "eikonal_weight",
    "batch",
    "field",
    "seed",
    "threads",
)
#: :func:`fit_sdf`'s options the stage does not declare, and their defaults
TUNING = {"normal_weight": 1.0, "distance_weight": None, "learning_rate": 2e-3}


def fit_sdf(
    points: np.ndarray, normals: np.ndarray | None = None, *, progress=None, **options: Any
) -> FitResult:
    """Fit a neural signed distance (or occupancy) field to a point cloud.

    Parameters
    ----------
    points : (n, 3) float
        The cloud, world units (n >= 10, finite).
    normals : (n, 3) float or None
        Unit outward normals; with them the loss has the normal term.
    progress : Progress or None
        A bar with the current (smoothed) loss.
    **options
        The fit's options (Other Parameters), by keyword: those the stage declares
        (:data:`FIT_PARAMS`) default to the declaration's values and are checked by it; the
        others (:data:`TUNING`) are the library's only.

    Other Parameters
    ----------------
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
        where ``recon info`` judges it); None: 3.0, ramped in from a tenth of it over the
        first quarter of the schedule. Without normals it is IGR's squared form
        E(||grad s|| - 1)^2 with IGR's 0.1: nothing but the zero level holds the slope, and
        3.0 slows the fit. The squared penalty barely pulls deviations under 0.1; the L1 one
        pulls every sample to 1 alike (figures in ``bench/calibration.md``).
    normal_weight : float
        Weight of E||grad s(p) - n_p|| (``sdf`` with normals only).
    distance_weight : float or None
        Weight of E|clamp(s(q)) - clamp(d(q))| on the wider, uniform and band samples q
        (``sdf`` with normals only): d(q) is the distance from q to its nearest point p
        (approximate: at most 10 % over), negative when q lies behind p's normal, left out
        where q is closer to p than p's 8th neighbour (the distance to the points is not the
        surface's there), off p's normal line by more than 60 degrees (beside an edge: the
        side is ambiguous) or farther from the points than the clamp; both clamped to twice
        the band's width (DeepSDF). It makes the field rise at the true slope inside thin walls
        and in enclosed air (a cup), where the eikonal term lets it sag and a larger
        eikonal weight fills the cavity instead. None: 1.0 with normals, 0 otherwise. With
        it on, each surface point of a step also gives a sample x = p + t n_p along its
        normal (t normal, 1.25 % of the cloud's longest side spread) whose value is held at
        sign(t) min(|t|, distance to the nearest point), weight 3, except where x lies behind
        that point's normal on the other side than t says (through a wall thinner than |t|):
        walls thinner than the band keep their inside.
    batch : int
        Surface points per step; as many near-surface samples, half as many wider ones
        (sigma 0.1 of the network box), half as many uniform in the box and, with normals,
        as many band samples (eikonal and distance terms only: offsets N(0, (u b)^2), u
        uniform in [0, 1], b 5 % of the diagonal).
    learning_rate : float
        Adam's initial step (cosine decay to 2 % of it).
    field : {"sdf", "occupancy"}
        ``occupancy`` needs normals (they label the training samples inside/outside).
    seed : int
        Seeds the initial weights and the sampling: same seed, same input, same threads:
        same field.
    threads : int or None
        CPU threads for torch (None: torch's default).

    Returns
    -------
    FitResult

    Raises
    ------
    InputError
        Too few points, NaN/inf coordinates, normals of the wrong shape.
    ParameterError
        A parameter out of range; ``occupancy`` without normals; ``distance_weight`` > 0
        without normals or with ``occupancy``.
    BackendError
        PyTorch is not installed (``pip install recon[learned]``).
    """
    unknown = sorted(set(options) - set(FIT_PARAMS) - set(TUNING))
    if unknown:
        raise TypeError(f"fit_sdf() got an unexpected keyword argument {unknown[0]!r}")
    v = SPEC.check({k: options.get(k, SPEC.param(k).default) for k in FIT_PARAMS}, complete=False)
    normal_weight, distance_weight, learning_rate = (
        options.get(k, default) for k, default in TUNING.items()
    )
    normal_weight = _float(normal_weight, "normal_weight", 0.0)
    if distance_weight is None:
        distance_weight = DISTANCE_WEIGHT if normals is not None and v["field"] == "sdf" else 0.0
    distance_weight = _float(distance_weight, "distance_weight", 0.0)
    learning_rate = _float(learning_rate, "learning_rate", 1e-8, 1.0)
    pts, nrm = _checked_points(points, normals)
    if v["frequencies"] is None:
        v["frequencies"] = 4 if nrm is not None else 2
    if v["eikonal_weight"] is None:
        v["eikonal_weight"] = 3.0 if nrm is not None else 0.1  # L1 with normals, squared without
    if v["field"] == "occupancy" and nrm is None:
        raise ParameterError(
            "field occupancy needs a cloud with normals (they tell inside from outside)"
        )
    if distance_weight > 0 and (nrm is None or v["field"] != "sdf"):
        raise ParameterError(
            "distance_weight needs field sdf and a cloud with normals (they sign the distance)"
        )
    threads = v.pop("threads")
    settings = Settings(
        normal_weight=normal_weight,
        distance_weight=distance_weight,
        learning_rate=learning_rate,
        **v,
    )
    return fit(pts, nrm, settings, threads, progress)


@SPEC.runner
def run_stage(
    data,
    *,
    resolution: int,
    padding: float,
    model: str | None,
    mesh: str | None,
    progress=None,
    **fit: Any,
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
    model : path or None
        Also write the fitted weights here (:func:`save_model`).
    mesh : path or None
        Also write the zero level set here (marching cubes on the grid, vertex normals
        from the network's gradient), as PLY.
    **fit
        The declared parameters of the fit (:data:`FIT_PARAMS`: iterations, max_seconds,
        width, depth, frequencies, eikonal_weight, batch, seed, field, threads), as in
        :func:`fit_sdf`.

    Returns
    -------
    StageResult
        A :class:`~recon_cli.grid.Grid` (``sdf``: signed distance, world units; ``occupancy``:
        ``0.5 - p(inside)``; both negative inside, the surface at 0). Report keys
        ``field``, ``points``, ``normals_used``, ``iterations``, ``train_seconds``,
        ``loss``, ``interrupted``, ``shape``, ``voxel_size``, ``eikonal``
        (:func:`recon_cli.stages.sdf.eikonal_check` on the written grid, as ``recon info``
        reports it), ``eikonal_near`` (its ``near`` part: the samples near the zero level
        but kinks, the figure the fit aims at), ``far_field`` (``sdf``: the samples beyond two
        cells of the zero level, given the exact distance to it, ``redistanced``, and whether
        exactly everywhere, ``exact``; None for ``occupancy``), and with ``mesh``:
        ``mesh_vertices``, ``mesh_faces``.
    """
    from recon_cli.geometry import PointCloud, TriangleMesh, float64
    from recon_cli.stages import StageResult

    if not isinstance(data, (PointCloud, TriangleMesh)):
        raise InputError(f"fit-sdf needs a point cloud (or mesh), got {type(data).__name__}")
    data = float64(data)  # parameters and the input's kind: checked by SPEC
    model_path = None if model in (None, "") else os.fspath(model)
    mesh_path = None if mesh in (None, "") else os.fspath(mesh)
    fitted = fit_sdf(data.points, data.normals, progress=progress, **fit)
    grid, far = _written_grid(fitted.model, data, resolution, padding, progress)
    values = np.asarray(grid.sdf)
    if not (np.nanmin(values) < 0.0 < np.nanmax(values)):
        # a field of one sign has no surface: the fit failed (thin parts beyond its capacity)
        raise StageFailed(
            f"fit-sdf: the fitted field is {'positive' if np.nanmin(values) >= 0 else 'negative'} "
            "everywhere on the grid (no surface); try more --iterations, --frequencies or --width"
        )
    report = _report(fitted, data, grid, model_path, mesh_path)
    report["far_field"] = far
    if model_path is not None:
        save_model(fitted.model, model_path)
    if mesh_path is not None:
        report.update(_write_mesh(fitted.model, grid, mesh_path))
    return StageResult(output=grid, report=report)


def _written_grid(model: SdfModel, data, resolution: int, padding: float, progress):
    """The field sampled on the stage's grid (the frame of ``recon sdf``), and its far field.

    ``sdf``: beyond two cells of the zero level the values are the exact signed distance to it
    (:func:`recon_cli.stages.sdf.redistance.redistance`; the surface stays the same to the
    bit); returns (the grid, the redistancing's figures, None for ``occupancy``).
    """
    from recon_cli.grid import Grid
    from recon_cli.progress import task
    from recon_cli.stages.sdf import grid_frame
    from recon_cli.stages.sdf.redistance import redistance

    pts = data.points
    origin, h, shape = grid_frame(pts.min(axis=0), pts.max(axis=0), resolution, None, padding)
    far = None
    with task(progress, "sampling the field", 2) as t:
        values = sample_grid(model, origin, h, shape)
        t.advance(1)
        if model.field == "sdf":
            values, far = redistance(values, origin, h)
        t.advance(1)
    grid = Grid(sdf=values, origin=origin, voxel_size=h, history=list(data.history))
    return grid, far


def _report(fitted: FitResult, data, grid, model_path, mesh_path) -> dict:
    """The stage's report (see :func:`run_stage`)."""
    from recon_cli.stages.sdf import eikonal_check

    pts = data.points
    eikonal = eikonal_check(grid) if fitted.model.field == "sdf" else None
    return {
        "field": fitted.model.field,
        "points": len(pts),
        "normals_used": data.normals is not None,
        "iterations": fitted.iterations,
        "train_seconds": fitted.seconds,
        "loss": fitted.loss,
        "interrupted": fitted.interrupted,
        "shape": list(grid.sdf.shape),
        "voxel_size": grid.voxel_size,
        "eikonal": eikonal,
        "eikonal_near": None if eikonal is None else eikonal["near"],
        "provenance": {
            "model": model_path,
            "mesh": mesh_path,
            "iterations_done": fitted.iterations,
            "eikonal_weight": fitted.eikonal_weight,
            "distance_weight": fitted.distance_weight,
            "frequencies": fitted.model.config["frequencies"],
        },
    }


def _write_mesh(model: SdfModel, grid, path: str) -> dict:
    """Write the zero level set with autodiff normals; its report keys."""
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.ply import write_ply

    v, f, n = extract_mesh(model, grid)
    mesh = TriangleMesh(
        vertices=v, faces=f, normals=n, history=list(grid.history), point_dtype=np.float32
    )
    write_ply(mesh, path)
    return {"mesh_vertices": len(v), "mesh_faces": len(f)}
