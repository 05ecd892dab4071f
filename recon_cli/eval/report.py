"""The reports of ``recon compare``.

Results table, ``report.md``, ``report.html``, and what a reader needs to trust the figures
(versions, date, machine, input provenance).

Every column states its unit and which way is better (↑ higher, ↓ lower); every method
lists the parameters it actually ran with (the stage's defaults, the values given, and what
the stage resolved itself, such as automatic ball radii). The HTML is one self-contained page
(inline CSS and a few lines of inline JavaScript to sort the tables by a click on a column
head; pictures are linked beside it): it works offline.
"""

from __future__ import annotations

import hashlib
import html
import os
import platform
import time
from collections.abc import Callable
from typing import Any

from recon_cli.geometry import PointCloud, TriangleMesh

# libraries whose versions make a comparison reproducible
LIBRARIES = ("numpy", "scipy", "numba", "open3d", "pymeshlab", "pillow")


def environment() -> dict[str, Any]:
    """Versions, date and machine of this run.

    Returns
    -------
    dict
        ``recon`` (version), ``python``, ``libraries`` (name -> version or None when not
        installed; read from package metadata, nothing is imported), ``date`` (UTC, ISO
        8601), ``machine`` (``system``, ``cpu``, ``cores``, ``memory_gb``, ``load_average``
        (1, 5, 15 min, or None)).
    """
    from importlib import metadata

    from recon_cli import __version__

    libs: dict[str, str | None] = {}
    for name in LIBRARIES:
        try:
            libs[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            libs[name] = None
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        load = None
    return {
        "recon": __version__,
        "python": platform.python_version(),
        "libraries": libs,
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {
            "system": f"{platform.system()} {platform.release()} {platform.machine()}",
            "cpu": _cpu_model(),
            "cores": os.cpu_count(),
            "memory_gb": _memory_gb(),
            "load_average": load,
        },
    }


def file_provenance(
    path: str | os.PathLike, obj: TriangleMesh | PointCloud | None = None
) -> dict[str, Any]:
    """Where an input came from: path, size, SHA-256, what it holds and its recorded history.

    Parameters
    ----------
    path : path
    obj : TriangleMesh or PointCloud, optional
        The file's content, already read (for counts and the PLY ``comment`` history).

    Returns
    -------
    dict
        ``path``, ``bytes``, ``sha256``, ``modified`` (UTC ISO), and with ``obj``: ``kind``
        (``"mesh"``/``"cloud"``), ``points``, ``faces``, ``normals`` (bool), ``history``
        (the provenance lines the file carries, e.g. ``recon 0.1.0 normals knn=30``).
    """
    path = os.fspath(path)
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    st = os.stat(path)
    out: dict[str, Any] = {
        "path": path,
        "bytes": int(st.st_size),
        "sha256": h.hexdigest(),
        "modified": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(st.st_mtime)),
    }
    if obj is not None:
        faces = obj.faces if isinstance(obj, TriangleMesh) else ()
        is_mesh = len(faces) > 0
        out.update(
            {
                "kind": "mesh" if is_mesh else "cloud",
                "points": int(len(obj.points)),
                "faces": int(len(faces)),
                "normals": obj.normals is not None,
                "history": [str(x) for x in getattr(obj, "history", [])],
            }
        )
    return out


# ----------------------------------------------------------------------------- table

# (title, unit kind, better, getter, format); unit kind "length" takes the comparison's unit
Column = tuple[str, str, str, Callable[[dict], Any], str]


def _m(key: str) -> Callable[[dict], Any]:
    return lambda r: None if r["metrics"] is None else r["metrics"][key]


COLUMNS: tuple[Column, ...] = (
    ("stage time", "s", "↓", lambda r: r["seconds"], "{:.3g}"),
    ("process time", "s", "↓", lambda r: r.get("process_seconds"), "{:.3g}"),
    ("peak memory", "MB", "↓", lambda r: r["peak_mb"], "{:.4g}"),
    ("faces", "", "", lambda r: r["faces"], "{}"),
    ("accuracy", "length", "↓", _m("accuracy"), "{:.4g}"),
    ("completeness", "length", "↓", _m("completeness"), "{:.4g}"),
    ("Chamfer-L1", "length", "↓", _m("chamfer_l1"), "{:.4g}"),
    ("Hausdorff", "length", "↓", _m("hausdorff"), "{:.4g}"),
    ("Hausdorff p95", "length", "↓", _m("hausdorff_p95"), "{:.4g}"),
)


