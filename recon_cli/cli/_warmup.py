"""Compile every numba kernel once, for the types recon uses, into the per-user cache.

``recon warmup`` (run by ``make install``; a ``pip install`` user runs it once) calls
:func:`warmup`. It lives with the command line because it drives the commands: it makes tiny inputs (a sphere cloud, a sphere mesh, their grids) in a
temporary folder and runs every command on them with each option that reaches a different
kernel, reading and writing the PLY encodings the readers specialise on (float32/float64,
little/big-endian, ASCII, colours, mixed polygons). Kernels whose argument types depend on
a file's property types rather than on a command (the PLY field gatherers) are called
for each type by :func:`recon_cli.io.ply.compile_ply_kernels`. Afterwards no command compiles: they load the compiled code from
the cache (:mod:`recon_cli._kernels.numba_setup` says where), which takes milliseconds.

:func:`uncompiled_kernels` lists the kernels that were never compiled in this process, so
a test can check that the warm-up reaches all of them.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import tempfile
import time
from typing import Any, Callable

import numpy as np


def kernel_modules() -> list[str]:
    """Names of recon's modules that define numba kernels (found by their source text, without importing)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]  # the recon_cli package
    mods = []
    for f in sorted(root.rglob("*.py")):
        if re.search(r"^@njit", f.read_text(encoding="utf-8"), re.M):
            rel = f.relative_to(root.parent).with_suffix("")
            mods.append(".".join(rel.parts))
    return mods


def _sphere_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on the unit sphere (Fibonacci spiral, slightly jittered) and their outward normals."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5**0.5) * i
    p = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    p += np.random.default_rng(seed).normal(scale=1e-3, size=p.shape)
    nrm = p / np.linalg.norm(p, axis=1, keepdims=True)
    return p, nrm


