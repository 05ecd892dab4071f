"""The reconstruction's steps in one process: cube, samples, tree, solve, surface, clean-up.

:func:`reconstruct` runs them in order for :func:`recon_cli.stages.poisson.screened_poisson`
(which has checked its inputs); the names follow the method's steps (module docstring of
:mod:`recon_cli.stages.poisson`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import TriangleMesh
from recon_cli.progress import task
from recon_cli.stages.poisson import (
    MAX_DEPTH,
    PoissonOptions,
    PoissonResult,
    fold_cells,
    speck_cells,
)

log = logging.getLogger("recon")


def reconstruct(
    pts: np.ndarray,
    nrm: np.ndarray,
    weight: np.ndarray | None,
    keep: np.ndarray,
    colors: np.ndarray | None,
    props: dict[str, np.ndarray],
    envelope: Any,
    opts: PoissonOptions,
    progress: Any = None,
) -> PoissonResult:
    """Screened Poisson of checked samples: the steps in order.

    Parameters
    ----------
    pts, nrm : (n, 3) float
        The kept points (world units) and their unit normals.
    weight : (n,) float or None
        Per-point confidence weights (mean 1), or None.
    keep : (N,) bool
        Which input points were kept (for the report's ignored count).
    colors : (n, k) array or None
    props : dict of str to (n,) array
        The kept points' colours and properties, carried onto the vertices.
    envelope : .envelope.Envelope or None
    opts : PoissonOptions
    progress : Progress or None
    """
    from recon_cli.stages.poisson.basis import basis_for
    from recon_cli.stages.poisson.timing import Timings

    basis, clock = basis_for(opts.degree), Timings()
    unit_nrm = nrm if (props or colors is not None) else None
    need_density = opts.density or (not isinstance(opts.trim, str) and opts.trim > 0)
    setup = prepare(pts, nrm, weight, envelope, basis, clock, progress, opts, density=need_density)
    del nrm  # memory: the normals are in the samples now
    sol, mesh, dropped, pulled, field_grid = solve_and_extract(
        setup, basis, opts, pts, clock, progress
    )
    vdens = None
    if need_density:
        from recon_cli.stages.poisson.splat import sample_density

        vdens = sample_density(setup.splats, (mesh.vertices - setup.origin) / setup.size)
    mesh, vdens, trimmed_faces, trimmed_area = trimmed(
        mesh, vdens, opts.trim, setup.smp, setup.splats, setup.origin, setup.size
    )
    fallback = 0
    if props or colors is not None:  # from the points on each vertex's side
        with clock.phase("attributes"):
            fallback = carry_attributes(mesh, pts, unit_nrm, props, colors, setup.finest_cell)
    if opts.density:
        assert vdens is not None  # made above whenever density is asked for
        mesh.attributes["density"] = vdens
    rep = report(
        mesh,
        sol,
        clock.total(),
        setup,
        opts.depth,
        ignored=int((~keep).sum()),
        removed=(*dropped, trimmed_faces, trimmed_area),
        fallback=fallback,
        attributes=sorted(props) + (["colors"] if colors is not None else []),
        pulled=pulled,
    )
    if field_grid is not None:
        rep["grid_shape"] = list(field_grid.shape)
    return PoissonResult(mesh, rep, field_grid)


def solve_and_extract(
    setup: Setup, basis: Any, opts: PoissonOptions, pts: np.ndarray, clock: Any, progress: Any
) -> tuple[Any, TriangleMesh, tuple, int, Any]:
    """The cascadic solve, the iso-surface and (``--grid``) the field on a grid.

    Returns the solution, the mesh (clipped to the cube, noise pieces dropped, pulled into the
    envelope), the counts of pieces dropped, the vertices pulled and the grid (or None).
    """
    with clock.phase("solve"):
        sol = basis.solve(
            setup.levels,
            setup.smp,
            setup.splats,
            opts.boundary,
            setup.full_depth,
            opts.cg_tolerance,
            progress,
            setup.sample_ok,
            setup.clip,
        )
    setup.levels = []
    with clock.phase("extract"):
        verts, faces, chi_fn, dropped, pulled = extract_surface(
            basis, sol, setup.origin, setup.size, setup.tree_depth, opts.with_grid,
            setup.domain, pts, setup.env, setup.noise,
        )  # fmt: skip
    field_grid = None
    if opts.with_grid and len(faces):
        with clock.phase("grid"):
            res = 1 << setup.tree_depth
            field_grid = field_grid_of(
                chi_fn, sol.iso, verts, setup.origin, setup.size, res, setup.domain, progress
            )
    return sol, TriangleMesh(vertices=verts, faces=faces), dropped, pulled, field_grid


def extract_surface(basis, sol, origin, size, tree_depth, with_grid, domain, pts, env, noise):
    """The iso-surface of a solve in the input's frame.

    Returns ``(verts, faces, chi_fn, (bubbles, islands, folds), pulled)``: clipped to the cube
    (free boundary), the closed pieces that are noise dropped, pulled into the envelope.
    """
    from recon_cli.stages.poisson.free import clip_to_cube

    verts, faces, chi_fn = basis.extract(sol, origin, size, tree_depth, with_grid)
    if domain is not None:
        verts, faces = clip_to_cube(verts, faces, *domain)
    verts, faces, *dropped = drop_bubbles(verts, faces, size / (1 << tree_depth), pts, noise)
    pulled = 0
    if env is not None:
        verts, pulled = env.pull_inside(verts, size / (1 << tree_depth))
    return verts, faces, chi_fn, tuple(dropped), pulled


@dataclass
class Setup:
    """What :func:`screened_poisson` solves: made by :func:`prepare`.

    The solve's cube (``origin``, ``size``: the unit cube's frame; ``depth`` the finest level
    allowed, deeper than asked when the cube grew for an envelope), the tree's depth and its
    complete levels, the free boundary's domain, the merged samples and their splats, the
    samples' median noise, the envelope's state, and the tree's levels (emptied after the solve).
    """

    origin: np.ndarray
    size: float
    depth: int
    tree_depth: int
    full_depth: int
    domain: tuple | None
    smp: Any
    splats: Any
    levels: list
    noise: float | None
    env: Any = None
    sample_ok: Any = None
    clip: Any = None
    outside_points: int = 0

    @property
    def finest_cell(self) -> float:
        """The side of the tree's finest cells (world units)."""
        return self.size / (1 << self.tree_depth)


