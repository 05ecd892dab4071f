"""``recon diff A B [MORE...] [--ref GT]``: distances, F-scores, topology, pictures."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from recon_cli.cli import options


@click.command("diff")
@click.argument(
    "files", metavar="A B [MORE...]", nargs=-1, required=True, type=click.Path(dir_okay=False)
)
@click.option(
    "--ref",
    "ref",
    type=click.Path(dir_okay=False),
    help="Reference (ground truth); every FILE is then a candidate.",
)
@click.option(
    "--samples",
    type=int,
    default=200_000,
    show_default=True,
    help="Area-uniform samples on each side.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the sampling.")
@click.option(
    "--tau",
    default="0.5%,1%",
    show_default=True,
    help=(
        "F-score thresholds: absolute distances, or percentages of the reference's bounding-box "
        "diagonal."
    ),
)
@click.option(
    "--json",
    "json_",
    is_flag=True,
    help="Print the result as JSON on stdout (with --ref: a list of rows).",
)
@click.option(
    "--csv",
    "csv_path",
    type=click.Path(allow_dash=True, dir_okay=False),
    help="Write the rows as CSV ('-': stdout).",
)
@click.option(
    "--heatmap",
    type=click.Path(dir_okay=False),
    help="Write the candidate with per-vertex distance (property and colours).",
)
@click.option(
    "--png",
    type=click.Path(dir_okay=False),
    help=(
        "Write a picture: each candidate's shape, accuracy and completeness heatmaps on one colour "
        "scale, and the reference."
    ),
)
@options.picture_opts
@click.pass_context
def cmd(ctx, files, ref, samples, seed, tau, json_, csv_path, heatmap, png, **picture):
    """Compare meshes or clouds.

    Two files: A (candidate) against B (reference). With --ref GT: each FILE against GT,
    one row each. Distances are exact point-to-triangle distances from area-uniform
    samples (point-to-point where a side is a cloud).
    """
    from recon_cli.errors import ParameterError
    from recon_cli.eval.diff import diff_files
    from recon_cli.stages import report_json

    if json_ and csv_path == "-":
        raise ParameterError("--json and --csv - would both write to stdout; give --csv a file")
    if ref is None:
        if len(files) != 2:
            raise ParameterError(
                "give two files (candidate, reference), or --ref GT with the candidates; got "
                f"{len(files)}"
            )
        candidates, reference = [files[0]], files[1]
    else:
        candidates, reference = list(files), ref
    rows = diff_files(
        candidates,
        reference,
        samples=samples,
        seed=seed,
        taus=tau,
        heatmap_path=heatmap,
        png_path=png,
        **picture,  # views, vmax, unit (options.picture_opts)
    )
    quiet = bool((ctx.find_root().obj or {}).get("quiet"))
    if not quiet:
        for row in rows:
            for w in row["warnings"]:
                click.echo(f"recon: warning: {row['candidate']}: {w}", err=True)
    if csv_path is not None:
        from recon_cli.io.atomic import write_bytes

        write_bytes(csv_path, to_csv(rows).encode())
    if json_:
        click.echo(report_json(rows if ref is not None else rows[0]))
    elif csv_path != "-":
        click.echo(format_table(rows))


def csv_columns(rows: list[dict]) -> list[tuple[str, Callable[..., Any]]]:
    """(column name, getter) pairs of the flat CSV view of diff rows."""
    cols: list[tuple[str, Callable[..., Any]]] = [
        ("candidate", lambda r: r["candidate"]),
        ("reference", lambda r: r["reference"]),
        ("mode", lambda r: r["mode"]),
        ("samples_candidate", lambda r: r["samples"]["candidate"]),
        ("samples_reference", lambda r: r["samples"]["reference"]),
    ]
    for key in (
        "accuracy",
        "completeness",
        "chamfer_l1",
        "chamfer_l2",
        "hausdorff",
        "hausdorff_p95",
        "hausdorff_p99",
    ):
        cols.append((key, lambda r, k=key: r[k]))
    for i, rel in enumerate(rows[0]["tau_relative"] if rows else []):
        tag = f"{rel * 100:.4g}%"
        cols.append((f"tau@{tag}", lambda r, i=i: r["tau"][i]))
        for key in ("precision", "recall", "fscore"):
            cols.append((f"{key}@{tag}", lambda r, k=key, i=i: r[k][i]))
    cols += [
        ("normal_consistency", lambda r: r["normal_consistency"]),
        ("normal_consistency_oriented", lambda r: r["normal_consistency_oriented"]),
    ]
    for side in ("candidate", "reference"):
        cols.append((f"area_{side}", lambda r, s=side: r["area"][s]))
        cols.append((f"volume_{side}", lambda r, s=side: r["volume"][s]))
        for key in (
            "vertices",
            "faces",
            "components",
            "boundary_loops",
            "non_manifold_edges",
            "non_manifold_vertices",
            "watertight",
            "genus",
        ):
            cols.append((f"{side}_{key}", lambda r, s=side, k=key: (r["topology"][s] or {}).get(k)))
    return cols


def to_csv(rows: list[dict]) -> str:
    """Diff rows as CSV text (header line first; empty cells for None)."""
    import csv
    import io

    cols = csv_columns(rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([name for name, _ in cols])
    for r in rows:
        w.writerow(
            [
                "" if (v := get(r)) is None else (f"{v:.9g}" if isinstance(v, float) else v)
                for _, get in cols
            ]
        )
    return buf.getvalue()


def format_table(rows: list[dict]) -> str:
    """A text table: one line per candidate, then each file's topology."""
    head = ["candidate", "accuracy", "complete", "chamf-L1", "chamf-L2", "hausdorff", "p95", "p99"]
    taus = rows[0]["tau_relative"]
    head += [f"F@{t * 100:.3g}%" for t in taus] + ["normals"]
    lines = []
    body = []
    for r in rows:
        cells = [_short(r["candidate"])]
        cells += [
            _g(r[k])
            for k in (
                "accuracy",
                "completeness",
                "chamfer_l1",
                "chamfer_l2",
                "hausdorff",
                "hausdorff_p95",
                "hausdorff_p99",
            )
        ]
        cells += [f"{f:.4f}" for f in r["fscore"]]
        cells.append("-" if r["normal_consistency"] is None else f"{r['normal_consistency']:.4f}")
        body.append(cells)
    widths = [max(len(c[i]) for c in [head, *body]) for i in range(len(head))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    r0 = rows[0]
    lines.append(
        f"reference {r0['reference']} (bbox diagonal {_g(r0['reference_diagonal'])}); "
        f"{r0['mode']}; "
        f"{r0['samples']['candidate']} / {r0['samples']['reference']} samples, seed {r0['seed']}"
    )
    lines.append(fmt.format(*head))
    lines += [fmt.format(*c) for c in body]
    lines.append("")
    lines.append("topology and size:")
    seen = [
        (
            r["candidate"],
            r["topology"]["candidate"],
            r["area"]["candidate"],
            r["volume"]["candidate"],
        )
        for r in rows
    ]
    seen.append(
        (
            r0["reference"] + " (ref)",
            r0["topology"]["reference"],
            r0["area"]["reference"],
            r0["volume"]["reference"],
        )
    )
    for name, topo, area, volume in seen:
        if topo is None:
            lines.append(f"  {_short(name)}: point cloud")
            continue
        parts = [f"{topo.get('vertices')} v", f"{topo.get('faces')} f"]
        for key, label in (
            ("components", "components"),
            ("boundary_loops", "holes"),
            ("non_manifold_edges", "nm edges"),
            ("non_manifold_vertices", "nm vertices"),
            ("genus", "genus"),
        ):
            if key in topo:
                parts.append(f"{label} {topo[key]}")
        if "watertight" in topo:
            parts.append("watertight" if topo["watertight"] else "open")
        parts.append(f"area {_g(area)}")
        if volume is not None:
            parts.append(f"volume {_g(volume)}")
        lines.append(f"  {_short(name)}: " + ", ".join(parts))
    for r in rows:
        if r.get("heatmap"):
            lines.append(f"heatmap written to {r['heatmap']}")
    return "\n".join(lines)


def _g(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def _short(path: str, n: int = 40) -> str:
    return path if len(path) <= n else "..." + path[-(n - 3) :]
