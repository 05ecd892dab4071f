"""``recon info FILE``."""

from __future__ import annotations

import click

from recon_cli.cli import options


@click.command("info")
@click.argument(
    "files", metavar="FILE...", nargs=-1, required=True, type=click.Path(allow_dash=True)
)
@options.json_opt
@options.format_opt
@click.pass_context
def cmd(ctx: click.Context, files: tuple[str, ...], json_: bool) -> None:
    """Describe clouds/meshes (PLY, OBJ, OFF, STL, XYZ, PCD, LAS/LAZ, COPC, E57) and grids.

    Counts, properties, bbox, topology, history.

    With --json: a JSON list with one object per FILE (also for a single file).
    """
    import os

    from recon_cli.cli._signals import immediate
    from recon_cli.errors import naming
    from recon_cli.info import describe
    from recon_cli.stages import report_json

    fmt = ctx.meta.get("recon.format")
    reports = []
    with immediate():  # reads and computes only: Ctrl-C ends it at once, even in a kernel
        for f in files:
            with naming(f):
                reports.append(
                    describe(f, fmt if (f == "-" or not os.path.splitext(f)[1]) else None)
                )
    if json_:
        click.echo(report_json(reports))  # always a list, one entry per FILE
        return
    for rep in reports:
        click.echo(format_info(rep))


def format_info(rep: dict) -> str:
    """``recon info``'s report as the text it prints."""
    lines = [f"{rep['file']}: {rep['kind'].replace('_', ' ')}"]
    lines += _grid_lines(rep) if rep["kind"] == "grid" else _geometry_lines(rep)
    if rep["history"]:
        lines.append("  history:")
        lines += [f"    {h}" for h in rep["history"]]
    return "\n".join(lines)


def _grid_lines(rep: dict) -> list[str]:
    """A grid's lines: shape, origin, voxel size, values and the eikonal check."""
    lines = [
        f"  shape          {' x '.join(map(str, rep['shape']))}",
        f"  origin         {', '.join(f'{v:.6g}' for v in rep['origin'])}",
        f"  voxel size     {rep['voxel_size']:.6g}",
        f"  unknown cells  {rep['unknown_cells']}",
    ]
    if rep["range"]:
        lines.append(f"  range          {rep['range'][0]:.6g} .. {rep['range'][1]:.6g}")
    lines.append(f"  inside cells   {rep['inside_cells']}")
    e = rep.get("eikonal")
    if e and e["cells"]:
        lines.append(
            f"  eikonal |grad| mean {e['mean']:.4f}, within 1±0.1: "
            f"{e['fraction_within_0.1'] * 100:.1f}% of {e['cells']} cells"
        )
    elif e is not None:
        lines.append("  eikonal        no interior cell with 6 known neighbours")
    near = (e or {}).get("near")
    if near and near["cells"]:
        lines.append(
            f"  eikonal near   |s| <= {near['distance']:.6g} ({near['of_diagonal']:.0%} of the "
            f"zero level's box diagonal), within 1±0.1: "
            f"{near['fraction_within_0.1'] * 100:.1f}% of {near['cells']} cells "
            f"({near['kinks']} at kinks left out)"
        )
    elif near and near["distance"] is None:
        lines.append("  eikonal near   no sign change: no zero level to measure near")
    return lines


def _geometry_lines(rep: dict) -> list[str]:
    """A cloud's or mesh's lines: counts, elements, bounding box, the format's details, topology."""
    lines = [f"  format         {rep['format']}", f"  vertices       {rep['vertices']}"]
    if rep.get("invalid_dropped"):
        lines.append(f"  invalid        {rep['invalid_dropped']} (NaN/inf coordinates, dropped)")
    if rep.get("organized"):
        lines.append(f"  organized      {rep['organized']} (width x height)")
    lines += [f"  sensor         {s}" for s in rep.get("sensors") or ()]
    if rep["kind"] == "mesh":
        lines.append(f"  faces          {rep['faces']}")
    for el, props in rep["properties"].items():
        lines.append(f"  element {el} ({rep['elements'][el]}): {'; '.join(props)}")
    if rep["bbox"]["min"] is not None:
        lines.append(f"  bbox min       {', '.join(f'{v:.6g}' for v in rep['bbox']['min'])}")
        lines.append(f"  bbox max       {', '.join(f'{v:.6g}' for v in rep['bbox']['max'])}")
        lines.append(f"  bbox diagonal  {rep['bbox']['diagonal']:.6g}")
    for k, v in (rep.get("details") or {}).items():
        lines.append(
            f"  {k.replace('_', ' '):<14} {', '.join(map(str, v)) if isinstance(v, list) else v}"
        )
    topo = rep.get("topology")
    if topo:
        lines.append("  topology:")
        lines += [f"    {k:<26} {v}" for k, v in topo.items()]
    return lines