def result_table(result: dict, unit: str | None = None) -> tuple[list[str], list[list[str]]]:
    """Head and body (strings) of the results table: one row per method.

    Column heads carry their unit in brackets and ↑/↓ for which way is better.
    """
    unit = unit or result.get("unit") or "model units"
    rows = result["methods"]
    taus: list[float] = next((r["metrics"]["tau_relative"] for r in rows if r["metrics"]), [])
    head = ["method", "status"]
    for title, kind, better, _, _ in COLUMNS:
        u = unit if kind == "length" else kind
        head.append(f"{title}{f' [{u}]' if u else ''}{f' {better}' if better else ''}")
    head += [f"F-score @{t * 100:.3g}% ↑" for t in taus]
    head += ["normal consistency ↑", "watertight", "components"]
    body = []
    for r in rows:
        cells = [r["method"], r["status"]]
        for _, _, _, get, fmt in COLUMNS:
            v = get(r)
            cells.append("—" if v is None else fmt.format(v))
        met = r["metrics"]
        cells += [
            "—" if met is None else f"{f:.4f}"
            for f in (met["fscore"] if met else [None] * len(taus))
        ]
        nc = None if met is None else met["normal_consistency"]
        cells.append("—" if nc is None else f"{nc:.4f}")
        topo = None if met is None else met["topology"]["candidate"]
        cells.append(
            "—" if not topo or "watertight" not in topo else ("yes" if topo["watertight"] else "no")
        )
        cells.append("—" if not topo or "components" not in topo else str(topo["components"]))
        body.append(cells)
    return head, body


def parameter_lines(row: dict) -> list[str]:
    """What a method ran with, as lines.

    Its stage parameters (resolved), the reference-library calls it made (exactly what was passed: a
    reference backend uses only some of the stage's parameters), then what its stage reported. Empty
    when it did not run.
    """
    out = []
    params = row.get("params_resolved")
    calls = row.get("library_calls") or []
    if params:
        head = "stage parameters" + (
            " (the backend passes only those in its library call)" if calls else ""
        )
        out.append(
            f"{head}: " + ", ".join(f"{k.replace('_', '-')}={_value(v)}" for k, v in params.items())
        )
    for c in calls:
        args = ", ".join(f"{k}={_value(v)}" for k, v in c["arguments"].items())
        out.append(f"library call: {c['call']}({args}), the library's defaults for the rest")
    rep = {
        k: v for k, v in (row.get("stage_report") or {}).items() if k not in ("stage", "provenance")
    }
    if rep:
        out.append(
            "stage reported: "
            + ", ".join(f"{k.replace('_', '-')} {_value(v)}" for k, v in rep.items())
        )
    return out


# ----------------------------------------------------------------------------- files


def write_reports(result: dict, out_dir: str) -> None:
    """Write ``results.json``, ``report.md`` and ``report.html`` (paths in ``result["files"]``)."""
    from recon_cli.io.atomic import write_bytes
    from recon_cli.stages import report_json

    write_bytes(result["files"]["results"], (report_json(result) + "\n").encode())
    write_bytes(result["files"]["markdown"], markdown(result, out_dir).encode())
    write_bytes(result["files"]["html"], html_page(result, out_dir).encode())


