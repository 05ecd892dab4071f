"""Shared click options and arguments, as named decorators (cf. rasterio's ``rio/options.py``)."""

from __future__ import annotations

import click

# paths are checked by the reader and the writer (one line naming the path, exit 2), not by click
input_arg = click.argument("input", metavar="IN", type=click.Path(allow_dash=True))
output_arg = click.argument("output", metavar="OUT", type=click.Path(allow_dash=True))

ascii_opt = click.option("--ascii", "ascii_", is_flag=True, help="Write ASCII PLY (default binary little-endian).")
json_opt = click.option(
    "--json",
    "json_",
    is_flag=True,
    help="Print the report as JSON (on stdout, or stderr when OUT is '-').",
)


def backend_opt(*choices: str):
    """``--backend`` with ``native`` first (the default) and the given reference libraries."""
    return click.option(
        "--backend",
        type=click.Choice(["native", *choices]),
        default="native",
        show_default=True,
        help="Implementation: ours (native) or a reference library (needs recon[reference]).",
    )


def stage_io(f):
    """IN, OUT, --ascii and --json: what every stage command takes."""
    for deco in reversed((input_arg, output_arg, ascii_opt, json_opt)):
        f = deco(f)
    return f
