"""Screened Poisson: ours against Open3D and PyMeshLab, row by row (issue 16).

For every input each method gives a row: faces, whether the untrimmed output is closed and
manifold and in how many pieces (our own topology report), wall seconds, peak memory, and
an accuracy figure; ours also gives the ratios ours/Open3D. **Ours runs as a process**
(``recon poisson IN OUT``, warm numba cache: what a user waits for, reading and writing
included; memory is the process's peak RSS, Python and numba included); the references run
in-process (forked child, peak RSS above the start, their import included), on the same
oriented points.

Inputs:

- the shared raw scans: ``bunny_scan_000.ply`` (40k points of one view) and
  ``stereo_fragment.ply`` (3.7k noisy stereo points), normals by our ``normals`` stage, depth 9
  and 10, untrimmed; the bunny also at depth 8 and 9 trimmed (ours ``--trim 0.2``, Open3D's vertex
  densities cut at the 5 % quantile, its documented recipe);
- smooth closed shapes, 100k samples: the kitten and the armadillo (true normals, clean and
  with noise of 0.25 % of the diagonal, depth 8 and 9), an analytic torus (clean and noisy),
  the mug (a thin shell) and the noisy kitten with normals estimated by our ``normals``;
- real-like depth-camera clouds (issue 29): 640 x 480 depth images of a tabletop (251k valid
  points) and (not ``--quick``) an office (270k) ray-cast by ``tests/sensors.py`` (Kinect-like
  noise, flying pixels), normals by our ``normals`` stage towards the camera, depth 9,
  untrimmed (time); the tabletop also trimmed: ours ``--trim auto``, Open3D's 5 % quantile
  and, where ``$POISSONRECON_BIN`` (or the reference build) holds ``PoissonRecon`` and
  ``SurfaceTrimmer``, those (``--trim 7``) as processes, with the issue's figures in the note:
  input points within 0.5 % of the diagonal of the mesh, mesh area farther than 1 % from every
  point, pieces, and the mean distance of the mesh to the true scene;
- 1M samples of the armadillo at depth 9 and 10 (time and memory), and (not ``--quick``)
  5M samples at depth 11, ours only (target: within 12 GiB).

Accuracy (column ``CD``, a fraction of the bounding-box diagonal of the truth), all by exact
point-to-triangle distances (:func:`recon_cli.mesh.distance.closest_points`; nearest
neighbours between two sets of 100k samples put a floor of ~1.3e-3 of the diagonal under
every figure, the sample spacing, and hid differences of 1e-4 between the methods): for
closed shapes the Chamfer-L1 (mean of the mean distance of 100k samples of the output to the
truth and of 100k samples of the truth to the output; the torus's truth is its analytic
distance) with the F-score at 0.5 %; for the trimmed bunny the one-sided accuracy (output
samples to the full bunny mesh, ``bunny_zipper.ply``: the scan sees one side only); for
untrimmed scans the fit (input points to the output), no F-score.
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
TAU = 0.005  # F-score threshold, fraction of the diagonal
N_EVAL = 100_000
NOISE = 0.0025

COLUMNS = [
    ("case", "case"),
    ("method", "method"),
    ("faces", "faces"),
    ("topology", "closed·manifold·pieces"),
    ("seconds", "s"),
    ("mb", "MB"),
    ("cd", "CD / diag"),
    ("f", "F@0.5 %"),
    ("faces_ratio", "faces ours/o3d"),
    ("time_ratio", "s ours/o3d"),
    ("mem_ratio", "MB ours/o3d"),
    ("cd_ratio", "CD ours/o3d"),
    ("note", "note"),
]


# ---------------------------------------------------------------------------------------------
# inputs


def _mesh(name: str):
    from recon_cli.io import read_ply

    return read_ply(SHARED / f"{name}.ply")


def _samples(name: str, n: int, noise: float = 0.0):
    from recon_cli.mesh.sampling import sample_surface

    return sample_surface(_mesh(name), n, seed=0, noise=noise)


def _with_our_normals(cloud):
    from recon_cli.stages import normals

    return normals.run_stage(cloud).output


def _torus(n: int, noise: float):
    from recon_cli.geometry import PointCloud

    sys.path.insert(0, str(ROOT / "tests"))
    from shapes import torus_cloud

    p, nrm = torus_cloud(n, seed=0)
    if noise:
        diag = float(np.linalg.norm(p.max(0) - p.min(0)))
        p = p + np.random.default_rng(5).normal(scale=noise * diag, size=p.shape)
    return PointCloud(points=p, normals=nrm, point_dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# accuracy


def _surface_samples(mesh, n: int, seed: int) -> np.ndarray:
    from recon_cli.mesh.sampling import sample_surface

    return sample_surface(mesh, n, seed=seed).points


def _torus_truth():
    sys.path.insert(0, str(ROOT / "tests"))
    from shapes import torus_cloud, torus_distance

    return torus_cloud(N_EVAL, seed=1)[0], lambda q: np.abs(torus_distance(q))


def _to_mesh(mesh, q: np.ndarray) -> np.ndarray:
    """Exact distance of the points ``q`` to the triangles of ``mesh``."""
    from recon_cli.mesh.distance import closest_points

    return closest_points(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), q)[0]


def _accuracy(mesh, truth, kind: str, cloud_points: np.ndarray) -> tuple[float, float]:
    """(CD / diagonal, F@0.5 %) of ``mesh`` against ``truth`` (see the module docstring)."""
    if len(mesh.faces) == 0:
        return float("nan"), float("nan")
    if kind == "fit":  # input points to the output surface
        diag = float(np.linalg.norm(cloud_points.max(0) - cloud_points.min(0)))
        return float(_to_mesh(mesh, cloud_points).mean()) / diag, float("nan")
    out = _surface_samples(mesh, N_EVAL, seed=2)
    if kind == "torus":
        pts, dist = truth
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
        d_out = dist(out)
    else:
        pts = _surface_samples(truth, N_EVAL, seed=1)
        diag = float(np.linalg.norm(truth.vertices.max(0) - truth.vertices.min(0)))
        d_out = _to_mesh(truth, out)
        if kind == "accuracy":  # a partial scan: only how far the output is from the truth
            return float(d_out.mean()) / diag, float("nan")
    d_in = _to_mesh(mesh, pts)
    tau = TAU * diag
    p, r = float((d_out < tau).mean()), float((d_in < tau).mean())
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return 0.5 * float(d_out.mean() + d_in.mean()) / diag, f


def _topology(mesh) -> str:
    from recon_cli.mesh.topology import report

    if len(mesh.faces) == 0:
        return "empty"
    rep = report(mesh)
    closed = "closed" if rep["watertight"] else f"open ({rep['boundary_edges']} boundary edges)"
    manifold = (
        "manifold"
        if rep["edge_manifold"] and rep["vertex_manifold"]
        else (f"NON-manifold ({rep['non_manifold_edges']} e, {rep['non_manifold_vertices']} v)")
    )
    return f"{closed} · {manifold} · {rep['components']}"


# ---------------------------------------------------------------------------------------------
# the three methods


NO_PYMESHLAB = False  # --no-pymeshlab (command line): ours and Open3D only
OUR_TRIM = 0.2  # --trim of the trimmed rows (a fraction of the median density at the samples)
REF_TRIM = 0.05  # Open3D's vertex-density quantile in the same rows


def _ours_process(cloud, depth: int, trimmed, workdir: Path) -> tuple[dict, object]:
    """``recon poisson`` as a process: wall seconds and peak RSS (MB) of the process, the mesh.

    ``trimmed``: False, True for ``--trim OUR_TRIM``, or the ``--trim`` value itself.
    """
    from recon_cli.io import read_ply, write_ply

    src, dst = workdir / "in.ply", workdir / "out.ply"
    write_ply(cloud, src)
    recon = Path(sys.executable).with_name("recon")
    cmd = [str(recon), "-q", "poisson", str(src), str(dst), "--depth", str(depth)]
    if trimmed:
        cmd += ["--trim", str(OUR_TRIM if trimmed is True else trimmed)]
    # through a small launcher: a child forked from this (large) process reports this
    # process's resident size as its own peak (ru_maxrss counts the pages it had before exec)
    proc = subprocess.run([sys.executable, "-c", LAUNCHER, *cmd], capture_output=True)
    if proc.returncode != 0:
        raise RuntimeError(
            f"recon poisson failed ({proc.returncode}): {proc.stderr.decode().strip()}"
        )
    dt, maxrss_kb = proc.stdout.decode().split()
    return {"seconds": float(dt), "peak_mb": int(maxrss_kb) / 1024.0}, read_ply(dst)


# runs a command, prints its wall seconds and peak RSS (KiB), exits with its status
LAUNCHER = """
import os, subprocess, sys, time
t0 = time.perf_counter()
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(p.pid, 0)
print(time.perf_counter() - t0, usage.ru_maxrss)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def _trim_quantile(mesh, dens: np.ndarray, q: float):
    """Drop the vertices below the ``q`` density quantile (Open3D's documented trim)."""
    from recon_cli.geometry import TriangleMesh

    keep = dens > np.quantile(dens, q)
    faces = mesh.faces[keep[mesh.faces].all(axis=1)]
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    return TriangleMesh(vertices=mesh.vertices[used], faces=remap[faces])


