"""Compile every numba kernel once, for the types recon uses, into the per-user cache.

``recon warmup`` (run by ``make install``; a ``pip install`` user runs it once) calls
:func:`warmup`. It lives with the command line because it drives the commands: it makes
tiny inputs (a sphere cloud, a sphere mesh, their grids) in a temporary folder
(:func:`make_inputs`) and runs every command on them with each option that reaches a
different kernel, reading and writing the PLY encodings the readers specialise on
(float32/float64, little/big-endian, ASCII, colours, mixed polygons). Kernels whose
argument types depend on a file's property types rather than on a command (the PLY field
gatherers) are called for each type by :func:`recon_cli.io.ply.compile_ply_kernels`.
Afterwards no command compiles: they load the compiled code from the cache
(:mod:`recon_cli._kernels.numba_setup` says where), which takes milliseconds.

The steps are grouped in phases (:data:`PHASES`, one function each, declared with
:func:`phase`), which run in worker processes, one per core (numba compiles in one thread
per process), the costliest first; a phase's steps run in order in one process. Workers
that need the same kernel at once do not both compile it: the first compiles it under a
lock of that kernel and the other then loads it from the cache
(:func:`serialize_kernel_compiles`; this also keeps two processes from writing one
kernel's cache index at once). Then the ahead-of-time extensions
(:mod:`recon_cli.aot.build`) are built in the same workers, one job per module, from the
signatures the workers' kernels hold.

A step is one line in a phase: ``recon("filter", f.c32, f.out(), "--radius", "0.2")`` runs
that command (its name in the report is the command line), or ``("name", function)`` for
what no command reaches. A stage package may instead declare its own runs as data,
``WARMUP = (("m64",), ("open", "--fixed-boundary"))`` (an input of :class:`Files`, then
options): :func:`all_phases` makes them a phase ``stage-<name>``.

:func:`uncompiled_kernels` lists the kernels that were never compiled, so a test can check
that the warm-up reaches all of them.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon_cli.cli._warmup_inputs import Files, make_inputs

Step = tuple[str, Callable[[], Any]]
# how long a worker waits for another's compile of the same kernel before compiling it too
LOCK_WAIT_S = 900.0


def kernel_modules() -> list[str]:
    """Names of recon's modules that define numba kernels (by their source text, not imported)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]  # the recon_cli package
    mods = []
    for f in sorted(root.rglob("*.py")):
        if re.search(r"^@njit", f.read_text(encoding="utf-8"), re.M):
            rel = f.relative_to(root.parent).with_suffix("")
            mods.append(".".join(rel.parts))
    return mods


def _library_only(mesh_path: str) -> None:
    """Kernels that only the library API reaches (no command)."""
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.ply import read_ply
    from recon_cli.mesh.topology import Connectivity
    from recon_cli.mesh.winding import winding_number

    mesh = read_ply(mesh_path)
    assert isinstance(mesh, TriangleMesh)  # the warm-up's own mesh file
    winding_number(mesh.vertices, mesh.faces, np.zeros((2, 3)), method="exact")
    _ = Connectivity(mesh.faces).vertex_faces  # the property runs its kernel


def recon(*args: str) -> Step:
    """A step running ``recon ARGS`` in this process, quiet, its reports dropped.

    It is named by its command line (paths by their file names).
    """

    def run() -> Any:
        from recon_cli.cli.main import cli

        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            return cli.main(args=["-q", *args], prog_name="recon", standalone_mode=False)

    name = " ".join(os.path.basename(a) if os.sep in a else a for a in args)
    return f"recon {name}", run


@dataclass(frozen=True)
class Phase:
    name: str
    weight: float  # its share of the warm-up's compile time: the costliest are started first
    steps: Callable[[Files], list[Step]]


PHASES: dict[str, Phase] = {}


def phase(weight: float) -> Callable[[Callable[[Files], list[Step]]], Callable]:
    """Declare a phase: a function of the :class:`Files` returning its steps.

    The steps run in order in one worker. ``weight`` orders the phases (the costliest first); any
    rough figure will do.
    """

    def declare(fn: Callable[[Files], list[Step]]) -> Callable[[Files], list[Step]]:
        name = fn.__name__.lstrip("_")
        PHASES[name] = Phase(name, weight, fn)
        return fn

    return declare


