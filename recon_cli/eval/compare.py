"""``recon compare``: run several methods on one input, time them, diff them against a reference.

A method is written ``[BACKEND:]STAGE[:NAME=VALUE[:NAME=VALUE...]]``: ``poisson:depth=8``,
``ballpivot``, ``open3d:poisson``, ``pymeshlab:poisson:depth=9``. A comma separates methods
(``poisson:depth=8,ballpivot``); a ``NAME=VALUE`` token after a comma continues the previous
method (``poisson:depth=8,scale=1.2``); inside a value, ``;`` stands for a comma
(``ballpivot:radii=0.01;0.02``). Every method runs through :func:`recon_cli.stages.apply_stage`
(``BACKEND`` becomes its ``backend`` parameter), each in a fresh child process so that its
wall time and peak memory are its own and a crash stays its own. A stage that cannot be
loaded (a plugin whose module is missing) is reported ``unavailable``; a method that raises is reported ``failed``
with its message; the others go on.

Outputs in ``DIR``: ``<method>.ply`` (each result), ``<method>.png`` (shaded + heatmap against
the reference), ``overview.png`` (all methods side by side), ``results.json``, ``report.md``
and ``report.html``.
"""

from __future__ import annotations

import contextlib
import html
import os
import re
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Sequence

from recon_cli.errors import InputError, ParameterError, ReconError

STATUS_OK = "ok"
STATUS_FAILED = "failed"
STATUS_UNAVAILABLE = "unavailable"
BACKENDS = ("native", "open3d", "pymeshlab")


@dataclass
class Method:
    """One method of a comparison: a stage, its backend and parameters (CLI string forms)."""

    stage: str
    backend: str | None = None
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        parts = ([self.backend] if self.backend else []) + [self.stage]
        parts += [f"{k.replace('_', '-')}={v}" for k, v in self.params.items()]
        return ":".join(parts)

    @property
    def slug(self) -> str:
        return re.sub(r"[^A-Za-z0-9.]+", "_", self.label).strip("_")

    def stage_params(self) -> dict[str, Any]:
        p = dict(self.params)
        if self.backend:
            p["backend"] = self.backend
        return p


def parse_methods(spec: str | Sequence[str]) -> list[Method]:
    """Methods from ``--methods`` text (see the module docstring); a sequence is joined by commas.

    Raises
    ------
    ParameterError
        Empty text, a parameter before any method, a malformed ``NAME=VALUE``, or the
        same method twice.
    """
    if not isinstance(spec, str):
        spec = ",".join(spec)
    methods: list[Method] = []
    for raw in spec.split(","):
        token = raw.strip()
        if not token:
            continue
        if "=" in token and ":" not in token.split("=", 1)[0]:
            if not methods:
                raise ParameterError(f"method parameter {token!r} comes before any method")
            _add_param(methods[-1], token)
            continue
        parts = token.split(":")
        backend = None
        if parts[0] in BACKENDS:
            backend = None if parts[0] == "native" else parts[0]
            parts = parts[1:]
        if not parts or not parts[0] or "=" in parts[0]:
            raise ParameterError(f"method {token!r} names no stage")
        m = Method(stage=parts[0], backend=backend)
        for p in parts[1:]:
            _add_param(m, p)
        methods.append(m)
    if not methods:
        raise ParameterError("no method given (e.g. --methods poisson:depth=8,ballpivot)")
    labels = [m.label for m in methods]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ParameterError(f"method {dup[0]!r} is given twice")
    return methods


