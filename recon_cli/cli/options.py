"""Shared click options and arguments, as named decorators (cf. rasterio's ``rio/options.py``)."""

from __future__ import annotations

import click

input_arg = click.argument("input", metavar="IN", type=click.Path(allow_dash=True, dir_okay=False))
output_arg = click.argument("output", metavar="OUT", type=click.Path(allow_dash=True, dir_okay=False))

ascii_opt = click.option(
    "--ascii", "ascii_", is_flag=True, help="Write text: ASCII PLY / STL, PCD 'DATA ascii' (default binary little-endian)."
)
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


def _to_meta(ctx: click.Context, param: click.Parameter, value):
    """Keep a file-format option in ``ctx.meta`` (read by ``_run.io_formats``), not as an argument."""
    if value is not None:
        ctx.meta[f"recon.{param.name}"] = value
    return value


def _format_opt(*decls: str, help: str):
    return click.option(*decls, metavar="FMT", default=None, expose_value=False, callback=_to_meta, help=help)


format_opt = _format_opt(
    "--format", "format", help="Format of '-' and of names without a suffix (ply, obj, off, stl, xyz, csv, pcd, las, laz, e57)."
)
input_format_opt = _format_opt("--input-format", "input_format", help="Format of IN, whatever its name (e.g. IN is '-').")
output_format_opt = _format_opt("--output-format", "output_format", help="Format of OUT, whatever its name.")
points_only_opt = click.option(
    "--points-only",
    "points_only",
    is_flag=True,
    expose_value=False,
    callback=_to_meta,
    help="Allow writing a mesh to a points-only format (XYZ, PCD, LAS): its vertices, without the faces.",
)


def stage_io(f):
    """IN, OUT, --ascii, --json and the format options: what every stage command takes."""
    for deco in reversed(
        (input_arg, output_arg, ascii_opt, json_opt, format_opt, input_format_opt, output_format_opt, points_only_opt)
    ):
        f = deco(f)
    return f