def open3d_poisson(cloud, depth: int, trimmed: bool):
    """Open3D's screened Poisson of ``cloud`` on all cores, trimmed when asked.

    Trimmed: the vertices below the ``REF_TRIM`` quantile of its density removed.
    """
    from recon_cli.backends import open3d_backend

    mesh, dens = open3d_backend.poisson(cloud, depth=depth, threads=-1)  # its default: all cores
    return _trim_quantile(mesh, dens, REF_TRIM) if trimmed else mesh


def _pymeshlab(cloud, depth: int, trimmed: bool):
    """PyMeshLab's screened Poisson; trimmed rows are not measured.

    Its density is not exposed here.
    """
    from recon_cli.backends import pymeshlab_backend

    return pymeshlab_backend.poisson(cloud, depth=depth)


def reference(fn, cloud, depth: int, trimmed: bool) -> tuple[dict, object]:
    """A reference in a forked child: time, memory, and the mesh (vertices and faces) sent back."""
    from recon_cli.geometry import TriangleMesh

    def run():
        m = fn(cloud, depth, trimmed)
        return (np.asarray(m.vertices), np.asarray(m.faces))

    m = measure(run, repeat=1)
    if not isinstance(m["result"], tuple):
        raise RuntimeError(str(m["result"]))
    v, f = m["result"]
    return m, TriangleMesh(vertices=v, faces=f)


