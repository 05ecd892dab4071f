"""Mesh tools: ``recon simplify`` and ``recon smooth`` against Open3D and PyMeshLab (issue 31).

**Ours runs as a process** (``recon simplify IN OUT``: start-up, PLY reading and writing
included, warm numba cache; memory is the process's peak RSS); the references run in-process
(forked child, peak RSS above the start), on the same mesh, about a local origin.

Simplification (ours; Open3D ``simplify_quadric_decimation``; PyMeshLab
``meshing_decimation_quadric_edge_collapse`` with ``preservetopology`` and ``preservenormal``,
the guarantees ours gives) to 10 % of the faces (an even count: a closed mesh has one):

- a 1.07M-face Poisson mesh made by ``recon poisson`` of 1M area-uniform samples of the
  armadillo at depth 9 (quick: 200k samples at depth 8); ours also with a cold numba cache
  (``NUMBA_CACHE_DIR`` empty: every kernel of the command compiled first, as after an
  upgrade without ``recon warmup``);
- the armadillo split twice (1-to-4 midpoint splits, 800k faces) with its vertices moved by
  0.2 % of the diagonal (``bench_diff``'s noisy mesh; quick: split once);
- the bunny scan (``bunny_zipper``: open, 5 holes) split twice: 1.11M faces of a real scan
  (quick: split once);
- the shared meshes (kitten, armadillo, bunny, mug).

Column ``CD``: exact point-to-triangle Chamfer (mean of both directions, 200k samples on each
mesh, :func:`recon_cli.mesh.distance.closest_points`) to the input, a fraction of its
bounding-box diagonal; ``H``: the largest sampled distance. ``topology``: closed, manifold,
genus of the output, by our topology report.

Smoothing (ours; Open3D ``filter_smooth_taubin``; PyMeshLab ``apply_coord_taubin_smoothing``),
10 iterations, lambda 0.5, mu -0.526: a unit sphere of 328k faces with radial noise of 0.5 %
(``err``: the radial RMS error left) and the 1M-face Poisson mesh; ``vol``: the volume's
relative change.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _util import measure

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
N_EVAL = 200_000

COLUMNS = [
    ("case", "case"),
    ("method", "method"),
    ("faces", "faces"),
    ("topology", "closed·manifold·genus"),
    ("seconds", "s"),
    ("mb", "MB"),
    ("cd", "CD / diag"),
    ("h", "H / diag"),
    ("err", "err"),
    ("vol", "vol"),
    ("time_ratio", "s ours/o3d"),
    ("mem_ratio", "MB ours/o3d"),
    ("quality_ratio", "CD, err or |vol| ours/o3d"),
    ("note", "note"),
]

# runs a command, prints its wall seconds and peak RSS (KiB), exits with its status
_LAUNCHER = """
import os, subprocess, sys, time
t0 = time.perf_counter()
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(p.pid, 0)
print(time.perf_counter() - t0, usage.ru_maxrss)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def _recon() -> str:
    return str(Path(sys.executable).with_name("recon"))


def _ours(args: list[str], src: Path, dst: Path, env: dict | None = None):
    """``recon ARGS SRC DST`` as a process: time, memory, the output.

    It runs through a launcher: a child forked from this big process would report this one's
    resident size as its peak.
    """
    from recon_cli.io import read_ply

    cmd = [_recon(), "-q", args[0], str(src), str(dst), *args[1:]]
    proc = subprocess.run(
        [sys.executable, "-c", _LAUNCHER, *cmd], capture_output=True, env=env or os.environ.copy()
    )
    if proc.returncode != 0:
        raise RuntimeError(f"recon {args[0]} failed: {proc.stderr.decode().strip()}")
    dt, kb = proc.stdout.decode().split()
    return {"seconds": float(dt), "peak_mb": int(kb) / 1024.0}, read_ply(dst)


def _reference(fn, *args):
    """A reference call in a forked child: time, memory and the mesh it returns."""
    from recon_cli.geometry import TriangleMesh

    def run():
        m = fn(*args)
        return np.asarray(m.vertices), np.asarray(m.faces)

    res = measure(run, repeat=1)
    if not isinstance(res["result"], tuple):
        raise RuntimeError(str(res["result"]))
    v, f = res["result"]
    return res, TriangleMesh(vertices=v, faces=f)


def _chamfer(a, b) -> tuple[float, float]:
    from recon_cli.geometry import bbox_diagonal
    from recon_cli.mesh.distance import closest_points
    from recon_cli.mesh.sampling import sample_surface

    diag = bbox_diagonal(a.vertices)
    pa = sample_surface(a, N_EVAL, seed=1).points
    pb = sample_surface(b, N_EVAL, seed=2).points
    d1 = closest_points(np.asarray(b.vertices, np.float64), b.faces, pa)[0]
    d2 = closest_points(np.asarray(a.vertices, np.float64), a.faces, pb)[0]
    return 0.5 * float(d1.mean() + d2.mean()) / diag, float(max(d1.max(), d2.max())) / diag


