"""``recon fit-sdf IN OUT.npz``: options from the stage's declaration (``recon_cli.stages.learned.SPEC``).

The one addition to the generated command: a training stopped by Ctrl-C still writes the best
field so far, and the command then exits 130.
"""

from __future__ import annotations

import click

from recon_cli.cli.options import stage_command
from recon_cli.stages import get_spec

cmd = stage_command("fit-sdf")
_NAMES = [p.name for p in get_spec("fit-sdf").params]


@click.pass_context
def _callback(
    ctx: click.Context, input: str, output: str, ascii_: bool, json_: bool, **values
) -> None:
    from recon_cli.cli._run import run_stage_command
    from recon_cli.cli.main import EXIT_INTERRUPTED

    given = {
        k: values[k]
        for k in _NAMES
        if ctx.get_parameter_source(k) is not click.core.ParameterSource.DEFAULT
    }
    report = run_stage_command(ctx, "fit-sdf", input, output, given, ascii_=ascii_, json_=json_)
    if report.get("interrupted"):
        click.echo(
            f"recon: interrupted: wrote the best field so far ({report['iterations']} iterations)",
            err=True,
        )
        ctx.exit(EXIT_INTERRUPTED)


cmd.callback = _callback