def all_phases() -> dict[str, Phase]:
    """:data:`PHASES` and a phase per stage whose package declares ``WARMUP`` (added once)."""
    import importlib

    from recon_cli.stages import STAGES

    for stage, where in list(STAGES.items()):
        module = where.partition(":")[0] if isinstance(where, str) else ""
        if not module or module.startswith("<") or f"stage-{stage}" in PHASES:
            continue
        runs = getattr(importlib.import_module(module), "WARMUP", None)
        if runs:
            PHASES[f"stage-{stage}"] = Phase(f"stage-{stage}", 5.0, _stage_steps(stage, runs))
    return PHASES


def _stage_steps(stage: str, runs: tuple[tuple[str, ...], ...]) -> Callable[[Files], list[Step]]:
    return lambda f: [recon(stage, getattr(f, src), f.out(), *opts) for src, *opts in runs]


@phase(weight=9)
def _ply(f: Files) -> list[Step]:
    from recon_cli.io.ply import compile_ply_kernels

    steps: list[Step] = [("ply field types", compile_ply_kernels)]
    for src in (f.c32, f.c64, f.mixed):
        steps += [
            recon("convert", src, f.out("be.ply"), "--big-endian"),
            recon("info", f.out("be.ply")),
            recon("convert", src, f.out("ascii.ply"), "--ascii"),
            recon("info", f.out("ascii.ply")),
        ]
    return steps


@phase(weight=3)
def _normals(f: Files) -> list[Step]:
    steps = []
    for src in (f.bare32, f.bare64):
        steps += [
            recon("normals", src, f.out(), "--orient", "mst"),
            recon("normals", src, f.out(), "--orient", "camera", "--camera", "0,0,5"),
            recon("normals", src, f.out(), "--orient", "direction", "--direction", "0,0,1"),
            recon("normals", src, f.out(), "--orient", "none"),
            recon("normals", src, f.out(), "--knn", "0", "--radius", "0.2", "--curvature"),
            recon("normals", src, f.out(), "--radius", "0.2"),
        ]
    return steps + [
        recon("normals", f.c32, f.out(), "--orient", "keep"),
        recon("normals", f.degenerate, f.out()),
        recon("normals", f.organized, f.out(), "--orient", "camera"),
        recon("normals", f.organized, f.out(), "--neighbours", "pixels", "--radius", "0.5"),
    ]


@phase(weight=4)
def _filter(f: Files) -> list[Step]:
    every = ["--crop", "-2,-2,-2,2,2,2", "--classes", "ground,building", "--returns", "last"]
    every += ["--radius-outliers", "0.3,2", "--outliers", "10,2", "--voxel", "0.2"]
    # box_codes reads the points in place: records (c32, c64) and contiguous rows (bare32, bare64)
    return (
        [recon("filter", f.classified, f.out(), *every)]
        + [
            recon("filter", src, f.out(), "--outliers", "10,2", "--voxel", "0.2")
            for src in (f.c32, f.c64)
        ]
        + [
            recon("filter", src, f.out(), "--crop", "-2,-2,-2,2,2,2")
            for src in (f.bare32, f.bare64)
        ]
    )


@phase(weight=50)
def _poisson(f: Files) -> list[Step]:
    """Degree 2, the default basis."""
    steps = []
    for src in (f.c32, f.c64):
        steps += [
            recon("poisson", src, f.out(), "--depth", "5"),
            recon(
                "poisson",
                src,
                f.out(),
                "--depth",
                "5",
                "--density",
                "--trim",
                "0.1",
                "--boundary",
                "dirichlet",
            ),
        ]
    return steps + [
        recon("poisson", f.c32, f.out(), "--depth", "7", "--degree", "2"),  # adaptive levels
        recon("poisson", f.dense, f.out(), "--depth", "7", "--degree", "2"),  # past the full depth
        recon("poisson", f.c32, f.out(), "--depth", "5", "--degree", "2", "--point-weight", "0"),
        recon("poisson", f.bare32, f.out(), "--depth", "5", "--estimate-normals"),
    ]


@phase(weight=15)
def _slabs(f: Files) -> list[Step]:
    """Poisson and normals in slabs in this process (out of core), from files by chunks."""
    return [
        recon("poisson", f.dense, f.out(), "--depth", "7", "--partitions", "2", "--density",
              "--trim", "0.1"),
        recon("poisson", f.half_codes, f.out(), "--depth", "7", "--partitions", "3"),
        recon("normals", f.bare32, f.out(), "--partitions", "2"),
        recon("normals", f.bare64, f.out(), "--partitions", "2", "--orient", "camera",
              "--camera", "0,0,5"),
    ]  # fmt: skip


