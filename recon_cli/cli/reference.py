"""The command-line reference: every command's ``--help``, as one page of the documentation.

The documentation's build (``docs/conf.py``) writes :func:`reference_page` to ``docs/cli/index.rst``
at its start, so the page is click's own help of each command (stages made from their
declarations, the other commands from their modules) and never copied by hand.
"""

from __future__ import annotations

import os

import click

WIDTH = 100  # the help's line width on the page


def _context(command: click.Command, name: str, parent: click.Context | None) -> click.Context:
    """The context ``command`` runs in as ``name`` (its own settings: ``-h``, widths)."""
    return command.make_context(
        name,
        [],
        parent=parent,
        resilient_parsing=True,  # no argument is checked: only the help is wanted
        terminal_width=WIDTH,
        max_content_width=WIDTH,
    )


def _help(command: click.Command, name: str, parent: click.Context | None) -> str:
    """The ``--help`` text of ``command`` run as ``name``."""
    return command.get_help(_context(command, name, parent))


def command_names() -> list[str]:
    """The commands of ``recon``: stages and the others, as ``recon --help`` lists them."""
    from recon_cli.cli.main import cli

    return cli.list_commands(click.Context(cli, info_name="recon"))


def reference_page() -> str:
    """The reference page (reStructuredText): ``recon --help``, then each command's help."""
    from recon_cli.cli.main import cli

    root = _context(cli, "recon", None)
    title = "Command-line reference"
    out = [
        ".. _cli-reference:",
        "",
        title,
        "=" * len(title),
        "",
        "Each command's ``--help``, as ``recon`` prints it. The options of a stage are its",
        "declared parameters (:doc:`../stages/index` gives them with their units and ranges).",
        "",
        "``recon``",
        "---------",
        "",
        "::",
        "",
        *_indented(_help(cli, "recon", None)),
        "",
    ]
    for name in command_names():
        command = cli.get_command(root, name)
        if command is None:  # pragma: no cover - every listed command loads
            continue
        head = f"``recon {name}``"
        out += [
            f".. _cli-{name}:",
            "",
            head,
            "-" * len(head),
            "",
            "::",
            "",
            *_indented(_help(command, name, root)),
            "",
        ]
    return "\n".join(out)


def write_reference(directory: str) -> list[str]:
    """Write :func:`reference_page` to ``directory/index.rst``; the files changed."""
    from recon_cli.tools.docs import write_changed

    os.makedirs(directory, exist_ok=True)
    path = write_changed(directory, "index.rst", reference_page())
    return [path] if path else []


def _indented(text: str) -> list[str]:
    return [("   " + line).rstrip() for line in text.splitlines()]
