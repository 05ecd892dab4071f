"""``recon poisson IN OUT``: its options come from the stage's declaration (``recon_cli.stages.poisson.SPEC``).

With ``--workers N`` or ``--scheduler ADDRESS`` the reconstruction runs on a Dask cluster in
slabs (:mod:`recon_cli.stages.poisson.distributed`) and IN is never loaded by this process:
the workers read it by chunks (a binary PLY, LAS/LAZ, or a folder or pattern of tiles).
"""

from __future__ import annotations

from typing import Any

import click

from recon_cli.cli.options import stage_command


def run_poisson(
    ctx: click.Context,
    stage: str,
    input: str,
    output: str,
    params: dict[str, Any],
    ascii_: bool = False,
    json_: bool = False,
) -> dict:
    """The poisson command: the stage as every stage runs (load, apply, save), or, with
    ``--workers`` / ``--scheduler``, from the file by chunks on a cluster."""
    from recon_cli.cli._run import run_stage_command

    if params.get("workers") is None and params.get("scheduler") is None:
        return run_stage_command(ctx, stage, input, output, params, ascii_=ascii_, json_=json_)
    import time

    from recon_cli.batch.cluster import open_client
    from recon_cli.cli._run import emit_report, io_formats, make_progress
    from recon_cli.errors import ParameterError, naming
    from recon_cli.io.atomic import check_output
    from recon_cli.io.load import save
    from recon_cli.stages import get_spec
    from recon_cli.stages.poisson import REPORT_KEYS, check_distributed_options
    from recon_cli.stages.poisson.distributed import reconstruct_files

    spec = get_spec(stage)
    v = spec.check(params, complete=True)
    check_distributed_options(
        v["backend"] if "backend" in v else "native",
        v["degree"],
        v["estimate_normals"],
        v["scheduler"],
        v["workers"],
        v["memory_limit"],
    )
    if input == "-":
        raise ParameterError("--workers/--scheduler read IN by chunks: give a file, not '-'")
    load_kw, save_kw = io_formats(ctx, input, output)
    if load_kw.get("format"):
        raise ParameterError(
            "--workers/--scheduler read IN by its suffix: leave out --input-format"
        )
    check_output(output)
    progress = make_progress(ctx)
    import os

    folder = os.path.dirname(os.path.abspath(output)) if output != "-" else None
    t0 = time.perf_counter()
    with open_client(v["scheduler"], v["workers"], v["memory_limit"]) as (client, info):
        with naming(input):
            res = reconstruct_files(
                input,
                client=client,
                partitions=v["partitions"],
                depth=v["depth"],
                scale=v["scale"],
                point_weight=v["point_weight"],
                samples_per_node=v["samples_per_node"],
                boundary=v["boundary"],
                density=v["density"],
                trim=v["trim"],
                temp_dir=folder,
                progress=progress,
            )
    t1 = time.perf_counter()
    save(res.mesh, output, ascii=ascii_, **save_kw)
    t2 = time.perf_counter()
    rep = res.report
    report = {k: rep[k] for k in REPORT_KEYS}
    report["backend"] = "native"
    report["distributed"] = {"cluster": info, **rep["distributed"]}
    report["timings"] = {
        "read": rep["timings"].get("read", 0.0),
        "stage": t1 - t0,
        "write": t2 - t1,
    }
    report["output"] = "<stdout>" if output == "-" else output
    emit_report(ctx, report, json_=json_, data_on_stdout=(output == "-"))
    return report


cmd = stage_command("poisson", run_poisson)