def _rows_for(
    case: str,
    cloud,
    depth: int,
    truth,
    kind: str,
    workdir: Path,
    trimmed: bool = False,
    pymeshlab: bool = True,
) -> list[dict]:
    out = []
    results = {}
    pymeshlab = pymeshlab and not trimmed and not NO_PYMESHLAB
    runners = [("recon (process)", None), ("open3d", open3d_poisson)] + (
        [("pymeshlab", _pymeshlab)] if pymeshlab else []
    )
    for name, fn in runners:
        try:
            m, mesh = (
                _ours_process(cloud, depth, trimmed, workdir)
                if fn is None
                else reference(fn, cloud, depth, trimmed)
            )
        except Exception as exc:  # one failing method must not hide the others
            out.append({"case": case, "method": name, "note": f"FAILED: {exc}"})
            continue
        cd, f = _accuracy(mesh, truth, kind, cloud.points)
        r = {
            "case": case,
            "method": name,
            "faces": len(mesh.faces),
            "topology": _topology(mesh),
            "seconds": m["seconds"],
            "mb": m["peak_mb"],
            "cd": cd,
            "f": f,
            "note": "",
        }
        results[name] = r
        out.append(r)
    ours, ref = results.get("recon (process)"), results.get("open3d")
    if ours and ref:
        for key, ratio in (
            ("faces", "faces_ratio"),
            ("seconds", "time_ratio"),
            ("mb", "mem_ratio"),
            ("cd", "cd_ratio"),
        ):
            ours[ratio] = ours[key] / ref[key] if ref[key] else float("nan")
        if kind not in ("fit", "accuracy"):
            ours["note"] = f"dF {ours['f'] - ref['f']:+.4f}"
    return out


# ---------------------------------------------------------------------------------------------
# real-like depth-camera clouds (issue 29): 640 x 480 organized depth images ray-cast by
# tests/sensors.py (Kinect-like noise growing with the squared distance, flying pixels at the
# depth edges, NaN misses dropped), normals by our normals stage oriented towards the camera

POISSONRECON_DEFAULT = "/work/ref/PoissonRecon/Bin/Linux/PoissonRecon"
SURFACE_TRIMMER = 7  # PoissonRecon's SurfaceTrimmer --trim in the trimmed rows (issue 29's)


