"""recon_cli.tools.docs: the documentation's stage pages, read back against the declarations."""

from __future__ import annotations

import os

import pytest
from docutils.core import publish_doctree
from docutils.nodes import field, table

from recon_cli.params import Param, StageSpec
from recon_cli.stages import StageResult, get_spec, register_stage, stage_names, unregister_stage
from recon_cli.tools import docs

QUIET = {"report_level": 5, "halt_level": 5}


def table_cells(rst: str) -> list[list[str]]:
    """The text of every cell of the one table in ``rst``, row by row, as a reader sees it."""
    tree = publish_doctree(rst, settings_overrides=QUIET)
    tables = list(tree.findall(table))
    assert len(tables) == 1
    rows = []
    for row in tables[0].findall(lambda n: n.tagname == "row"):
        rows.append([entry.astext() for entry in row.findall(lambda n: n.tagname == "entry")])
    return rows


def expected_row(p: Param) -> list[str]:
    """What a parameter's row must say, from the declaration's fields."""
    allowed = f"{p.option} / --no-{p.dashed}" if p.type == "bool" else p.range_text()
    return [p.option, p.type, p.default_text(), allowed or "any", p.unit or "–"]


@pytest.mark.parametrize("name", stage_names())
def test_every_stage_table_equals_its_declaration(name):
    """Each stage's parameter table holds exactly its declaration's rows and meanings."""
    spec = get_spec(name)
    rows = table_cells(docs.param_table(spec))
    assert rows[0] == list(spec.TABLE_COLUMNS)
    assert len(rows) == len(spec.params) + 1
    for p, row in zip(spec.params, rows[1:], strict=True):
        assert row[:5] == expected_row(p), p.name
        meaning = row[5]
        assert meaning.startswith(p.help), p.name
        for value, what in p.special.items():
            assert what in meaning, (p.name, value)
        assert " ".join(meaning.split()) == meaning  # one paragraph, no stray markup


@pytest.mark.parametrize("name", stage_names())
def test_every_stage_page_names_its_command_and_function(name):
    """Each stage page names its command and function, its fields readable as reStructuredText."""
    page = docs.stage_page(name)
    fn = name.replace("-", "_")
    assert f"\n:Python: :func:`recon_cli.{fn}`\n" in page
    assert f"\n.. autofunction:: recon_cli.{fn}\n" in page
    # the rest is plain reStructuredText: the fields read back as written
    tree = publish_doctree(page.replace(f":func:`recon_cli.{fn}`", fn), settings_overrides=QUIET)
    fields = {f[0].astext(): f[1].astext() for f in tree.findall(field)}
    assert fields["Command"].startswith(f"recon {name} IN OUT")
    assert " ".join(get_spec(name).summary.split()) in " ".join(tree.astext().split())


def test_markup_in_help_text_reads_back_as_written():
    """Characters that reStructuredText reads as markup stay text in the table."""
    spec = StageSpec(
        name="toy-markup",
        summary="A toy.",
        takes=("cloud",),
        gives=("cloud",),
        params=(
            Param(
                "alpha_", "float", 0.5, "Mean of |x| * 2 over `x`, a_ b_ (not a link).", unit="m"
            ),
            Param("mode", "choice", "a", "Which.", choices=("a", "b|c")),
        ),
    )
    rows = table_cells(docs.param_table(spec))
    assert rows[1][5] == "Mean of |x| * 2 over `x`, a_ b_ (not a link)."
    assert rows[1][0] == "--alpha-"
    assert rows[2][3] == "a | b|c"


def test_pages_follow_the_registry(tmp_path):
    """A registered stage gets its page; an unregistered one loses it; unchanged pages are kept."""
    spec = StageSpec(
        name="toy-docs",
        summary="A toy stage for the documentation test.",
        takes=("cloud",),
        gives=("cloud",),
        params=(Param("strength", "float", 2.0, "How strong.", unit="voxels", min=0, max=8),),
    )

    @spec.runner
    def run_stage(data, *, strength, progress=None):
        return StageResult(data)

    out = str(tmp_path / "stages")
    docs.write_pages(out)
    assert not os.path.exists(os.path.join(out, "toy-docs.rst"))
    register_stage(spec)
    try:
        changed = docs.write_pages(out)
        page = os.path.join(out, "toy-docs.rst")
        assert set(changed) == {page, os.path.join(out, "index.rst")}
        with open(page, encoding="utf-8") as f:
            rows = table_cells(f.read().replace(".. autofunction::", ".. note::"))
        assert rows[1] == ["--strength", "float", "2", "0 <= x <= 8", "voxels", "How strong."]
        with open(os.path.join(out, "index.rst"), encoding="utf-8") as f:
            assert "   toy-docs\n" in f.read()
    finally:
        unregister_stage("toy-docs")
    assert docs.write_pages(out) == [os.path.join(out, "index.rst")]
    assert not os.path.exists(page)
    assert sorted(os.listdir(out)) == sorted(["index.rst", *(f"{n}.rst" for n in stage_names())])


@pytest.mark.parametrize("name", stage_names())
def test_every_stage_page_includes_its_guide(name, tmp_path):
    """Each built-in stage's package holds a guide.md, which its page includes by its path."""
    guide = docs.guide_path(name)
    assert guide is not None and os.path.basename(guide) == docs.GUIDE
    with open(guide, encoding="utf-8") as f:
        assert len(f.read().split()) > 30  # a guide, not a stub
    page = docs.stage_page(name, str(tmp_path))
    include = [line for line in page.splitlines() if line.startswith(".. include:: ")]
    assert len(include) == 1
    target = os.path.join(tmp_path, include[0].removeprefix(".. include:: "))
    assert os.path.samefile(target, guide)
    assert docs.guide_path("no-such-stage") is None


def test_bench_summary_keeps_every_measured_ratio():
    """The bench summary keeps every measured ratio of the results file."""
    results = """# recon benchmark

## bench_x (2026-12-01 10:00, 5 s)

| stage | case | ours s | reference | ref s | time ours/ref | note |
|---|---|---|---|---|---|---|
| x | small | 1.0 | lib | 2.0 | 0.5 | fine |
| x | huge | 9.0 |  | — | — | no reference |

| case | method | s | s ours/o3d |
|---|---|---|---|
| cube | recon | 3 | 1.5 |
| cube | open3d | 2 |  |

## bench_y (2026-12-01 11:00, 5 s)

| stage | case | ours s |
|---|---|---|
| y | only ours | 4.0 |
"""
    assert docs.bench_summary(results).splitlines() == [
        "**bench_x (2026-12-01 10:00, 5 s)**",
        "",
        "| stage | case | reference | time ours/ref |",
        "|---|---|---|---|",
        "| x | small | lib | 0.5 |",
        "",
        "| case | method | s ours/o3d |",
        "|---|---|---|",
        "| cube | recon | 1.5 |",
    ]
