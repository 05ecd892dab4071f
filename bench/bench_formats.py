"""File formats: our readers vs the libraries users would otherwise call, on the same files.

* LAZ (1.1M points, the Autzen tile tiled 10 times): ``recon_cli.io.load`` vs ``laspy.read``
  (ours is laspy plus the float64 coordinates and attribute arrays; target <= 1.2x);
* PCD binary and XYZ text (1M points; ``--quick``: 200k): ours vs ``open3d.io.read_point_cloud``
  (target <= 1x);
* PCD binary_compressed: ours (our LZF kernel) vs Open3D;
* OBJ mesh: ours vs our binary PLY reader on the same mesh (target <= 3x per vertex; the two
  measured alternately, the note gives ns per vertex, wall and CPU) and vs ``trimesh.load``
  (the library we judged against writing our own); ``recon info`` on both as processes;
* STL binary: ours (with the exact weld) vs ``trimesh.load`` (which also merges vertices);
* ``recon info FILE`` as a process for each of our files (what a user waits for: start-up,
  imports, the cached kernels' load and the read);
* GLB (5M faces; ``--quick``: 320k): write and read vs our binary PLY writer and reader on the same
  mesh, float32 and float64 at state-plane offsets with normals and colours, the two measured
  alternately (target: write <= 1.2x PLY), and the write vs trimesh's GLB export.

Each in-process figure is the median wall time of runs in forked children (``_util.measure``);
the note adds the median CPU seconds (user + system) of the same runs and their ratio, which
is the fairer figure on a loaded machine.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _util import measure_once, row

ROOT = Path(__file__).resolve().parents[1]
RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def _cpu_of(fn):
    def run():
        c0 = time.process_time()
        fn()
        return time.process_time() - c0

    return run


def measure(fn, repeat: int) -> dict:
    """As ``_util.measure`` (median wall and peak memory over forked runs) plus median CPU time."""
    runs = [measure_once(_cpu_of(fn)) for _ in range(repeat)]
    return {
        "seconds": statistics.median(r[0] for r in runs),
        "peak_mb": statistics.median(r[1] for r in runs),
        "cpu": statistics.median(r[2] for r in runs),
    }


def _row(case, ours, ref_name, ref, note):
    extra = f"CPU {ours['cpu']:.3g} / {ref['cpu']:.3g} s = {ours['cpu'] / ref['cpu']:.2f}"
    return row("formats", case, ours, ref_name, ref, f"{extra}; {note}" if note else extra)


def _process_once(path: str) -> tuple[float, float]:
    """``recon info PATH`` as a process once: (wall, CPU (user + system) seconds)."""
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run([*RECON, "-q", "info", path], capture_output=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise RuntimeError(f"recon info {path}: exit {r.returncode}: {r.stderr.decode()[-300:]}")
    return wall, ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime


def _process(path: str, repeat: int) -> dict:
    """``recon info PATH`` as a process: median wall and CPU seconds (after one run not counted)."""
    runs = [_process_once(path) for _ in range(repeat + 1)][1:]
    return {
        "seconds": statistics.median(w for w, _ in runs),
        "peak_mb": float("nan"),
        "cpu": statistics.median(c for _, c in runs),
    }


AUTZEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "autzen_trim.laz"


def _tile_laz(path: str, copies: int) -> int:
    import laspy

    # the single-threaded backend: lazrs' parallel one starts a thread pool, and the timed reads
    # run in forked children, which a pool started before the fork would deadlock
    src = laspy.read(AUTZEN, laz_backend=laspy.LazBackend.Lazrs)
    h = laspy.LasHeader(point_format=src.header.point_format.id, version=src.header.version)
    h.scales = src.header.scales
    h.offsets = src.header.offsets
    out = laspy.LasData(h)
    arr = np.concatenate([src.points.array] * copies)
    span = int(np.ptp(src.points.array["X"])) + 100
    for k in range(copies):  # side by side, so the tile stays a plausible survey
        arr["X"][k * len(src.points) : (k + 1) * len(src.points)] += k * span
    out.points = laspy.ScaleAwarePointRecord(arr, h.point_format, h.scales, h.offsets)
    out.write(path, laz_backend=laspy.LazBackend.Lazrs)
    return len(arr)


def _cloud(n: int):
    from recon_cli.geometry import PointCloud

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(n, 3)).astype(np.float32) * 10
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    return PointCloud(points=pts, normals=nrm, colors=col, point_dtype=np.float32)


def _grid_mesh(n_side: int):
    from recon_cli.geometry import TriangleMesh

    x, y = np.meshgrid(
        np.arange(n_side, dtype=np.float32), np.arange(n_side, dtype=np.float32), indexing="ij"
    )
    v = np.column_stack(
        [x.ravel() * 0.001, y.ravel() * 0.001, np.sin(x.ravel() * 0.01) * 0.1]
    ).astype(np.float32)
    idx = np.arange(n_side * n_side).reshape(n_side, n_side)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return TriangleMesh(vertices=v, faces=f, point_dtype=np.float32)


def rows(quick: bool) -> list[dict]:
    """The section's rows: reading each format in-process against its reference library.

    Clouds, OBJ and STL meshes; then ``recon info FILE`` of each file as a process (start-up and
    imports included).
    """
    rep = 3 if quick else 5
    n = 200_000 if quick else 1_000_000
    out: list[dict] = []
    with tempfile.TemporaryDirectory() as d:
        files: list[tuple[str, str]] = []
        out += _cloud_rows(d, quick, n, rep, files)
        # OBJ vs our binary PLY of the same mesh (per vertex: the same vertices), and vs trimesh
        mesh = _grid_mesh(400 if quick else 1000)
        obj_out, obj_files = obj_rows(mesh, d, rep)
        out += obj_out
        files += obj_files
        out.append(_stl_row(mesh, d, rep, files))
        # what the user waits for: `recon info FILE` as a process
        for name, path in files:
            p = _process(path, 2 if quick else 3)
            out.append(
                {
                    "stage": "formats",
                    "case": f"`recon info` process, {name}",
                    "ours_s": p["seconds"],
                    "ours_mb": float("nan"),
                    "ref": "",
                    "ref_s": float("nan"),
                    "ref_mb": float("nan"),
                    "time_ratio": float("nan"),
                    "mem_ratio": float("nan"),
                    "note": f"CPU {p['cpu']:.3g} s (start-up and imports included)",
                }
            )
        out.append(obj_process_row(obj_files, 2 if quick else 3))
        out += gltf_rows(d, quick, rep)
    return out


def _alternately(a, b, rep: int) -> tuple[dict, dict]:
    """``measure`` of ``a`` and ``b``, their runs interleaved (both see the same machine load)."""
    ra, rb = [], []
    for _ in range(rep):
        ra.append(measure_once(_cpu_of(a)))
        rb.append(measure_once(_cpu_of(b)))

    def stats(runs):
        return {
            "seconds": statistics.median(r[0] for r in runs),
            "peak_mb": statistics.median(r[1] for r in runs),
            "cpu": statistics.median(r[2] for r in runs),
        }

    return stats(ra), stats(rb)


def gltf_rows(d: str, quick: bool, rep: int) -> list[dict]:
    """GLB write and read vs our binary PLY on the same mesh; the write vs trimesh's export."""
    import trimesh

    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.load import load, save

    m32 = _grid_mesh(400 if quick else 1582)
    rng = np.random.default_rng(2)
    nrm = rng.normal(size=m32.vertices.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    m64 = TriangleMesh(
        vertices=m32.vertices.astype(np.float64) * 1000 + [6.36e5, 8.49e5, 400.0],
        faces=m32.faces,
        normals=nrm,
        colors=rng.integers(0, 256, (len(nrm), 3)).astype(np.uint8),
    )
    out = []
    glb, ply, other = (os.path.join(d, name) for name in ("m.glb", "m.ply", "t.glb"))
    for tag, mesh in (("float32", m32), ("float64 at 1e6, normals, colours", m64)):
        save(mesh, glb)  # kernels compiled or loaded outside the timed runs
        save(mesh, ply)
        label = f"{len(mesh.faces) // 1000}k faces, {tag}"
        ours, ref = _alternately(lambda m=mesh: save(m, glb), lambda m=mesh: save(m, ply), rep)
        out.append(_row(f"write GLB, {label}", ours, "our binary PLY writer", ref, "target ≤ 1.2×"))
        ours, ref = _alternately(lambda: len(load(glb).faces), lambda: len(load(ply).faces), rep)
        out.append(_row(f"read GLB, {label}", ours, "our binary PLY reader", ref, ""))
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_normals=mesh.normals, process=False)
        ref = measure(lambda tm=tm: tm.export(other), rep)
        ours = measure(lambda m=mesh: save(m, glb), rep)
        out.append(_row(f"write GLB, {label}", ours, "trimesh export (float32 positions)", ref, ""))
    return out


