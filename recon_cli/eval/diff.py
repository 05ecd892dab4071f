"""``recon diff`` on files: candidate files against a reference file.

It writes the heatmaps and the picture.

The metrics come from :mod:`recon_cli.eval.metrics`, the picture from :mod:`recon_cli.eval.figure`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from recon_cli.errors import ParameterError, naming
from recon_cli.eval.metrics import (
    check_samples,
    check_vmax,
    compare_meshes,
    heatmap,
    load_geometry,
    shared_vmax,
    vertex_distances,
)
from recon_cli.geometry import PointCloud, TriangleMesh


def diff_files(
    candidates: Sequence[str | os.PathLike],
    reference: str | os.PathLike,
    samples: int = 200_000,
    seed: int = 0,
    taus: Sequence[float | str] | str | None = None,
    heatmap_path: str | os.PathLike | None = None,
    png_path: str | os.PathLike | None = None,
    views: Sequence[str] | None = None,
    vmax: float | None = None,
    unit: str | None = None,
) -> list[dict[str, Any]]:
    """:func:`~recon_cli.eval.metrics.compare_meshes` of each candidate file against the reference.

    The heatmaps and the picture are written too when their paths are given.

    Parameters
    ----------
    candidates : sequence of paths
        Meshes or clouds (PLY).
    reference : path
        The ground truth (PLY mesh, or a cloud: then point-to-point).
    samples, seed, taus
        As in :func:`compare_meshes`.
    heatmap_path : path, optional
        Write the candidate with per-vertex ``distance`` (to the reference) and colours;
        with several candidates, ``<stem>_<candidate stem>.ply`` beside it.
    png_path : path, optional
        Write a picture (:func:`recon_cli.eval.figure.sheet`): per candidate its shape
        (boundary and non-manifold edges marked), its accuracy heatmap (its vertices
        coloured by distance to the reference) and its completeness heatmap (the
        reference's vertices coloured by distance to it: red where it misses a part), then
        the reference; one colour scale for all.
    views : sequence of str, optional
        Views of the picture (:func:`recon_cli.eval.render.resolve_views`; default the
        four-azimuth turntable).
    vmax : float, optional
        Top of the colour scale of the heatmaps (PLY and PNG); default
        :func:`~recon_cli.eval.metrics.shared_vmax`.
    unit : str, optional
        Unit of the coordinates, written on the picture's colour bar.

    Returns
    -------
    list of dict
        One row per candidate: ``candidate``, ``reference`` (paths) and the keys of
        :func:`compare_meshes`, plus ``heatmap`` (path or None).
    """
    if not candidates:
        raise ParameterError("no candidate file to compare")
    samples = check_samples(samples)
    if png_path is not None:
        from recon_cli.eval.figure import require_pillow
        from recon_cli.eval.render import resolve_views

        resolve_views(views)  # unknown view names fail before any work
        require_pillow()
    if vmax is not None:
        vmax = check_vmax(vmax)
    ref = load_geometry(reference, "reference")
    cands = [load_geometry(c, "candidate") for c in candidates]
    rows: list[dict[str, Any]] = []
    for path, cand in zip(candidates, cands, strict=True):
        row: dict[str, Any] = {"candidate": os.fspath(path), "reference": os.fspath(reference)}
        with naming(f"{os.fspath(path)} vs {os.fspath(reference)}"):
            row.update(compare_meshes(cand, ref, samples=samples, seed=seed, taus=taus))
        row["heatmap"] = None
        rows.append(row)
    if heatmap_path is None and png_path is None:
        return rows
    from recon_cli.io.load import save

    dists, missed, vmax = heatmap_distances(cands, ref, min(rows[0]["tau"]), vmax)
    if heatmap_path is not None:
        for k, (path, cand, d) in enumerate(zip(candidates, cands, dists, strict=True)):
            out = heatmap_path if len(cands) == 1 else _suffixed(heatmap_path, _stem(path), k)
            save(heatmap(cand, d, vmax=vmax), out)  # in the format its suffix names
            rows[k]["heatmap"] = os.fspath(out)
    if png_path is not None:
        from recon_cli.eval.figure import diff_rows, sheet
        from recon_cli.eval.render import write_png

        panels = [
            (_stem(p), c, d, m) for p, c, d, m in zip(candidates, cands, dists, missed, strict=True)
        ]
        fig = sheet(
            diff_rows(panels, (_stem(reference), ref)),
            views,
            vmax=vmax,
            unit=unit,
            diagonal=rows[0]["reference_diagonal"],
            title=f"recon diff against {os.path.basename(os.fspath(reference))}",
        )
        write_png(fig.image, png_path)
    return rows


def heatmap_distances(
    candidates: Sequence[TriangleMesh | PointCloud],
    reference: TriangleMesh | PointCloud,
    tau: float,
    vmax: float | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """The distances ``recon diff``'s heatmaps show, and the top of their shared colour scale.

    Parameters
    ----------
    candidates : sequence of TriangleMesh or PointCloud
    reference : TriangleMesh or PointCloud
    tau : float
        The smallest F-score threshold (absolute): the scale reaches at least it.
    vmax : float, optional
        The top of the scale, when given (else :func:`~recon_cli.eval.metrics.shared_vmax`).

    Returns
    -------
    accuracy : list of (n_candidate_vertices,) float64
        Each candidate's vertices' distances to the reference.
    completeness : list of (n_reference_vertices,) float64
        The reference's vertices' distances to each candidate (large where it misses a part).
    vmax : float
        One scale for both directions, so a heatmap is coloured alike wherever it is shown.
    """
    dists = [vertex_distances(c, reference) for c in candidates]
    missed = [vertex_distances(reference, c) for c in candidates]
    if vmax is None:
        vmax = shared_vmax(dists + missed, tau)
    return dists, missed, float(vmax)


def _stem(path: str | os.PathLike) -> str:
    return os.path.splitext(os.path.basename(os.fspath(path)))[0] or os.fspath(path)


def _suffixed(path: str | os.PathLike, stem: str, k: int) -> str:
    root, ext = os.path.splitext(os.fspath(path))
    return f"{root}_{k}_{stem}{ext or '.ply'}"