def _sphere_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated sphere with ``n`` vertices, faces wound outward."""
    from scipy.spatial import ConvexHull

    p, _ = _sphere_cloud(n, seed=1)
    f = ConvexHull(p).simplices.astype(np.int64)
    c = p[f].mean(axis=1)
    nrm = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = np.einsum("ij,ij->i", nrm, c) < 0
    f[flip] = f[flip][:, ::-1]
    return p, f


def _library_only(mesh_path: str) -> None:
    """Kernels that only the library API reaches (no command)."""
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.mesh.winding import winding_number

    mesh = read_ply(mesh_path)
    winding_number(mesh.vertices, mesh.faces, np.zeros((2, 3)), method="exact")
    Connectivity(mesh.faces).vertex_faces


def _pcd(src: str, dst: str, mode: str) -> Callable[[], Any]:
    def run() -> None:
        from recon_cli.io.load import load
        from recon_cli.io.pcd import write_pcd

        write_pcd(load(src), dst, data=mode)

    return run


def _steps(tmp: str) -> list[tuple[str, Callable[[], Any]]]:
    from recon_cli.geometry import PointCloud, TriangleMesh
    from recon_cli.io.ply import compile_ply_kernels, write_ply

    def path(name: str) -> str:
        return os.path.join(tmp, name)

    def recon(*args: str) -> Callable[[], Any]:
        def run() -> Any:
            from recon_cli.cli.main import cli

            # the commands' reports (info and diff print theirs on stdout) are not wanted here
            with (
                contextlib.redirect_stdout(io.StringIO()),
                contextlib.redirect_stderr(io.StringIO()),
            ):
                return cli.main(args=["-q", *args], prog_name="recon", standalone_mode=False)

        return run

    def inputs() -> None:
        p, nrm = _sphere_cloud(600)
        rgb = (np.abs(nrm) * 255).astype(np.uint8)
        for dtype in (np.float32, np.float64):
            tag = np.dtype(dtype).name
            write_ply(
                PointCloud(points=p.astype(dtype), point_dtype=dtype), path(f"bare_{tag}.ply")
            )
            write_ply(
                PointCloud(
                    points=p.astype(dtype), normals=nrm.astype(dtype), colors=rgb, point_dtype=dtype
                ),
                path(f"cloud_{tag}.ply"),
            )
        v, f = _sphere_mesh(300)
        for dtype in (np.float32, np.float64):
            tag = np.dtype(dtype).name
            write_ply(
                TriangleMesh(vertices=v.astype(dtype), faces=f, point_dtype=dtype),
                path(f"mesh_{tag}.ply"),
            )
        # an open mesh with a stray component: repair and the topology report have work to do
        keep = f[np.asarray(v)[f].mean(axis=1)[:, 2] < 0.7]
        far = np.array([[5.0, 5.0, 5.0], [5.1, 5.0, 5.0], [5.0, 5.1, 5.0]])
        write_ply(
            TriangleMesh(
                vertices=np.vstack([v, far]),
                faces=np.vstack([keep, [[len(v), len(v) + 1, len(v) + 2]]]),
            ),
            path("open.ply"),
        )
        # dense enough that Poisson's adaptive tree goes past its complete levels
        pd, nd = _sphere_cloud(20_000, seed=1)
        write_ply(
            PointCloud(
                points=pd.astype(np.float32), normals=nd.astype(np.float32), point_dtype=np.float32
            ),
            path("dense.ply"),
        )
        # an open scan (half of it): coarse leaves hold surface, so Poisson extracts at the leaves' size
        up = pd[:, 2] > 0
        write_ply(PointCloud(points=pd[up], normals=nd[up]), path("half.ply"))
        # ... with integer codes (Poisson's --attributes votes on them)
        codes = {"classification": (pd[up, 0] > 0).astype(np.uint8) + 1}
        write_ply(
            PointCloud(points=pd[up], normals=nd[up], attributes=codes), path("half_codes.ply")
        )
        # Poisson's envelope: a closed sphere around the clouds
        write_ply(TriangleMesh(vertices=1.5 * v, faces=f), path("envelope.ply"))
        # repeated and collinear points: degenerate neighbourhoods borrow their normal
        line = np.column_stack([np.linspace(2, 3, 12), np.zeros(12), np.zeros(12)])
        write_ply(
            PointCloud(points=np.vstack([p, np.repeat(p[:1], 40, axis=0), line])),
            path("degenerate.ply"),
        )
        # an organized depth image (NaN pixels, a VIEWPOINT): normals from its pixel grid
        hh, ww = 12, 16
        yy, xx = np.mgrid[0:hh, 0:ww].astype(np.float32)
        grid = np.stack([xx * 0.1, yy * 0.1, 2.0 + 0.01 * xx * yy], axis=-1).reshape(-1, 3)
        grid[::7] = np.nan
        with open(path("organized.pcd"), "wb") as fh:
            fh.write(
                b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                + f"WIDTH {ww}\nHEIGHT {hh}\nVIEWPOINT 0.8 0.6 0 1 0 0 0\n".encode()
                + f"POINTS {hh * ww}\nDATA binary\n".encode()
            )
            fh.write(grid.astype("<f4").tobytes())
        # three triangles on one edge: repair chooses which two stay together
        fin = np.array(
            [[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=np.float64
        )
        write_ply(
            TriangleMesh(vertices=fin, faces=np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])),
            path("fin.ply"),
        )
        # a mixed-polygon mesh (a quad among triangles): the general list reader
        with open(path("mixed.ply"), "wb") as fh:
            fh.write(
                b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
            )
            fh.write(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f4").tobytes())
            fh.write(
                bytes([4])
                + np.array([0, 1, 2, 3], "<i4").tobytes()
                + bytes([3])
                + np.array([0, 2, 3], "<i4").tobytes()
            )

    c32, c64, m32, m64 = (
        path("cloud_float32.ply"),
        path("cloud_float64.ply"),
        path("mesh_float32.ply"),
        path("mesh_float64.ply"),
    )
    out = path("out.ply")
    steps: list[tuple[str, Callable[[], Any]]] = [
        ("inputs", inputs),
        ("ply field types", compile_ply_kernels),
    ]
    for src in (c32, c64, path("mixed.ply")):
        steps += [
            (
                f"convert {os.path.basename(src)}",
                recon("convert", src, path("be.ply"), "--big-endian"),
            ),
            ("read big-endian", recon("info", path("be.ply"))),
            ("convert ascii", recon("convert", src, path("ascii.ply"), "--ascii")),
            ("read ascii", recon("info", path("ascii.ply"))),
        ]
    for src in (path("bare_float32.ply"), path("bare_float64.ply")):
        for orient in (
            ["--orient", "mst"],
            ["--orient", "camera", "--camera", "0,0,5"],
            ["--orient", "direction", "--direction", "0,0,1"],
            ["--orient", "none"],
        ):
            steps.append((f"normals {orient[1]}", recon("normals", src, out, *orient)))
        steps.append(
            (
                "normals radius",
                recon("normals", src, out, "--knn", "0", "--radius", "0.2", "--curvature"),
            )
        )
        steps.append(("normals knn+radius", recon("normals", src, out, "--radius", "0.2")))
    steps.append(("normals keep", recon("normals", c32, out, "--orient", "keep")))
    organized = path("organized.pcd")
    steps.append(("normals pixels", recon("normals", organized, out, "--orient", "camera")))
    steps.append(
        (
            "normals pixels radius",
            recon("normals", organized, out, "--neighbours", "pixels", "--radius", "0.5"),
        )
    )
    steps.append(("normals degenerate", recon("normals", path("degenerate.ply"), out)))
    for src in (c32, c64):
        steps += [
            ("poisson", recon("poisson", src, out, "--depth", "5")),
            (
                "poisson density",
                recon(
                    "poisson",
                    src,
                    out,
                    "--depth",
                    "5",
                    "--density",
                    "--trim",
                    "0.1",
                    "--boundary",
                    "dirichlet",
                ),
            ),
            ("poisson degree 1", recon("poisson", src, out, "--depth", "5", "--degree", "1")),
            (
                "poisson degree 1 density",
                recon(
                    "poisson",
                    src,
                    out,
                    "--depth",
                    "5",
                    "--degree",
                    "1",
                    "--density",
                    "--trim",
                    "0.1",
                    "--boundary",
                    "dirichlet",
                ),
            ),
            ("ballpivot", recon("ballpivot", src, out)),
            ("sdf cloud", recon("sdf", src, path("cloud.npz"), "--resolution", "16")),
        ]
    for deg in ("1", "2"):
        steps.append(
            (
                f"poisson adaptive levels, degree {deg}",
                recon("poisson", c32, out, "--depth", "7", "--degree", deg),
            )
        )
        steps.append(
            (
                f"poisson levels past the full depth, degree {deg}",
                recon("poisson", path("dense.ply"), out, "--depth", "7", "--degree", deg),
            )
        )
    steps.append(
        (
            "poisson open scan (leaf extraction)",
            recon("poisson", path("half.ply"), out, "--depth", "7"),
        )
    )
    steps.append(
        (
            "poisson degree 2",
            recon("poisson", path("dense.ply"), out, "--depth", "7", "--degree", "2"),
        )
    )
    steps.append(
        (
            "poisson free boundary, envelope, confidence, grid",
            recon(
                "poisson",
                path("half_codes.ply"),
                out,
                "--depth",
                "6",
                "--boundary",
                "free",
                "--confidence",
                "--envelope",
                path("envelope.ply"),
                "--grid",
                path("poisson_grid.npz"),
            ),
        )
    )
    steps.append(
        (
            "poisson degree 2 unscreened",
            recon("poisson", c32, out, "--depth", "5", "--degree", "2", "--point-weight", "0"),
        )
    )
    steps.append(
        (
            "poisson estimate-normals",
            recon("poisson", path("bare_float32.ply"), out, "--depth", "5", "--estimate-normals"),
        )
    )
    for src in (m32, m64, path("open.ply")):
        steps += [
            ("info mesh", recon("info", src)),
            ("repair", recon("repair", src, out)),
            (
                "repair all",
                recon(
                    "repair",
                    src,
                    out,
                    "--merge-tolerance",
                    "1e-6",
                    "--fill-holes",
                    "100",
                    "--min-component",
                    "0.1",
                    "--keep-largest",
                ),
            ),
            ("sdf winding", recon("sdf", src, path("mesh.npz"), "--resolution", "16")),
            (
                "sdf pseudonormal",
                recon(
                    "sdf",
                    src,
                    path("mesh.npz"),
                    "--resolution",
                    "16",
                    "--sign",
                    "pseudonormal",
                    "--band",
                    "2",
                ),
            ),
        ]
    steps.append(("repair mixed polygons", recon("repair", path("mixed.ply"), out)))
    steps.append(("repair non-manifold edge", recon("repair", path("fin.ply"), out)))
    steps += [
        ("simplify", recon("simplify", m32, out, "--ratio", "0.3")),
        ("simplify open", recon("simplify", path("open.ply"), out, "--faces", "21")),
        ("smooth", recon("smooth", m64, out)),
        ("smooth open", recon("smooth", path("open.ply"), out, "--fixed-boundary")),
    ]
    for grid in (path("mesh.npz"), path("cloud.npz")):
        steps += [
            ("info grid", recon("info", grid)),
            ("mcubes", recon("mcubes", grid, out)),
            ("mcubes mt", recon("mcubes", grid, out, "--method", "mt", "--allow-degenerate")),
        ]
    # every other file format, both ways, from float32 and float64 sources (their parsers are kernels too)
    for src, kind in ((c32, "cloud"), (c64, "cloud"), (m32, "mesh"), (m64, "mesh")):
        tag = os.path.basename(src)[:-4]
        suffixes = ("obj", "off", "stl") if kind == "mesh" else ("xyz", "csv", "pcd", "obj")
        for suffix in suffixes:
            dst = path(f"{tag}.{suffix}")
            steps += [
                (f"write {suffix}", recon("convert", src, dst)),
                (f"read {suffix}", recon("info", dst)),
            ]
    for src in (c32, c64):
        tag = os.path.basename(src)[:-4]
        for mode in ("ascii", "binary", "binary_compressed"):
            dst = path(f"{tag}_{mode}.pcd")
            steps += [
                (f"write pcd {mode}", _pcd(src, dst, mode)),
                (f"read pcd {mode}", recon("info", dst)),
            ]
        dst = path(f"{tag}.stl")
        steps += [
            ("write stl ascii", recon("convert", m32, dst, "--ascii")),
            ("read stl ascii", recon("info", dst)),
        ]
    steps += [
        (
            "diff",
            recon(
                "diff",
                m32,
                path("open.ply"),
                "--samples",
                "2000",
                "--heatmap",
                path("heat.ply"),
                "--png",
                path("diff.png"),
                "--view",
                "iso",
                "--view",
                "top",
            ),
        ),
        ("diff ref", recon("diff", "--ref", m64, c32, m32, "--samples", "2000")),
        (
            "diff cloud picture",
            recon("diff", c32, m32, "--samples", "2000", "--png", path("cloud.png")),
        ),
        ("library only", lambda: _library_only(m64)),
    ]
    return steps


def warmup(progress: Any = None, log: Callable[[str], None] | None = None) -> dict:
    """Run every kernel once on tiny inputs so that numba compiles (or loads) each of them.

    Parameters
    ----------
    progress : Progress or None
        Shows one bar over the steps (and numba's "compiling kernels" line).
    log : callable or None
        Called with one line per step that failed (a step's failure does not stop the others).

    Returns
    -------
    dict
        ``steps`` (count), ``failed`` (list of step names), ``seconds``, ``cache_dir``,
        ``uncompiled`` (kernels never compiled, see :func:`uncompiled_kernels`) and
        ``bytecode`` (every module's ``.pyc`` written, see :func:`compile_bytecode`).
    """
    from recon_cli import aot
    from recon_cli._kernels.numba_setup import CACHE_DIR
    from recon_cli.progress import task

    t0 = time.perf_counter()
    failed = []
    bytecode = compile_bytecode()
    with tempfile.TemporaryDirectory(prefix="recon-warmup-") as tmp, _jit_only():
        steps = _steps(tmp)
        with task(progress, "warming up kernels", len(steps)) as t:
            for name, fn in steps:
                try:
                    fn()
                except Exception as exc:  # noqa: BLE001  (report and go on: the other kernels still compile)
                    failed.append(name)
                    if log is not None:
                        log(f"warm-up step {name!r} failed: {type(exc).__name__}: {exc}")
                t.advance(1)
    ahead = build_ahead_of_time(progress, log)
    return {
        "steps": len(steps),
        "failed": failed,
        "seconds": time.perf_counter() - t0,
        "cache_dir": CACHE_DIR,
        "uncompiled": uncompiled_kernels(),
        "bytecode": bytecode,
        "aot_built": ahead["built"],
        "aot_dir": ahead["dir"] if ahead["built"] else None,
        "aot_modules": ahead["modules"],
        "aot_reason": ahead["reason"],
    }


@contextlib.contextmanager
def _jit_only():
    """The warm-up's steps run the numba kernels themselves (an ahead-of-time build would
    leave them uncompiled, and the build exports the signatures they compiled)."""
    from recon_cli import aot

    before = os.environ.get("RECON_AOT")
    os.environ["RECON_AOT"] = "0"
    aot.reset()
    try:
        yield
    finally:
        if before is None:
            del os.environ["RECON_AOT"]
        else:
            os.environ["RECON_AOT"] = before
        aot.reset()


def build_ahead_of_time(progress: Any = None, log: Callable[[str], None] | None = None) -> dict:
    """Build the ahead-of-time kernels and the signal handler (:mod:`recon_cli.aot.build`)
    from the kernels compiled in this process; one line through ``log`` saying what came of it."""
    from recon_cli.aot.build import build
    from recon_cli.cli._signals import HANDLER_C
    from recon_cli.progress import task

    with task(progress, "compiling kernels ahead of time", 1) as t:
        out = build(c_libraries={"signal_handler": HANDLER_C}, log=log)
        t.advance(1)
    if log is not None:
        if out["built"]:
            log(
                f"ahead-of-time kernels: {out['reason'] or 'built'} ({', '.join(out['modules'])}) in {out['dir']}"
            )
        else:
            log(
                f"ahead-of-time kernels not built ({out['reason']}): ball pivoting and marching cubes run JIT, "
                "with numba's start-up in each command"
            )
    return out


def compile_bytecode() -> bool:
    """Write the ``.pyc`` of every module of the package (``compileall``), so no command
    compiles Python source either: an editable install (``make install``) or an environment
    with ``PYTHONDONTWRITEBYTECODE`` set would otherwise compile every recon module it
    imports in every process (~45 ms of CPU for a stage command). False when some file
    could not be written (a read-only install: pip wrote its ``.pyc`` files already)."""
    import compileall
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]  # the recon_cli package
    try:
        return bool(compileall.compile_dir(str(root), quiet=2))
    except OSError:
        return False


def kernels() -> dict[str, Any]:
    """Every numba dispatcher defined in :func:`kernel_modules`, by ``module.name``."""
    import importlib

    from numba.core.registry import CPUDispatcher

    out = {}
    for mod_name in kernel_modules():
        mod = importlib.import_module(mod_name)
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == mod_name:
                out[f"{mod_name}.{name}"] = obj
    return out


def uncompiled_kernels() -> list[str]:
    """Kernels neither compiled in this process nor in the cache.

    A kernel loaded from the cache brings its callees' code with it (their own dispatchers
    stay empty), so a callee counts as compiled when the cache holds an index for it.
    Kernels inlined into their callers (``inline="always"``) are left out.
    """
    out = []
    for name, d in kernels().items():
        if d.signatures or d.targetoptions.get("inline") == "always":
            continue
        index = getattr(getattr(d._cache, "_cache_file", None), "_index_path", None)
        if index is None or not os.path.exists(index):
            out.append(name)
    return sorted(out)
