"""``recon convert IN OUT``: between any two formats (PLY to PLY: re-encoded, everything kept)."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("convert")
@options.input_arg
@options.output_arg
@options.ascii_opt
@click.option("--big-endian", is_flag=True, help="Write binary big-endian PLY.")
@options.format_opt
@options.input_format_opt
@options.output_format_opt
@options.points_only_opt
@click.pass_context
def cmd(ctx: click.Context, input: str, output: str, ascii_: bool, big_endian: bool) -> None:
    """Convert between formats, chosen by suffix.

    PLY, OBJ, OFF, STL, XYZ/TXT/CSV/PTS, PCD, LAS/LAZ, GLB/glTF (COPC, E57 read only). A PLY from
    a PLY keeps every element and property.
    """
    from recon_cli.cli._run import io_formats
    from recon_cli.io.atomic import write_bytes
    from recon_cli.io.load import FORMATS, check_read, decode, format_of, save
    from recon_cli.io.ply import parse_ply, read_bytes, serialize_ply

    if ascii_ and big_endian:
        raise click.UsageError("--ascii and --big-endian exclude each other")
    load_kw, save_kw = io_formats(ctx, input, output)
    fin = format_of(input, load_kw["format"])
    fout = format_of(output, save_kw["format"]) or FORMATS["ply"]
    if big_endian and fout.name != "ply":
        raise click.UsageError(f"--big-endian is for PLY output, not {fout.name.upper()}")
    if fin is None or fin.name not in ("las", "e57", "copc") or input == "-":
        data = read_bytes(input)
        if fout.name == "ply" and (fin is None or fin.name == "ply") and bytes(data[:3]) == b"ply":
            ply = parse_ply(data, input)
            ply.format = (
                "ascii"
                if ascii_
                else ("binary_big_endian" if big_endian else "binary_little_endian")
            )
            write_bytes(output, serialize_ply(ply))
            return
        obj = decode(data, input, fin)[0]
    else:
        from recon_cli.io.load import load

        obj = load(input, **load_kw)
    dropped = getattr(check_read(obj, input), "invalid_dropped", 0)
    if dropped and not (ctx.find_root().obj or {}).get("quiet"):
        click.echo(f"{input}: {dropped} points with a NaN or infinite coordinate dropped", err=True)
    save(obj, output, ascii=ascii_, **save_kw)
