"""The command line as a user waits for it: each stage's command as a process, cold and warm.

Per row: ``cold`` is the wall time of the command with an empty numba cache (it compiles
what it needs: what a user saw before ``recon warmup`` existed), ``warm`` the wall time once
the cache holds the kernels (``make install`` runs ``recon warmup``; median of repeats),
``floor`` numba's own floor (a fresh process that imports numba and calls one cached kernel,
numba as it comes), ``lean floor`` the same process with what recon's own process does around
a command (recon_cli/cli/_process.py: OpenBLAS single-threaded, the collector paused during
start-up and frozen at exit; numba_setup's cache loads without numba's registries): the least a
recon process using numba's cache can cost. ``stage`` is the stage's in-process time from the
command's ``--json`` report, and ``read`` its input reading time. ``warm - floor`` is what
recon adds to numba's floor, ``warm - lean`` what the command costs beyond the lean floor.
With ``RECON_BENCH_CPU=1`` the process and reference figures are CPU seconds (user + system,
all threads; the ``stage``/``read`` columns stay the report's wall times): on a loaded
shared machine wall time mostly measures the other users. ``RECON_BENCH_CLI_ONLY=mcubes,ballpivot``
runs those commands' rows only.

Targets (issue 17): after ``make install`` the first run of ``recon normals`` on the
sample scan takes <= 1.5x the second (``first/warm``); warm on small inputs (1k points, a
70k-face mesh for ``recon info``) <= 0.5 s above the floor; ``recon mcubes`` 256^3:
(warm - floor - read) <= 0.5x scikit-image's in-process ``marching_cubes``; ``recon
ballpivot`` warm <= 1.0x Open3D's in-process ball pivoting (``ref s`` holds the reference's
in-process time where there is one).

The ballpivot rows and the mcubes 256^3 row time our command as a process and the reference in
this process back to back, alternating (``2 * repeat + 1`` rounds), and give medians of both CPU
and wall seconds in the note. With the ahead-of-time kernels ``recon warmup`` builds
(recon_cli/aot), those commands never import numba: the mcubes note also gives the figure
against a python + numpy floor and the whole process against scikit-image.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
RECON = [sys.executable, "-m", "recon_cli.cli.main"]

COLUMNS = [
    ("stage", "command"),
    ("case", "input"),
    ("cold_s", "cold s"),
    ("first_s", "first after warmup s"),
    ("warm_s", "warm s"),
    ("floor_s", "numba floor s"),
    ("above_s", "warm - floor s"),
    ("lean_s", "lean floor s"),
    ("above_lean_s", "warm - lean s"),
    ("stage_s", "stage in-process s"),
    ("read_s", "read s"),
    ("ref", "reference"),
    ("ref_s", "ref in-process s"),
    ("ratio", "ratio"),
    ("note", "note"),
]

# RECON_BENCH_CPU=1: every figure is CPU seconds (user + system, all threads) instead of wall
# seconds; on a shared, overloaded machine wall times mostly measure the other users
CPU_TIME = os.environ.get("RECON_BENCH_CPU") == "1"

# numba's own floor: a throwaway module with one cached kernel (numba as it comes, its own
# cache directory), imported and called by a fresh process
FLOOR_MODULE = (
    "import numpy as np\n"
    "from numba import njit\n"
    "@njit(cache=True)\n"
    "def grow(x, cap):\n"
    "    y = np.empty(cap, x.dtype)\n"
    "    y[: x.shape[0]] = x\n"
    "    return y\n"
)
FLOOR = "import numpy as np, floor_kernel\nfloor_kernel.grow(np.zeros(2), 4)\n"
# the same with recon's process settings (cli/_process.py) and cache loads (numba_setup)
LEAN_FLOOR = (
    "import gc, os\n"
    "os.environ.setdefault('OPENBLAS_NUM_THREADS', '1'); gc.disable()\n"
    "import numpy as np\n"
    "from recon_cli._kernels.arrays import grow1\n"
    "grow1(np.zeros(2), 4)\n"
    "gc.freeze()\n"
)


def _cpu_children() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _wall(args: list[str], env: dict | None = None) -> tuple[float, str]:
    """Wall time of the process (CPU time when CPU_TIME is set) and its stdout.

    CPU time is user + system of the children.
    """
    c0 = _cpu_children()
    t = time.perf_counter()
    r = subprocess.run(args, env=env, capture_output=True, text=True, cwd=ROOT)
    dt = time.perf_counter() - t
    cpu = _cpu_children() - c0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(args[3:])}: exit {r.returncode}: {r.stderr.strip()[-400:]}")
    return (cpu if CPU_TIME else dt), r.stdout


def _clock() -> float:
    return time.process_time() if CPU_TIME else time.perf_counter()


def floor(repeat: int, tmp: Path) -> tuple[float, float]:
    """Median wall times of numba's floor and of the lean floor (see the module docstring)."""
    (tmp / "floor_kernel.py").write_text(FLOOR_MODULE)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(tmp)
    plain = [sys.executable, "-c", FLOOR]
    lean = [sys.executable, "-c", LEAN_FLOOR]
    _wall(plain, env)  # cached
    _wall(lean)
    a, b = [], []
    for _ in range(repeat):
        a.append(_wall(plain, env)[0])
        b.append(_wall(lean)[0])
    return statistics.median(a), statistics.median(b)


