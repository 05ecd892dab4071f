"""Rows of a new bench run that got more than 10 % slower than the figures recorded.

``make bench`` compares each section it runs with the same section of ``bench/results.md``
before writing it: a row (the same case, method and stage) whose time went up by more than
:data:`SLOWER` fails the run, after the results are written. The time compared is the row's
ratio to its reference where it has one (ours / reference, measured back to back: the machine's
load cancels), else its own seconds.
"""

from __future__ import annotations

import math

# a row this much slower than recorded is a regression
SLOWER = 0.10
# the columns that identify a row, and those that time it (the first one a table has wins)
KEY_COLUMNS = ("stage", "case", "method", "command", "input", "operation")
TIME_COLUMNS = ("time ours/ref", "s ours/o3d", "time ratio", "ratio", "ours s", "s", "warm s")


def parse_table(section: str) -> list[dict[str, str]]:
    """The rows of the first markdown table in ``section`` as dicts by header."""
    lines = [ln.strip() for ln in section.splitlines() if ln.strip().startswith("|")]
    if len(lines) < 2:
        return []
    head = [h.strip() for h in lines[0].strip("|").split("|")]
    out = []
    for ln in lines[2:]:
        cells = [c.strip() for c in ln.strip("|").split("|")]
        if len(cells) == len(head):
            out.append(dict(zip(head, cells, strict=True)))
    return out


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def _key(row: dict[str, str]) -> tuple:
    return tuple(row.get(k, "") for k in KEY_COLUMNS)


def regressions(old_section: str, new_section: str) -> list[str]:
    """One line per row of ``new_section`` slower than in ``old_section`` by more than 10 %."""
    old = {_key(r): r for r in parse_table(old_section)}
    out = []
    for r in parse_table(new_section):
        before = old.get(_key(r))
        if before is None:
            continue
        column = next((c for c in TIME_COLUMNS if c in r and c in before), None)
        if column is None:
            continue
        a, b = _number(before[column]), _number(r[column])
        if a > 0 and b > (1 + SLOWER) * a:
            what = " / ".join(v for v in _key(r) if v)
            out.append(f"{what}: {column} {a:g} -> {b:g} (+{b / a - 1:.0%})")
    return out
