"""Shared click options and arguments, as named decorators (cf. rasterio's ``rio/options.py``)."""

from __future__ import annotations

import click

# paths are checked by the reader and the writer (one line naming the path, exit 2), not by click
input_arg = click.argument("input", metavar="IN", type=click.Path(allow_dash=True))
output_arg = click.argument("output", metavar="OUT", type=click.Path(allow_dash=True))

ASCII_HELP = "Write text: ASCII PLY / STL, PCD 'DATA ascii' (default binary little-endian)."
JSON_HELP = "Print the report as JSON (on stdout, or stderr when OUT is '-')."
PLAN_HELP = (
    "Print the run's predicted peak memory and the memory it may use, then exit: nothing is "
    "run or written (IN's header is read, or IN when the header does not tell)."
)
ascii_opt = click.option("--ascii", "ascii_", is_flag=True, help=ASCII_HELP)
json_opt = click.option("--json", "json_", is_flag=True, help=JSON_HELP)


def backend_opt(*choices: str):
    """``--backend`` with ``native`` first (the default) and the given reference libraries."""
    return click.option(
        "--backend",
        type=click.Choice(["native", *choices]),
        default="native",
        show_default=True,
        help="Implementation: ours (native) or a reference library (needs recon[reference]).",
    )


def _to_meta(ctx: click.Context, param: click.Parameter, value):
    """Keep a file-format option in ``ctx.meta`` (for ``_run.io_formats``), not as an argument."""
    if value is not None:
        ctx.meta[f"recon.{param.name}"] = value
    return value


def _format_options() -> tuple:
    from recon_cli.io.load import format_choices  # the registry: one list for every option

    return (
        (
            ("--format", "format"),
            f"Format of '-' and of names without a suffix: {format_choices()}.",
        ),
        (
            ("--input-format", "input_format"),
            "Format of IN, whatever its name (e.g. IN is '-'); as --format.",
        ),
        (("--output-format", "output_format"), "Format of OUT, whatever its name; as --format."),
    )


_FORMAT_OPTIONS = _format_options()
_POINTS_ONLY_HELP = (
    "Allow writing a mesh to a points-only format (XYZ, PCD, LAS): its vertices, without the faces."
)


def format_params() -> list[click.Option]:
    """``--format``, ``--input-format``, ``--output-format`` and ``--points-only`` as click options.

    Their values go to ``ctx.meta`` (read by ``_run.io_formats``), not to the callback.
    """
    opts = [
        click.Option(
            list(decls), metavar="FMT", default=None, expose_value=False, callback=_to_meta, help=h
        )
        for decls, h in _FORMAT_OPTIONS
    ]
    opts.append(
        click.Option(
            ["--points-only", "points_only"],
            is_flag=True,
            expose_value=False,
            callback=_to_meta,
            help=_POINTS_ONLY_HELP,
        )
    )
    return opts


format_opt, input_format_opt, output_format_opt = (
    click.option(*decls, metavar="FMT", default=None, expose_value=False, callback=_to_meta, help=h)
    for decls, h in _FORMAT_OPTIONS
)
points_only_opt = click.option(
    "--points-only",
    "points_only",
    is_flag=True,
    expose_value=False,
    callback=_to_meta,
    help=_POINTS_ONLY_HELP,
)


def stage_io(f):
    """IN, OUT, --ascii, --json and the format options: what every stage command takes."""
    for deco in reversed(
        (
            input_arg,
            output_arg,
            ascii_opt,
            json_opt,
            format_opt,
            input_format_opt,
            output_format_opt,
            points_only_opt,
        )
    ):
        f = deco(f)
    return f


# ---- options generated from a stage's declaration ------------------------------------------------
def option_for(p) -> click.Option:
    """The click option of a declared :class:`~recon_cli.params.Param`.

    Values are taken as text and checked by the declaration (one checker for the command
    line, pipelines and the library); booleans are ``--x/--no-x`` flags.
    """
    notes = [p.unit] if p.unit else []
    rng = p.range_text()
    if rng and p.type != "choice":
        notes.append(rng)
    notes += [f"{k!s}: {v}" for k, v in p.special.items()]
    notes.append(f"default: {p.default_text()}")
    help_text = f"{p.help} [{'; '.join(notes)}]"
    if p.type == "bool":
        return click.Option(
            [f"{p.option}/--no-{p.dashed}", p.name], default=bool(p.default), help=help_text
        )
    metavar = (
        p.metavar
        or {
            "int": "N",
            "float": "F",
            "vector": "X,Y,Z",
            "floats": "F,...",
            "any": "VALUE",
            "choice": "[" + "|".join(p.choices) + "]",
        }[p.type]
    )
    return click.Option([p.option, p.name], type=str, default=None, metavar=metavar, help=help_text)