def _cloud_rows(d: str, quick: bool, n: int, rep: int, files: list) -> list[dict]:
    """Point clouds read: LAZ vs laspy, PCD and XYZ vs Open3D (their files added to ``files``)."""
    import laspy
    import open3d as o3d

    from recon_cli.io.load import load, save

    out = []
    laz = os.path.join(d, "tile.laz")
    npts = _tile_laz(laz, 2 if quick else 10)
    # no warm-up read here: lazrs decompresses on a thread pool, which must not exist before a
    # fork
    ours = measure(lambda: len(load(laz).points), rep)
    ref = measure(lambda: len(laspy.read(laz).points), rep)
    out.append(
        _row(
            f"read {npts // 1000}k-point LAZ (Autzen, format 3)",
            ours,
            "laspy.read",
            ref,
            "target ≤ 1.2×",
        )
    )
    files.append(("LAZ", laz))

    cloud = _cloud(n)
    # PCD binary and compressed
    for data in ("binary", "binary_compressed"):
        pcd = os.path.join(d, f"{data}.pcd")
        if data == "binary":
            save(cloud, pcd)
        else:
            from recon_cli.io.pcd import write_pcd

            write_pcd(cloud, pcd, data=data)
        load(pcd)
        ours = measure(lambda pcd=pcd: len(load(pcd).points), rep)
        ref = measure(lambda pcd=pcd: len(o3d.io.read_point_cloud(pcd).points), rep)
        out.append(
            _row(
                f"read {n // 1000}k-point PCD {data} (xyz, normals, rgb)",
                ours,
                "open3d.io.read_point_cloud",
                ref,
                "target ≤ 1×",
            )
        )
        files.append((f"PCD {data}", pcd))
    out += _xyz_rows(d, cloud, n, rep, files)
    return out


