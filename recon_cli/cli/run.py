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
    from recon_cli.cli._run import emit_report, io_formats, make_progress
    from recon_cli.io.load import load, save
    from recon_cli.pipeline import load_pipeline, run_pipeline

    pipe = load_pipeline(pipeline)
    t0 = time.perf_counter()
    load_kw, save_kw = io_formats(ctx, input, output)
    data = load(input, **load_kw)
    out, reports = run_pipeline(pipe, data, progress=make_progress(ctx))
    save(out, output, ascii=ascii_, **save_kw)
    summary = {
        "pipeline": pipeline,
        "input": input,
        "output": "<stdout>" if output == "-" else output,
        "seconds": time.perf_counter() - t0,
        "stages": reports,
    }
    emit_report(ctx, summary, json_=json_, data_on_stdout=(output == "-"))
