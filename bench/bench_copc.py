"""COPC by region (issue 46): a 1 % window of a large COPC file against the whole file.

The file: ``tests/copc_files.synthetic_records`` (a rolling terrain at 4 points per m², point
format 7, millimetre grid near UTM coordinates), 30M points (``--quick``: 2M), octree root grid
128, written by copc-lib (the ``test`` extra) once into the temporary folder and reused after
(about 10 minutes and 6 GB at 30M; ``python bench/bench_copc.py --file [N]`` only writes it and
prints its path).

Each figure is the median of ``repeat`` runs of the command as a process: wall seconds and the
process's own peak resident memory (``wait4``'s ``ru_maxrss``).

- ours: ``recon filter BIG.copc.laz OUT.ply --crop W``, W a square of 10 % by 10 % of the area
  (all heights: 1 % of the points): only the octree nodes W meets are decoded;
- reference: the same command with ``--input-format las``: the file read whole by the LAS
  reader, then cropped by the filter. The two outputs are checked to be the same file.

The note adds the same command on a 2 m square (a few points): the command's start-up
(interpreter, numpy, numba, laspy, the hierarchy), and the ratios above it, which are what the
reading itself costs. Target (issue 46): ratio <= 0.05 in time and memory, as processes. The
commands import no numba once ``recon warmup`` has built the ahead-of-time kernels (``make
install``, ``make bench``); without that build both pay numba's import (about 65 MB, 0.5 s).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT / "tests"))

from _util import row  # noqa: E402

RECON = [sys.executable, "-m", "recon_cli.cli.main", "-q"]
# bump when tests/copc_files.py changes what it writes: the cached file is then made again
GENERATOR = 1
ROOT_CELLS, MAX_LEVEL = 128, 10
FULL = 30_000_000


def _file(n: int) -> Path:
    """The synthetic COPC file of ``n`` points, written once into the temporary folder."""
    path = Path(tempfile.gettempdir()) / f"recon-bench-copc-g{GENERATOR}-{n}.copc.laz"
    if not path.exists():
        from copc_files import synthetic_records, write_copc

        rec, scales, offsets = synthetic_records(n, seed=0)
        part = path.with_suffix(".part")
        write_copc(part, rec, scales, offsets, 7, root_cells=ROOT_CELLS, max_level=MAX_LEVEL)
        os.replace(part, path)
    return path


def _run(args: list[str], out: Path) -> tuple[float, float]:
    """Run a command: (wall seconds, its peak resident memory in MB); stdout to ``out``."""
    with open(out, "wb") as so, tempfile.TemporaryFile() as se:
        t0 = time.perf_counter()
        p = subprocess.Popen(args, stdout=so, stderr=se, cwd=ROOT)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode:
            se.seek(0)
            raise RuntimeError(f"{' '.join(args)}: exit {p.returncode}: {se.read()[-400:]!r}")
    return wall, usage.ru_maxrss / 1024.0


def _medians(commands: list[tuple[list[str], Path]], repeat: int) -> list[dict]:
    """Each command's median (wall, peak MB) over ``repeat`` rounds, the commands interleaved.

    Interleaving makes a change of the machine's load weigh on all of them alike.
    """
    runs = [[_run(args, out) for args, out in commands] for _ in range(repeat)]
    return [
        {
            "seconds": statistics.median(r[i][0] for r in runs),
            "peak_mb": statistics.median(r[i][1] for r in runs),
        }
        for i in range(len(commands))
    ]


def _window(path: Path, side: float) -> str:
    """A square of ``side`` (a fraction of the width, or metres when > 1) at the centre."""
    import laspy

    with laspy.open(path) as r:
        lo, hi = r.header.mins, r.header.maxs
    mid = (lo + hi) / 2
    half = (side if side > 1 else side * (hi - lo)[:2].max()) / 2
    box = (mid[0] - half, mid[1] - half, lo[2] - 1, mid[0] + half, mid[1] + half, hi[2] + 1)
    return ",".join(repr(float(v)) for v in box)


def rows(quick: bool) -> list[dict]:
    """The section's row: a 1 % window of the COPC file against reading it whole, as processes.

    Both give the same output (checked); the note gives the nodes decoded and the cost above the
    start-up of a 2 m window.
    """
    n = 2_000_000 if quick else FULL
    repeat = 3
    big = _file(n)
    with tempfile.TemporaryDirectory() as d:
        a, b, c = (Path(d) / f"{k}.ply" for k in "abc")
        cmd = [*RECON, "filter", str(big)]
        win = ["--crop", _window(big, 0.1)]
        ours, ref, start = _medians(
            [
                ([*cmd, str(a), *win, "--json"], Path(d) / "a.json"),
                ([*cmd, str(b), *win, "--input-format", "las"], Path(d) / "b.json"),
                ([*cmd, str(c), "--crop", _window(big, 2.0)], Path(d) / "c.json"),
            ],
            repeat,
        )
        if a.read_bytes() != b.read_bytes():
            raise RuntimeError("the window read and the whole read cropped differ")
        rep = json.loads((Path(d) / "a.json").read_text())
    w = rep["read"]["window"]

    def above(k: str) -> float:
        return (ours[k] - start[k]) / (ref[k] - start[k])

    note = (
        f"decoded {w['points_decoded']:,} points ({w['nodes_read']} of {w['nodes']} nodes), kept "
        f"{rep['points_out']:,}; same output; start-up (2 m window) {start['seconds']:.2f} s, "
        f"{start['peak_mb']:.0f} MB; above it: time {above('seconds'):.3f}, memory "
        f"{above('peak_mb'):.3f}; target <= 0.05"
    )
    return [
        row(
            "copc",
            f"filter --crop 1 % window of a {n // 1_000_000}M-point COPC file",
            ours,
            "same command, read whole (--input-format las)",
            ref,
            note,
        )
    ]


if __name__ == "__main__":
    if "--file" in sys.argv:
        rest = sys.argv[sys.argv.index("--file") + 1 :]
        print(_file(int(rest[0]) if rest else FULL))
    else:
        for r in rows("--quick" in sys.argv):
            print(r)