def _xyz_rows(d: str, cloud, n: int, rep: int, files: list) -> list[dict]:
    """XYZ text read vs Open3D: as Open3D writes it, and ours from doubles."""
    import open3d as o3d

    from recon_cli.io.load import load
    from recon_cli.io.xyz import xyz_bytes

    out = []
    # XYZ text (x y z: the columns Open3D's reader takes): as Open3D writes it (%.10f), and ours
    # from double data (%.17g: mostly beyond the exact fast path, numpy converts those)
    xyz = os.path.join(d, "o3d.xyz")
    p = o3d.geometry.PointCloud()
    p.points = o3d.utility.Vector3dVector(cloud.points.astype(np.float64) * 1000 + [5e5, 5e6, 100])
    o3d.io.write_point_cloud(xyz, p)
    load(xyz)
    xyz17 = os.path.join(d, "c.xyz")
    rng = np.random.default_rng(1)
    plain = type(cloud)(
        points=rng.normal(size=(n, 3)) * 1000 + [5e5, 5e6, 100], point_dtype=np.float64
    )
    Path(xyz17).write_bytes(xyz_bytes(plain))
    cases = (
        (xyz, "written by Open3D (%.10f, UTM-like)", "XYZ %.10f"),
        (xyz17, "of doubles (%.17g)", "XYZ %.17g"),
    )
    for path, what, name in cases:
        ours = measure(lambda path=path: len(load(path).points), rep)
        ref = measure(lambda path=path: len(o3d.io.read_point_cloud(path).points), rep)
        case = f"read {n // 1000}k-point XYZ {what}"
        out.append(_row(case, ours, "open3d.io.read_point_cloud", ref, "target ≤ 1×"))
        files.append((name, path))
    return out


