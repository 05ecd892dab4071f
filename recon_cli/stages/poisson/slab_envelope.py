"""``--envelope`` in slabs: the single process's envelope (:mod:`.envelope`), step by step.

What one process does with the envelope, each slab does for its own part, and the coordinator
puts together what is global:

- **The cube** grows to hold the envelope before the slabs are planned (:func:`grown_cube`,
  as :func:`.steps.envelope_cube`: the finest lattice kept); the slabs work in the job's turned
  axes, so they get the envelope turned (:meth:`.envelope.Envelope.turned`).
- **Samples and carving** (:func:`envelope_samples`): each slab says which of its samples lie
  inside (they alone screen and make the iso-value), counts its own points outside, and gives
  the carving's masks (:func:`.envelope.carving_masks`) of its own samples inside: the cells
  their rays cross and those they hold. Both masks are ORs over the samples, so the
  coordinator ORs the slabs' into the whole cloud's and makes the one
  :class:`.envelope.Carving` (:func:`envelope_round`).
- **The tree** is refined along the envelope and the carving's sheet: the coordinator makes
  those items once, and each slab takes the ones in its usable range (:func:`take_tree_items`)
  for its tree, its own ones for the coarse tree (:func:`.slab.items`).
- **The clip**: chi read after the solve (the nodes' values, the vertices' roots, so the grid)
  is clipped as one process clips it (:func:`field_clip`, the envelope and the carving given to
  the field and extraction steps), and the vertices the extraction puts outside are pulled
  inside after the noise pieces are dropped (:func:`pull_vertices`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.errors import InputError
from recon_cli.slabs.runners import timed
from recon_cli.stages.poisson.slab import Job, Slab


@dataclass
class EnvelopeRun:
    """The envelope's global state in a run in slabs (the coordinator's).

    ``env`` the envelope in the job's axes, ``carving`` the whole cloud's
    :class:`.envelope.Carving`, ``outside_points`` the input points outside the envelope.
    """

    env: Any
    carving: Any
    outside_points: int


def grown_cube(
    envelope: Any, origin: np.ndarray, size: float, depth: int, perm: tuple, params: dict
) -> tuple[np.ndarray, float, int, Any]:
    """The solve's cube (input axes) grown to hold ``envelope``, as one process grows it.

    Not with the free boundary (whose cube is the points' one doubled, as one process does).
    ``params["grown"]`` gets the levels added (the report's depths are the asked ones).
    Returns (origin, size, depth, the envelope turned to the job's axes ``perm``).
    """
    from recon_cli.stages.poisson.steps import envelope_cube

    deeper = depth
    if params["boundary"] != "free":
        origin, size, deeper = envelope_cube(envelope, origin, size, depth)
    params["grown"] = deeper - depth
    return origin, size, deeper, envelope.turned(perm)


@timed
def envelope_samples(slab: Slab, env: Any, level: int) -> dict:
    """Which of the slab's samples lie inside ``env`` (job axes), and its part of the carving.

    Sets ``slab.sample_ok`` (s,) for its samples, own and pad's. Returns its own points outside
    (``outside``), its own samples inside (``inside``), and :func:`.envelope.carving_masks` of
    its own samples inside at ``level`` (``free``, ``held``: bit-packed).
    """
    from recon_cli.stages.poisson.envelope import carving_masks

    job = slab.job
    pos = slab.smp.pos
    slab.sample_ok = env.inside(np.asarray(job.origin) + job.size * pos)
    own_pts = slab.pts if slab.own_pt is None else slab.pts[slab.own_pt]
    mine = slab.own_s & slab.sample_ok
    free, held = carving_masks(pos[mine], slab.smp.normal[mine], level)
    return {
        "outside": int(np.count_nonzero(~env.inside(own_pts))) if len(own_pts) else 0,
        "inside": int(np.count_nonzero(mine)),
        "free": np.packbits(free),
        "held": np.packbits(held),
    }


@timed
def take_tree_items(slab: Slab, pos: np.ndarray, level: np.ndarray) -> dict:
    """Keep the items (unit cube (m, 3), levels (m,)) the slab's tree is refined along."""
    slab.tree_items = (pos, level)
    return {"items": len(pos)}


def envelope_round(runner: Any, job: Job, env: Any, tree_depth: int, usable: list) -> EnvelopeRun:
    """The slabs' samples against the envelope, the carving, the tree's items along both.

    ``env`` in the job's axes; ``usable`` each slab's usable x range (unit cube): the items it
    takes. After the slabs' splat depths and noise, before their items (:func:`.slab.items`).

    Raises
    ------
    InputError
        Every point lies outside the envelope.
    """
    from recon_cli.stages.poisson.envelope import Carving, carve_level, refine_level

    level = carve_level(tree_depth)
    msgs = runner.run("envelope", envelope_samples, lambda k: (env, level))
    if not sum(m["inside"] for m in msgs):
        raise InputError("every point lies outside the envelope")
    cells = 1 << (3 * level)
    free = np.zeros(cells, bool)
    held = np.zeros(cells, bool)
    for m in msgs:
        free |= np.unpackbits(m.pop("free"), count=cells).astype(bool)
        held |= np.unpackbits(m.pop("held"), count=cells).astype(bool)
    carving = Carving.of_masks(free, held, level)
    del free, held
    lv = refine_level(tree_depth, job.full_depth)
    extra = np.concatenate(
        [env.surface_items(np.asarray(job.origin), job.size, lv), carving.boundary_items()]
    )
    extra = extra[np.argsort(extra[:, 0], kind="stable")]
    xs = extra[:, 0]

    def part(k: int) -> tuple:
        a, b = np.searchsorted(xs, usable[k][0]), np.searchsorted(xs, usable[k][1])
        return extra[a:b], np.full(b - a, lv, np.int64)

    runner.run("envelope", take_tree_items, part)
    return EnvelopeRun(env, carving, sum(m["outside"] for m in msgs))


def field_clip(slab: Slab, run: EnvelopeRun, iso: float) -> Any:
    """Chi's clip by the envelope for the slab's field (:class:`.envelope.FieldClip`)."""
    from recon_cli.stages.poisson.envelope import FieldClip

    job = slab.job
    cell = job.size / (1 << slab.tree_depth)
    return FieldClip(run.env, run.carving, np.asarray(job.origin), job.size, cell, iso)


def pull_vertices(slab: Slab, env: Any, keep: np.ndarray) -> int:
    """Move the slab's vertices outside ``env`` inside it (:meth:`.envelope.Envelope.pull_inside`).

    As one process does once the noise pieces are dropped: ``keep`` (f,) the faces kept. Returns
    how many of the kept vertices the slab writes (not its right seam's) moved.
    """
    v = slab.verts
    if not len(v):
        return 0
    moved_v, _ = env.pull_inside(v, slab.job.size / (1 << slab.tree_depth))
    moved = np.any(moved_v != v, axis=1)
    used = np.zeros(len(v), bool)
    used[slab.faces[keep].reshape(-1)] = True
    used[len(v) - slab.seam["right"] :] = False  # the next slab's vertices
    slab.verts = moved_v
    return int(np.count_nonzero(moved & used))
