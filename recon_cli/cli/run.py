"""``recon run PIPELINE.toml IN OUT``."""

from __future__ import annotations

import time

import click

from recon_cli.cli import options


@click.command("run")
@click.argument("pipeline", metavar="PIPELINE.toml", type=click.Path(dir_okay=False))
@options.stage_io
@click.pass_context
def cmd(ctx: click.Context, pipeline: str, input: str, output: str, ascii_: bool, json_: bool) -> None:
    """Run the stages listed in PIPELINE.toml on IN and write OUT.

    The file is checked first: unknown stages or parameters are errors naming the line.
    """
    from recon_cli.cli._run import emit_report, make_progress
    from recon_cli.io.load import load, save
    from recon_cli.pipeline import load_pipeline, run_pipeline

    from recon_cli.cli._signals import immediate
    from recon_cli.errors import naming
    from recon_cli.io.atomic import check_output

    pipe = load_pipeline(pipeline)
    check_output(output)
    t0 = time.perf_counter()
    with immediate():
        data = load(input)
        with naming(input):
            out, reports = run_pipeline(pipe, data, progress=make_progress(ctx))
    save(out, output, ascii=ascii_)
    summary = {
        "pipeline": pipeline,
        "input": input,
        "output": "<stdout>" if output == "-" else output,
        "seconds": time.perf_counter() - t0,
        "stages": reports,
    }
    emit_report(ctx, summary, json_=json_, data_on_stdout=(output == "-"))