def _stl_row(mesh, d: str, rep: int, files: list) -> dict:
    """Binary STL read (welded) vs trimesh."""
    import trimesh

    from recon_cli.io.load import load, save

    stl = os.path.join(d, "m.stl")
    save(mesh, stl)
    load(stl)
    ours = measure(lambda: len(load(stl).vertices), rep)
    tm = measure(lambda: len(trimesh.load(stl).vertices), rep)
    files.append(("STL binary", stl))
    return _row(
        f"read binary STL ({len(mesh.faces) // 1000}k triangles), welded",
        ours,
        "trimesh.load (merges vertices)",
        tm,
        "",
    )


def obj_rows(mesh, d: str, rep: int) -> tuple[list[dict], list[tuple[str, str]]]:
    """OBJ read against our binary PLY read of the same mesh, and against trimesh.

    The same mesh makes the ratio per vertex; OBJ and PLY are measured alternately (back to back on
    a loaded machine).
    """
    import trimesh

    from recon_cli.io.load import load, save
    from recon_cli.io.obj import obj_bytes

    obj = os.path.join(d, "m.obj")
    ply = os.path.join(d, "m.ply")
    Path(obj).write_bytes(obj_bytes(mesh))
    save(mesh, ply)
    load(obj)
    load(ply)
    nv = len(mesh.vertices)
    runs_o, runs_p = [], []
    for _ in range(rep):  # alternately, so both see the same load
        runs_o.append(measure_once(_cpu_of(lambda: len(load(obj).faces))))
        runs_p.append(measure_once(_cpu_of(lambda: len(load(ply).faces))))

    def stats(runs):
        return {
            "seconds": statistics.median(r[0] for r in runs),
            "peak_mb": statistics.median(r[1] for r in runs),
            "cpu": statistics.median(r[2] for r in runs),
        }

    ours, ref = stats(runs_o), stats(runs_p)
    per = (
        f"per vertex: OBJ {1e9 * ours['seconds'] / nv:.0f} ns vs PLY "
        f"{1e9 * ref['seconds'] / nv:.0f} ns wall "
        f"= {ours['seconds'] / ref['seconds']:.2f}×, CPU {1e9 * ours['cpu'] / nv:.0f} vs "
        f"{1e9 * ref['cpu'] / nv:.0f} ns "
        f"= {ours['cpu'] / ref['cpu']:.2f}×; target ≤ 3×; {os.path.getsize(obj) / 1e6:.0f} MB OBJ"
    )
    label = f"read OBJ mesh ({nv // 1000}k vertices, {len(mesh.faces) // 1000}k faces)"
    out = [_row(label, ours, "our binary PLY reader, same mesh", ref, per)]
    tm = measure(lambda: len(trimesh.load(obj, process=False).faces), rep)
    out.append(_row(label, ours, "trimesh.load(process=False)", tm, ""))
    return out, [("OBJ", obj), ("PLY binary, same mesh", ply)]


def obj_process_row(obj_files, repeat: int) -> dict:
    """``recon info`` on the OBJ and the binary PLY of the same mesh as processes, alternately."""
    (_, obj), (_, ply) = obj_files
    _process_once(obj)
    _process_once(ply)
    po, pp = [], []
    for _ in range(repeat):  # alternately
        po.append(_process_once(obj))
        pp.append(_process_once(ply))
    o = {
        "seconds": statistics.median(w for w, _ in po),
        "cpu": statistics.median(c for _, c in po),
        "peak_mb": float("nan"),
    }
    r = {
        "seconds": statistics.median(w for w, _ in pp),
        "cpu": statistics.median(c for _, c in pp),
        "peak_mb": float("nan"),
    }
    return _row(
        "`recon info` process, OBJ vs binary PLY of the same mesh",
        o,
        "`recon info` process, binary PLY",
        r,
        "start-up and imports included; target ≤ 3× per vertex",
    )
