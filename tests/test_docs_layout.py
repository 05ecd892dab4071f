"""The README fits two screens and links to what exists; bench/calibration.md is a reference.

Issue 48: the README says what recon is, how to install it, ``make demo``, ``make test``, a
three-command example with its picture, and links (the rest is the user guide). The calibration
file has one entry per tuned constant: where it is, its value, what was measured and the command
that measures it again, and a constant named with its value in the heading has that value in
the file the entry names.
"""

from __future__ import annotations

import re

import pytest

from shared_data import ROOT

README = ROOT / "README.md"
CALIBRATION = ROOT / "bench" / "calibration.md"
# two screens of a terminal: the README's text, its code blocks and its picture included
MAX_README_LINES = 80
FIELDS = ("Where", "Value", "Measured", "Re-measure", "Notes")


def test_readme_fits_two_screens_and_says_the_essentials():
    """README.md: at most 80 lines, with install, make targets, three commands and their picture."""
    text = README.read_text(encoding="utf-8")
    lines = text.splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md: {len(lines)} lines"
    for needed in ("## Install", "make demo", "make test", "make docs"):
        assert needed in text, needed
    # the three-command example and the picture recon diff made of it
    block = re.search(r"## Three commands\n+```sh\n(.*?)```", text, re.S)
    assert block is not None
    commands = [c for c in block.group(1).splitlines() if c.strip()]
    assert len(commands) == 3 and all(c.startswith("recon ") for c in commands)
    assert "--png" in commands[-1]
    assert re.search(r"!\[[^\]]+\]\(docs/images/[^)]+\.png\)", text)


def test_readme_links_point_at_files_in_the_tree():
    """The README links at least 10 targets, and every local one exists in the tree."""
    targets = re.findall(r"\]\(([^)#]+)\)", README.read_text(encoding="utf-8"))
    assert len(targets) >= 10  # the guide's pages, not a copy of them
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, missing


def _entries() -> list[tuple[str, str]]:
    """(heading, body) of every ``###`` entry of bench/calibration.md."""
    parts = re.split(r"^### ", CALIBRATION.read_text(encoding="utf-8"), flags=re.M)[1:]
    return [(p.partition("\n")[0], p.partition("\n")[2]) for p in parts]


ENTRIES = _entries()


def test_calibration_has_entries_for_every_section():
    """bench/calibration.md has 20+ entries in 5+ sections and no dated headings."""
    text = CALIBRATION.read_text(encoding="utf-8")
    sections = re.findall(r"^## (.*)$", text, re.M)
    assert len(ENTRIES) >= 20 and len(sections) >= 5
    # no dated records as headings: the history is in docs/design/
    assert not re.search(r"^#+ .*\b20\d\d-\d\d-\d\d\b", text, re.M)


@pytest.mark.parametrize(("heading", "body"), ENTRIES, ids=[h[:40] for h, _ in ENTRIES])
def test_calibration_entry_is_in_reference_form(heading, body):
    """Each calibration entry: five fields, real files, a command, the heading's value in code."""
    fields = re.findall(r"^- \*\*([A-Za-z-]+)\*\*", body, re.M)
    assert tuple(fields) == FIELDS, (heading, fields)
    where = re.search(r"^- \*\*Where\*\*: (.*(?:\n  .*)*)", body, re.M).group(1)
    files = re.findall(r"`(recon_cli/[^`]+\.py)`", where)
    assert files, f"{heading}: Where names no file"
    missing = [f for f in files if not (ROOT / f).is_file()]
    assert not missing, (heading, missing)
    remeasure = re.search(r"^- \*\*Re-measure\*\*: (.*)", body, re.M).group(1)
    assert "`" in remeasure, f"{heading}: no command"
    # a constant named with its value in the heading is assigned that value where it is said to be
    source = "\n".join((ROOT / f).read_text(encoding="utf-8") for f in files)
    for name, value in re.findall(r"`(?:[a-z_.]+\.)?([A-Z_][A-Z0-9_]*) = ([^`]+)`", heading):
        assigned = rf"^\s*{name}\s*(?::[^=\n]*)?=\s*{re.escape(value)}\s*(?:#.*)?$"
        assert re.search(assigned, source, re.M), f"{heading}: {name} = {value} not in {files}"
