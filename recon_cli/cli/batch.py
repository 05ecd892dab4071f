"""``recon batch PIPELINE.toml INPUTS... --out DIR``."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("batch")
@click.argument("pipeline", metavar="PIPELINE.toml", type=click.Path(dir_okay=False))
@click.argument("inputs", metavar="INPUTS...", nargs=-1, required=True)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder: DIR/<name>.ply (.npz for a grid) and DIR/batch.json.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Worker processes of the local cluster  [default: cores / threads per worker]",
)
@click.option(
    "--threads-per-worker",
    type=click.IntRange(min=1),
    default=None,
    help="Threads per worker process  [default: 1]",
)
@click.option(
    "--memory-limit",
    default=None,
    metavar="SIZE",
    help="Memory limit per worker, e.g. 4GiB; 'auto' shares the machine's memory out, "
    "'none' = no limit [default: auto]",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Use the Dask cluster whose scheduler is at ADDRESS (tcp://host:8786) instead of a "
    "local one.",
)
@click.option(
    "--force",
    is_flag=True,
    help="Redo inputs whose output is already newer than input and pipeline.",
)
@options.ascii_opt
@options.json_opt
@click.pass_context
def cmd(
    ctx: click.Context,
    pipeline: str,
    inputs: tuple[str, ...],
    out_dir: str,
    workers: int | None,
    threads_per_worker: int | None,
    memory_limit: str | None,
    scheduler: str | None,
    force: bool,
    ascii_: bool,
    json_: bool,
) -> int:
    """Run PIPELINE.toml on every input (files, folders, globs) on Dask.

    Each input becomes DIR/<name>.ply (or .npz when the pipeline ends in a grid), written
    atomically. A failing input never stops the others; an input whose output is newer
    than the input and the pipeline file is skipped (--force redoes it), so an interrupted
    batch resumes where it stopped. By default a local cluster sized to the machine runs
    the inputs; --scheduler uses an existing Dask cluster (inputs and DIR must then be on
    a filesystem the workers share). DIR/batch.json records status, stage timings, peak
    memory and output counts per input.

    Exit status 0 when every input is ok or skipped, 4 when some failed, 130 when
    interrupted (Ctrl-C): the local cluster is closed, the outputs finished so far stay,
    the rest are recorded as interrupted in DIR/batch.json, and a rerun resumes.
    """
    import logging

    from recon_cli.batch import run_batch
    from recon_cli.cli._run import is_quiet, make_progress, verbosity
    from recon_cli.cli.exits import EXIT_BATCH_SOME_FAILED
    from recon_cli.stages import report_json

    summary = run_batch(
        pipeline,
        inputs,
        out_dir,
        workers=workers,
        threads_per_worker=threads_per_worker,
        memory_limit=memory_limit,
        scheduler=scheduler,
        force=force,
        progress=make_progress(ctx),
        ascii=ascii_,
        # Dask's own messages: none by default (failures are in the report), warnings with -v, all
        # with -vv
        log_level={0: logging.CRITICAL, 1: logging.WARNING}.get(verbosity(ctx), logging.INFO),
    )
    if json_:
        click.echo(report_json(summary))
    elif not is_quiet(ctx):
        click.echo(format_summary(summary), err=True)
    return EXIT_BATCH_SOME_FAILED if summary["counts"].get("failed", 0) else 0


def format_summary(summary: dict) -> str:
    """One line per input, then the counts."""
    lines = []
    for r in summary["inputs"]:
        status = r["status"]
        if status == "ok":
            stats = r.get("output_stats", {})
            what = ", ".join(
                f"{k} {v}"
                for k, v in stats.items()
                if k in ("points", "vertices", "faces", "grid_shape", "tiles")
            )
            mem = r.get("peak_memory_mb")
            mem_text = f", {mem:.0f} MB" if isinstance(mem, (int, float)) else ""
            lines.append(
                f"{status:<8} {r['input']} -> {r['output']} ({what}; {r['seconds']:.2f} "
                f"s{mem_text})"
            )
        elif status == "skipped":
            lines.append(f"{status:<8} {r['input']} (up to date: {r['output']})")
        else:
            lines.append(f"{status:<8} {r.get('error', r['input'])}")
    c = summary["counts"]
    lines.append(
        f"{c.get('ok', 0)} ok, {c.get('failed', 0)} failed, {c.get('skipped', 0)} skipped "
        f"in {summary['seconds']:.1f} s; summary in {summary['out']}/batch.json"
    )
    return "\n".join(lines)
