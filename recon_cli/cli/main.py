"""Entry point: the ``recon`` group, lazy subcommands, and the one place errors become exit codes.

Exit codes: 0 success; 1 a stage failed on valid input; 2 bad input or parameters (click's usage
errors too); 3 a reference backend is missing or failed; 4 a batch in which some inputs failed
(``EXIT_BATCH_SOME_FAILED``: ``recon batch`` returns it); 130 interrupted (SIGINT, Ctrl-C), 143
terminated (SIGTERM); 141 standard output closed by its reader (a broken pipe: quiet, as ``head``
users expect). Output path errors (missing folder, read-only file system) are exit 2 like bad
input; a full file system (writing OUT or the spill files) is exit 1, as a run that failed.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import signal
import sys

import click

from recon_cli import __version__
from recon_cli.cli.exits import (  # noqa: F401  (the codes are imported from here too)
    EXIT_BATCH_SOME_FAILED,
    EXIT_BROKEN_PIPE,
    EXIT_INTERRUPTED,
)
from recon_cli.errors import ReconError

# numpy's huge pages wait on memory compaction at first touch (bench/calibration.md, Output)
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")

# the commands that are not stages: name -> (module under recon_cli.cli holding a click command
# named ``cmd``, summary); imported only when run, so ``recon --help`` stays instant. Every
# registered stage (recon_cli.stages.STAGES, plugins) is a command too, made from its declaration.
COMMANDS: dict[str, tuple[str, str]] = {
    "info": (
        "info",
        "Describe a cloud/mesh (any format) or a grid: counts, properties, topology, history.",
    ),
    "diff": ("diff", "Compare meshes: distances, F-score, topology, pictures."),
    "compare": ("compare", "Run several methods on one input and compare them."),
    "run": ("run", "Run a pipeline file (TOML) on one input."),
    "batch": ("batch", "Run a pipeline file on many inputs (Dask)."),
    "convert": (
        "convert",
        "Convert between PLY, OBJ, OFF, STL, XYZ/CSV, PCD, LAS/LAZ, glTF/GLB (E57 in).",
    ),
    "view": ("view", "Write one HTML page showing a mesh or cloud in 3-D (WebGL, no network)."),
    "warmup": ("warmup", "Compile every kernel once (run after installing; make install does)."),
}


class _Escape(BaseException):
    """Carries an interrupt or a broken pipe from a command to :func:`main` untouched by click."""

    def __init__(self, exc: BaseException):
        super().__init__(exc)
        self.exc = exc


class LazyGroup(click.Group):
    """Subcommands imported when used.

    Every registered stage (built-in or from a plugin's ``recon.stages`` entry point) is a command
    made from its declaration.
    """

    def list_commands(self, ctx: click.Context) -> list[str]:
        """The commands that are not stages, and every registered stage."""
        return sorted(set(COMMANDS) | set(_stages()))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        """The command ``name``, imported (or made from its stage's declaration) on first use."""
        if name in COMMANDS:
            from recon_cli.cli import _process

            # a stage command ends the start-up pause when its stage starts (cli/_run.py)
            _process.resume()
            cmd = importlib.import_module(f"recon_cli.cli.{COMMANDS[name][0]}").cmd
        elif _is_stage(name):
            from recon_cli.cli.options import stage_command

            cmd = stage_command(name)
        else:
            return None
        return with_global_options(cmd)

    def invoke(self, ctx: click.Context):
        """Run the command; recon's errors become one line and their exit code."""
        try:
            return super().invoke(ctx)
        except (KeyboardInterrupt, BrokenPipeError) as exc:
            # past click's own handling (a blank line and Abort; exit 1 on a broken pipe) to main()
            raise _Escape(exc) from None

    def make_context(self, *args, **kwargs) -> click.Context:
        """Click's context; a usage error is one line and exit 2, as recon's own errors."""
        try:
            return super().make_context(*args, **kwargs)
        except KeyboardInterrupt as exc:  # Ctrl-C while the arguments are parsed
            raise _Escape(exc) from None

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The command list of ``recon --help``, summaries read without importing the stages."""
        from recon_cli.stages import stage_summary

        rows = [(name, COMMANDS[name][1]) for name in COMMANDS]
        rows += [(name, stage_summary(name)) for name in _stages()]
        with formatter.section("Commands"):
            formatter.write_dl(sorted(rows))


def _is_stage(name: str) -> bool:
    """Whether command ``name`` is a stage's.

    A built-in stage is known without reading the installed packages' entry points, which
    would cost every stage command's start-up more than the stage itself often takes.
    """
    from recon_cli.stages import BUILTIN

    return name not in COMMANDS and (name in BUILTIN or name in _stages())


def _stages() -> list[str]:
    """Every registered stage that no other command shadows (the registry, without importing it)."""
    from recon_cli.stages import stage_names

    return [n for n in stage_names() if n not in COMMANDS]


# ---- global options: before or after the subcommand ----------------------------------------------
def _set_quiet(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value:
        _configure(ctx.find_root(), quiet=True)


def _set_verbose(ctx: click.Context, param: click.Parameter, value: int) -> None:
    if value:
        _configure(ctx.find_root(), verbose=value)


def _root_json() -> bool:
    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and (ctx.find_root().obj or {}).get("json", False))


def _configure(root: click.Context, quiet: bool | None = None, verbose: int | None = None) -> None:
    """Record -q/-v on the root context and set the log level (called from either position)."""
    root.ensure_object(dict)
    if quiet is not None:
        root.obj["quiet"] = root.obj.get("quiet", False) or quiet
    if verbose is not None:
        root.obj["verbose_count"] = root.obj.get("verbose_count", 0) + verbose
    q = root.obj.get("quiet", False)
    v = root.obj.get("verbose_count", 0)
    root.obj["verbose"] = 0 if q else v
    level = logging.WARNING if v == 0 or q else (logging.INFO if v == 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="recon: %(message)s", stream=sys.stderr, force=True)
    logging.getLogger("recon").setLevel(level)


def with_global_options(cmd: click.Command) -> click.Command:
    """Add ``-q`` and ``-v`` to a subcommand, so they work after it too: ``recon info IN -q``."""
    have = {o for p in cmd.params for o in getattr(p, "opts", [])}
    for p in cmd.params:
        if p.name == "json_":  # `recon --json info x.ply` = `recon info x.ply --json`
            p.default = _root_json
    if "-q" not in have:
        cmd.params.append(
            click.Option(
                ["--quiet", "-q"],
                is_flag=True,
                expose_value=False,
                callback=_set_quiet,
                is_eager=True,
                help="No progress bars or reports on stderr.",
            )
        )
    if "-v" not in have:
        cmd.params.append(
            click.Option(
                ["--verbose", "-v"],
                count=True,
                expose_value=False,
                callback=_set_verbose,
                is_eager=True,
                help="More detail (-vv: debug).",
            )
        )
    return cmd


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="recon")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or reports on stderr.")
@click.option(
    "--verbose", "-v", count=True, help="More detail: timings, solver iterations (-vv: debug)."
)
@click.option(
    "--json", "json_", is_flag=True, help="Reports as JSON (for the commands that write reports)."
)
@click.pass_context
def cli(ctx: click.Context, quiet: bool, verbose: int, json_: bool) -> None:
    """recon: surface reconstruction from point clouds.

    Stages read IN and write OUT; '-' is stdin/stdout (binary PLY), so stages pipe:

        recon normals scan.ply - | recon poisson - - | recon repair - mesh.ply
    """
    _configure(ctx, quiet=quiet, verbose=verbose)
    ctx.obj["json"] = json_


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; map recon's errors to one line on stderr and an exit code."""
    from recon_cli.cli import _process, _signals

    process = argv is None  # the process's own command line (`recon ...`), not a caller in Python
    if process:
        # before numpy loads: see _process (start-up and exit: ~0.4 s of a numba process)
        _process.start()
    try:
        with _signals.handlers():
            code = _main(argv)
    finally:
        if process:
            _process.finish()
    sys.exit(code)


def _main(argv: list[str] | None) -> int:
    try:
        try:
            rv = cli.main(args=argv, prog_name="recon", standalone_mode=False)
        except _Escape as esc:
            raise esc.exc from None
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return 2 if isinstance(exc, click.UsageError) else exc.exit_code
    except click.exceptions.Abort as exc:
        return _interrupted(getattr(exc.__cause__, "signum", signal.SIGINT))
    except KeyboardInterrupt as exc:
        return _interrupted(getattr(exc, "signum", signal.SIGINT))
    except SystemError as exc:
        # Ctrl-C seen while a numba kernel returned: "CPUDispatcher(...) returned a result with an
        # exception set"
        cause = _interrupt_cause(exc)
        if cause is None:
            raise
        return _interrupted(getattr(cause, "signum", signal.SIGINT))
    except ReconError as exc:
        click.echo(
            f"recon: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
            err=True,
        )
        return exc.exit_code
    except BrokenPipeError:
        # the reader went away (``recon ... - | head``): quiet, and no second error when Python
        # flushes stdout at exit
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno() if sys.stdout is not None else 1)
        return EXIT_BROKEN_PIPE
    except MemoryError:
        click.echo("recon: error: out of memory", err=True)
        return 1
    except OSError as exc:
        # a file-system failure nothing above named: still one line naming the file
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"recon: error: {where}{exc.strerror or exc}", err=True)
        return 2
    return rv if isinstance(rv, int) else 0


def _interrupted(signum: int) -> int:
    click.echo("recon: interrupted" if signum == signal.SIGINT else "recon: terminated", err=True)
    return 128 + int(signum)


def _interrupt_cause(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt in the cause/context chain of ``exc``, if any."""
    seen = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return link
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return None


if __name__ == "__main__":  # pragma: no cover
    main()
