"""``recon view MESH_OR_CLOUD [--diff REF] -o page.html``: a self-contained WebGL page."""

from __future__ import annotations

import click


@click.command("view")
@click.argument("path", metavar="MESH_OR_CLOUD", type=click.Path(dir_okay=False, allow_dash=True))
@click.option(
    "-o",
    "--output",
    "out",
    required=True,
    type=click.Path(dir_okay=False, allow_dash=True),
    help="The page to write (HTML; '-': stdout).",
)
@click.option(
    "--diff",
    "reference",
    type=click.Path(dir_okay=False),
    help=(
        "Reference: colour the input by its distance to it, on recon diff's scale, with recon "
        "diff's numbers and a labelled colour bar."
    ),
)
@click.option(
    "--view",
    "view",
    default="iso",
    show_default=True,
    help="First view: front, back, left, right, top, bottom, iso, or AZ,EL in degrees.",
)
@click.option(
    "--up",
    type=click.Choice(["y", "z"]),
    default="y",
    show_default=True,
    help="The axis shown upwards (z: LiDAR, maps); the views and the orbit turn about it.",
)
@click.option("--title", help="Title of the page [default: the file names].")
@click.option(
    "--samples",
    type=int,
    help="With --diff: area-uniform samples on each side [default: 200000].",
)
@click.option("--seed", type=int, help="With --diff: seed of the sampling [default: 0].")
@click.option(
    "--tau",
    help="With --diff: F-score thresholds, absolute or % of the reference's diagonal "
    "[default: 0.5%,1%].",
)
@click.option(
    "--vmax",
    type=float,
    help="With --diff: distance at the top of the colour scale [default: recon diff's].",
)
@click.option("--unit", help="With --diff: unit of the coordinates, shown on the colour bar.")
@click.option("--json", "json_", is_flag=True, help="Print the report as JSON on stdout.")
@click.pass_context
def cmd(ctx, path, out, reference, view, up, title, json_, **diff):
    """Write one HTML page showing a mesh or cloud in 3-D (WebGL; opens with no network).

    Drag to rotate, right-drag to pan, wheel to zoom. The first view is the one recon
    diff --png draws for --view. With --diff REF the input is coloured by its distance to REF
    (recon diff's colour scale and numbers); the reference coloured by its distance to the
    input can be shown too.
    """
    from recon_cli.errors import ParameterError
    from recon_cli.eval.view import view_files
    from recon_cli.stages import report_json

    if json_ and str(out) == "-":
        raise ParameterError("--json and -o - would both write to stdout; give -o a file")
    # --samples, --seed, --tau, --vmax, --unit
    given = [f"--{name}" for name, value in diff.items() if value is not None]
    if reference is None and given:
        raise ParameterError(f"{', '.join(given)} need --diff REFERENCE")
    kwargs = {"view": view, "up": up}
    if title is not None:
        kwargs["title"] = title
    if reference is not None:
        kwargs.update(
            samples=200_000 if diff["samples"] is None else diff["samples"],
            seed=0 if diff["seed"] is None else diff["seed"],
            taus=diff["tau"],
            vmax=diff["vmax"],
            unit=diff["unit"],
        )
    report = view_files(path, out, reference, **kwargs)
    if json_:
        click.echo(report_json(report))
    elif not (ctx.find_root().obj or {}).get("quiet"):
        what = f"{report['faces']:,} faces" if report["kind"] == "mesh" else "points"
        click.echo(
            f"wrote {report['output']} ({report['bytes'] / 1e6:.3g} MB): "
            f"{report['vertices']:,} vertices, {what}",
            err=True,
        )