def prepare(
    pts: np.ndarray,
    nrm: np.ndarray,
    weight: np.ndarray | None,
    envelope: Any,
    basis: Any,
    clock: Any,
    progress: Any,
    opts: PoissonOptions,
    *,
    density: bool,
) -> Setup:
    """The unit cube, the samples, their splats and noise, the envelope and the tree.

    Points are merged per finest cell, as PoissonRecon does; the tree goes as deep as the splats,
    no deeper. Of ``opts``, the depth, scale, boundary, full depth, samples per node and point
    weight; ``density``: the splats keep what the vertices' density needs.
    """
    from recon_cli.stages.poisson.splat import make_splats, merge_samples

    with clock.phase("samples"):
        origin, size, depth, domain = solve_cube(pts, opts.scale, opts.boundary, opts.depth)
        if envelope is not None and domain is None:
            origin, size, depth = envelope_cube(envelope, origin, size, depth)
        full_depth = min(opts.full_depth, depth)
        smp = merge_samples((pts - origin) / size, nrm, depth, weight)
    with clock.phase("density"):  # kernel density -> area per point and splat level
        splats = make_splats(
            smp, depth, opts.samples_per_node, opts.point_weight, density, merge=basis.merge_splats
        )
        tree_depth = basis.tree_depth(splats.tree_depth, domain is not None)
        full_depth = min(full_depth, tree_depth)
    with clock.phase("noise"):  # noisy neighbourhoods are screened less (Splats.screening)
        noise = screening_noise(pts, origin, size, smp, splats, tree_depth, opts.point_weight)
    setup = Setup(origin, size, depth, tree_depth, full_depth, domain, smp, splats, [], noise)
    item_pos, item_level = splats.pos, splats.level
    if envelope is not None:  # chi clipped by it after the solve; the tree refined along it
        with clock.phase("envelope"):
            env, setup.sample_ok, setup.clip, setup.outside_points, item_pos, item_level = (
                envelope_setup(envelope, pts, smp, splats, origin, size, tree_depth, full_depth)
            )
            setup.env = env
    with clock.phase("tree"):
        assert item_pos is not None and item_level is not None  # the items, before the solve
        with task(progress, "poisson: tree"):
            setup.levels = basis.build_tree(
                item_pos, item_level, tree_depth, full_depth, opts.boundary
            )
        # memory: the splat items made the fields and the tree, the samples' normals and keys
        # the splats
        del item_pos, item_level
        splats.pos = splats.vec = splats.level = smp.normal = smp.keys = None
    log.info(
        "poisson: %d points, %d samples, depth %d (tree %d), nodes per level %s",
        len(pts),
        len(smp.count),
        depth,
        tree_depth,
        [len(lv.node_keys) for lv in setup.levels],
    )
    return setup