def _topology(mesh) -> str:
    from recon_cli.mesh.topology import report

    r = report(mesh)
    closed = "closed" if r["watertight"] else f"open ({r['boundary_loops']} loops)"
    manifold = "manifold" if r["edge_manifold"] and r["vertex_manifold"] else "NON-manifold"
    return f"{closed} · {manifold} · {r['genus']}"


def _ratios(rows: list[dict], key: str) -> None:
    """Ours / each reference, on our row (time, memory, quality ``key``)."""
    ours = rows[0]
    for ref in rows[1:]:
        if "seconds" not in ref or "seconds" not in ours:
            continue
        tag = ref["method"]
        parts = [
            f"s {ours['seconds'] / ref['seconds']:.2f}x",
            f"MB {ours['mb'] / ref['mb']:.2f}x" if ref["mb"] > 0 else "",
            f"{key} {abs(ours[key] / ref[key]):.3f}x" if ref.get(key) else "",
        ]
        ref["note"] = (
            ref.get("note", "") + f" ours/{tag}: " + ", ".join(p for p in parts if p)
        ).strip()
        if tag == "open3d":
            ours["time_ratio"] = ours["seconds"] / ref["seconds"]
            ours["mem_ratio"] = ours["mb"] / ref["mb"] if ref["mb"] > 0 else float("nan")
            ours["quality_ratio"] = abs(ours[key] / ref[key]) if ref.get(key) else float("nan")


def _simplify_run(name: str, mesh, target: int, src: Path, dst: Path):
    """One run of a simplification method: (time and memory, the mesh it made)."""
    from recon_cli.backends import open3d_backend, pymeshlab_backend

    args = ["simplify", "--faces", str(target)]
    if name == "recon (process)":
        return _ours(args, src, dst)
    if name == "recon (cold cache)":
        with tempfile.TemporaryDirectory() as cache:
            return _ours(args, src, dst, dict(os.environ, NUMBA_CACHE_DIR=cache))
    if name == "open3d":
        return _reference(open3d_backend.simplify_quadric, mesh, target)
    return _reference(pymeshlab_backend.simplify_quadric, mesh, target)


