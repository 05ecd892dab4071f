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
    """A table cell: a float to ``digits`` significant digits (NaN: a dash), else the text."""
    if isinstance(v, float):
        if math.isnan(v):
            return "—"
        return f"{v:.{digits}g}"
    return str(v)


HEAD = (
    "| stage | case | ours s | ours MB | reference | ref s | ref MB | time ours/ref | mem ours/ref "
    "| note |"
)
KEYS = (
    "stage",
    "case",
    "ours_s",
    "ours_mb",
    "ref",
    "ref_s",
    "ref_mb",
    "time_ratio",
    "mem_ratio",
    "note",
)


def table(rows: list[dict], columns: list[tuple[str, str]] | None = None) -> list[str]:
    """The rows as a markdown table.

    The usual ours-vs-reference columns, or a module's own ``COLUMNS``.
    """
    head, keys = (
        (HEAD, KEYS)
        if columns is None
        else ("| " + " | ".join(h for _, h in columns) + " |", [k for k, _ in columns])
    )
    lines = [head, "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |")
    return lines


def old_sections(path: Path) -> dict[str, str]:
    """Sections of an earlier results file, by module (``## bench_x ...`` up to the next one)."""
    if not path.exists():
        return {}
    out: dict[str, str] = {}
    name = None
    for line in path.read_text().splitlines(keepends=True):
        if line.startswith("## bench_"):
            name = line.split()[1]
            out[name] = ""
        if name:
            out[name] += line
    return out


def main() -> int:
    """Run the bench modules' ``rows`` and write their sections to ``--out``.

    Exit 1 when a row is more than 10 % slower than recorded in ``--out`` (unless ``--no-check``).
    """
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default=str(HERE / "results.md"))
    ap.add_argument(
        "--only",
        nargs="*",
        help="bench module names (e.g. ply normals); the other sections of --out are kept",
    )
    ap.add_argument("--quick", action="store_true", help="smaller inputs, fewer repeats")
    ap.add_argument(
        "--no-check",
        action="store_true",
        help="do not fail on rows more than 10 %% slower than recorded in --out",
    )
    args = ap.parse_args()
    from regressions import regressions

    recorded = old_sections(Path(args.out))
    slower: list[str] = []
    every = sorted(p.stem for p in HERE.glob("bench_*.py"))
    mods = [m for m in every if m.removeprefix("bench_") in args.only] if args.only else every
    sections = old_sections(Path(args.out)) if args.only else {}
    for m in mods:
        t0 = time.perf_counter()
        print(f"# {m} ...", file=sys.stderr, flush=True)
        mod = importlib.import_module(m)
        try:
            rows = mod.rows(args.quick)
        except Exception as exc:  # one broken bench must not hide the others
            rows = [{"stage": m, "case": f"FAILED: {exc!r}"}]
        took = time.perf_counter() - t0
        print(f"# {m} done in {took:.1f}s", file=sys.stderr, flush=True)
        when = time.strftime("%Y-%m-%d %H:%M")
        text = (
            "\n".join(
                [
                    f"## {m} ({when}{', quick' if args.quick else ''}, {took:.0f} s)",
                    "",
                    *table(rows, getattr(mod, "COLUMNS", None)),
                    "",
                ]
            )
            + "\n"
        )
        print(text, flush=True)
        if not args.quick and m in recorded:
            slower += [f"{m}: {line}" for line in regressions(recorded[m], text)]
        sections[m] = text
    lines = [
        f"# recon benchmark ({platform.machine()}, Python {platform.python_version()}, "
        f"{os.cpu_count()} cores)",
        "",
        "Times are medians of repeated runs, each in a forked child; memory is the peak RSS "
        "above the start",
        "of each run. Ours and the reference run back to back in one process: read the ratios. "
        "Each section",
        "says when it was measured (`make bench` runs all; `run_bench.py --only NAME` redoes "
        "one section).",
        "",
    ]
    for m in every:
        if m in sections:
            lines.append(sections[m].rstrip("\n") + "\n")
    Path(args.out).write_text("\n".join(lines))
    if slower and not args.no_check:
        print("rows more than 10 % slower than recorded:", *slower, sep="\n  ", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
