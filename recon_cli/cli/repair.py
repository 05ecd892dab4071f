"""``recon repair IN OUT``."""

from __future__ import annotations

import click

from recon_cli.cli import options
from recon_cli.cli._run import run_stage_command


@click.command("repair")
@options.stage_io
@click.option(
    "--merge-tolerance",
    default=None,
    metavar="F|exact",
    help="Merge vertices closer than F times the bounding-box diagonal (default: exact duplicates only).",
)
@click.option(
    "--fill-holes",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    metavar="N",
    help="Close boundary loops of at most N edges (0: no filling).",
)
@click.option(
    "--min-component",
    type=click.FloatRange(0.0, 1.0),
    default=0.0,
    show_default=True,
    metavar="F",
    help="Drop components with fewer than this fraction of the faces.",
)
@click.option("--keep-largest", is_flag=True, help="Keep only the component with most faces.")
@options.backend_opt("pymeshlab")
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, merge_tolerance, fill_holes, min_component, keep_largest, backend):
    """Make a mesh manifold, clean and consistently oriented.

    Steps, in order: merge duplicate vertices; remove degenerate and duplicate faces and
    unreferenced vertices; keep two faces per edge; split pinched vertices; orient
    consistently (closed parts outward); fill holes up to N edges; drop small components.
    A clean mesh passes through unchanged.
    """
    params = {
        "merge_tolerance": merge_tolerance,
        "fill_holes": fill_holes,
        "min_component": min_component,
        "keep_largest": keep_largest,
        "backend": backend,
    }
    run_stage_command(ctx, "repair", input, output, params, ascii_=ascii_, json_=json_)