def report(
    mesh: TriangleMesh,
    sol: Any,
    timings: dict,
    setup: Setup,
    depth: int,
    *,
    ignored: int,
    removed: tuple,
    fallback: int,
    attributes: list[str],
    pulled: int,
) -> dict[str, Any]:
    """The report of :func:`screened_poisson` (its keys are listed in its Returns section).

    ``setup`` gives the tree's depth (counted from the asked ``depth``), the samples, the finest
    cell, the noise and the points outside the envelope; ``removed`` is (bubbles, islands, folds,
    trimmed faces, trimmed area); ``pulled`` the vertices pulled inside the envelope.
    """
    bubbles, islands, folds, trimmed, trimmed_area = removed
    tree_depth = setup.tree_depth - (setup.depth - depth)
    envelope = (setup.outside_points, pulled) if setup.env is not None else None
    return {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "depth": depth,
        "tree_depth": tree_depth,
        "iso_value": sol.iso,
        "solver_iterations": int(sol.iterations),
        "residual": float(sol.residual),
        "bubbles_removed": bubbles,
        "islands_removed": islands,
        "folds_removed": folds,
        "trimmed_faces": int(trimmed),
        "trimmed_area": trimmed_area,
        "noise": setup.noise,
        "attributes": attributes,
        "attribute_fallback_vertices": fallback,
        "envelope_outside_points": None if envelope is None else envelope[0],
        "envelope_pulled_vertices": None if envelope is None else envelope[1],
        "samples": int(len(setup.smp.count)),
        "ignored_points": ignored,
        "finest_cell": setup.finest_cell,
        "levels": sol.per_level,
        "timings": timings,
    }


def screening_noise(
    pts: np.ndarray,
    origin: np.ndarray,
    size: float,
    smp: Any,
    splats: Any,
    tree_depth: int,
    point_weight: float,
) -> float | None:
    """The samples' median noise, their clean fractions set on ``splats`` (None unscreened).

    Noisy neighbourhoods are screened less (:meth:`.splat.Splats.screening`).
    """
    from recon_cli.stages.poisson.splat import noise_fraction

    if point_weight <= 0:
        return None
    splats.clean, sample_noise = noise_fraction((pts - origin) / size, smp, tree_depth)
    return float(np.median(sample_noise))


