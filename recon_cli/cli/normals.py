"""``recon normals IN OUT``: estimate and orient point normals."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("normals")
@options.stage_io
@click.option("--knn", type=int, default=30, show_default=True, help="Neighbours per point (with --radius: at most this many).")
@click.option("--radius", type=float, default=None, help="Neighbourhood radius, in the units of IN (with --knn 0: radius only).")
@click.option(
    "--orient",
    type=click.Choice(["mst", "camera", "direction", "keep", "none"]),
    default="mst",
    show_default=True,
    help="mst: consistent propagation, outward; camera/direction: towards --camera/--direction; "
    "keep: signs of the input normals; none: unoriented.",
)
@click.option("--camera", metavar="X,Y,Z", default=None, help="Viewpoint for --orient camera.")
@click.option("--direction", metavar="X,Y,Z", default=None, help="Direction for --orient direction.")
@click.option("--curvature", is_flag=True, help="Also write the vertex property 'curvature' (surface variation).")
@options.backend_opt("open3d")
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, knn, radius, orient, camera, direction, curvature, backend):
    """Estimate normals by PCA of each point's neighbourhood and orient them.

    Degenerate neighbourhoods (fewer than 3 points, collinear, duplicates) are counted in
    the report and take their nearest regular neighbour's normal.
    """
    from recon_cli.cli._run import run_stage_command

    params = {
        "knn": None if knn == 0 else knn,
        "radius": radius,
        "orient": orient,
        "camera": camera,
        "direction": direction,
        "curvature": curvature,
        "backend": backend,
    }
    run_stage_command(ctx, "normals", input, output, params, ascii_=ascii_, json_=json_)
