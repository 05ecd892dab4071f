"""What a 3D Tiles 1.1 tileset recon writes must satisfy (the structure the spec asks for).

No 3D Tiles validator installs from the npm registry here, so :func:`check_tileset` checks
what the spec requires of ``tileset.json`` and its tiles: the asset version, every tile's box
and geometric error (never larger than its parent's), refinement, that every content URI names
a GLB in the folder whose vertices (read with our reader, node matrix applied, turned from
glTF's y-up to the tileset's z-up) lie in the content's box and the tile's, and that every
child's box lies in its parent's. Each content is also checked by the glTF-Validator.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon_cli.io.load import load

# glTF's y-up to 3D Tiles' z-up: (x, y, z) -> (x, -z, y)
Z_UP = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def box_bounds(box: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned bounds of a 3D Tiles ``box`` (centre and three half-axes)."""
    b = np.asarray(box, np.float64)
    assert b.shape == (12,) and np.isfinite(b).all(), box
    half = np.abs(b[3:].reshape(3, 3)).sum(axis=0)
    return b[:3] - half, b[:3] + half


def _inside(lo, hi, outer_lo, outer_hi, slack) -> bool:
    return bool((lo >= outer_lo - slack).all() and (hi <= outer_hi + slack).all())


def tile_vertices(folder: Path, uri: str) -> np.ndarray:
    """A content's vertices in the tileset's frame (before the root's transform)."""
    mesh = load(folder / uri)
    return np.asarray(mesh.vertices, np.float64) @ Z_UP.T


def check_tileset(folder: Path) -> dict:
    """Check ``folder``'s tileset (module docstring); returns ``tileset.json`` and the tiles.

    ``{"doc": ..., "tiles": [(tile dict, depth)], "contents": [paths]}``.
    """
    doc = json.loads((folder / "tileset.json").read_text())
    assert doc["asset"]["version"] == "1.1"
    root = doc["root"]
    assert root["refine"] == "REPLACE"
    assert doc["geometricError"] >= root["geometricError"] >= 0
    found: list[tuple[dict, int]] = []
    contents: list[Path] = []
    stack = [(root, 0, None)]
    while stack:
        tile, depth, parent = stack.pop()
        found.append((tile, depth))
        assert "transform" not in tile or tile is root
        lo, hi = box_bounds(tile["boundingVolume"]["box"])
        slack = 1e-6 * float(np.linalg.norm(hi - lo)) + 1e-9
        if parent is not None:
            assert tile["geometricError"] <= parent["geometricError"]
            assert _inside(lo, hi, *box_bounds(parent["boundingVolume"]["box"]), slack)
        uri = tile["content"]["uri"]
        assert uri.endswith(".glb") and not uri.startswith(("/", ".."))
        contents.append(folder / uri)
        clo, chi = box_bounds(tile["content"]["boundingVolume"]["box"])
        assert _inside(clo, chi, lo, hi, slack)
        v = tile_vertices(folder, uri)
        # content stored as float32 offsets from the box centre: within a float32 unit of the box
        room = slack + 2.0**-22 * float(np.abs(chi - clo).max())
        assert _inside(v.min(axis=0), v.max(axis=0), clo, chi, room), uri
        if not tile.get("children"):
            assert tile["geometricError"] == 0
        for child in tile.get("children", []):
            stack.append((child, depth + 1, tile))
    return {"doc": doc, "tiles": found, "contents": contents}


def load_in_browser(folder: Path, budget_s: float = 600.0) -> dict:
    """Load the tileset in ``folder`` with 3d-tiles-renderer in headless chromium.

    ``tools/gltf/load_tiles.html``, served over HTTP with the tileset and the npm packages,
    refines everywhere (error target 0), so that every tile is loaded, draws the tiles (WebGL
    by SwiftShader) and reports ``done``, ``errors`` (page errors and the renderer's load
    errors; console errors are added here), ``models`` (tile contents loaded), ``drawn``
    (meshes shown), ``pixels`` (covered, of 400 x 300) and the renderer's ``stats``. Chromium
    is Debian's, driven by Playwright (tests/browser.py).
    """
    import functools
    import http.server
    import tempfile
    import threading

    import pytest

    from browser import chromium
    from gltf_checks import TOOLS

    if not (TOOLS / "node_modules" / "3d-tiles-renderer").is_dir():
        pytest.fail("3d-tiles-renderer is not installed: run `make js`")
    with tempfile.TemporaryDirectory() as site:
        root = Path(site)
        (root / "node_modules").symlink_to(TOOLS / "node_modules")
        (root / "tileset").symlink_to(Path(folder).resolve())
        (root / "load_tiles.html").symlink_to(TOOLS / "load_tiles.html")

        class Quiet(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):
                pass

        server = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(Quiet, directory=site)
        )
        threading.Thread(target=server.serve_forever, daemon=True).start()
        port = server.server_address[1]
        console: list[str] = []
        try:
            with chromium() as context:
                page = context.new_page()
                page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
                page.on("pageerror", lambda e: console.append(str(e)))
                page.goto(f"http://127.0.0.1:{port}/load_tiles.html?tileset=/tileset/tileset.json")
                page.wait_for_function(
                    "JSON.parse(document.getElementById('result').textContent).done === true",
                    timeout=budget_s * 1000,
                    polling=500,
                )
                result = json.loads(page.locator("#result").text_content())
        finally:
            server.shutdown()
            server.server_close()
    result["errors"] = result["errors"] + [c for c in console if c not in result["errors"]]
    return result