def compare_methods(
    input_path: str | os.PathLike,
    methods: Sequence[Method] | str,
    reference_path: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    samples: int = 200_000,
    seed: int = 0,
    taus: Sequence[float | str] | str | None = None,
    views: Sequence[str] = ("iso",),
    isolate: bool = True,
    progress: Any = None,
) -> dict[str, Any]:
    """Run ``methods`` on the input file, time them, diff each output against the reference.

    Parameters
    ----------
    input_path : path
        The input (PLY cloud, usually with normals).
    methods : sequence of Method, or str
        See :func:`parse_methods`.
    reference_path : path or None
        Ground truth mesh or cloud; None gives timings and topology only.
    out_dir : path
        Folder for the outputs (created if missing).
    samples, seed, taus
        As in :func:`recon_cli.eval.metrics.compare_meshes`.
    views : sequence of str
        Views of the pictures (:data:`recon_cli.eval.render.VIEWS`).
    isolate : bool
        Run each method in a fresh child process (true wall time and peak memory, crash
        isolation). False runs in this process (peak memory then from ``tracemalloc``:
        Python and numpy allocations only).
    progress : Progress or None

    Returns
    -------
    dict
        ``input``, ``reference``, ``samples``, ``seed``, ``methods`` (list of rows:
        ``method``, ``stage``, ``backend``, ``params``, ``status``, ``error``, ``seconds``
        (wall time of the stage), ``peak_mb`` (peak resident memory above the start of the
        stage), ``output``, ``picture``, ``faces``, ``vertices``, ``metrics`` (the
        :func:`~recon_cli.eval.metrics.compare_meshes` dict or None)), ``overview`` (picture
        path or None) and ``files`` (report paths).

    Raises
    ------
    ParameterError
        Unknown stage names or parameters, bad ``samples`` or views (before anything runs).
    InputError
        Unreadable input or reference.
    """
    from recon_cli.eval.metrics import check_samples, compare_meshes, default_vmax, load_geometry, vertex_distances
    from recon_cli.eval.render import camera, comparison_image, write_png
    from recon_cli.stages import STAGES, get_stage, stage_parameters

    if isinstance(methods, str):
        methods = parse_methods(methods)
    methods = list(methods)
    if not methods:
        raise ParameterError("no method given")
    samples = check_samples(samples)
    for v in views:
        camera(v)
    # decide what can run before running anything
    available: dict[str, bool] = {}
    for m in methods:
        if m.stage not in STAGES:
            raise ParameterError(f"unknown stage {m.stage!r} in method {m.label!r} (stages: {', '.join(sorted(STAGES))})")
        try:
            get_stage(m.stage)
        except ParameterError:
            available[m.label] = False
            continue
        available[m.label] = True
        known = stage_parameters(m.stage)
        for k in m.stage_params():
            if k not in known:
                raise ParameterError(f"method {m.label!r}: stage {m.stage!r} has no parameter {k!r} (parameters: {', '.join(sorted(known))})")
    load_geometry(input_path)  # fail early on an unreadable input
    reference = load_geometry(reference_path) if reference_path is not None else None
    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError("exists and is not a folder", out_dir)
    os.makedirs(out_dir, exist_ok=True)

    rows: list[dict[str, Any]] = []
    outputs: dict[str, Any] = {}
    for m in methods:
        row: dict[str, Any] = {
            "method": m.label,
            "stage": m.stage,
            "backend": m.backend or "native",
            "params": dict(m.params),
            "status": STATUS_UNAVAILABLE,
            "error": None,
            "seconds": None,
            "peak_mb": None,
            "output": None,
            "picture": None,
            "vertices": None,
            "faces": None,
            "metrics": None,
        }
        rows.append(row)
        if not available[m.label]:
            row["error"] = f"stage {m.stage!r} is not available (its module cannot be imported)"
            continue
        out_path = os.path.join(out_dir, m.slug + ".ply")
        with progress.task(f"running {m.label}") if progress is not None else contextlib.nullcontext():
            res = _run_isolated(input_path, m, out_path) if isolate else _run_here(input_path, m, out_path)
        row.update({k: res[k] for k in ("status", "error", "seconds", "peak_mb")})
        if res["status"] != STATUS_OK:
            continue
        row["output"] = out_path
        obj = load_geometry(out_path)
        outputs[m.label] = obj
        row["vertices"] = int(len(obj.points))
        row["faces"] = int(len(getattr(obj, "faces", ())))
        if reference is not None:
            try:
                row["metrics"] = compare_meshes(obj, reference, samples=samples, seed=seed, taus=taus)
            except InputError as exc:  # e.g. an empty reconstruction
                row["status"], row["error"] = STATUS_FAILED, f"cannot compare the output: {exc}"

    overview = None
    good = [r for r in rows if r["status"] == STATUS_OK]
    if good:
        dists = {}
        if reference is not None:
            dists = {r["method"]: vertex_distances(outputs[r["method"]], reference) for r in good}
        vmax = None
        if dists:
            taus_abs = [min(r["metrics"]["tau"]) for r in good if r["metrics"]]
            vmax = max([default_vmax(list(dists.values()))] + taus_abs)
        ref_panel = [("reference", reference, None)] if reference is not None else []
        for r in good:
            pic = os.path.join(out_dir, _slug(r["method"]) + ".png")
            panels = [(r["method"], outputs[r["method"]], dists.get(r["method"]))] + ref_panel
            write_png(comparison_image(panels, views=views, vmax=vmax, panel_size=280), pic)
            r["picture"] = pic
        panels = [(r["method"], outputs[r["method"]], dists.get(r["method"])) for r in good] + ref_panel
        overview = os.path.join(out_dir, "overview.png")
        write_png(comparison_image(panels, views=views, vmax=vmax, panel_size=280), overview)

    result = {
        "input": os.fspath(input_path),
        "reference": None if reference_path is None else os.fspath(reference_path),
        "samples": samples,
        "seed": int(seed),
        "methods": rows,
        "overview": overview,
        "files": {
            "results": os.path.join(out_dir, "results.json"),
            "markdown": os.path.join(out_dir, "report.md"),
            "html": os.path.join(out_dir, "report.html"),
        },
    }
    _write_reports(result, out_dir)
    return result


