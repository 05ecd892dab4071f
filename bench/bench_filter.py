"""``recon filter`` as a process against Open3D in-process, one operation a row.

Input: area-uniform samples of the armadillo (1M points; 200k with ``--quick``), 0.25 % noise,
1 % of the points replaced by uniform outliers in the box, float64 normals and uint8 colours,
as a binary PLY. Ours: the wall time (and CPU time, user + system of every thread) of
``recon -q filter IN OUT --OP --json``, start-up, reading and writing included: what a user
waits for. Open3D: in this process, ``read_point_cloud(IN)``, the operation and
``write_point_cloud(OUT)`` (its read and write included, as ours are; ``op s`` is the
operation alone). Ours and Open3D alternate, ``2 * repeat + 1`` rounds, medians.

Target (issue 29): every row <= 1.0x Open3D's time. ``points`` compares the counts kept
(ours / Open3D's); the tests check that the kept sets and centroids are Open3D's exactly.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_cli import alternating  # noqa: E402

COLUMNS = [
    ("stage", "command"),
    ("case", "operation"),
    ("ours_s", "ours wall s"),
    ("ours_cpu", "ours CPU s"),
    ("stage_s", "stage s"),
    ("ref", "reference"),
    ("ref_s", "ref wall s"),
    ("ref_cpu", "ref CPU s"),
    ("op_s", "ref op s"),
    ("time_ratio", "wall ours/ref"),
    ("cpu_ratio", "CPU ours/ref"),
    ("note", "note"),
]


def make_input(path: Path, n: int) -> float:
    """Write the benchmark cloud; returns its median nearest-neighbour spacing."""
    from scipy.spatial import cKDTree

    from recon_cli.geometry import PointCloud
    from recon_cli.io.ply import write_ply

    from shared_data import sampled_cloud

    c = sampled_cloud("armadillo", n, 0.0025)
    rng = np.random.default_rng(0)
    pts = np.array(c.points, dtype=np.float64)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    k = n // 100
    pts[rng.choice(n, k, replace=False)] = rng.uniform(lo, hi, (k, 3))
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    write_ply(PointCloud(points=pts, normals=c.normals, colors=colors), path)
    sample = pts[rng.choice(n, 5000, replace=False)]
    d, _ = cKDTree(pts).query(sample, k=2)
    return float(np.median(d[:, 1]))


def operations(pts_lo, pts_hi, spacing: float) -> list[tuple[str, list[str], object]]:
    """(case, our options, the Open3D call on a cloud) per row."""
    import open3d as o3d

    mid, half = (pts_lo + pts_hi) / 2, (pts_hi - pts_lo) / 4
    box = [*(mid - half), *(mid + half)]
    voxel = 2.0 * spacing
    radius = 3.0 * spacing
    aabb = o3d.geometry.AxisAlignedBoundingBox(box[:3], box[3:])
    return [
        ("invalid points (none to drop)", [], lambda pc: pc.remove_non_finite_points()),
        (
            "crop (central half box)",
            ["--crop", ",".join(repr(float(x)) for x in box)],
            lambda pc: pc.crop(aabb),
        ),
        (
            f"voxel {voxel:.3g} (2 spacings)",
            ["--voxel", repr(voxel)],
            lambda pc: pc.voxel_down_sample(voxel),
        ),
        (
            "outliers 20,2",
            ["--outliers", "20,2"],
            lambda pc: pc.remove_statistical_outlier(20, 2.0)[0],
        ),
        (
            f"radius outliers {radius:.3g},4 (3 spacings)",
            ["--radius-outliers", f"{radius!r},4"],
            lambda pc: pc.remove_radius_outlier(4, radius)[0],
        ),
    ]


def _reference(
    o3d: Any, src: Path, dst: Path, op: Callable, op_times: list[float], kept: list[int]
) -> Callable[[], None]:
    """Open3D reads ``src``, runs ``op`` (timed alone into ``op_times``), writes ``dst``."""

    def run() -> None:
        cloud = o3d.io.read_point_cloud(str(src))
        t = time.perf_counter()
        res = op(cloud)
        op_times.append(time.perf_counter() - t)
        kept.append(len(res.points))
        o3d.io.write_point_cloud(str(dst), res)

    return run


def rows(quick: bool) -> list[dict]:
    """The section's rows: each ``recon filter`` operation as a process against Open3D in-process.

    Alternating runs (:func:`alternating`) on a 1M-point cloud (quick: 200k); the note compares the
    points kept.
    """
    import open3d as o3d

    n = 200_000 if quick else 1_000_000
    rounds = 3 if quick else 5
    out = []
    with tempfile.TemporaryDirectory(prefix="recon-bench-filter-") as tmpd:
        tmp = Path(tmpd)
        src, dst, ref_dst = tmp / "in.ply", tmp / "out.ply", tmp / "ref.ply"
        spacing = make_input(src, n)
        pc = o3d.io.read_point_cloud(str(src))
        pts = np.asarray(pc.points)
        for case, args, op in operations(pts.min(axis=0), pts.max(axis=0), spacing):
            op_times: list[float] = []
            kept: list[int] = []
            reference = _reference(o3d, src, ref_dst, op, op_times, kept)
            r = {"stage": "recon filter", "case": f"{case}, {n // 1000}k", "ref": "open3d"}
            try:
                a = alternating(["filter", str(src), str(dst), *args], reference, rounds)
            except RuntimeError as exc:
                r["note"] = f"FAILED: {exc}"
                out.append(r)
                continue
            from recon_cli.io.ply import read_ply

            ours_kept = len(read_ply(dst))
            r.update(
                ours_s=a["ours_wall"],
                ours_cpu=a["ours_cpu"],
                stage_s=a["stage_s"],
                ref_s=a["ref_wall"],
                ref_cpu=a["ref_cpu"],
                op_s=statistics.median(op_times),
            )
            r["time_ratio"] = r["ours_s"] / r["ref_s"]
            r["cpu_ratio"] = r["ours_cpu"] / r["ref_cpu"]
            r["note"] = (
                f"{rounds} alternating rounds; points kept ours {ours_kept}, open3d {kept[-1]}; "
                f"ours / Open3D's operation alone: wall {r['ours_s'] / r['op_s']:.2f}; "
                f"load {os.getloadavg()[0]:.1f}"
            )
            out.append(r)
    return out


if __name__ == "__main__":
    for r in rows("--quick" in sys.argv):
        print(r, flush=True)