def numpy_floor(repeat: int) -> float:
    """Median cost of a process that imports numpy (OpenBLAS 1-threaded, as recon's) and exits."""
    code = "import os\nos.environ.setdefault('OPENBLAS_NUM_THREADS', '1')\nimport numpy\n"
    return statistics.median(_wall([sys.executable, "-c", code])[0] for _ in range(repeat))


def command(args: list[str], repeat: int, cold: bool) -> dict:
    """Cold, first and warm wall times of ``recon -q ARGS --json``, and its report.

    Cold: an empty cache; warm: the median of ``repeat`` runs.
    """
    out: dict = {}
    if cold:
        with tempfile.TemporaryDirectory(prefix="recon-cold-cache-") as cache:
            out["cold_s"], _ = _wall(
                [*RECON, "-q", *args], env=dict(os.environ, NUMBA_CACHE_DIR=cache)
            )
    runs = []
    for _ in range(repeat + 1):
        dt, stdout = _wall([*RECON, "-q", *args, "--json"])
        runs.append(dt)
    out["first_s"] = runs[0]
    out["warm_s"] = statistics.median(runs[1:])
    report = json.loads(stdout) if stdout.strip() else {}
    timings = report.get("timings", {}) if isinstance(report, dict) else {}
    out["stage_s"] = timings.get("stage", float("nan"))
    out["read_s"] = timings.get("read", float("nan"))
    return out


def _inputs(tmp: Path, quick: bool) -> dict[str, str]:
    from bench_mcubes import metaballs

    from recon_cli.geometry import PointCloud
    from recon_cli.grid import Grid
    from recon_cli.io.npz import write_grid
    from recon_cli.io.ply import write_ply
    from recon_cli.mesh.sampling import sample_surface

    from shared_data import load_shared, shared_path

    p = {
        "scan": str(ROOT / "sample_data" / "bunny_scan_000.ply"),
        "zipper": str(shared_path("bunny_zipper")),
        "kitten": str(shared_path("kitten")),
    }
    small = sample_surface(load_shared("kitten"), 1000, seed=0)
    write_ply(PointCloud(points=small.points), tmp / "k1k.ply")
    p["k1k"] = str(tmp / "k1k.ply")
    n = 20_000 if quick else 100_000
    arm = sample_surface(load_shared("armadillo"), n, seed=0)
    write_ply(arm, tmp / "arm.ply")
    p["arm"] = str(tmp / "arm.ply")
    for size in (64, 256):
        write_grid(
            Grid(sdf=metaballs(size), origin=np.zeros(3), voxel_size=1.0 / size),
            tmp / f"mb{size}.npz",
        )
        p[f"mb{size}"] = str(tmp / f"mb{size}.npz")
    subprocess.run(
        [
            *RECON,
            "-q",
            "normals",
            p["scan"],
            str(tmp / "scan_n.ply"),
            "--orient",
            "camera",
            "--camera",
            "0,0,1",
        ],
        check=True,
        cwd=ROOT,
    )
    p["scan_n"] = str(tmp / "scan_n.ply")
    return p


