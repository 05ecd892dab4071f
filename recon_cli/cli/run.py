"""``recon run PIPELINE.toml IN OUT`` (``--validate``: check only; ``--set STAGE.PARAM=VALUE``)."""

from __future__ import annotations

import time

import click

from recon_cli.cli import options


@click.command("run")
@click.argument("pipeline", metavar="PIPELINE.toml", type=click.Path(dir_okay=False))
@click.argument("input", metavar="IN", required=False, type=click.Path(allow_dash=True))
@click.argument("output", metavar="OUT", required=False, type=click.Path(allow_dash=True))
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="STAGE.PARAM=VALUE",
    help="Override a parameter without editing the file (repeatable): poisson.depth=9, "
    "or 2.depth=9 for the second stage.",
)
@click.option(
    "--validate",
    is_flag=True,
    help="Check the pipeline (and IN, when given) and exit; nothing is written.",
)
@options.ascii_opt
@options.json_opt
@options.format_opt
@options.input_format_opt
@options.output_format_opt
@options.points_only_opt
@options.execution_opts
@click.pass_context
def cmd(
    ctx: click.Context,
    pipeline: str,
    input: str | None,
    output: str | None,
    overrides: tuple[str, ...],
    validate: bool,
    ascii_: bool,
    json_: bool,
    **how: str | None,
) -> None:
    """Run the stages listed in PIPELINE.toml on IN and write OUT.

    The whole pipeline is checked before anything runs: unknown stages or parameters,
    values of the wrong type or out of range, and stages that do not fit together (each
    error names the file and line); then IN is read and checked against the first stage.
    The execution options (--workers, --memory, ...) apply to every stage that honours them.
    """
    from recon_cli.cli._run import emit_report, io_formats, make_progress
    from recon_cli.errors import ParameterError
    from recon_cli.pipeline import check_input, input_hint, load_pipeline, run_pipeline

    pipe = load_pipeline(pipeline, overrides)
    hint = input_hint(pipe)  # a first filter's --crop / --level: a COPC file read in part
    if validate:
        if output is not None:
            raise ParameterError(
                "--validate writes nothing: give PIPELINE.toml and, optionally, IN"
            )
        summary = {
            "pipeline": pipeline,
            "valid": True,
            "stages": [{"stage": s.name, "line": s.line, "params": s.params} for s in pipe.steps],
        }
        if input is not None:
            from recon_cli.io.load import load

            check_input(pipe, load(input, hint=hint), input)
            summary["input"] = input
        emit_report(ctx, summary, json_=json_)
        return
    if input is None or output is None:
        raise click.UsageError("missing IN and OUT (or pass --validate)")
    from recon_cli.cli._signals import immediate
    from recon_cli.errors import naming
    from recon_cli.execution import run_on
    from recon_cli.io.load import check_destination, check_read, load_detailed, read_report, save
    from recon_cli.stages import get_spec

    check_destination(output, get_spec(pipe.steps[-1].name).gives if pipe.steps else ())
    t0 = time.perf_counter()
    load_kw, save_kw = io_formats(ctx, input, output)
    with run_on(**options.execution_values(how, output)), immediate():
        data, details, _ = load_detailed(input, hint=hint, **load_kw)
        check_read(data, input)
        with naming(input):
            check_input(pipe, data, input)
            out, reports = run_pipeline(pipe, data, progress=make_progress(ctx))
    save(out, output, ascii=ascii_, **save_kw)
    summary = {
        "pipeline": pipeline,
        "input": input,
        "output": "<stdout>" if output == "-" else output,
        "seconds": time.perf_counter() - t0,
        "stages": reports,
    }
    read = read_report(data, details)  # invalid points dropped, a COPC window: never silently
    if read:
        summary["read"] = read
    emit_report(ctx, summary, json_=json_, data_on_stdout=(output == "-"))
