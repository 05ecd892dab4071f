"""``recon ballpivot IN OUT [--radii auto|r1,r2,...]``."""

from __future__ import annotations

import click

from recon_cli.cli import options
from recon_cli.cli._run import run_stage_command


@click.command("ballpivot")
@options.stage_io
@click.option(
    "--radii",
    default="auto",
    show_default=True,
    help="Ball radii in input units, comma-separated (e.g. 0.002,0.004), or 'auto': "
    "2x and 4x the median nearest-neighbour spacing.",
)
@options.backend_opt("open3d", "pymeshlab")
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, radii, backend):
    """Ball-pivoting reconstruction (Bernardini et al. 1999) of an oriented cloud.

    Needs point normals (run `recon normals` first); faces are wound to agree with them.
    The mesh interpolates the points, is edge- and vertex-manifold, and keeps every input
    point as a vertex (points no ball reached stay unreferenced). The radii used are
    printed and recorded in the output's history.
    """
    run_stage_command(ctx, "ballpivot", input, output, {"radii": radii, "backend": backend}, ascii_=ascii_, json_=json_)