# ----------------------------------------------------------------------------- running


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9.]+", "_", label).strip("_")


def _add_param(m: Method, token: str) -> None:
    if "=" not in token:
        raise ParameterError(f"method parameter {token!r} is not NAME=VALUE")
    k, v = token.split("=", 1)
    k = k.strip().replace("-", "_")
    if not k or not v.strip():
        raise ParameterError(f"method parameter {token!r} is not NAME=VALUE")
    m.params[k] = v.strip().replace(";", ",")


def _run_here(input_path: str | os.PathLike, m: Method, out_path: str) -> dict[str, Any]:
    import tracemalloc

    from recon_cli.io.load import load, save
    from recon_cli.stages import apply_stage

    data = load(input_path)
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        result = apply_stage(m.stage, data, m.stage_params())
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    except ReconError as exc:
        return {"status": STATUS_FAILED, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__, "seconds": None, "peak_mb": None}
    finally:
        tracemalloc.stop()
    save(result.output, out_path)
    return {"status": STATUS_OK, "error": None, "seconds": seconds, "peak_mb": peak}


def _run_isolated(input_path: str | os.PathLike, m: Method, out_path: str) -> dict[str, Any]:
    import multiprocessing as mp

    # spawn, not fork: the parent may hold numba/OpenMP threads that a fork would break
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, os.fspath(input_path), m.stage, m.stage_params(), out_path), daemon=True)
    proc.start()
    send.close()
    try:
        res = recv.recv()
    except EOFError:
        res = None
    proc.join()
    if res is None:
        return {
            "status": STATUS_FAILED,
            "error": f"the method's process died (exit code {proc.exitcode})",
            "seconds": None,
            "peak_mb": None,
        }
    return res


def _child(conn, input_path: str, stage: str, params: dict, out_path: str) -> None:
    """Child process: load, run one stage (timed, peak memory), save; send a small dict back."""
    try:
        from recon_cli import memory
        from recon_cli.io.load import load, save
        from recon_cli.stages import apply_stage

        data = load(input_path)
        memory.reset_peak()
        base = memory.rss_mb() or 0.0
        t0 = time.perf_counter()
        result = apply_stage(stage, data, params)
        seconds = time.perf_counter() - t0
        peak = max(0.0, (memory.peak_mb() or 0.0) - base)
        save(result.output, out_path)
        conn.send({"status": STATUS_OK, "error": None, "seconds": seconds, "peak_mb": peak})
    except ReconError as exc:
        conn.send({"status": STATUS_FAILED, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__, "seconds": None, "peak_mb": None})
    except BaseException as exc:  # a bug in a method must not take the comparison down
        last = traceback.format_exception_only(type(exc), exc)[-1].strip()
        conn.send({"status": STATUS_FAILED, "error": f"unexpected error: {last}", "seconds": None, "peak_mb": None})
    finally:
        conn.close()


# ----------------------------------------------------------------------------- reports


_COLUMNS = (
    ("time s", lambda r: r["seconds"], "{:.3g}"),
    ("peak MB", lambda r: r["peak_mb"], "{:.4g}"),
    ("faces", lambda r: r["faces"], "{}"),
    ("accuracy", lambda r: _m(r, "accuracy"), "{:.4g}"),
    ("completeness", lambda r: _m(r, "completeness"), "{:.4g}"),
    ("chamfer-L1", lambda r: _m(r, "chamfer_l1"), "{:.4g}"),
    ("hausdorff", lambda r: _m(r, "hausdorff"), "{:.4g}"),
    ("hausdorff p95", lambda r: _m(r, "hausdorff_p95"), "{:.4g}"),
)