@phase(weight=10)
def _poisson_features(f: Files) -> list[Step]:
    """Free boundary, envelope, confidence, the grid and attribute votes."""
    return [
        recon(
            "poisson",
            f.half_codes,
            f.out(),
            "--depth",
            "6",
            "--boundary",
            "free",
            "--confidence",
            "--envelope",
            f.envelope,
            "--grid",
            f.out("poisson_grid.npz"),
        )
    ]


@phase(weight=25)
def _poisson_leaves(f: Files) -> list[Step]:
    """An open scan: coarse leaves hold surface, so Poisson extracts at the leaves' size."""
    return [recon("poisson", f.half, f.out(), "--depth", "7")]


@phase(weight=12)
def _poisson_degree1(f: Files) -> list[Step]:
    steps = []
    for src in (f.c32, f.c64):
        steps += [
            recon("poisson", src, f.out(), "--depth", "5", "--degree", "1"),
            recon(
                "poisson",
                src,
                f.out(),
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
        ]
    return steps + [
        recon("poisson", f.c32, f.out(), "--depth", "7", "--degree", "1"),
        recon("poisson", f.dense, f.out(), "--depth", "7", "--degree", "1"),
    ]


@phase(weight=20)
def _ballpivot(f: Files) -> list[Step]:
    return [recon("ballpivot", src, f.out()) for src in (f.c32, f.c64)]


@phase(weight=30)
def _sdf_mcubes(f: Files) -> list[Step]:
    """Grids from meshes and clouds, and marching cubes on them."""
    grids = {"mesh": f.out("mesh.npz"), "cloud": f.out("cloud.npz")}
    steps = [recon("sdf", src, grids["cloud"], "--resolution", "16") for src in (f.c32, f.c64)]
    for src in (f.m32, f.m64, f.open):
        steps += [
            recon("sdf", src, grids["mesh"], "--resolution", "16"),
            recon(
                "sdf",
                src,
                grids["mesh"],
                "--resolution",
                "16",
                "--sign",
                "pseudonormal",
                "--band",
                "2",
            ),
        ]
    for grid in grids.values():
        steps += [
            recon("info", grid),
            recon("mcubes", grid, f.out()),
            recon("mcubes", grid, f.out(), "--method", "mt", "--allow-degenerate"),
        ]
    return steps


@phase(weight=15)
def _mesh_tools(f: Files) -> list[Step]:
    return [
        recon("simplify", f.m32, f.out(), "--ratio", "0.3"),
        recon("simplify", f.open, f.out(), "--faces", "21"),
        recon("tiles", f.m64, f.out("tiles"), "--tile-faces", "64"),  # simplify, distances, GLB
    ]


@phase(weight=6)
def _repair(f: Files) -> list[Step]:
    steps = []
    for src in (f.m32, f.m64, f.open):
        steps += [
            recon("info", src),
            recon("repair", src, f.out()),
            recon(
                "repair",
                src,
                f.out(),
                "--merge-tolerance",
                "1e-6",
                "--fill-holes",
                "100",
                "--min-component",
                "0.1",
                "--keep-largest",
            ),
        ]
    return steps + [recon("repair", f.mixed, f.out()), recon("repair", f.fin, f.out())]


@phase(weight=45)
def _obj(f: Files) -> list[Step]:
    steps = []
    for src in (f.c32, f.c64, f.m32, f.m64):
        dst = f.out(os.path.basename(src)[:-4] + ".obj")
        steps += [recon("convert", src, dst), recon("info", dst)]
    return steps


@phase(weight=16)
def _formats(f: Files) -> list[Step]:
    """Every other file format, both ways, from float32 and float64 sources."""
    steps = []
    for src, suffixes in (
        (f.c32, ("xyz", "csv", "pcd", "glb")),
        (f.c64, ("xyz", "csv", "pcd", "glb")),
        (f.m32, ("off", "stl", "glb", "gltf")),
        (f.m64, ("off", "stl", "glb", "gltf")),
    ):
        for suffix in suffixes:
            dst = f.out(f"{os.path.basename(src)[:-4]}.{suffix}")
            steps += [recon("convert", src, dst), recon("info", dst)]
    for src in (f.c32, f.c64):
        for mode in ("ascii", "binary", "binary_compressed"):
            dst = f.out(f"{os.path.basename(src)[:-4]}_{mode}.pcd")
            steps += [(f"write pcd {mode}", _pcd(src, dst, mode)), recon("info", dst)]
    return steps + [
        recon("convert", f.m32, f.out("ascii.stl"), "--ascii"),
        recon("info", f.out("ascii.stl")),
    ]


@phase(weight=6)
def _diff(f: Files) -> list[Step]:
    views = ["--view", "iso", "--view", "top"]
    return [
        recon(
            "diff",
            f.m32,
            f.open,
            "--samples",
            "2000",
            "--heatmap",
            f.out("heat.ply"),
            "--png",
            f.out("diff.png"),
            *views,
        ),
        recon("diff", "--ref", f.m64, f.c32, f.m32, "--samples", "2000"),
        recon("diff", f.c32, f.m32, "--samples", "2000", "--png", f.out("cloud.png")),
    ]


@phase(weight=1)
def _library(f: Files) -> list[Step]:
    """Kernels that only the library API reaches (no command)."""
    return [("library only", lambda: _library_only(f.m64))]


def _pcd(src: str, dst: str, mode: str) -> Callable[[], Any]:
    def run() -> None:
        from recon_cli.io.load import load
        from recon_cli.io.pcd import write_pcd

        write_pcd(load(src), dst, data=mode)

    return run


def warmup(
    progress: Any = None, log: Callable[[str], None] | None = None, jobs: int | None = None
) -> dict:
    """Run every kernel once on tiny inputs, then build the ahead-of-time kernels.

    Numba compiles (or loads) each kernel as its step runs.

    Parameters
    ----------
    progress : Progress or None
        Shows one bar over the steps and the ahead-of-time jobs.
    log : callable or None
        Called with one line per step that failed (a step's failure does not stop the others).
    jobs : int or None
        Worker processes (default: the cores this process may use); 1 runs everything here.

    Returns
    -------
    dict
        ``steps`` (count), ``failed`` (list of step names), ``seconds``, ``jobs``, ``phases``
        (``{"seconds", "cpu"}`` of each: wall and CPU), ``cache_dir``, ``uncompiled``
        (kernels never compiled, see :func:`uncompiled_kernels`), ``bytecode`` (every
        module's ``.pyc`` written, see :func:`compile_bytecode`) and the ahead-of-time
        build's ``aot_*``.

    """
    from recon_cli._kernels.numba_setup import CACHE_DIR
    from recon_cli.progress import task

    t0 = time.perf_counter()
    jobs = max(1, jobs or usable_cores())
    with tempfile.TemporaryDirectory(prefix="recon-warmup-") as tmp:
        make_inputs(tmp)
        order = sorted(all_phases().values(), key=lambda ph: -ph.weight)
        counts = {ph.name: len(ph.steps(Files(tmp, tmp))) for ph in order}
        total = sum(counts.values()) + len(_aot_modules()) + 1
        with task(progress, "warming up kernels", total) as t:
            run = _run_here if jobs == 1 else _run_in_workers
            result = run(tmp, order, jobs, t.advance, _failure_log(log), log)
            ahead = result.pop("ahead")
    failed = [name for name, _ in result["failed"]]
    return {
        "steps": sum(counts.values()),
        "failed": failed,
        "seconds": time.perf_counter() - t0,
        "jobs": jobs,
        "phases": result["phases"],
        "cache_dir": CACHE_DIR,
        "uncompiled": result["uncompiled"],
        "bytecode": result["bytecode"],
        "aot_built": ahead["built"],
        "aot_dir": ahead["dir"] if ahead["built"] else None,
        "aot_modules": ahead["modules"],
        "aot_reason": ahead["reason"],
    }


def usable_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _failure_log(log: Callable[[str], None] | None) -> Callable[[tuple[str, str]], None]:
    def failed(step: tuple[str, str]) -> None:
        if log is not None:
            log(f"warm-up step {step[0]!r} failed: {step[1]}")

    return failed


def _aot_modules() -> tuple[str, ...]:
    from recon_cli.aot.build import modules_to_build

    return modules_to_build()


def run_phase(name: str, root: str, tick: Callable[[int], Any] | None = None) -> dict:
    """Run phase ``name``'s steps in order; a step's failure is noted and the others run.

    Returns ``{"phase", "failed": [(step, message)], "seconds", "sigs"}``, ``sigs`` the variants
    the ahead-of-time modules' kernels hold in this process so far.
    """
    from recon_cli.aot.build import signatures

    t0, c0 = time.perf_counter(), time.process_time()
    own = os.path.join(root, "phase-" + name)
    os.makedirs(own, exist_ok=True)
    failed = []
    for step, fn in all_phases()[name].steps(Files(root, own)):
        try:
            fn()
        except Exception as exc:  # noqa: BLE001  (report, go on: the other kernels still compile)
            failed.append((step, f"{type(exc).__name__}: {exc}"))
        if tick is not None:
            tick(1)
    sigs = {m: signatures(m) for m in _aot_modules() if m in sys.modules}
    return {
        "phase": name,
        "failed": failed,
        "seconds": round(time.perf_counter() - t0, 2),
        "cpu": round(time.process_time() - c0, 2),
        "sigs": sigs,
    }


def _run_here(
    root: str,
    order: list[Phase],
    jobs: int,
    tick: Callable[[int], Any],
    failed_step: Callable[[tuple[str, str]], None],
    log: Callable[[str], None] | None = None,
) -> dict:
    """Every phase in this process, then the ahead-of-time build from its kernels."""
    phases, failed = {}, []
    bytecode = compile_bytecode()
    with _jit_only():
        for ph in order:
            r = run_phase(ph.name, root, tick)
            phases[ph.name] = {"seconds": r["seconds"], "cpu": r["cpu"]}
            failed += r["failed"]
            for step in r["failed"]:
                failed_step(step)
    ahead = build_ahead_of_time(log=log, done=lambda: tick(1))
    tick(len(_aot_modules()) + 1 - ahead.get("jobs", 0))
    return {
        "phases": phases,
        "failed": failed,
        "bytecode": bytecode,
        "ahead": ahead,
        "uncompiled": uncompiled_kernels(),
    }


# set in each worker process by _worker_init: where it reports finished steps
_worker: dict[str, Any] = {}


def _worker_init(queue: Any, lock_dir: str) -> None:
    os.environ["RECON_AOT"] = "0"  # the steps run the numba kernels themselves, as _jit_only
    _worker["queue"] = queue
    serialize_kernel_compiles(lock_dir)


def _worker_phase(name: str, root: str) -> dict:
    return run_phase(name, root, tick=_worker["queue"].put)


def _run_in_workers(
    root: str,
    order: list[Phase],
    jobs: int,
    tick: Callable[[int], Any],
    failed_step: Callable[[tuple[str, str]], None],
    log: Callable[[str], None] | None = None,
) -> dict:
    """The phases in ``jobs`` worker processes, then the ahead-of-time jobs in the same workers.

    The costliest phases start first, each on the next free worker.
    """
    import multiprocessing
    import queue as queue_mod
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = multiprocessing.get_context("spawn")  # no fork of a process that loaded LLVM
    q = ctx.Queue()
    lock_dir = os.path.join(root, "locks")
    os.makedirs(lock_dir)
    phases: dict[str, dict] = {}
    failed: list[tuple[str, str]] = []
    sigs: dict[str, dict[str, list]] = {}

    def drain() -> None:
        while True:
            try:
                tick(q.get_nowait())
            except queue_mod.Empty:
                return

    workers = min(jobs, len(order))
    with (
        ProcessPoolExecutor(
            workers, mp_context=ctx, initializer=_worker_init, initargs=(q, lock_dir)
        ) as pool,
        _stopping_workers(pool),
    ):
        pending = {pool.submit(_worker_phase, ph.name, root): ph.name for ph in order}
        bytecode = compile_bytecode()  # here, while the workers start
        while pending:
            done, _ = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            drain()
            for fut in done:
                name = pending.pop(fut)
                try:
                    r = fut.result()
                except Exception as exc:  # noqa: BLE001  (a worker died: its phase's steps failed)
                    r = {
                        "seconds": 0.0,
                        "cpu": 0.0,
                        "failed": [(f"phase {name}", f"{type(exc).__name__}: {exc}")],
                        "sigs": {},
                    }
                phases[name] = {"seconds": r["seconds"], "cpu": r["cpu"]}
                failed += r["failed"]
                for step in r["failed"]:
                    failed_step(step)
                for module, kernels_ in r["sigs"].items():
                    for kernel, variants in kernels_.items():
                        sigs.setdefault(module, {}).setdefault(kernel, []).extend(variants)
        # the cache is complete now: a worker checks it while the others build
        try:
            uncompiled = pool.submit(uncompiled_kernels)
        except RuntimeError:  # the pool is broken (a worker died): checked here below
            uncompiled = None
        ahead = build_ahead_of_time(log=log, sigs=sigs, submit=pool.submit, done=lambda: tick(1))
        drain()
        try:
            unreached = uncompiled.result() if uncompiled is not None else uncompiled_kernels()
        except RuntimeError:
            unreached = uncompiled_kernels()
    tick(len(_aot_modules()) + 1 - ahead.get("jobs", 0))
    return {
        "phases": phases,
        "failed": failed,
        "bytecode": bytecode,
        "ahead": ahead,
        "uncompiled": unreached,
    }


@contextlib.contextmanager
def _stopping_workers(pool: Any):
    """On an interruption, drop the queued phases and end the workers at once.

    Ctrl-C, or SIGTERM as recon's handlers raise it: the workers are not left to finish their
    compiles.
    """
    import multiprocessing

    try:
        yield
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in multiprocessing.active_children():
            proc.terminate()
        raise


def serialize_kernel_compiles(lock_dir: str) -> None:
    """Compile or load each cached kernel under a file lock of that kernel in ``lock_dir``.

    The lock is shared by the warm-up's workers: a worker that needs a kernel another one is
    compiling waits, then loads it from the cache, instead of compiling it too (and no two
    processes rewrite one kernel's cache index at once, where one's variant could be lost). A
    kernel's callees take their own locks; a lock not had within :data:`LOCK_WAIT_S` is done
    without.
    """
    import fcntl
    import hashlib

    from numba.core import sigutils
    from numba.core.dispatcher import Dispatcher

    full = Dispatcher.compile
    if getattr(full, "recon_serialized", False):
        return
    held: set[str] = set()

    def compile(self, sig):
        index = getattr(getattr(self._cache, "_cache_file", None), "_index_path", None)
        if index is None or index in held:
            return full(self, sig)
        if tuple(sigutils.normalize_signature(sig)[0]) in self.overloads:
            return full(self, sig)
        name = hashlib.blake2b(index.encode(), digest_size=8).hexdigest()
        with open(os.path.join(lock_dir, name), "w") as fh:
            deadline = time.monotonic() + LOCK_WAIT_S
            while True:
                try:
                    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        break
                    time.sleep(0.02)
            held.add(index)
            try:
                return full(self, sig)
            finally:
                held.discard(index)  # the lock goes with the file's closing

    compile.recon_serialized = True  # type: ignore[attr-defined]
    Dispatcher.compile = compile  # type: ignore[method-assign]  # numba's, wrapped for the run


@contextlib.contextmanager
def _jit_only():
    """Make the warm-up's steps run the numba kernels, not an ahead-of-time build.

    A build would leave the kernels uncompiled, and it exports the signatures they compiled.
    """
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


def build_ahead_of_time(
    progress: Any = None,
    log: Callable[[str], None] | None = None,
    sigs: dict | None = None,
    submit: Callable[..., Any] | None = None,
    done: Callable[[], None] | None = None,
) -> dict:
    """Build the ahead-of-time kernels and the signal handler (:mod:`recon_cli.aot.build`).

    From the variants ``sigs`` (default: those the kernels hold in this process), the jobs through
    ``submit`` when given; one line through ``log`` saying what came of it. ``jobs`` in the
    result: how many jobs ran (each called ``done``).
    """
    from recon_cli.aot.build import build
    from recon_cli.cli._signals import HANDLER_C
    from recon_cli.progress import task

    ran = [0]

    def job_done() -> None:
        ran[0] += 1
        if done is not None:
            done()

    with task(progress, "compiling kernels ahead of time", 1) as t:
        out = build(
            c_libraries={"signal_handler": HANDLER_C},
            log=log,
            sigs=sigs,
            submit=submit,
            done=job_done,
        )
        t.advance(1)
    out["jobs"] = ran[0]
    _log_ahead(out, log)
    return out


def _log_ahead(out: dict, log: Callable[[str], None] | None) -> None:
    """One line saying what came of the ahead-of-time build."""
    if log is not None:
        if out["built"]:
            modules = ", ".join(out["modules"])
            log(f"ahead-of-time kernels: {out['reason'] or 'built'} ({modules}) in {out['dir']}")
        else:
            log(
                f"ahead-of-time kernels not built ({out['reason']}): ball pivoting and marching "
                "cubes run JIT, with numba's start-up in each command"
            )


def compile_bytecode() -> bool:
    """Write the ``.pyc`` of every module of the package (``compileall``).

    So no command compiles Python source either: an editable install (``make install``) or an
    environment with ``PYTHONDONTWRITEBYTECODE`` set would otherwise compile every recon module it
    imports in every process. False when some file could not be written (a read-only install:
    pip wrote its ``.pyc`` files already).
    """
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
