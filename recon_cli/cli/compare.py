"""``recon compare IN --methods ... --ref GT --out DIR``."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("compare")
@options.input_arg
@click.option(
    "--methods",
    "methods",
    multiple=True,
    required=True,
    help=(
        "Methods, comma-separated or repeated: [BACKEND:]STAGE[:NAME=VALUE...], e.g. "
        "poisson:depth=8,ballpivot,open3d:poisson."
    ),
)
@click.option(
    "--ref",
    "ref",
    type=click.Path(dir_okay=False),
    help="Reference (ground truth) to diff each output against.",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for outputs, pictures and reports.",
)
@click.option(
    "--samples",
    type=int,
    default=200_000,
    show_default=True,
    help="Area-uniform samples on each side.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the sampling.")
@click.option(
    "--tau",
    default="0.5%,1%",
    show_default=True,
    help="F-score thresholds (absolute, or % of the reference's diagonal).",
)
@options.picture_opts
@click.option(
    "--json", "json_", is_flag=True, help="Print results.json on stdout instead of the table."
)
@click.pass_context
def cmd(ctx, input, methods, ref, out_dir, samples, seed, tau, views, vmax, unit, json_):
    """Run several methods on IN, time each, diff each against --ref.

    Write DIR/report.md, report.html, results.json.
    """
    from recon_cli.cli._run import is_quiet, make_progress
    from recon_cli.eval.compare import compare_methods, parse_methods
    from recon_cli.eval.report import result_table
    from recon_cli.stages import report_json

    result = compare_methods(
        input,
        parse_methods(list(methods)),
        ref,
        out_dir,
        samples=samples,
        seed=seed,
        taus=tau,
        views=views,
        vmax=vmax,
        unit=unit,
        progress=make_progress(ctx),
    )
    if json_:
        click.echo(report_json(result))
        return
    head, body = result_table(result)
    widths = [max(len(c[i]) for c in [head, *body]) for i in range(len(head))]
    click.echo("  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)))
    for cells in body:
        click.echo("  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)))
    if not is_quiet(ctx):
        for r in result["methods"]:
            if r["error"]:
                click.echo(f"recon: {r['method']}: {r['status']}: {r['error']}", err=True)
        click.echo(
            f"report: {result['files']['markdown']}, {result['files']['html']}, "
            f"{result['files']['results']}",
            err=True,
        )
        if result["plot"]:
            click.echo(f"quality against time: {result['plot']}", err=True)