def _m(row: dict, key: str) -> Any:
    return None if row["metrics"] is None else row["metrics"][key]


def result_table(result: dict) -> tuple[list[str], list[list[str]]]:
    rows = result["methods"]
    taus = next((r["metrics"]["tau_relative"] for r in rows if r["metrics"]), [])
    head = ["method", "status"] + [c[0] for c in _COLUMNS] + [f"F-score @{t * 100:.3g}%" for t in taus]
    head += ["normal consistency", "watertight", "components"]
    body = []
    for r in rows:
        cells = [r["method"], r["status"]]
        for _, get, fmt in _COLUMNS:
            v = get(r)
            cells.append("—" if v is None else fmt.format(v))
        met = r["metrics"]
        cells += ["—" if met is None else f"{f:.4f}" for f in (met["fscore"] if met else [None] * len(taus))]
        nc = None if met is None else met["normal_consistency"]
        cells.append("—" if nc is None else f"{nc:.4f}")
        topo = None if met is None else met["topology"]["candidate"]
        cells.append("—" if not topo or "watertight" not in topo else ("yes" if topo["watertight"] else "no"))
        cells.append("—" if not topo or "components" not in topo else str(topo["components"]))
        body.append(cells)
    return head, body


def _write_reports(result: dict, out_dir: str) -> None:
    from recon_cli.io.atomic import write_bytes
    from recon_cli.stages import report_json

    write_bytes(result["files"]["results"], (report_json(result) + "\n").encode())
    head, body = result_table(result)
    rel = lambda p: os.path.relpath(p, out_dir)  # noqa: E731 - pictures are linked beside the report
    md = [f"# recon compare: {result['input']}", ""]
    md.append(f"Reference: {result['reference'] or '(none: timings and topology only)'}; "
              f"{result['samples']} samples per side, seed {result['seed']}.")
    md += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    md += ["| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |" for cells in body]
    problems = [r for r in result["methods"] if r["error"]]
    if problems:
        md += ["", "## Not measured", ""] + [f"- `{r['method']}` ({r['status']}): {r['error']}" for r in problems]
    if result["overview"]:
        md += ["", "## All methods", "", f"![overview]({rel(result['overview'])})"]
    for r in result["methods"]:
        if r["picture"]:
            md += ["", f"## {r['method']}", "", f"![{r['method']}]({rel(r['picture'])})"]
    write_bytes(result["files"]["markdown"], ("\n".join(md) + "\n").encode())

    e = html.escape
    h = [
        "<!DOCTYPE html>",
        "<html><head><meta charset='utf-8'>",
        f"<title>recon compare: {e(result['input'])}</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}td:first-child{text-align:left}"
        "tr.failed,tr.unavailable{color:#999}img{max-width:100%}</style>",
        "</head><body>",
        f"<h1>recon compare: {e(result['input'])}</h1>",
        f"<p>Reference: {e(result['reference'] or '(none)')}; {result['samples']} samples per side, seed {result['seed']}.</p>",
        "<table><tr>" + "".join(f"<th>{e(c)}</th>" for c in head) + "</tr>",
    ]
    for r, cells in zip(result["methods"], body):
        h.append(f"<tr class='{e(r['status'])}'>" + "".join(f"<td>{e(c)}</td>" for c in cells) + "</tr>")
    h.append("</table>")
    if problems:
        h.append("<h2>Not measured</h2><ul>")
        h += [f"<li><code>{e(r['method'])}</code> ({e(r['status'])}): {e(r['error'])}</li>" for r in problems]
        h.append("</ul>")
    if result["overview"]:
        h.append(f"<h2>All methods</h2><img src='{e(rel(result['overview']))}' alt='overview'>")
    for r in result["methods"]:
        if r["picture"]:
            h.append(f"<h2>{e(r['method'])}</h2><img src='{e(rel(r['picture']))}' alt='{e(r['method'])}'>")
    h.append("</body></html>")
    write_bytes(result["files"]["html"], ("\n".join(h) + "\n").encode())
