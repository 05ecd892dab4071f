"""``python -m recon_cli.tools.docs DIR``: write the documentation's page of every stage.

One reStructuredText page per registered stage (``DIR/<stage>.rst``) and their index
(``DIR/index.rst``): the stage's summary and description, what it takes and gives, its guide
(the ``guide.md`` beside the module holding its declaration, when there is one: what it does in
detail, its report's keys), its parameter table (:meth:`recon_cli.params.StageSpec.table_rows`)
and its library function. The Sphinx build runs this at its start (``docs/conf.py``), so no
table is ever copied by hand; a test reads the tables back and compares them with the
declarations.
"""

from __future__ import annotations

import inspect
import os
import re
import sys
from collections.abc import Sequence

from recon_cli.params import StageSpec, describe_kinds

TITLE = "Stages"


def _literal(text: str) -> str:
    """``text`` as inline code (reStructuredText has no escape inside double backquotes)."""
    return f"``{text}``" if "`" not in text else f":code:`{text}`"


def _cell(text: str) -> str:
    """A table cell's text, with the characters reStructuredText would read as markup escaped."""
    out = []
    for k, part in enumerate(text.split("``")):
        if k % 2 == 0:  # outside inline code
            part = part.replace("\\", "\\\\").replace("*", "\\*").replace("|", "\\|")
            part = re.sub(r"(\w)_(?=\W|$)", r"\1\\_", part).replace("`", "\\`")
        out.append(part)
    return "``".join(out)


def param_table(spec: StageSpec) -> str:
    """The parameter table of ``spec`` as a reStructuredText list table."""
    lines = [".. list-table::", "   :header-rows: 1", "   :widths: auto", ""]
    for i, row in enumerate([spec.TABLE_COLUMNS, *spec.table_rows(code=_literal)]):
        for j, cell in enumerate(row):
            text = cell if i == 0 else _cell(cell)
            lines.append(("   * - " if j == 0 else "     - ") + (text or "–"))
    return "\n".join(lines)


GUIDE = "guide.md"


def guide_path(name: str) -> str | None:
    """The guide of stage ``name``: ``guide.md`` beside the module of its declaration, or None."""
    import importlib.util

    from recon_cli.stages import STAGES

    where = STAGES.get(name, "")
    module = where.partition(":")[0]
    if not module or module.startswith("<"):  # registered in this process: no file
        return None
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        return None
    path = os.path.join(os.path.dirname(spec.origin), GUIDE)
    return path if os.path.exists(path) else None


def stage_page(name: str, directory: str | None = None) -> str:
    """The page of stage ``name``: what it does, its guide, its parameter table and its function.

    ``directory`` is where the page goes (the guide is included by its path from there); None
    leaves the guide out.
    """
    from recon_cli.api import function_name
    from recon_cli.stages import get_spec

    spec = get_spec(name)
    fn = function_name(name)
    title = f"``recon {name}``"
    out = [f".. _stage-{name}:", "", title, "=" * len(title), "", _cell(spec.summary), ""]
    description = inspect.cleandoc(spec.description or "")
    if description and description != spec.summary.strip():
        out += [_cell(description), ""]
    out += [
        f":Takes: {describe_kinds(spec.takes) if spec.declared else 'any data'}",
        f":Gives: {describe_kinds(spec.gives) if spec.declared else 'any data'}",
        f":Command: ``recon {name} IN OUT [OPTIONS]`` (``-`` for standard input or output)",
        f':Pipeline: a ``[[stage]]`` table with ``name = "{name}"``',
        f":Python: :func:`recon_cli.{fn}`",
        "",
    ]
    guide = guide_path(name) if directory is not None else None
    if guide is not None:
        rel = os.path.relpath(guide, directory).replace(os.sep, "/")
        out += [f".. include:: {rel}", "   :parser: myst_parser.sphinx_", ""]
    out += [
        "Parameters",
        "----------",
        "",
        "Every parameter is an option of the command, a key of the pipeline stage and a keyword",
        "of the function, with the same type, default and range.",
        "",
        param_table(spec),
        "",
        "Python",
        "------",
        "",
        f".. autofunction:: recon_cli.{fn}",
        "",
    ]
    return "\n".join(out)


def index_page(names: Sequence[str]) -> str:
    """The index of the stage pages."""
    out = [
        TITLE,
        "=" * len(TITLE),
        "",
        "Each stage is a command (``recon STAGE IN OUT``), a pipeline step and a function of",
        ":mod:`recon_cli`, all made from one declaration: the tables below are generated from it.",
        "",
        ".. toctree::",
        "   :maxdepth: 1",
        "",
    ]
    out += [f"   {name}" for name in names]
    return "\n".join(out) + "\n"


def write_changed(directory: str, file: str, text: str) -> str | None:
    """Write ``text`` to ``directory/file`` unless it holds it already; its path if written."""
    path = os.path.join(directory, file)
    old = None
    if os.path.exists(path):
        with open(path, encoding="utf-8") as f:
            old = f.read()
    if old == text:  # unchanged files keep their time: Sphinx rebuilds only what changed
        return None
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
    return path


def write_pages(directory: str) -> list[str]:
    """Write every stage's page and the index into ``directory``; the files changed."""
    from recon_cli.stages import stage_names

    os.makedirs(directory, exist_ok=True)
    names = list(stage_names())
    pages = {f"{name}.rst": stage_page(name, directory) for name in names}
    pages["index.rst"] = index_page(names)
    changed = [p for file, text in pages.items() if (p := write_changed(directory, file, text))]
    for file in os.listdir(directory):
        if file.endswith(".rst") and file not in pages:  # a stage no longer registered
            os.remove(os.path.join(directory, file))
    return changed


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _is_ratio(column: str) -> bool:
    return "ours/" in column or column == "ratio"


def bench_summary(results: str) -> str:
    """The ratios of ``bench/results.md`` (Markdown ``results``): one table per bench section.

    Each table keeps a row's first two cells (what and on what), its reference and its ratio
    columns (``time ours/ref``, ``s ours/o3d``, ...), for the rows with a measured ratio.
    """
    out: list[str] = []
    section, header, keep, head, titled = "", None, [], [], ""
    for line in [*results.splitlines(), ""]:
        if line.startswith("## "):
            section, header = line[3:].strip(), None
        elif not line.startswith("|"):
            header = None
        elif header is None:
            header = _cells(line)
            keep = [0, 1, *(j for j, c in enumerate(header) if c in ("reference", "method"))]
            keep = sorted(set(keep)) + [j for j, c in enumerate(header) if _is_ratio(c)]
            if not any(_is_ratio(header[j]) for j in keep):
                keep = []
            title = [f"**{section}**", ""] if titled != section else []
            head = ["", *title, "| " + " | ".join(header[j] for j in keep) + " |"]
            head.append("|" + "---|" * len(keep))
        elif keep and not set(line) <= set("|-: "):
            row = _cells(line)
            ratios = [row[j] for j in keep if _is_ratio(header[j])]
            if any(r.replace(".", "", 1).isdigit() for r in ratios):
                out += head + ["| " + " | ".join(row[j] for j in keep) + " |"]
                head, titled = [], section  # the table's head once, above its first row
    return "\n".join(out).strip() + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Write the stage pages into the directory named in ``argv`` (default ``docs/stages``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    write_pages(args[0] if args else os.path.join("docs", "stages"))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
