"""``recon sdf IN OUT.npz``."""

from __future__ import annotations

import click

from recon_cli.cli import options
from recon_cli.cli._run import run_stage_command


@click.command("sdf")
@options.stage_io
@click.option("--resolution", type=int, default=128, show_default=True, help="Cells along the longest side of the box.")
@click.option("--voxel-size", type=float, default=None, help="Sample spacing in world units (overrides --resolution).")
@click.option("--padding", type=float, default=0.05, show_default=True, help="Margin, fraction of the box's longest side.")
@click.option(
    "--sign",
    type=click.Choice(["winding", "pseudonormal"]),
    default="winding",
    show_default=True,
    help="Meshes: inside where the winding number is not 0 (exact on closed meshes of either orientation; robust to holes) or by pseudonormals.",
)
@click.option("--band", type=float, default=None, help="Meshes: exact distances only within this many voxels.")
@click.option("--knn", type=int, default=10, show_default=True, help="Clouds: neighbours averaged per sample (IMLS).")
@options.backend_opt("open3d")
@click.pass_context
def cmd(ctx, input, output, ascii_, json_, resolution, voxel_size, padding, sign, band, knn, backend):
    """Signed distance grid (.npz, negative inside) of a mesh or an oriented point cloud.

    Clouds need normals; samples far from every point are unknown (NaN) and `recon mcubes`
    leaves them out.
    """
    params = {"resolution": resolution, "padding": padding, "sign": sign, "knn": knn, "backend": backend}
    if voxel_size is not None:
        params["voxel_size"] = voxel_size
    if band is not None:
        params["band"] = band
    run_stage_command(ctx, "sdf", input, output, params, ascii_=ascii_, json_=json_)
