"""Screened Poisson: ours (sparse multilevel grid, numba) vs Open3D and PyMeshLab.

Armadillo sampled with true normals (100k and 1M points), depth 8 and 9, and the mug (a thin
shell: sparse 100k samples over a large area, the hardest case for the finest level) at 100k,
depth 9; depth 10 on 1M points ours only. The raw single-view bunny scan (40k points, normals
by our normals stage) at depth 9 and 10, and 1,000 points of a sphere at depth 12 and 14 (ours
only: the adaptive tree stops where the samples stop, so depth beyond the data costs nothing). Big cases run once (repeat=1). Each run is a forked child, so the peak
memory is that run's own (including the imports of the reference library it calls).
"""

from __future__ import annotations

import sys
from pathlib import Path

from _util import measure, row

ROOT = Path(__file__).resolve().parents[1]


def _cloud(n: int, name: str = "armadillo"):
    from recon_cli.io import read_ply
    from recon_cli.mesh.sampling import sample_surface

    shared = ROOT.parent / "shared" / "data" / f"{name}.ply"
    return sample_surface(read_ply(shared), n, seed=0)


def _raw_scan():
    from recon_cli import normals
    from recon_cli.io import read_ply

    return normals.run_stage(read_ply(ROOT.parent / "shared" / "data" / "bunny_scan_000.ply")).output


def _sphere(n: int):
    import numpy as np

    p = np.random.default_rng(0).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _faces_closed(mesh) -> tuple:
    """(faces, closed and manifold, pieces) by our own topology report."""
    from recon_cli.mesh.topology import report

    rep = report(mesh)
    ok = rep["watertight"] and rep["edge_manifold"] and rep["vertex_manifold"]
    return len(mesh.faces), bool(ok), rep["components"]


def rows(quick: bool) -> list[dict]:
    from recon_cli.backends import open3d_backend, pymeshlab_backend
    from recon_cli.poisson import screened_poisson

    warm = _cloud(5000)
    screened_poisson(warm.points, warm.normals, depth=7)  # compile / load the numba cache (every kernel)
    cases = [("armadillo", 100_000, 8)] if quick else [
        ("armadillo", 100_000, 8), ("armadillo", 100_000, 9), ("mug", 100_000, 9),
        ("armadillo", 1_000_000, 8), ("armadillo", 1_000_000, 9),
    ]
    out = []
    for name, n, depth in cases:
        c = _cloud(n, name)
        repeat = 1 if (n >= 1_000_000 or depth >= 9) else (2 if quick else 3)
        ours = measure(lambda: screened_poisson(c.points, c.normals, depth=depth).report["faces"], repeat=repeat)
        o3d = measure(lambda: len(open3d_backend.poisson(c, depth=depth)[0].faces), repeat=repeat)
        pml = measure(lambda: len(pymeshlab_backend.poisson(c, depth=depth).faces), repeat=repeat)
        case = f"{name} {n // 1000}k depth {depth}"
        out.append(row("poisson", case, ours, "open3d", o3d, note=f"faces ours {ours['result']}, open3d {o3d['result']}"))
        out.append(row("poisson", case, ours, "pymeshlab", pml, note=f"pymeshlab faces {pml['result']}"))
    scan = _raw_scan()
    for depth in (9, 10):
        ours = measure(lambda: _faces_closed(screened_poisson(scan.points, scan.normals, depth=depth).mesh), repeat=1)
        o3d = measure(lambda: _faces_closed(open3d_backend.poisson(scan, depth=depth)[0]), repeat=1)
        out.append(row("poisson", f"bunny scan raw depth {depth}", ours, "open3d", o3d,
                       note=f"faces, closed manifold pieces: ours {ours['result']}, open3d {o3d['result']}"))
    sph = _sphere(1000)
    for depth in (12, 14):
        ours = measure(lambda: len(screened_poisson(sph, sph, depth=depth).mesh.faces), repeat=1)
        out.append(row("poisson", f"sphere 1k points depth {depth}", ours, note=f"ours only; faces {ours['result']}"))
    if not quick:
        c = _cloud(1_000_000)
        ours = measure(lambda: screened_poisson(c.points, c.normals, depth=10).report["faces"], repeat=1)
        out.append(row("poisson", "armadillo 1000k depth 10", ours, note=f"ours only; faces {ours['result']}"))
    return out


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    for r in rows("--quick" in sys.argv):
        print(r)
