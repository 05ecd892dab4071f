"""``make bench``: time our stages against the reference libraries, in one process.

Every ``bench/bench_*.py`` module provides ``rows(quick: bool) -> list[dict]`` built with
:func:`_util.row`. Each measurement is the median of several runs, each run in a forked
child so its peak memory is its own. The table goes to stdout and to ``--out``.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import platform
import sys
import time
from pathlib import Path

# measurements fork; GNU OpenMP (numba's usual threading layer) aborts a child forked after
# its threads started, the workqueue layer does not. Set before anything imports numba.
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))


def fmt(v, digits=3) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "—"
        return f"{v:.{digits}g}"
    return str(v)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default=str(HERE / "results.md"))
    ap.add_argument("--only", nargs="*", help="bench module names (e.g. ply normals)")
    ap.add_argument("--quick", action="store_true", help="smaller inputs, fewer repeats")
    args = ap.parse_args()
    mods = sorted(p.stem for p in HERE.glob("bench_*.py"))
    if args.only:
        mods = [m for m in mods if m.removeprefix("bench_") in args.only]
    rows = []
    for m in mods:
        t0 = time.perf_counter()
        print(f"# {m} ...", file=sys.stderr, flush=True)
        mod = importlib.import_module(m)
        try:
            rows += mod.rows(args.quick)
        except Exception as exc:  # one broken bench must not hide the others
            rows.append({"stage": m, "case": f"FAILED: {exc!r}"})
        print(f"# {m} done in {time.perf_counter() - t0:.1f}s", file=sys.stderr, flush=True)
    head = "| stage | case | ours s | ours MB | reference | ref s | ref MB | time ours/ref | mem ours/ref | note |"
    lines = [
        f"# recon benchmark ({time.strftime('%Y-%m-%d %H:%M')}, {platform.machine()}, {platform.python_version()})",
        "",
        "Times are medians of repeated runs; memory is the peak RSS above the start of each run.",
        "",
        head,
        "|" + "---|" * 10,
    ]
    for r in rows:
        lines.append(
            "| "
            + " | ".join(
                fmt(r.get(k, ""))
                for k in ("stage", "case", "ours_s", "ours_mb", "ref", "ref_s", "ref_mb", "time_ratio", "mem_ratio", "note")
            )
            + " |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