def _office_sdf():
    """An office seen from inside, in metres.

    A 6 x 6 x 2.8 m room, two desks, a monitor, a cabinet, a shelf, a person, a ball and a ring.
    """
    sys.path.insert(0, str(ROOT / "tests"))
    from sensors import box_sdf, union
    from shapes import rounded_box_sdf, sphere_sdf, torus_sdf

    def person(p):
        head = sphere_sdf(p - (0.3, 3.2, 1.6), 0.12)
        body = rounded_box_sdf(p - (0.3, 3.2, 0.75), half=(0.2, 0.12, 0.75), radius=0.1)
        return np.minimum(head, body)

    return union(
        lambda p: -box_sdf(p, (-3.0, -1.0, 0.0), (3.0, 5.0, 2.8)),
        lambda p: box_sdf(p, (-2.4, 2.0, 0.72), (-0.6, 2.8, 0.76)),
        lambda p: box_sdf(p, (-2.3, 2.1, 0.0), (-2.2, 2.7, 0.72)),
        lambda p: box_sdf(p, (-0.9, 2.1, 0.0), (-0.6, 2.7, 0.72)),
        lambda p: box_sdf(p, (-1.8, 2.55, 0.76), (-1.2, 2.6, 1.15)),
        lambda p: rounded_box_sdf(p - (1.6, 1.4, 0.37), half=(0.8, 0.4, 0.37), radius=0.03),
        person,
        lambda p: sphere_sdf(p - (1.8, 1.4, 0.9), 0.15),
        lambda p: torus_sdf(p - (-1.5, 2.3, 0.82), 0.12, 0.05),
        lambda p: box_sdf(p, (2.4, 3.0, 0.0), (2.95, 4.5, 2.0)),
    )


def _depth_camera(scene: str):
    """(oriented cloud, the scene's sdf) of a 640 x 480 depth image of ``scene``."""
    sys.path.insert(0, str(ROOT / "tests"))
    from recon_cli.geometry import PointCloud
    from recon_cli.stages import normals

    from sensors import DepthCamera, depth_image, look_at, tabletop_scene, valid_rows

    if scene == "tabletop":
        sdf, eye, target, seed = tabletop_scene(), (0.2, -2.6, 1.3), (0.0, 0.4, 0.25), 0
    else:
        sdf, eye, target, seed = _office_sdf(), (-0.5, -0.6, 1.5), (0.3, 4.0, 0.6), 1
    cam = DepthCamera(
        eye=np.array(eye), rotation=look_at(eye, target), width=640, height=480, max_range=6.0
    )
    p = valid_rows(depth_image(cam, sdf, np.random.default_rng(seed)))
    cloud = PointCloud(points=p, point_dtype=np.float64)
    return normals.run_stage(cloud, orient="camera", camera=tuple(eye)).output, sdf


def poissonrecon_dir() -> Path | None:
    """The folder of the built ``PoissonRecon`` and ``SurfaceTrimmer``, None when not built.

    ``$POISSONRECON_BIN`` names the PoissonRecon executable (default: the reference build's),
    SurfaceTrimmer lies beside it (``make poissonrecon surfacetrimmer`` of mkazhdan/PoissonRecon).
    """
    exe = Path(os.environ.get("POISSONRECON_BIN", POISSONRECON_DEFAULT))
    if exe.exists() and (exe.parent / "SurfaceTrimmer").exists():
        return exe.parent
    return None


def poissonrecon_process(cloud, depth: int, workdir: Path, bindir: Path):
    """PoissonRecon --density then SurfaceTrimmer as processes (their defaults otherwise).

    Returns the wall seconds and peak RSS of PoissonRecon and the trimmed mesh (in the input's
    frame).
    """
    from recon_cli.io import read_ply

    pts = np.asarray(cloud.points, np.float64)
    centre = 0.5 * (pts.min(0) + pts.max(0))  # float32 PLY: about the centre
    names = ("x", "y", "z", "nx", "ny", "nz")
    rows_ = np.zeros(len(pts), dtype=[(k, "<f4") for k in names])
    for a in range(3):
        rows_[names[a]] = pts[:, a] - centre[a]
        rows_[names[a + 3]] = cloud.normals[:, a]
    src, out, cut = workdir / "pr_in.ply", workdir / "pr_out.ply", workdir / "pr_trim.ply"
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
    header += "".join(f"property float {k}\n" for k in names) + "end_header\n"
    src.write_bytes(header.encode() + rows_.tobytes())
    cmd = [str(bindir / "PoissonRecon"), "--in", str(src), "--out", str(out)]
    cmd += ["--depth", str(depth), "--density"]
    proc = subprocess.run([sys.executable, "-c", LAUNCHER, *cmd], capture_output=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"PoissonRecon failed: {proc.stderr.decode().strip()[-200:]}")
    dt, maxrss_kb = proc.stdout.decode().split()
    trim = [str(bindir / "SurfaceTrimmer"), "--in", str(out), "--out", str(cut)]
    subprocess.run(trim + ["--trim", str(SURFACE_TRIMMER)], check=True, capture_output=True)
    mesh = read_ply(cut)
    mesh.vertices = np.asarray(mesh.vertices, np.float64) + centre
    return {"seconds": float(dt), "peak_mb": int(maxrss_kb) / 1024.0}, mesh