def markdown(result: dict, out_dir: str) -> str:
    """``report.md``: the table with units and ↑/↓, the setting, parameters and pictures."""
    head, body = result_table(result)
    rel = lambda p: os.path.relpath(p, out_dir)  # noqa: E731 - pictures are linked beside the report
    md = [f"# recon compare: {result['input']}", ""]
    md += [f"- {line}" for line in _setting_lines(result)]
    md += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    md += ["| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |" for cells in body]
    md += ["", _legend_line(result)]
    problems = [r for r in result["methods"] if r["error"]]
    if problems:
        md += ["", "## Not measured", ""] + [
            f"- `{r['method']}` ({r['status']}): {r['error']}" for r in problems
        ]
    md += ["", "## Parameters each method ran with", ""]
    for r in result["methods"]:
        lines = parameter_lines(r)
        md.append(f"- `{r['method']}` ({r['backend']}){'' if lines else ': not run'}")
        md += [f"  - {line}" for line in lines]
    if result.get("plot"):
        md += ["", "## Quality against time", "", f"![quality against time]({rel(result['plot'])})"]
    if result["overview"]:
        md += ["", "## All methods", "", f"![overview]({rel(result['overview'])})"]
    for r in result["methods"]:
        if r["picture"]:
            md += ["", f"## {r['method']}", "", f"![{r['method']}]({rel(r['picture'])})"]
    md += ["", "## Inputs", ""] + [f"- {line}" for line in _input_lines(result)]
    return "\n".join(md) + "\n"


_SORT_JS = """
document.querySelectorAll('table.sortable th').forEach(function (th) {
  th.title = 'click to sort';
  th.addEventListener('click', function () {
    var col = th.cellIndex, body = th.closest('table').tBodies[0], rows = Array.from(body.rows);
    var asc = th.dataset.dir !== 'asc';
    th.closest('tr').querySelectorAll('th').forEach(function (h) { delete h.dataset.dir; });
    th.dataset.dir = asc ? 'asc' : 'desc';
    function key(r) {
      var c = r.cells[col], v = c.dataset.v;
      return v === undefined ? c.textContent : parseFloat(v);
    }
    rows.sort(function (a, b) {
      var x = key(a), y = key(b), nx = typeof x === 'number', ny = typeof y === 'number';
      if (nx !== ny) return nx ? -1 : 1;  /* numbers first, then text (— last) */
      var d = nx ? x - y : String(x).localeCompare(String(y));
      return asc ? d : -d;
    });
    rows.forEach(function (r) { body.appendChild(r); });
  });
});
"""


def html_page(result: dict, out_dir: str) -> str:
    """``report.html``: the content of :func:`markdown`, offline, tables sortable by a click."""
    e = html.escape
    rel = lambda p: os.path.relpath(p, out_dir)  # noqa: E731
    head, body = result_table(result)
    h = [
        "<!DOCTYPE html>",
        "<html lang='en'><head><meta charset='utf-8'>",
        f"<title>recon compare: {e(result['input'])}</title>",
        "<style>body{font-family:sans-serif;margin:2em;color:#222}"
        "table{border-collapse:collapse;margin:1em 0}"
        "td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}"
        "td:first-child,th:first-child{text-align:left}"
        "th{background:#f2f2f2;cursor:pointer;user-select:none}"
        "th[data-dir=asc]::after{content:' ▲'}th[data-dir=desc]::after{content:' ▼'}"
        "tr.failed,tr.unavailable{color:#999}img{max-width:100%}"
        "code{background:#f4f4f4;padding:1px 3px}.note{color:#555}</style>",
        "</head><body>",
        f"<h1>recon compare: {e(result['input'])}</h1>",
        "<ul>" + "".join(f"<li>{e(line)}</li>" for line in _setting_lines(result)) + "</ul>",
        "<table class='sortable'><thead><tr>"
        + "".join(f"<th>{e(c)}</th>" for c in head)
        + "</tr></thead><tbody>",
    ]
    for r, cells in zip(result["methods"], body, strict=True):
        tds = []
        for c in cells:
            try:
                tds.append(f"<td data-v='{float(c)!r}'>{e(c)}</td>")
            except ValueError:
                tds.append(f"<td>{e(c)}</td>")
        h.append(f"<tr class='{e(r['status'])}'>" + "".join(tds) + "</tr>")
    h.append("</tbody></table>")
    h.append(f"<p class='note'>{e(_legend_line(result))}</p>")
    problems = [r for r in result["methods"] if r["error"]]
    if problems:
        h.append("<h2>Not measured</h2><ul>")
        h += [
            f"<li><code>{e(r['method'])}</code> ({e(r['status'])}): {e(r['error'])}</li>"
            for r in problems
        ]
        h.append("</ul>")
    h.append("<h2>Parameters each method ran with</h2>")
    h.append(
        "<table class='sortable'><thead><tr><th>method</th><th>backend</th>"
        "<th>parameters</th></tr></thead><tbody>"
    )
    for r in result["methods"]:
        lines = parameter_lines(r)
        ran = "<br>".join(e(x) for x in lines) if lines else "not run"
        h.append(
            f"<tr><td><code>{e(r['method'])}</code></td><td>{e(r['backend'])}</td>"
            f"<td style='text-align:left'>{ran}</td></tr>"
        )
    h.append("</tbody></table>")
    if result.get("plot"):
        h.append(
            "<h2>Quality against time</h2>"
            f"<img src='{e(rel(result['plot']))}' alt='quality against time'>"
        )
    if result["overview"]:
        h.append(f"<h2>All methods</h2><img src='{e(rel(result['overview']))}' alt='overview'>")
    for r in result["methods"]:
        if r["picture"]:
            h.append(
                f"<h2>{e(r['method'])}</h2>"
                f"<img src='{e(rel(r['picture']))}' alt='{e(r['method'])}'>"
            )
    h.append(
        "<h2>Inputs</h2><ul>"
        + "".join(f"<li>{e(line)}</li>" for line in _input_lines(result))
        + "</ul>"
    )
    h.append(f"<script>{_SORT_JS}</script>")
    h.append("</body></html>")
    return "\n".join(h) + "\n"