def _skimage(grid_path: str):
    """One in-process run of scikit-image's ``marching_cubes`` on the grid (warmed up once)."""
    from skimage.measure import marching_cubes

    from recon_cli.io.npz import read_grid

    g = read_grid(grid_path)
    marching_cubes(g.sdf, 0.0)
    return lambda: marching_cubes(g.sdf, 0.0)


def _open3d_bpa(cloud_path: str):
    """One in-process run of Open3D's ball pivoting on the cloud with our automatic radii.

    Warmed up once.
    """
    from recon_cli.backends import open3d_backend
    from recon_cli.io.ply import read_ply
    from recon_cli.stages.ballpivot import auto_radii

    c = read_ply(cloud_path)
    rr = auto_radii(np.asarray(c.points, dtype=np.float64))
    open3d_backend.ball_pivoting(c, rr)
    return lambda: open3d_backend.ball_pivoting(c, rr)


def alternating(args: list[str], reference, rounds: int) -> dict:
    """Our command as a process and the reference in this process, alternated ``rounds`` times.

    The two run back to back each round: medians of CPU seconds (user + system, all threads) and
    wall seconds of each.
    """
    ours_cpu, ours_wall, ref_cpu, ref_wall = [], [], [], []
    report: dict = {}
    for _ in range(rounds):
        c0 = _cpu_children()
        t = time.perf_counter()
        r = subprocess.run(
            [*RECON, "-q", *args, "--json"], capture_output=True, text=True, cwd=ROOT
        )
        ours_wall.append(time.perf_counter() - t)
        ours_cpu.append(_cpu_children() - c0)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(args)}: exit {r.returncode}: {r.stderr.strip()[-400:]}")
        report = json.loads(r.stdout)
        c0, t = time.process_time(), time.perf_counter()
        reference()
        ref_wall.append(time.perf_counter() - t)
        ref_cpu.append(time.process_time() - c0)
    med = statistics.median
    timings = report.get("timings", {})
    return {
        "ours_cpu": med(ours_cpu),
        "ours_wall": med(ours_wall),
        "ref_cpu": med(ref_cpu),
        "ref_wall": med(ref_wall),
        "stage_s": timings.get("stage", float("nan")),
        "read_s": timings.get("read", float("nan")),
    }


def rows(quick: bool) -> list[dict]:
    """The section's rows: each stage's command as a process, cold and warm, and the floors.

    Every command runs as ``recon -q ARGS`` (cold with an empty numba cache, warm with it filled)
    against numba's floor and the lean floor; ballpivot and mcubes 256^3 also against their
    reference in-process (:func:`_against_reference`).
    """
    repeat = 2 if quick else 3
    with tempfile.TemporaryDirectory(prefix="recon-bench-cli-") as tmpd:
        tmp = Path(tmpd)
        p = _inputs(tmp, quick)
        o = str(tmp / "out.ply")
        fl, lean = floor(repeat + 2, tmp)
        cases = [
            (
                "normals",
                "sample scan 40k, --orient camera",
                ["normals", p["scan"], o, "--orient", "camera", "--camera", "0,0,1"],
                True,
            ),
            ("normals", "sample scan 40k, --orient mst", ["normals", p["scan"], o], not quick),
            ("normals", "1k points", ["normals", p["k1k"], o], True),
            ("info", "bunny_zipper (69k faces)", ["info", p["zipper"]], True),
            (
                "poisson",
                "sample scan, --depth 8",
                ["poisson", p["scan_n"], o, "--depth", "8"],
                not quick,
            ),
            (
                "ballpivot",
                "raw sample scan 40k (normals towards the scanner)",
                ["ballpivot", p["scan_n"], o],
                not quick,
            ),
            (
                "ballpivot",
                f"armadillo {'20k' if quick else '100k'} samples",
                ["ballpivot", p["arm"], o],
                False,
            ),
            ("repair", "kitten", ["repair", p["kitten"], o], False),
            (
                "sdf",
                "kitten, --resolution 128",
                ["sdf", p["kitten"], str(tmp / "k.npz")],
                not quick,
            ),
            ("mcubes", "metaballs 64^3", ["mcubes", p["mb64"], o], True),
            ("mcubes", "metaballs 256^3", ["mcubes", p["mb256"], o], False),
        ]
        only = os.environ.get(
            "RECON_BENCH_CLI_ONLY"
        )  # e.g. "mcubes,ballpivot": those commands' rows only
        if only:
            cases = [c for c in cases if c[0] in only.split(",")]
        out = []
        for stage, case, args, cold in cases:
            r = {
                "stage": f"recon {stage}",
                "case": case,
                "floor_s": fl,
                "lean_s": lean,
                "cold_s": float("nan"),
            }
            if stage == "ballpivot" or (stage == "mcubes" and "256" in case):
                try:
                    out.append(
                        _against_reference(r, stage, case, args, p, fl, lean, rounds=2 * repeat + 1)
                    )
                except RuntimeError as exc:
                    r["note"] = f"FAILED: {exc}"
                    out.append(r)
                continue
            try:
                r.update(command(args, repeat, cold))
            except RuntimeError as exc:
                r["note"] = f"FAILED: {exc}"
                out.append(r)
                continue
            r["above_s"] = r["warm_s"] - fl
            r["above_lean_s"] = r["warm_s"] - lean
            notes = []
            if stage == "normals" and "camera" in case:
                notes.append(f"first/warm {r['first_s'] / r['warm_s']:.2f} (target <= 1.5)")
            if case in ("1k points",) or stage == "info":
                notes.append("target warm - floor <= 0.5 s")
            r["note"] = "; ".join(notes)
            out.append(r)
        return out


