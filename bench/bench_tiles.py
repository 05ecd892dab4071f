"""``recon tiles`` against writing the same mesh as one GLB (issue 46: target <= 2x).

The mesh is a terrain: a 1582 x 1582 grid (5M faces; ``--quick``: 400 x 400, 320k) of
state-plane-like coordinates (6.4e5, 8.5e5) with hills and 5 cm noise, so that the
simplification of the coarser levels has real work. Both commands run as processes on the
same PLY file, alternately: ``recon tiles m.ply OUT`` (default ``--tile-faces``) and ``recon
convert m.ply m.glb``. The note gives the tiles command's read / stage / write seconds from its
``--json`` report and the CPU seconds of both. A second row loads the tileset in headless
chromium through 3d-tiles-renderer (``tests/tiles_checks.load_in_browser``: every tile fetched,
parsed and drawn) and gives its wall time, the tiles loaded and the errors.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _util import row

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def terrain(n_side: int):
    """A ``n_side`` x ``n_side`` grid terrain mesh (2 (n_side - 1)^2 faces), float64."""
    from recon_cli.geometry import TriangleMesh

    x, y = np.meshgrid(np.arange(n_side, dtype=np.float64), np.arange(n_side, dtype=np.float64))
    rng = np.random.default_rng(0)
    z = 3 * np.sin(x / 40) * np.cos(y / 55) + rng.normal(scale=0.05, size=x.shape)
    v = np.column_stack([x.ravel(), y.ravel(), z.ravel()]) + [6.36e5, 8.49e5, 400.0]
    idx = np.arange(n_side * n_side).reshape(n_side, n_side)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return TriangleMesh(vertices=v, faces=f)


def _process(args: list[str]) -> tuple[float, float, str]:
    """(wall seconds, CPU seconds of the child, stdout) of one ``recon`` process."""
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run([*RECON, "-q", *args], capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise RuntimeError(f"recon {' '.join(args)}: exit {r.returncode}: {r.stderr[-300:]}")
    return wall, ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime, r.stdout


def rows(quick: bool) -> list[dict]:
    """The section's rows: ``recon tiles`` against ``recon convert`` to one GLB, as processes.

    Run alternately on the same terrain PLY; a second row loads the tileset in headless Chromium.
    """
    from recon_cli.io.load import save

    mesh = terrain(400 if quick else 1582)
    repeat = 2 if quick else 1
    with tempfile.TemporaryDirectory() as d:
        src, glb, out = (os.path.join(d, name) for name in ("m.ply", "m.glb", "tiles"))
        save(mesh, src)
        tiles_runs, glb_runs, reports = [], [], []
        for _ in range(repeat):  # alternately: both see the same load
            shutil.rmtree(out, ignore_errors=True)
            wall, cpu, text = _process(["tiles", "--json", src, out])
            tiles_runs.append((wall, cpu))
            reports.append(json.loads(text))
            glb_runs.append(_process(["convert", src, glb])[:2])
        from tiles_checks import load_in_browser

        t0 = time.perf_counter()
        page = load_in_browser(Path(out))
        browser = {"seconds": time.perf_counter() - t0, "peak_mb": float("nan")}
    ours = {"seconds": statistics.median(w for w, _ in tiles_runs), "peak_mb": float("nan")}
    ref = {"seconds": statistics.median(w for w, _ in glb_runs), "peak_mb": float("nan")}
    t = reports[-1]["timings"]
    cpu_t = statistics.median(c for _, c in tiles_runs)
    cpu_g = statistics.median(c for _, c in glb_runs)
    note = (
        f"{reports[-1]['tiles']} tiles, {reports[-1]['levels']} levels; read {t['read']:.3g} s, "
        f"tiles {t['stage']:.3g} s, write {t['write']:.3g} s; CPU {cpu_t:.3g} / {cpu_g:.3g} s; "
        "target ≤ 2×"
    )
    label = f"{len(mesh.faces) // 1000}k-face terrain, processes"
    loaded = (
        f"{page['models']} of {reports[-1]['tiles']} tiles loaded, {page['drawn']} drawn, "
        f"{len(page['errors'])} errors (done: {page['done']}); SwiftShader WebGL"
    )
    return [
        row("tiles", label, ours, "recon convert to one GLB", ref, note),
        row("tiles", f"{label}: load in chromium (3d-tiles-renderer)", browser, note=loaded),
    ]