def _trim_figures(mesh, pts: np.ndarray, sdf) -> str:
    """Issue 29's figures of a trimmed surface.

    Input points within 0.5 % of the diagonal of it, its area farther than 1 % from every input
    point, pieces, and its mean distance to the true scene (area-weighted, a fraction of the
    diagonal).
    """
    from scipy.spatial import cKDTree

    from recon_cli.mesh.topology import Connectivity

    if len(mesh.faces) == 0:
        return "empty"
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    near = float((_to_mesh(mesh, pts) <= 0.005 * diag).mean())
    s = _surface_samples(mesh, N_EVAL, seed=3)
    far = float((cKDTree(pts).query(s, workers=-1)[0] > 0.01 * diag).mean())
    pieces = int(Connectivity(np.asarray(mesh.faces), len(mesh.vertices)).face_components.max())
    truth = float(np.abs(sdf(s)).mean()) / diag
    return f"near {near:.4f} · far {far:.4%} · pieces {pieces + 1} · truth {truth:.2e}"


def _depth_camera_rows(scene: str, depth: int, work: Path, trimmed: bool) -> list[dict]:
    """Depth-camera rows, untrimmed and trimmed, ours against Open3D and PoissonRecon.

    Untrimmed: ours (process) and Open3D, time and fit. Trimmed: ours ``--trim auto``, Open3D's 5 %
    vertex-density quantile and (when found) PoissonRecon + SurfaceTrimmer ``--trim 7``, with
    :func:`_trim_figures` in the note.
    """
    cloud, sdf = _depth_camera(scene)
    label = f"depth camera {scene} 640x480 ({len(cloud.points) // 1000}k), d{depth}"
    if not trimmed:
        return _rows_for(label, cloud, depth, None, "fit", work, pymeshlab=False)
    label += f", trimmed (ours auto, o3d {REF_TRIM:.0%} quantile, SurfaceTrimmer {SURFACE_TRIMMER})"
    out, meshes = [], {}
    runs = [("recon (process)", lambda: _ours_process(cloud, depth, "auto", work))]
    runs.append(("open3d", lambda: reference(open3d_poisson, cloud, depth, True)))
    bindir = poissonrecon_dir()
    if bindir is not None:
        runs.append(
            ("PoissonRecon (process)", lambda: poissonrecon_process(cloud, depth, work, bindir))
        )
    for name, run in runs:
        try:
            m, mesh = run()
        except Exception as exc:  # one failing method must not hide the others
            out.append({"case": label, "method": name, "note": f"FAILED: {exc}"})
            continue
        meshes[name] = m
        out.append(
            {
                "case": label,
                "method": name,
                "faces": len(mesh.faces),
                "topology": _topology(mesh),
                "seconds": m["seconds"],
                "mb": m["peak_mb"],
                "note": _trim_figures(mesh, np.asarray(cloud.points), sdf),
            }
        )
    if bindir is None:
        out.append(
            {"case": label, "method": "PoissonRecon", "note": "not built: no $POISSONRECON_BIN"}
        )
    ours, ref = meshes.get("recon (process)"), meshes.get("open3d")
    if ours and ref:
        out[0]["time_ratio"] = ours["seconds"] / ref["seconds"]
        out[0]["mem_ratio"] = ours["peak_mb"] / ref["peak_mb"]
    return out


