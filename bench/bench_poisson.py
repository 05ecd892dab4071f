"""Screened Poisson: ours (sparse multilevel grid, numba) vs Open3D and PyMeshLab.

Armadillo sampled with true normals (100k and 1M points), depth 8 and 9, and the mug (a thin
shell: sparse 100k samples over a large area, the hardest case for the finest level) at 100k,
depth 9; depth 10 on 1M points ours only. Big cases run once (repeat=1). Each run is a forked child, so the peak
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
    if not quick:
        c = _cloud(1_000_000)
        ours = measure(lambda: screened_poisson(c.points, c.normals, depth=10).report["faces"], repeat=1)
        out.append(row("poisson", "armadillo 1000k depth 10", ours, note=f"ours only; faces {ours['result']}"))
    return out


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    for r in rows("--quick" in sys.argv):
        print(r)
