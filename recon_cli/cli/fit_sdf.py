"""``recon fit-sdf IN OUT.npz``."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("fit-sdf")
@options.input_arg
@options.output_arg
@options.json_opt
@click.option("--resolution", type=int, default=128, show_default=True, help="Grid cells along the longest side of the box.")
@click.option("--iterations", type=int, default=2000, show_default=True, help="Optimiser steps.")
@click.option("--max-seconds", type=float, default=None, help="Stop training after this many seconds (first of the two limits wins).")
@click.option("--width", type=int, default=128, show_default=True, help="Hidden units per layer.")
@click.option("--depth", type=int, default=4, show_default=True, help="Hidden layers.")
@click.option("--frequencies", type=int, default=6, show_default=True, help="Octaves of the positional encoding (0: none).")
@click.option("--batch", type=int, default=2048, show_default=True, help="Surface points per step.")
@click.option("--eikonal-weight", type=float, default=None, help="Weight of the eikonal loss E[(|grad s| - 1)^2] (default 3 with normals, 0.1 without).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the weights and sampling (fixed seed: same field).")
@click.option(
    "--field",
    type=click.Choice(["sdf", "occupancy"]),
    default="sdf",
    show_default=True,
    help="sdf: signed distance (IGR); occupancy: logistic inside probability, written as 0.5 - p.",
)
@click.option("--threads", type=int, default=None, help="CPU threads for training (default: torch's).")
@click.option("--model", "model", type=click.Path(dir_okay=False), default=None, help="Also write the fitted weights (.npz) here.")
@click.option(
    "--mesh",
    "mesh",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the zero level set (PLY; vertex normals from the network's gradient).",
)
@click.pass_context
def cmd(ctx, input, output, json_, resolution, iterations, max_seconds, width, depth, frequencies, batch, eikonal_weight,
        seed, field, threads, model, mesh):
    """Fit a neural signed distance field to a cloud; write it on a grid (.npz).

    With normals the loss holds the zero level on the points, the gradient to the normals
    and |grad s| to 1 (eikonal); without, the zero level and the eikonal term (IGR). `recon
    mcubes OUT.npz mesh.ply` extracts the surface; `recon info OUT.npz` reports the eikonal
    statistics. Needs PyTorch (pip install recon[learned]). Ctrl-C stops training and writes
    the best field so far (exit 130).
    """
    import time

    from recon_cli.cli._run import emit_report, make_progress
    from recon_cli.io.load import load, save
    from recon_cli.stages import apply_stage

    params = {
        "resolution": resolution, "iterations": iterations, "width": width, "depth": depth,
        "frequencies": frequencies, "batch": batch, "seed": seed, "field": field,
    }
    for k, v in (("eikonal_weight", eikonal_weight), ("max_seconds", max_seconds), ("threads", threads), ("model", model), ("mesh", mesh)):
        if v is not None:
            params[k] = v
    t0 = time.perf_counter()
    data = load(input)
    t1 = time.perf_counter()
    result = apply_stage("fit-sdf", data, params, progress=make_progress(ctx))
    t2 = time.perf_counter()
    save(result.output, output)
    t3 = time.perf_counter()
    report = dict(result.report)
    report["timings"] = {"read": t1 - t0, "stage": t2 - t1, "write": t3 - t2}
    report["output"] = "<stdout>" if output == "-" else output
    emit_report(ctx, report, json_=json_, data_on_stdout=(output == "-"))
    if report.get("interrupted"):
        from recon_cli.cli.main import EXIT_INTERRUPTED

        click.echo(f"recon: interrupted: wrote the best field so far ({report['iterations']} iterations)", err=True)
        ctx.exit(EXIT_INTERRUPTED)
