"""The closing sheet on bunny_scan_000 in a sphere envelope: ours against PoissonRecon.

``recon poisson --envelope`` (as a process) against PoissonRecon 18.75 ``--envelope`` (the
binary built in ``/work/ref``), the same oriented points (normals by ``recon normals``),
spheres 1.03x and 1.2x the scan's radius about its box's centre, depths 7 and 8. Sheet
vertices: farther than 4 finest cells from the points; their distance to the sphere in finest
cells (the points' cube 1.1x / 2^depth, the same for both), the share within 4 cells, the
vertices outside, whether the mesh is watertight. Figures in ``bench/calibration.md``.

Usage: ``python bench/envelope_sheet.py [DEPTH ...]`` (from the repository's root).
"""

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, "tests")
from scipy.spatial import cKDTree  # noqa: E402  (after the tests' folder is on the path)

from recon_cli.geometry import PointCloud, TriangleMesh  # noqa: E402
from recon_cli.io import read_ply, write_ply  # noqa: E402
from recon_cli.mesh.topology import report  # noqa: E402
from recon_cli.stages.normals import run_stage as normals  # noqa: E402
from recon_cli.stages.poisson.envelope import Envelope  # noqa: E402

from shapes import icosphere  # noqa: E402
from shared_data import load_shared  # noqa: E402

PR = "/work/ref/PoissonRecon/Bin/Linux/PoissonRecon"
RECON = os.path.join(os.path.dirname(sys.executable), "recon")


def main() -> None:
    """Measure and print one line per depth, sphere and program."""
    scan = load_shared("bunny_scan_000")
    c = normals(PointCloud(points=scan.points)).output
    p = c.points
    tmp = tempfile.mkdtemp()
    write_ply(PointCloud(points=p, normals=c.normals), f"{tmp}/in.ply")

    def sheet(mv, cell, centre, R):
        dpts = cKDTree(p).query(mv)[0]
        sh = dpts > 4 * cell
        ds = np.abs(R - np.linalg.norm(mv[sh] - centre, axis=1)) / cell
        return sh.sum(), np.median(ds), np.quantile(ds, 0.9), (ds < 4).mean()

    depths = [int(a) for a in sys.argv[1:]] or [7, 8]
    for depth in depths:
        cell = (p.max(0) - p.min(0)).max() * 1.1 / (1 << depth)
        for fac in (1.03, 1.2):
            centre = 0.5 * (p.min(0) + p.max(0))
            R = fac * np.linalg.norm(p - centre, axis=1).max()
            v, f = icosphere(4, R, centre)
            write_ply(TriangleMesh(vertices=v, faces=f), f"{tmp}/env.ply")
            for who in ("recon", "PoissonRecon"):
                t = time.time()
                if who == "recon":
                    cmd = [
                        RECON,
                        "poisson",
                        f"{tmp}/in.ply",
                        f"{tmp}/out.ply",
                        "--depth",
                        str(depth),
                        "--envelope",
                        f"{tmp}/env.ply",
                    ]
                else:
                    cmd = [
                        PR,
                        "--in",
                        f"{tmp}/in.ply",
                        "--out",
                        f"{tmp}/out.ply",
                        "--depth",
                        str(depth),
                        "--envelope",
                        f"{tmp}/env.ply",
                    ]
                subprocess.run(cmd, check=True, capture_output=True)
                dt = time.time() - t
                m = read_ply(f"{tmp}/out.ply")
                n, med, p90, frac = sheet(m.vertices, cell, centre, R)
                out = int((~Envelope(TriangleMesh(vertices=v, faces=f)).inside(m.vertices)).sum())
                t2 = report(m)
                print(
                    f"depth {depth} sphere {fac}x {who:12s} verts {len(m.vertices)} sheet {n} "
                    f"to envelope: median {med:.2f} p90 {p90:.2f} cells, within 4 {frac:.3f}; "
                    f"outside {out}; watertight {t2['watertight']} components {t2['components']}; "
                    f"{dt:.1f} s wall (load {os.getloadavg()[0]:.1f})",
                    flush=True,
                )


if __name__ == "__main__":
    main()
