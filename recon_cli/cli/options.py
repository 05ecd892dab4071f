"""Shared click options and arguments, as named decorators (cf. rasterio's ``rio/options.py``)."""

from __future__ import annotations

import click

input_arg = click.argument("input", metavar="IN", type=click.Path(allow_dash=True, dir_okay=False))
output_arg = click.argument("output", metavar="OUT", type=click.Path(allow_dash=True, dir_okay=False))

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


def picture_opts(f):
    """``--view``, ``--vmax`` and ``--unit``: how ``recon diff --png`` and ``recon compare`` draw."""
    for deco in reversed((
        click.option(
            "--view",
            "views",
            multiple=True,
            default=("turntable",),
            show_default=True,
            help="View of the pictures (repeatable): turntable (4 azimuths), front, back, left, right, top, bottom, iso, or AZ,EL in degrees.",
        ),
        click.option("--vmax", type=float, help="Distance at the top of the heatmaps' colour scale [default: 99th percentile, at least the smallest tau]."),
        click.option("--unit", help="Unit of the coordinates, written on the colour bar and in reports (e.g. mm) [default: model units]."),
    )):
        f = deco(f)
    return f