def _against_reference(
    r: dict, stage: str, case: str, args: list[str], p: dict, fl: float, lean: float, rounds: int
) -> dict:
    """A row of ours as a process against the reference in-process, run alternately.

    The runs alternate (:func:`alternating`): the row's figures are CPU or wall seconds as the rest
    of the table (``RECON_BENCH_CPU``), the note gives both ratios.
    """
    if stage == "mcubes":
        r["ref"], ref = "skimage marching_cubes", _skimage(p["mb256"])
    else:
        r["ref"], ref = (
            "open3d ball pivoting",
            _open3d_bpa(p["scan_n"] if "scan" in case else p["arm"]),
        )
    a = alternating(args, ref, rounds)
    kind = "cpu" if CPU_TIME else "wall"
    r.update(
        warm_s=a[f"ours_{kind}"], ref_s=a[f"ref_{kind}"], stage_s=a["stage_s"], read_s=a["read_s"]
    )
    r["first_s"] = float("nan")
    r["above_s"], r["above_lean_s"] = r["warm_s"] - fl, r["warm_s"] - lean
    notes = [
        f"{rounds} alternating runs; ours {a['ours_cpu']:.3f} CPU s / {a['ours_wall']:.3f} wall s, "
        f"reference {a['ref_cpu']:.3f} CPU s / {a['ref_wall']:.3f} wall s"
    ]
    if stage == "mcubes":
        # the floors are of this table's kind (CPU or wall); the read is the report's wall time
        r["ratio"] = (r["warm_s"] - fl - a["read_s"]) / r["ref_s"]
        notes.append("ratio = (warm - numba floor - read) / skimage, target <= 0.5")
        npf = numpy_floor(5)
        notes.append(
            "a process without numba (ahead-of-time kernels): (warm - python+numpy floor "
            f"{npf:.3f} - read) / "
            f"skimage {(r['warm_s'] - npf - a['read_s']) / r['ref_s']:.2f}, whole process / "
            "skimage "
            f"{r['warm_s'] / r['ref_s']:.2f}"
        )
    else:
        r["ratio"] = r["warm_s"] / r["ref_s"]
        notes.append(
            "ratio = ours as a process / Open3D in-process, target <= 1.0: CPU "
            f"{a['ours_cpu'] / a['ref_cpu']:.2f}, "
            f"wall {a['ours_wall'] / a['ref_wall']:.2f}"
        )
    r["note"] = "; ".join(notes)
    return r


if __name__ == "__main__":
    quick = "--quick" in sys.argv
    for r in rows(quick):
        print(r, flush=True)
