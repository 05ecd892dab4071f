"""``recon convert IN OUT``: re-encode PLY (binary/ASCII), everything kept."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("convert")
@options.input_arg
@options.output_arg
@options.ascii_opt
@click.option("--big-endian", is_flag=True, help="Write binary big-endian.")
def cmd(input: str, output: str, ascii_: bool, big_endian: bool) -> None:
    """Re-encode a PLY file; every element and property is kept."""
    from recon_cli.io.atomic import write_bytes
    from recon_cli.io.ply import parse_ply, read_bytes, serialize_ply

    if ascii_ and big_endian:
        raise click.UsageError("--ascii and --big-endian exclude each other")
    ply = parse_ply(read_bytes(input), input)
    ply.format = "ascii" if ascii_ else ("binary_big_endian" if big_endian else "binary_little_endian")
    write_bytes(output, serialize_ply(ply))
