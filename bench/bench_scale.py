"""Poisson at scale on one machine (issue 44): out of core in one process, against PoissonRecon.

The cloud: area-weighted samples of the shared armadillo with their true normals and 0.25 % of
the diagonal of noise (``python bench/bench_scale.py --make N PATH`` writes one), a binary PLY
of doubles. Rows, each command run once as a process through a launcher whose
``RUSAGE_CHILDREN`` is the command's own peak resident memory (the whole process, input
reading included):

- ``recon poisson --memory M`` in one process: the slab engine in this process when the cloud
  needs more than ``M`` in one piece (the report's slab count and spilled bytes in the note);
- ``recon poisson --workers 2`` (a local Dask cluster; the largest process's peak);
- PoissonRecon 18.75 ``--degree 2`` (all threads) on the same points and normals, when built
  (``$POISSONRECON_BIN``, as ``bench_poisson`` finds it);
- the same cloud in 1, 2, 4 and 8 slabs in one process: the largest Hausdorff distance between
  two of the meshes in finest cells, their face counts' spread, every mesh's topology.

Chamfer distances to the armadillo are exact point-to-triangle distances of 200k samples each
way; ratios are ours / PoissonRecon's.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _util import row

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
NOISE = 0.0025

_LAUNCH = (
    "import resource, subprocess, sys, time\n"
    "t = time.perf_counter()\n"
    "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
    "sys.stderr.write(r.stderr)\n"
    "print(r.stdout.rstrip())\n"
    "print('wall', time.perf_counter() - t)\n"
    "print('maxrss', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
    "sys.exit(r.returncode)\n"
)


def make_cloud(n: int, path: str) -> None:
    """Write ``n`` noisy samples of the shared armadillo with their normals to ``path``."""
    from recon_cli.io.load import save
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.sampling import sample_surface

    cloud = sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0, noise=NOISE)
    save(cloud, path)


def _run(cmd: list[str]) -> tuple[str, float, float]:
    """A command as a process: its stdout, wall seconds and peak RSS in MB."""
    proc = subprocess.run(
        [sys.executable, "-c", _LAUNCH, *cmd], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{Path(cmd[0]).name} failed: {proc.stderr.strip()[-300:]}")
    text, _, tail = proc.stdout.rpartition("\nwall ")
    wall, _, maxrss = tail.partition("\nmaxrss ")
    return text, float(wall), float(maxrss) / 1024.0


def _recon(src: str, out: str, depth: int, *extra: str) -> tuple[dict, float, float]:
    cmd = [sys.executable, "-m", "recon_cli.cli.main", "poisson", src, out]
    text, wall, peak = _run([*cmd, "--depth", str(depth), "--json", "-q", *extra])
    return json.loads(text), wall, peak


def _area_samples(vertices, faces, n: int, seed: int) -> np.ndarray:
    """``n`` area-weighted random points of a mesh, its areas taken 10M faces at a time."""
    area = np.empty(len(faces))
    for i in range(0, len(faces), 10_000_000):
        f = faces[i : i + 10_000_000]
        p0 = vertices[f[:, 0]]
        e = np.cross(vertices[f[:, 1]] - p0, vertices[f[:, 2]] - p0)
        area[i : i + len(f)] = 0.5 * np.linalg.norm(e, axis=1)
    cum = np.cumsum(area)
    rng = np.random.default_rng(seed)
    f = faces[np.searchsorted(cum, rng.random(n) * cum[-1])]
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    p0 = vertices[f[:, 0]]
    return p0 + u[:, None] * (vertices[f[:, 1]] - p0) + v[:, None] * (vertices[f[:, 2]] - p0)


def _chamfer(mesh, truth) -> float:
    """Mean distance both ways between 200k area samples of each and the other surface.

    Exact point-to-triangle distances; from the truth's samples to ``mesh`` only the faces
    around each sample's 16 nearest vertices are candidates, so a 140M-face mesh fits in memory
    (the whole mesh's search structure did not: killed at 23 GiB).
    """
    from scipy.spatial import cKDTree

    from recon_cli.mesh.distance import closest_points

    verts, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    a = _area_samples(verts, faces, 200_000, 1)
    b = _area_samples(np.asarray(truth.vertices, np.float64), np.asarray(truth.faces), 200_000, 2)
    d1 = closest_points(truth.vertices, truth.faces, a)[0]
    near = np.zeros(len(verts), bool)
    near[cKDTree(verts).query(b, k=16)[1].ravel()] = True
    d2 = closest_points(verts, faces[near[faces].any(axis=1)], b)[0]
    return float(d1.mean() + d2.mean())


def _topology(mesh) -> str:
    from recon_cli.mesh.topology import report

    r = report(mesh)
    dup = len(mesh.vertices) - len(np.unique(mesh.vertices, axis=0))
    closed = r["watertight"] and r["edge_manifold"] and r["vertex_manifold"]
    shape = "closed manifold" if closed else "NOT closed manifold"
    return f"{shape}, {r['components']} piece(s), {dup} dup. vertices"


def _poissonrecon(src_ply: str, out: str, depth: int) -> tuple[float, float] | None:
    """PoissonRecon ``--degree 2`` on the cloud (float32 about its centre): wall s, peak MB."""
    exe = os.environ.get("POISSONRECON_BIN")
    if not exe or not Path(exe).exists():
        return None
    _, wall, peak = _run(
        [exe, "--in", src_ply, "--out", out, "--depth", str(depth), "--degree", "2"]
    )
    return wall, peak


def _float32_copy(src: str, dst: str) -> np.ndarray:
    """The cloud as PoissonRecon reads it (float32 about its centre); returns the centre."""
    from recon_cli.io.load import load

    c = load(src)
    pts = np.asarray(c.points, np.float64)
    centre = 0.5 * (pts.min(0) + pts.max(0))
    names = ("x", "y", "z", "nx", "ny", "nz")
    rows_ = np.zeros(len(pts), dtype=[(k, "<f4") for k in names])
    for a in range(3):
        rows_[names[a]] = pts[:, a] - centre[a]
        rows_[names[a + 3]] = c.normals[:, a]
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
    header += "".join(f"property float {k}\n" for k in names) + "end_header\n"
    Path(dst).write_bytes(header.encode() + rows_.tobytes())
    return centre


def _scale_rows(folder: str, n: int, depth: int, memory: str) -> list[dict]:
    from recon_cli.io.load import load
    from recon_cli.io.ply import read_ply

    truth = read_ply(SHARED / "armadillo.ply")
    src = os.path.join(folder, f"armadillo_{n}.ply")
    make_cloud(n, src)
    label = f"armadillo {n // 1000}k noisy, d{depth}"
    pr_in = os.path.join(folder, "pr_in.ply")
    centre = _float32_copy(src, pr_in)
    pr_out = os.path.join(folder, "pr_out.ply")
    pr = _poissonrecon(pr_in, pr_out, depth)
    ref = None
    ref_cd = float("nan")
    if pr is not None:
        mesh = read_ply(pr_out)
        mesh.vertices = np.asarray(mesh.vertices, np.float64) + centre
        ref = {"seconds": pr[0], "peak_mb": pr[1]}
        ref_cd = _chamfer(mesh, truth)
        del mesh
    out = []
    for how, extra in (
        (f"one process, --memory {memory}", ("--memory", memory)),
        ("--workers 2", ("--workers", "2")),
    ):
        dst = os.path.join(folder, "ours.ply")
        rep, wall, peak = _recon(src, dst, depth, *extra)
        mesh = load(dst)
        cd = _chamfer(mesh, truth)
        dist = rep.get("distributed", {})
        spilled = sum(p.get("bytes_moved", 0) for p in dist.get("phases", {}).values())
        note = (
            f"Chamfer {cd:.5g}" + (f" ({cd / ref_cd:.3f}x PoissonRecon's)" if ref else "")
            + f"; {_topology(mesh)}; slabs {dist.get('partitions', {}).get('count', 1)}"
            + f" ({dist.get('partitions', {}).get('why', 'one piece')}); moved/spilled "
            f"{spilled / 1e9:.1f} GB"
        )  # fmt: skip
        out.append(
            row(
                "scale",
                f"{label}, {how}",
                {"seconds": wall, "peak_mb": peak},
                "PoissonRecon 18.75 --degree 2" if ref else "",
                ref,
                note,
            )
        )
        del mesh
    return out


def _seam_row(folder: str, n: int, depth: int) -> dict:
    """The same cloud in 1, 2, 4 and 8 slabs in one process: the meshes agree."""
    from recon_cli.io.load import load
    from recon_cli.mesh.distance import closest_points

    src = os.path.join(folder, f"armadillo_{n}.ply")
    if not os.path.exists(src):
        make_cloud(n, src)
    meshes, cell, t0 = {}, None, time.perf_counter()
    tops = []
    for k in (1, 2, 4, 8):
        dst = os.path.join(folder, f"slabs{k}.ply")
        rep, _, _ = _recon(src, dst, depth, "--partitions", str(k))
        cell = rep.get("finest_cell", cell)
        meshes[k] = load(dst)
        tops.append(f"{k}: {_topology(meshes[k])}")
    worst = 0.0
    for a in meshes:
        for b in meshes:
            if a < b:
                ma, mb = meshes[a], meshes[b]
                d = max(
                    closest_points(mb.vertices, mb.faces, ma.vertices)[0].max(),
                    closest_points(ma.vertices, ma.faces, mb.vertices)[0].max(),
                )
                worst = max(worst, float(d))
    faces = [len(m.faces) for m in meshes.values()]
    spread = (max(faces) - min(faces)) / min(faces)
    hd = f"{worst / cell:.3f} finest cell" if cell else f"{worst:.3g}"
    note = f"Hausdorff between any two {hd}; faces within {spread:.3%}; " + "; ".join(tops)
    return row(
        "scale",
        f"armadillo {n // 1000}k noisy, d{depth}, 1/2/4/8 slabs",
        {"seconds": time.perf_counter() - t0, "peak_mb": float("nan")},
        "",
        None,
        note,
    )


def rows(quick: bool) -> list[dict]:
    """The section's rows: Poisson out of core and on 2 workers against PoissonRecon, as processes.

    4M points at depth 11 and 20M at 12 with 6 GiB (quick: 1M at 10 with 1 GB), then a seam row.
    """
    cases = (
        [(1_000_000, 10, "1GB")] if quick else [(4_000_000, 11, "6GiB"), (20_000_000, 12, "6GiB")]
    )
    out = []
    with tempfile.TemporaryDirectory(dir=os.environ.get("RECON_BENCH_TMP")) as d:
        for n, depth, memory in cases:
            out += _scale_rows(d, n, depth, memory)
        n, depth = (1_000_000, 10) if quick else (4_000_000, 11)
        out.append(_seam_row(d, n, depth))
    return out


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--make":
        make_cloud(int(sys.argv[2]), sys.argv[3])
    else:
        sys.exit(
            "usage: python bench/bench_scale.py --make N PATH (or run it through run_bench.py)"
        )