def _simplify_rows(case: str, mesh, work: Path, cold: bool = False, repeat: int = 1) -> list[dict]:
    """Ours (warm cache; also cold when ``cold``), Open3D and PyMeshLab to 10 % of the faces.

    Ours and Open3D run ``repeat`` times, alternating (the median time is kept: one run on a
    busy machine can wait minutes for a core).
    """
    from recon_cli.io import write_ply

    target = 2 * (len(mesh.faces) // 20)
    src, dst = work / "in.ply", work / "out.ply"
    write_ply(mesh, src)
    out = []
    methods = ("recon (process)", "open3d", "pymeshlab") + (("recon (cold cache)",) if cold else ())
    times: dict[str, list[float]] = {name: [] for name in methods}
    for r in range(repeat):
        for name in methods[:2] if r else methods:
            try:
                m, res = _simplify_run(name, mesh, target, src, dst)
            except Exception as exc:  # one failing method must not hide the others
                out.append({"case": case, "method": name, "note": f"FAILED: {exc}"})
                continue
            times[name].append(m["seconds"])
            if r:
                continue
            cd, h = _chamfer(mesh, res)
            out.append(
                {
                    "case": case,
                    "method": name,
                    "faces": len(res.faces),
                    "topology": _topology(res),
                    "seconds": m["seconds"],
                    "mb": m["peak_mb"],
                    "cd": cd,
                    "h": h,
                    "note": "",
                }
            )
    for row in out:
        if times.get(row["method"]):
            row["seconds"] = float(np.median(times[row["method"]]))
            if len(times[row["method"]]) > 1:
                row["note"] = "runs " + ", ".join(f"{t:.1f}" for t in times[row["method"]]) + " s"
    _ratios(out, "cd")
    if cold and "seconds" in out[-1] and "seconds" in out[1]:
        out[-1]["note"] = f"s cold/open3d {out[-1]['seconds'] / out[1]['seconds']:.2f}x"
    return out


def _split(mesh, levels: int):
    """``mesh`` with each triangle split 1-to-4 ``levels`` times (the same surface)."""
    from bench_diff import subdivide

    from recon_cli.geometry import TriangleMesh

    v, f = np.asarray(mesh.vertices, np.float64), mesh.faces
    for _ in range(levels):
        v, f = subdivide(v, f)
    return TriangleMesh(v, f)


def _noisy_sphere(subdivisions: int):
    sys.path.insert(0, str(ROOT / "tests"))
    from recon_cli.geometry import TriangleMesh

    from shapes import icosphere

    v, f = icosphere(subdivisions)
    rng = np.random.default_rng(0)
    v = v * (1.0 + rng.normal(scale=0.005, size=(len(v), 1)))
    return TriangleMesh(v, f)


def _volume(mesh) -> float:
    from recon_cli.mesh.topology import Connectivity

    return Connectivity(mesh.faces, len(mesh.vertices), mesh.vertices).signed_volume()


def _smooth_rows(case: str, mesh, work: Path, sphere: bool) -> list[dict]:
    from recon_cli.backends import open3d_backend, pymeshlab_backend
    from recon_cli.io import write_ply
    from recon_cli.stages.smooth import taubin_mu

    iters, lam = 10, 0.5
    mu = taubin_mu(lam, 0.1)
    src, dst = work / "in.ply", work / "out.ply"
    write_ply(mesh, src)
    v_in = _volume(mesh)
    out = []
    for name in ("recon (process)", "open3d", "pymeshlab"):
        try:
            if name == "recon (process)":
                m, res = _ours(["smooth", "--iterations", str(iters)], src, dst)
            elif name == "open3d":
                m, res = _reference(open3d_backend.smooth_taubin, mesh, iters, lam, mu)
            else:
                m, res = _reference(pymeshlab_backend.smooth_taubin, mesh, iters, lam, mu)
        except Exception as exc:
            out.append({"case": case, "method": name, "note": f"FAILED: {exc}"})
            continue
        row = {
            "case": case,
            "method": name,
            "faces": len(res.faces),
            "seconds": m["seconds"],
            "mb": m["peak_mb"],
            "vol": _volume(res) / v_in - 1.0,
            "note": "",
        }
        if sphere:
            r = np.linalg.norm(np.asarray(res.vertices, np.float64), axis=1)
            row["err"] = float(np.sqrt(np.mean((r - 1.0) ** 2)))
        out.append(row)
    _ratios(out, "err" if sphere else "vol")
    return out


def _poisson_mesh(n: int, depth: int, work: Path):
    """``recon poisson`` of ``n`` area-uniform samples of the armadillo (true normals)."""
    from recon_cli.io import read_ply, write_ply
    from recon_cli.mesh.sampling import sample_surface

    cloud = sample_surface(read_ply(SHARED / "armadillo.ply"), n, seed=0)
    src, dst = work / "cloud.ply", work / "poisson.ply"
    write_ply(cloud, src)
    subprocess.run(
        [_recon(), "-q", "poisson", str(src), str(dst), "--depth", str(depth)], check=True
    )
    return read_ply(dst)


def rows(quick: bool) -> list[dict]:
    """The section's rows: ``recon simplify`` and ``recon smooth`` as processes, against references.

    Open3D and PyMeshLab run in-process on the same meshes: a Poisson mesh of the armadillo and a
    split, noisy armadillo.
    """
    from recon_cli.io import read_ply

    # warm our numba cache the way a user's install does (no compile time in the rows)
    subprocess.run([_recon(), "-q", "warmup"], check=False, capture_output=True)
    out: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        n, depth = (200_000, 8) if quick else (1_000_000, 9)
        big = _poisson_mesh(n, depth, work)
        label = f"Poisson armadillo {len(big.faces) / 1e6:.2f}M faces"
        out += _simplify_rows(f"{label} -> 10 %", big, work, cold=True, repeat=3)
        levels = 1 if quick else 2
        arma = _split(read_ply(SHARED / "armadillo.ply"), levels)
        rng = np.random.default_rng(1)
        diag = np.linalg.norm(arma.vertices.max(0) - arma.vertices.min(0))
        arma.vertices = arma.vertices + rng.normal(scale=0.002 * diag, size=arma.vertices.shape)
        case = f"armadillo split ×{levels} + 0.2 % noise, {len(arma.faces) // 1000}k faces"
        out += _simplify_rows(f"{case} -> 10 %", arma, work, repeat=3)
        bunny = _split(read_ply(SHARED / "bunny_zipper.ply"), levels)
        case = f"bunny scan split ×{levels}, {len(bunny.faces) / 1e6:.2f}M faces"
        out += _simplify_rows(f"{case} -> 10 %", bunny, work, repeat=3)
        for name in ("kitten", "mug") if quick else ("kitten", "armadillo", "bunny_zipper", "mug"):
            mesh = read_ply(SHARED / f"{name}.ply")
            out += _simplify_rows(f"{name} {len(mesh.faces) // 1000}k faces -> 10 %", mesh, work)
        sphere = _noisy_sphere(6 if quick else 7)
        out += _smooth_rows(
            f"noisy sphere {len(sphere.faces) // 1000}k faces, 10 iterations", sphere, work, True
        )
        out += _smooth_rows(f"{label}, 10 iterations", big, work, False)
    return out


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    for r in rows("--quick" in sys.argv):
        print(r)
