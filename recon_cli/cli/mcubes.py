"""``recon mcubes IN.npz OUT.ply``."""

from __future__ import annotations

import click

from recon_cli.cli import options
from recon_cli.cli._run import run_stage_command


@click.command("mcubes")
@options.stage_io
@click.option("--iso", type=float, default=0.0, show_default=True, help="Level to extract (grid units).")
@click.option(
    "--method",
    type=click.Choice(["mc", "mt"]),
    default="mc",
    show_default=True,
    help="mc: marching cubes (asymptotic decider); mt: marching tetrahedra.",
)
@click.option(
    "--allow-degenerate",
    is_flag=True,
    help="Keep crossings exactly at corners (may make zero-area triangles).",
)
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, iso, method, allow_degenerate):
    """Mesh the ISO level set of a grid (.npz from `recon sdf`); vertex normals from the field.

    The mesh is closed and manifold wherever the level set stays inside the grid and away
    from unknown (NaN) cells; unknown cells are left out.
    """
    params = {"iso": iso, "method": method, "allow_degenerate": allow_degenerate}
    run_stage_command(ctx, "mcubes", input, output, params, ascii_=ascii_, json_=json_)
