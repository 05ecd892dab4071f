"""``recon warmup``: compile every kernel once, so that no later command compiles."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("warmup")
@click.option(
    "--jobs",
    "-j",
    type=click.IntRange(min=1),
    default=None,
    help="Worker processes compiling at once [default: the usable cores].",
)
@options.json_opt
@click.pass_context
def cmd(ctx, jobs, json_):
    """Compile recon's numba kernels for the types it uses, into the per-user cache.

    `make install` runs it; after `pip install recon`, run it once (a few minutes of CPU,
    spread over the cores): otherwise the first run of each command compiles its kernels.
    The cache is $NUMBA_CACHE_DIR if set, else
    $XDG_CACHE_HOME/recon/numba/<fingerprint of the kernel sources> (~/.cache/recon/numba/...).

    It then compiles the kernels of `recon ballpivot`, `recon mcubes` and the serial ones of
    `recon filter` ahead of time (numba.pycc, needs a C compiler) into <cache>/aot/<fingerprint>,
    so those commands never import numba; the report says whether that build was made, and why
    not. RECON_AOT=0 switches it off.
    """
    from recon_cli.cli._run import emit_report, make_progress
    from recon_cli.cli._warmup import warmup
    from recon_cli.errors import StageFailed

    report = warmup(
        progress=make_progress(ctx),
        log=lambda line: click.echo(f"recon: {line}", err=True),
        jobs=jobs,
    )
    emit_report(ctx, report, json_=json_)
    if report["failed"]:
        raise StageFailed(
            f"warm-up: {len(report['failed'])} step(s) failed: {', '.join(report['failed'])}"
        )