def execution_opts(f):
    """The options of :class:`recon_cli.execution.Execution` (``recon run``'s)."""
    from recon_cli.execution import PARAMS

    for p in reversed(PARAMS):
        f.__click_params__ = [*getattr(f, "__click_params__", []), option_for(p)]
    return f


def execution_values(given: dict, output: str | None) -> dict:
    """The execution options given, the spill folder's parent defaulting to OUT's folder."""
    from recon_cli.execution import Execution

    where = {k: v for k, v in given.items() if v is not None}
    if "temp_dir" not in where and given:  # spill files on the disk the output goes to
        parent = Execution().spill_parent(output)
        if parent is not None:
            where["temp_dir"] = parent
    return where


def stage_command(stage: str) -> click.Command:
    """The ``recon STAGE IN OUT [options]`` command, built from the stage's declaration.

    Every registered stage's command is made here (built-in and plugin alike): its options
    from the parameters, its help from the description. A stage that keeps its best result on
    Ctrl-C (``keeps_partial``) writes it and the command then exits 130.
    """
    import inspect

    from recon_cli.execution import PARAMS as EXECUTION_PARAMS
    from recon_cli.stages import get_spec

    spec = get_spec(stage)
    names = [p.name for p in spec.params]
    how = [p for p in EXECUTION_PARAMS if p.name in spec.execution]

    @click.pass_context
    def callback(
        ctx: click.Context,
        input: str,
        output: str,
        ascii_: bool,
        json_: bool,
        plan: bool,
        **values,
    ) -> None:
        from recon_cli.cli._run import run_stage_command
        from recon_cli.execution import run_on

        given = {
            k: values[k]
            for k in names
            if ctx.get_parameter_source(k) is not click.core.ParameterSource.DEFAULT
        }
        where = execution_values({p.name: values[p.name] for p in how}, output)
        with run_on(**where):
            report = run_stage_command(
                ctx, spec.name, input, output, given, ascii_=ascii_, json_=json_, plan=plan
            )
        if spec.keeps_partial and report.get("interrupted"):
            # the stage caught Ctrl-C and returned its best result, which is written: still 130
            from recon_cli.cli.exits import EXIT_INTERRUPTED

            what = {"grid": "field", "mesh": "mesh"}.get(spec.gives[0], "result")
            done = f" ({report['iterations']} iterations)" if "iterations" in report else ""
            click.echo(f"recon: interrupted: wrote the best {what} so far{done}", err=True)
            ctx.exit(EXIT_INTERRUPTED)

    doc = inspect.cleandoc(spec.description or spec.summary)
    out_arg = click.Argument(
        ["output"], metavar="OUT", type=click.Path(allow_dash=True)
    )  # checked by reader/writer: one line
    in_arg = click.Argument(
        ["input"], metavar="IN", type=click.Path(allow_dash=True)
    )  # checked by reader/writer: one line
    params: list[click.Parameter] = [
        in_arg,
        out_arg,
        click.Option(["--ascii", "ascii_"], is_flag=True, help=ASCII_HELP),
        click.Option(["--json", "json_"], is_flag=True, help=JSON_HELP),
        click.Option(["--plan"], is_flag=True, help=PLAN_HELP),
    ]
    params += [option_for(p) for p in spec.params]
    params += [option_for(p) for p in how]
    params += format_params()
    return click.Command(
        spec.name, callback=callback, params=params, help=doc, short_help=spec.summary
    )


def picture_opts(f):
    """``--view``, ``--vmax`` and ``--unit``.

    How ``recon diff --png`` and ``recon compare`` draw.
    """
    for deco in reversed(
        (
            click.option(
                "--view",
                "views",
                multiple=True,
                default=("turntable",),
                show_default=True,
                help=(
                    "View of the pictures (repeatable): turntable (4 azimuths), front, back, left, "
                    "right, top, bottom, iso, or AZ,EL in degrees."
                ),
            ),
            click.option(
                "--vmax",
                type=float,
                help=(
                    "Distance at the top of the heatmaps' colour scale [default: 99th percentile, "
                    "at least the smallest tau]."
                ),
            ),
            click.option(
                "--unit",
                help=(
                    "Unit of the coordinates, written on the colour bar and in reports (e.g. mm) "
                    "[default: model units]."
                ),
            ),
        )
    ):
        f = deco(f)
    return f