def solve_cube(
    pts: np.ndarray, scale: float, boundary: str, depth: int
) -> tuple[np.ndarray, float, int, tuple[np.ndarray, float] | None]:
    """The solve's cube around ``pts`` (n, 3): (origin, side, depth, the free boundary's domain).

    With the free boundary the points' cube is the middle half of the solve's, one level
    deeper; the domain is then the points' cube (origin, side), else None.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    size = float((hi - lo).max()) * scale
    origin = 0.5 * (lo + hi) - 0.5 * size
    if boundary != "free":
        return origin, size, depth, None
    return origin - 0.5 * size, 2.0 * size, depth + 1, (origin.copy(), size)


def field_grid_of(
    chi_fn: Any,
    iso: float,
    verts: np.ndarray,
    origin: np.ndarray,
    size: float,
    res: int,
    domain: tuple[np.ndarray, float] | None,
    progress: Any,
) -> Any:
    """The solved field on the finest lattice around the surface (``--grid``, :mod:`.field`)."""
    from recon_cli.stages.poisson.field import indicator_grid
    from recon_cli.stages.poisson.free import FREE_DOMAIN

    assert chi_fn is not None  # made with_grid
    with task(progress, "poisson: grid"):
        return indicator_grid(
            chi_fn, iso, verts, origin, size, res, FREE_DOMAIN if domain else (0.0, 1.0)
        )


def carry_attributes(
    mesh: TriangleMesh,
    pts: np.ndarray,
    unit_nrm: np.ndarray | None,
    props: dict[str, np.ndarray],
    colors: np.ndarray | None,
    cell: float,
) -> int:
    """Put the points' properties and colours on ``mesh``'s vertices (:mod:`.attributes`).

    Returns the count of vertices that fell back to the nearest point (no point on their side).
    """
    from recon_cli.stages.poisson.attributes import transfer

    assert unit_nrm is not None  # kept when there are properties to carry
    moved = transfer(pts, unit_nrm, props, colors, mesh.vertices, mesh.faces, cell)
    mesh.attributes.update(moved.values)
    mesh.colors = moved.colors
    return int(moved.fallback)


def envelope_cube(
    envelope: Any, origin: np.ndarray, size: float, depth: int
) -> tuple[np.ndarray, float, int]:
    """The solve's cube grown to hold the checked envelope, the finest lattice kept."""
    from recon_cli.stages.poisson.envelope import covering_cube

    v = envelope.vertices[np.unique(envelope.faces)]
    return covering_cube(v, origin, size, depth, MAX_DEPTH + 2)


def envelope_setup(
    envelope: Any,
    pts: np.ndarray,
    smp: Any,
    splats: Any,
    origin: np.ndarray,
    size: float,
    tree_depth: int,
    full_depth: int,
) -> tuple[Any, np.ndarray, Any, int, np.ndarray, np.ndarray]:
    """The envelope's part of the set-up, the tree refined along its surface.

    Returns the envelope, the samples inside it, the field's clip (``clip(iso)``), the count of
    points outside it, and the tree's items (positions, levels).
    """
    import functools

    from recon_cli.stages.poisson.envelope import (
        Carving,
        FieldClip,
        carve_level,
        refine_level,
    )

    env = envelope  # checked by _checked_envelope
    outside_points = int(np.count_nonzero(~env.inside(pts)))
    sample_ok = env.inside(origin + size * smp.pos)
    if not sample_ok.any():
        raise InputError("every point lies outside the envelope")
    carving = Carving(smp.pos[sample_ok], smp.normal[sample_ok], carve_level(tree_depth))
    clip = functools.partial(FieldClip, env, carving, origin, size, size / (1 << tree_depth))
    lv = refine_level(tree_depth, full_depth)
    # the tree refined along the envelope and along the carving's sheet
    extra = np.concatenate([env.surface_items(origin, size, lv), carving.boundary_items()])
    item_pos = np.concatenate([splats.pos, extra])
    item_level = np.concatenate([splats.level, np.full(len(extra), lv, np.int64)])
    return env, sample_ok, clip, outside_points, item_pos, item_level


def trimmed(
    mesh: TriangleMesh,
    vdens: np.ndarray | None,
    trim: float | str,
    smp: Any,
    splats: Any,
    origin: np.ndarray,
    size: float,
) -> tuple[TriangleMesh, np.ndarray | None, int, float]:
    """``mesh`` trimmed as ``trim`` asks: (mesh, vertex densities, faces cut, area removed).

    ``"auto"`` cuts by :func:`.trim.support_ratio` from the samples, a value ``T > 0`` at ``T``
    times the median density at the samples (``vdens`` (n,) the vertices' densities then).
    """
    from recon_cli.stages.poisson.splat import sample_density
    from recon_cli.stages.poisson.trim import trim_auto, trim_by_density

    if not len(mesh.faces) or trim == 0:
        return mesh, vdens, 0, 0.0
    if trim == "auto":
        cut = trim_auto(mesh, smp.pos * size + origin, carry=vdens)
        if len(cut.mesh.faces) == 0:
            raise InputError("trim auto removes the whole surface: no part lies near the samples")
        return cut.mesh, cut.carried, len(mesh.faces) - cut.untouched_faces, cut.removed_area
    assert vdens is not None  # made whenever trim > 0
    at_samples = sample_density(splats, smp.pos)
    cut = trim_by_density(mesh, vdens, float(trim) * float(np.median(at_samples)))
    if len(cut.mesh.faces) == 0:
        raise ParameterError(f"trim {trim:g} removes the whole surface: use a smaller value")
    return cut.mesh, cut.density, len(mesh.faces) - cut.untouched_faces, cut.removed_area