# ----------------------------------------------------------------------------- internals


def _setting_lines(result: dict) -> list[str]:
    env = result.get("environment") or {}
    mach = env.get("machine") or {}
    libs = ", ".join(f"{k} {v}" for k, v in (env.get("libraries") or {}).items() if v)
    unit = result.get("unit") or "model units"
    ref = result["reference"]
    diag = result.get("reference_diagonal")
    lines = [
        f"Reference: {ref or '(none: timings and topology only)'}"
        + (f"; its bounding-box diagonal is {diag:.4g} {unit}" if diag else ""),
        f"Distances in {unit}; {result['samples']} area-uniform samples per side, "
        f"seed {result['seed']}.",
    ]
    if env:
        load = mach.get("load_average")
        lines.append(
            f"recon {env.get('recon')} (Python {env.get('python')}; {libs}), run {env.get('date')}."
        )
        lines.append(
            f"Machine: {mach.get('cpu') or 'unknown CPU'}, {mach.get('cores')} cores, "
            f"{mach.get('memory_gb')} GB memory, {mach.get('system')}"
            + (
                f"; load average {load[0]} at the start "
                "(times are from a shared machine when it is above 0)"
                if load
                else ""
            )
            + "."
        )
    return lines


def _legend_line(result: dict) -> str:
    return (
        "↓ lower is better, ↑ higher is better. Stage time: wall time of the stage itself; "
        "process time: the method's whole child process (start-up, reading the input, the stage, "
        "writing the output), what a user waits for; peak memory: resident high-water mark of the "
        "process above its level before the stage. "
        "F-score thresholds are % of the reference's bounding-box diagonal."
    )


def _input_lines(result: dict) -> list[str]:
    out = []
    for role in ("input", "reference"):
        p = (result.get("provenance") or {}).get(role)
        if not p:
            continue
        what = ""
        if "kind" in p:
            what = (
                f"; {p['kind']}, {p['points']} points"
                + (f", {p['faces']} faces" if p["faces"] else "")
                + (", with normals" if p["normals"] else ", no normals")
            )
        hist = (
            "; history: " + " | ".join(p["history"])
            if p.get("history")
            else "; no recorded history"
        )
        out.append(
            f"{role}: {p['path']} ({p['bytes']} bytes, sha256 {p['sha256'][:16]}…, "
            f"modified {p['modified']}{what}){hist}"
        )
    return out


def _value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return ",".join(_value(x) for x in v)
    if v is None:
        return "none"
    return str(v)


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _memory_gb() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (AttributeError, OSError, ValueError):
        return None