def rows(quick: bool, only: list[str] | None = None) -> list[dict]:
    """The rows; ``only``: just the cases whose label contains one of these strings."""

    def want(case: str) -> bool:
        return not only or any(o in case for o in only)

    # warm our numba cache the way a user's install does (no compile time in the rows)
    subprocess.run(
        [str(Path(sys.executable).with_name("recon")), "-q", "warmup"],
        check=False,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    out: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        out += _scan_rows(quick, want, work)
        out += _smooth_rows(quick, want, work)
        for scene in ("tabletop",) if quick else ("tabletop", "office"):
            if want(f"depth camera {scene}"):
                out += _depth_camera_rows(scene, 9, work, trimmed=False)
        if want("depth camera tabletop, trimmed"):
            out += _depth_camera_rows("tabletop", 9, work, trimmed=True)
        noisy = _samples("kitten", 100_000, NOISE)
        noisy.normals = None
        if want("kitten 100k noisy, our normals, d9"):
            out += _rows_for(
                "kitten 100k noisy, our normals, d9",
                _with_our_normals(noisy),
                9,
                _mesh("kitten"),
                "chamfer",
                work,
            )
        if not quick:
            out += _large_rows(want, work)
    return out


def _scan_rows(quick: bool, want, work: Path) -> list[dict]:
    """The raw bunny scan and stereo fragment, and the bunny scan trimmed."""
    from recon_cli.io import read_ply

    out: list[dict] = []
    bunny_truth = _mesh("bunny_zipper")
    scan = _with_our_normals(read_ply(SHARED / "bunny_scan_000.ply"))
    stereo = _with_our_normals(read_ply(SHARED / "stereo_fragment.ply"))
    for depth in (9,) if quick else (9, 10):
        if want(f"bunny scan raw, d{depth}"):
            out += _rows_for(f"bunny scan raw, d{depth}", scan, depth, None, "fit", work)
        if want(f"stereo fragment, d{depth}"):
            out += _rows_for(f"stereo fragment, d{depth}", stereo, depth, None, "fit", work)
    for depth in (8, 9):
        if not want(f"bunny scan, d{depth}, trimmed"):
            continue
        out += _rows_for(
            f"bunny scan, d{depth}, trimmed (ours {OUR_TRIM}, o3d {REF_TRIM:.0%} quantile)",
            scan,
            depth,
            bunny_truth,
            "accuracy",
            work,
            trimmed=True,
        )
    return out


def _smooth_rows(quick: bool, want, work: Path) -> list[dict]:
    """100k samples of smooth shapes (kitten, armadillo, torus, mug), clean and noisy."""
    smooth = (
        [("kitten", 0.0, 8), ("kitten", NOISE, 9)]
        if quick
        else [
            ("kitten", 0.0, 8),
            ("kitten", 0.0, 9),
            ("kitten", NOISE, 8),
            ("kitten", NOISE, 9),
            ("armadillo", 0.0, 8),
            ("armadillo", 0.0, 9),
            ("armadillo", NOISE, 9),
            ("torus", 0.0, 8),
            ("torus", NOISE, 9),
            ("mug", 0.0, 9),
        ]
    )
    out: list[dict] = []
    for name, noise, depth in smooth:
        label = f"{name} 100k{' noisy' if noise else ''}, d{depth}"
        if not want(label):
            continue
        if name == "torus":
            out += _rows_for(label, _torus(100_000, noise), depth, _torus_truth(), "torus", work)
        else:
            out += _rows_for(
                label, _samples(name, 100_000, noise), depth, _mesh(name), "chamfer", work
            )
    return out


def _large_rows(want, work: Path) -> list[dict]:
    """1M and 5M samples of the armadillo (the full run only)."""
    out: list[dict] = []
    if any(want(f"armadillo 1M, d{depth}") for depth in (9, 10)):
        big = _samples("armadillo", 1_000_000)
        for depth in (9, 10):
            if not want(f"armadillo 1M, d{depth}"):
                continue
            out += _rows_for(
                f"armadillo 1M, d{depth}",
                big,
                depth,
                _mesh("armadillo"),
                "chamfer",
                work,
                pymeshlab=depth < 10,
            )
        del big
    if want("armadillo 5M, d11"):
        huge = _samples("armadillo", 5_000_000)
        m, mesh = _ours_process(huge, 11, False, work)
        out.append(
            {
                "case": "armadillo 5M, d11",
                "method": "recon (process)",
                "faces": len(mesh.faces),
                "topology": _topology(mesh),
                "seconds": m["seconds"],
                "mb": m["peak_mb"],
                "note": "ours only; target within 12 GiB",
            }
        )
    return out


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    # --quick: fewer rows; --only "A;B": only the cases whose label contains A or B;
    # --no-pymeshlab: ours and Open3D only
    NO_PYMESHLAB = "--no-pymeshlab" in sys.argv
    only = sys.argv[sys.argv.index("--only") + 1].split(";") if "--only" in sys.argv else None
    for r in rows("--quick" in sys.argv, only):
        print(r)
