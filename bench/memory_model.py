"""Each stage's predicted peak memory against the peak it reaches: the figures of ``memory_model``.

``python bench/memory_model.py [--quick] [STAGE ...]``: noisy armadillo samples (0.25 % of the
diagonal, true normals, ``sample_surface``) of 250k to 10M points, a midpoint-subdivided
armadillo mesh for the mesh stages, SDF grids for ``mcubes``; each run is ``recon STAGE IN OUT
ARGS --json`` as a process, whose report gives ``memory.predicted_bytes`` and
``memory.peak_bytes``. Prints one JSON line a run (MiB, peak / predicted) and a Markdown table
at the end (``bench/calibration.md``, "Memory model"). ``--quick``: the runs of 1M points and
less. The issue's target: every process's peak within 1/1.5 to 1.5 times its prediction
(``ratio``: the process's peak over the prediction).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))
MIB = 1 << 20

# (stage, input, args, quick): inputs "cloud:N", "mesh:LEVELS" (subdivisions of the armadillo:
# 4**LEVELS * 50k faces) or "grid:RES" (recon sdf of the 1M cloud at that resolution)
CASES: list[tuple[str, str, list[str], bool]] = [
    ("poisson", "cloud:1000000", ["--depth", "8"], True),
    ("poisson", "cloud:1000000", ["--depth", "9"], True),
    ("poisson", "cloud:1000000", ["--depth", "10"], False),
    ("poisson", "cloud:1000000", ["--depth", "8", "--partitions", "3"], True),
    ("poisson", "cloud:1000000", ["--depth", "9", "--partitions", "2"], True),
    ("poisson", "cloud:1000000", ["--depth", "9", "--partitions", "4"], True),
    ("poisson", "cloud:1000000", ["--depth", "10", "--partitions", "4"], False),
    ("poisson", "cloud:4000000", ["--depth", "9", "--partitions", "3"], False),
    ("poisson", "cloud:10000000", ["--depth", "10"], False),
    ("normals", "cloud:1000000", [], True),
    ("normals", "cloud:1000000", ["--knn", "60"], True),
    ("normals", "cloud:4000000", [], False),
    ("ballpivot", "cloud:250000", [], True),
    ("ballpivot", "cloud:500000", [], True),
    ("ballpivot", "cloud:1000000", [], True),
    ("ballpivot", "cloud:2000000", [], False),
    ("sdf", "cloud:250000", [], True),
    ("sdf", "cloud:1000000", [], True),
    ("sdf", "cloud:1000000", ["--resolution", "256"], False),
    ("sdf", "mesh:2", [], True),
    ("mcubes", "grid:128", [], True),
    ("simplify", "mesh:2", [], True),
    ("repair", "mesh:2", [], True),
    ("smooth", "mesh:2", [], True),
    ("filter", "cloud:1000000", ["--outliers", "16,2"], True),
    ("filter", "cloud:1000000", ["--voxel", "0.5"], True),
    ("filter", "cloud:10000000", ["--voxel", "0.5"], False),
    ("fit-sdf", "cloud:250000", ["--iterations", "30"], True),
    ("fit-sdf", "cloud:250000", ["--iterations", "30", "--resolution", "64"], True),
    ("fit-sdf", "cloud:1000000", ["--iterations", "30"], True),
]


def subdivided(levels: int):
    """The armadillo with every triangle cut in four ``levels`` times (shared midpoints)."""
    import numpy as np

    from recon_cli.geometry import TriangleMesh
    from recon_cli.io.ply import read_ply

    mesh = read_ply(SHARED / "armadillo.ply")
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    for _ in range(levels):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        mid = len(v) + inv.reshape(3, -1).T  # (faces, 3): the midpoints of edges 01, 12, 20
        v = np.concatenate([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
        a, b, c = f.T
        ab, bc, ca = mid.T
        f = np.concatenate(
            [np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
        )
    return TriangleMesh(vertices=v, faces=f)


def make_input(kind: str, folder: str) -> str:
    """The input file of ``kind`` in ``folder`` (made once)."""
    what, _, n = kind.partition(":")
    path = os.path.join(folder, f"{what}_{n}.{'npz' if what == 'grid' else 'ply'}")
    if os.path.exists(path):
        return path
    from recon_cli.io.load import save

    if what == "cloud":
        from recon_cli.io.ply import read_ply
        from recon_cli.mesh.sampling import sample_surface

        mesh = read_ply(SHARED / "armadillo.ply")
        save(sample_surface(mesh, int(n), seed=0, noise=0.0025), path)
    elif what == "mesh":
        save(subdivided(int(n)), path)
    else:
        src = make_input("cloud:1000000", folder)
        run("sdf", src, path, ["--resolution", n])
    return path


def sampled_peak(proc: subprocess.Popen, every: float = 0.01) -> int:
    """The largest resident memory of ``proc`` sampled every ``every`` seconds until it ends.

    Neither the report's peak (reset as the stage starts) nor ``wait4``'s ``ru_maxrss`` (which
    keeps the parent's high-water mark across the child's exec) sees the whole process alone.
    """
    peak = 0
    while proc.poll() is None:
        try:
            with open(f"/proc/{proc.pid}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        peak = max(peak, int(line.split()[1]) * 1024)
        except (OSError, ValueError):
            pass
        time.sleep(every)
    return peak


def run(stage: str, src: str, out: str, args: list[str]) -> dict:
    """``recon STAGE src out args --json`` as a process: its report, its peak and CPU seconds.

    ``rss_bytes``: the larger of the report's peak (the stage and the write) and the process's
    resident memory sampled while it runs (:func:`sampled_peak`: reading IN too).
    """
    cmd = [sys.executable, "-m", "recon_cli.cli.main", stage, src, out, *args, "--json", "-q"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se:
        proc = subprocess.Popen(cmd, stdout=so, stderr=se, text=True)
        sampled = sampled_peak(proc)
        so.seek(0)
        se.seek(0)
        if proc.returncode:
            sys.exit(f"recon {stage} {src} {' '.join(args)}: {se.read().strip()}")
        rep = json.loads(so.read())
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    rep["rss_bytes"] = max(sampled, rep["memory"]["peak_bytes"])
    cpu = ("ru_utime", "ru_stime")
    rep["cpu_seconds"] = sum(getattr(after, k) - getattr(before, k) for k in cpu)
    return rep


def main(argv: list[str]) -> list[dict]:
    """Run each stage's case as a process and tabulate predicted against measured memory.

    ``--quick`` keeps the quick cases; other arguments name the stages to run. Prints a JSON line
    per case and a markdown table; returns the rows.
    """
    quick = "--quick" in argv
    stages = [a for a in argv if not a.startswith("--")]
    rows = []
    folder = os.environ.get("RECON_MEMORY_BENCH_DIR") or tempfile.mkdtemp(prefix="memory-model-")
    for stage, kind, args, is_quick in CASES:
        if (quick and not is_quick) or (stages and stage not in stages):
            continue
        src = make_input(kind, folder)
        out = os.path.join(folder, "out." + ("npz" if stage in ("sdf", "fit-sdf") else "ply"))
        t0 = time.perf_counter()
        rep = run(stage, src, out, args)
        mem = rep["memory"]
        row = {
            "stage": stage,
            "input": kind,
            "args": " ".join(args),
            "predicted_mib": round(mem["predicted_bytes"] / MIB),
            "peak_mib": round(mem["peak_bytes"] / MIB),
            "rss_mib": round(rep["rss_bytes"] / MIB),
            "ratio": round(rep["rss_bytes"] / mem["predicted_bytes"], 2),
            "slabs": (rep.get("distributed") or {}).get("partitions", {}).get("count", 1),
            "wall_s": round(time.perf_counter() - t0),
            "cpu_s": round(rep["cpu_seconds"]),
        }
        print(json.dumps(row), flush=True)
        rows.append(row)
    head = "| stage | input | args | slabs | predicted | report's peak | process | ratio | wall |"
    print("\n" + head)
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['stage']} | {r['input']} | {r['args']} | {r['slabs']} | "
            f"{r['predicted_mib']} MiB | {r['peak_mib']} MiB | {r['rss_mib']} MiB | "
            f"{r['ratio']} | {r['wall_s']} s |"
        )
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