def drop_bubbles(
    verts: np.ndarray, faces: np.ndarray, cell: float, points: np.ndarray, noise: float | None
) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """Drop the closed pieces that are noise, never the largest.

    Returns the vertices and faces left and how many specks, islands and folds went.

    - **Specks:** pieces smaller than :func:`speck_cells` finest cells on every side.
      Noisy, sparse samples leave chi slightly across the iso-value around single lattice
      points off the surface: closed specks of 8-16 triangles, one or two cells across (on
      the shared stereo fragment at depth 9: 53 of them, 0.8-1.2 cells, beside one surface
      of 128 cells). A piece that small cannot stand for a real feature at this depth (the
      lattice samples chi once per cell). Where the samples' median ``noise`` (finest cells)
      is larger, a depth finer than the noise leaves blobs inside the band the samples
      scatter over, up to several times the noise across; a piece under
      :data:`SPECK_SIGMAS` times the noise fits in that band and is taken for one.
    - **Islands:** larger pieces with fewer than :data:`ISLAND_POINTS` of the input
      ``points`` within :data:`BUBBLE_CELLS` cells of their bounding box. A few outliers
      away from the surface splat a dipole that Poisson closes into a blob (on the stereo
      fragment: 82 triangles, 3.6 cells across, around 5 stray points); a real part,
      however small, carries the samples it was made from.
    - **Folds:** pieces under :data:`FOLD_SPAN_SIGMAS` times the noise across whose every
      vertex lies within :data:`FOLD_SIGMAS` times the noise of the vertices of the pieces
      that stay whatever (the largest and those longer than that: :func:`fold_cells`). Such a
      piece lies wholly inside the band that piece's own samples scatter over: the data
      cannot tell it from a fold of that band. A real part farther out, or longer (the inner
      wall of a thin shell), stays.

    Every piece of the extraction is closed, so what is left is too. ``verts``, ``points``
    and ``cell`` are in the same units (the report counts ``bubbles_removed``,
    ``islands_removed`` and ``folds_removed``).
    """
    if not len(faces):
        return verts, faces, 0, 0, 0
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.stages.poisson.octree import points_in_boxes
    from recon_cli.stages.poisson.pieces import (
        noise_pieces,
        piece_boxes,
        piece_reach,
        reach_vertices,
    )

    lab = Connectivity(faces, len(verts)).face_components
    n = int(lab.max()) + 1
    if n == 1:
        return verts, faces, 0, 0, 0
    # boxes of the pieces but the largest (piece 0, which always stays): few faces
    rest = lab != 0
    _, lo, hi = piece_boxes(verts, faces[rest], lab[rest], n)

    def farthest(which, anchor, a, b):
        m = reach_vertices(verts, faces, lab, which, anchor, a, b)
        return piece_reach(m["points"], m["ids"], len(a), m["targets"])

    speck, island, fold = noise_pieces(
        lo,
        hi,
        0,
        cell,
        speck_cells(noise),
        fold_cells(noise),
        lambda a, b: points_in_boxes(points, a, b),
        farthest,
    )
    gone = speck | island | fold
    if not gone.any():
        return verts, faces, 0, 0, 0
    faces = faces[~gone[lab]]
    used = np.zeros(len(verts), bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    counts = int(speck.sum()), int(island.sum()), int(fold.sum())
    return verts[used], remap[faces].astype(faces.dtype), *counts
