"""Repair of a ~1M-face mesh with injected defects: ours vs the equivalent PyMeshLab filter chain.

The input tiles 20 copies of the armadillo (50k faces each, 20 components) and injects
every defect the repair stage handles: removed patches (holes), 5 % flipped faces,
duplicated faces, fins glued onto edges (non-manifold edges) and 1 % of the faces with
their own vertex copies (duplicate vertices, pinched vertices). PyMeshLab runs
remove duplicate vertices / null faces / duplicate faces / unreferenced vertices, repair
non-manifold edges (remove faces) and vertices (split), re-orient coherently
(:func:`recon_cli.backends.pymeshlab_backend.repair`). Its time includes building the
MeshSet and reading the result back, as calling it from recon does.

Both sides are warmed up in the parent first (each repairs a small mesh), so every
measured child pays for the repair of the big mesh only, not for loading a library:
PyMeshLab's import and plugin loading (about 45 MB) or numba's first kernel call (its
compiler and type system, about 85 MB, which reading the input already triggers here).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from _util import measure, row

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def damaged_mesh(copies: int):
    """The armadillo tiled ``copies`` times and damaged by every kind of :mod:`mesh_damage`.

    Patches removed, faces flipped and duplicated, fins glued, vertices split; seeded.
    """
    import mesh_damage as D
    from shared_data import load_shared

    m = D.tile(load_shared("armadillo"), copies)
    rng = np.random.default_rng(0)
    m = D.remove_patches(m, rng, k=2 * copies, min_sep=0.01)
    m = D.flip_faces(m, rng, 0.05)
    m = D.duplicate_faces(m, rng, 100 * copies)
    m = D.glue_fins(m, rng, 25 * copies)
    return D.split_vertices(m, rng, 0.01)


def rows(quick: bool) -> list[dict]:
    """The section's row: our repair against PyMeshLab's on a damaged tiled armadillo, in-process.

    Each in a forked child; the note gives the faces out and whether ours is manifold and oriented.
    """
    from recon_cli.backends import pymeshlab_backend
    from recon_cli.mesh.topology import report
    from recon_cli.stages.repair import repair

    copies = 4 if quick else 20
    rep = 1 if quick else 3
    mesh = damaged_mesh(copies)
    # one-time library loading happens here, outside the measured children (see the docstring)
    tiny = damaged_mesh(1)
    repair(tiny)
    pymeshlab_backend.repair(tiny)
    report(tiny)
    pymeshlab_backend.topological_measures(tiny)

    def ours():
        out, r = repair(mesh)
        return len(out.faces)

    def theirs():
        return len(pymeshlab_backend.repair(mesh).faces)

    a = measure(ours, rep)
    b = measure(theirs, rep)
    ok = report(repair(mesh)[0])
    note = (
        f"faces out {a['result']} vs {b['result']}; ours "
        f"manifold={ok['edge_manifold'] and ok['vertex_manifold']}"
        f" oriented={ok['consistently_oriented']}; target ≤ 1×"
    )
    label = (
        f"repair {len(mesh.faces) / 1e6:.2f}M faces (holes, flips, duplicates, fins, split "
        "vertices)"
    )
    out = [row("repair", label, a, "pymeshlab clean/repair/re-orient chain", b, note)]

    def ours_report():
        return report(mesh)["non_manifold_edges"]

    def theirs_report():
        return pymeshlab_backend.topological_measures(mesh)["non_two_manifold_edges"]

    c = measure(ours_report, rep)
    d = measure(theirs_report, rep)
    out.append(
        row(
            "repair",
            f"topology report {len(mesh.faces) / 1e6:.2f}M faces",
            c,
            "pymeshlab get_topological_measures",
            d,
        )
    )
    return out
