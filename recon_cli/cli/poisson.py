"""``recon poisson IN OUT``: screened Poisson reconstruction of an oriented cloud."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("poisson")
@options.stage_io
@click.option("--depth", type=int, default=8, show_default=True, help="Deepest octree level allowed (finest cell = bounding cube / 2^depth); the tree stops where the samples do.")
@click.option("--scale", type=float, default=1.1, show_default=True, help="Reconstruction cube / largest side of the bounding box.")
@click.option("--point-weight", type=float, default=4.0, show_default=True, help="Screening weight (0 = classic unscreened Poisson).")
@click.option("--samples-per-node", type=float, default=1.5, show_default=True, help="Samples per node at a sample's depth (as PoissonRecon): sparser samples are splatted coarser.")
@click.option("--boundary", type=click.Choice(["neumann", "dirichlet"]), default="neumann", show_default=True, help="Condition on the faces of the cube.")
@click.option("--density", is_flag=True, help="Write the per-vertex sampling density as vertex property 'density'.")
@click.option("--trim", type=float, default=0.0, show_default=True, metavar="Q", help="Remove the surface whose density is in the lowest Q quantile (0..1).")
@click.option("--estimate-normals", is_flag=True, help="Estimate and orient normals first (as 'recon normals' does).")
@options.backend_opt("open3d", "pymeshlab")
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, depth, scale, point_weight, samples_per_node, boundary, density, trim, estimate_normals, backend):
    """Screened Poisson reconstruction (Kazhdan & Hoppe 2013) on a sparse octree.

    IN must carry normals (run 'recon normals' first, or pass --estimate-normals). Colours
    on IN are interpolated onto the output vertices. With -v the solver's iterations and
    residual per level are logged.
    """
    from recon_cli.cli._run import run_stage_command

    params = {
        "depth": depth,
        "scale": scale,
        "point_weight": point_weight,
        "samples_per_node": samples_per_node,
        "boundary": boundary,
        "density": density,
        "trim": trim,
        "estimate_normals": estimate_normals,
        "backend": backend,
    }
    run_stage_command(ctx, "poisson", input, output, params, ascii_=ascii_, json_=json_)
