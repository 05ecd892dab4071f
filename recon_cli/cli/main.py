"""Entry point: the ``recon`` group, lazy subcommands, and the one place errors become exit codes.

Exit codes: 0 success; 1 a stage failed on valid input; 2 bad input or parameters
(click's usage errors too); 3 a reference backend is missing or failed; 4 a batch in
which some inputs failed (``EXIT_BATCH_SOME_FAILED``: ``recon batch`` returns it); 130 interrupted.
"""

from __future__ import annotations

import importlib
import logging
import sys

import click

from recon_cli import __version__

# subcommand -> module under recon_cli.cli holding a click command named ``cmd``;
# imported only when run, so ``recon --help`` stays instant
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("info", "Describe a cloud/mesh (any format) or a grid: counts, properties, topology, history."),
    "normals": ("normals", "Estimate and orient point normals."),
    "poisson": ("poisson", "Screened Poisson reconstruction of an oriented cloud."),
    "ballpivot": ("ballpivot", "Ball-pivoting reconstruction of an oriented cloud."),
    "repair": ("repair", "Make a mesh manifold, clean and consistently oriented."),
    "sdf": ("sdf", "Signed distance grid (.npz) of a mesh or oriented cloud."),
    "mcubes": ("mcubes", "Marching cubes: mesh the zero level set of a grid."),
    "diff": ("diff", "Compare meshes: distances, F-score, topology, pictures."),
    "compare": ("compare", "Run several methods on one input and compare them."),
    "run": ("run", "Run a pipeline file (TOML) on one input."),
    "batch": ("batch", "Run a pipeline file on many inputs (Dask)."),
    "convert": ("convert", "Convert between PLY, OBJ, OFF, STL, XYZ/CSV, PCD, LAS/LAZ (E57 in)."),
}

EXIT_INTERRUPTED = 130
# ``recon batch``: the batch ran to the end but some inputs failed (see DIR/batch.json)
EXIT_BATCH_SOME_FAILED = 4


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module = COMMANDS[name][0]
        try:
            mod = importlib.import_module(f"recon_cli.cli.{module}")
        except ModuleNotFoundError as exc:
            if exc.name != f"recon_cli.cli.{module}":
                raise
            return _missing(name)
        return mod.cmd

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, COMMANDS[name][1]) for name in sorted(COMMANDS)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def _missing(name: str) -> click.Command:
    @click.command(name, context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
    def missing() -> None:
        from recon_cli.errors import ParameterError

        raise ParameterError(f"'recon {name}' is not available in this version of recon yet")

    return missing


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="recon")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or reports on stderr.")
@click.option("--verbose", "-v", count=True, help="More detail: timings, solver iterations (-vv: debug).")
@click.pass_context
def cli(ctx: click.Context, quiet: bool, verbose: int) -> None:
    """recon: surface reconstruction from point clouds.

    Stages read IN and write OUT; '-' is stdin/stdout (binary PLY), so stages pipe:

        recon normals scan.ply - | recon poisson - - | recon repair - mesh.ply
    """
    ctx.ensure_object(dict)
    ctx.obj["quiet"] = quiet
    ctx.obj["verbose"] = 0 if quiet else verbose
    level = logging.WARNING if verbose == 0 or quiet else (logging.INFO if verbose == 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="recon: %(message)s", stream=sys.stderr, force=True)
    logging.getLogger("recon").setLevel(level)


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; map recon's errors to one line on stderr and an exit code."""
    from recon_cli.errors import ReconError

    try:
        rv = cli.main(args=argv, prog_name="recon", standalone_mode=False)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2 if isinstance(exc, click.UsageError) else exc.exit_code)
    except click.exceptions.Abort:
        click.echo("recon: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except KeyboardInterrupt:
        click.echo("recon: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except ReconError as exc:
        click.echo(f"recon: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", err=True)
        sys.exit(exc.exit_code)
    except BrokenPipeError:
        sys.exit(1)
    except MemoryError:
        click.echo("recon: error: out of memory", err=True)
        sys.exit(1)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":  # pragma: no cover
    main()
