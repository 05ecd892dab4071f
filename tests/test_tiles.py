"""recon tiles: 3D Tiles 1.1 tilesets (structure, levels of detail, the globe, refusals)."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import recon_cli
from recon_cli.errors import OutputError, ParameterError
from recon_cli.geometry import TriangleMesh
from recon_cli.io.load import load, save
from recon_cli.mesh.distance import closest_points
from recon_cli.stages.tiles import tiles

from gltf_checks import validate
from shapes import mesh_family
from shared_data import SHARED
from tiles_checks import Z_UP, box_bounds, check_tileset, load_in_browser, tile_vertices

RECON = [sys.executable, "-m", "recon_cli.cli.main"]


@functools.cache
def _autzen() -> TriangleMesh:
    """The shared LiDAR tile as a mesh (Delaunay triangles of its points), its LAS VLRs kept."""
    from scipy.spatial import Delaunay

    cloud = load(SHARED / "autzen_trim.laz")
    pts = np.asarray(cloud.points, np.float64)[::4]
    tri = Delaunay(pts[:, :2] - pts[:, :2].mean(0))
    rgb = np.asarray(cloud.colors)[::4] if cloud.colors is not None else None
    return TriangleMesh(
        vertices=pts, faces=tri.simplices, colors=rgb, obj_info=list(cloud.obj_info)
    )


@functools.cache
def _autzen_tileset(folder: str) -> dict:
    ts, rep = tiles(_autzen(), tile_faces=8000)
    ts.write(folder)
    return rep


@pytest.fixture(scope="module")
def autzen_dir(tmp_path_factory):
    """The Autzen lidar tile's tileset, written once for the module: (folder, report)."""
    folder = tmp_path_factory.mktemp("autzen") / "tileset"
    return folder, _autzen_tileset(str(folder))


def test_lidar_tileset_lands_in_place_on_the_globe(autzen_dir):
    """The lidar tileset is valid glTF and lands at Autzen stadium on the globe."""
    import pyproj

    folder, rep = autzen_dir
    found = check_tileset(folder)
    doc = found["doc"]
    # every content passes the glTF validator
    for r in validate(*found["contents"]):
        assert r["errors"] == 0 and r["warnings"] == 0, r
    assert rep["units"] == "metres" and rep["crs"].startswith("NAD_1983_HARN")
    # Autzen stadium, Eugene, Oregon
    assert abs(rep["latitude"] - 44.05) < 0.02 and abs(rep["longitude"] + 123.07) < 0.02
    transform = np.array(doc["root"]["transform"]).reshape(4, 4).T
    # the leaves hold the mesh's own vertices: through the root's transform, each lands where
    # PROJ puts the vertex (state-plane feet to ECEF metres), within a millimetre
    from scipy.spatial import cKDTree

    m = _autzen()
    crs = pyproj.CRS.from_wkt(recon_cli.io.las.coordinate_system(m.obj_info))
    ecef = np.column_stack(
        pyproj.Transformer.from_crs(crs, 4978, always_xy=True).transform(
            m.vertices[:, 0], m.vertices[:, 1], m.vertices[:, 2] * 0.3048
        )
    )
    leaves = [t for t, _ in found["tiles"] if not t.get("children")]
    placed = np.vstack([tile_vertices(folder, t["content"]["uri"]) for t in leaves])
    placed = placed @ transform[:3, :3].T + transform[:3, 3]
    d, _ = cKDTree(ecef).query(placed)
    assert d.max() < 1e-3
    assert len(np.unique(np.round(placed, 2), axis=0)) == len(m.vertices)  # every vertex, once


def test_tileset_loads_in_a_browser_through_3d_tiles_renderer(autzen_dir):
    """The tileset loads in a browser through 3d-tiles-renderer: every tile, the leaves drawn."""
    folder, rep = autzen_dir
    got = load_in_browser(folder)
    assert got["done"] and got["errors"] == [], got
    # every tile fetched and parsed, the leaves drawn, the terrain in view
    assert got["models"] == got["stats"]["loaded"] == rep["tiles"] and got["stats"]["failed"] == 0
    assert got["drawn"] == rep["leaves"] and got["pixels"] > 0.05 * 400 * 300


def test_terrain_is_a_quadtree_and_errors_bound_the_full_mesh(autzen_dir):
    """Terrain tiles form a quadtree whose geometric errors bound the full mesh's distance."""
    folder, rep = autzen_dir
    found = check_tileset(folder)
    inner = [t for t, _ in found["tiles"] if t.get("children")]
    assert rep["levels"] >= 3 and all(len(t["children"]) <= 4 for t in inner)
    assert all(e > 0 for e in (t["geometricError"] for t in inner))
    leaves_under = {}

    def collect(tile):
        if not tile.get("children"):
            return [tile_vertices(folder, tile["content"]["uri"])]
        out = [v for c in tile["children"] for v in collect(c)]
        leaves_under[id(tile)] = np.vstack(out)
        return out

    collect(found["doc"]["root"])
    for t in inner:
        content = load(folder / t["content"]["uri"])
        v = np.asarray(content.vertices, np.float64) @ Z_UP.T
        d = closest_points(v, content.faces, leaves_under[id(t)])[0]
        # the full-resolution vertices under a tile are within its geometric error of it
        assert d.max() <= t["geometricError"] * (1 + 1e-6) + 1e-6, (d.max(), t["geometricError"])
        # and coarser levels hold fewer faces than their leaves
        assert len(content.faces) <= 8000
    assert rep["faces_written"] > rep["faces_in"]


def test_compact_mesh_is_an_octree_in_its_own_units(tmp_path):
    """A mesh without a coordinate system tiles as an octree in its own units, every face once."""
    m = mesh_family(4)  # a torus at a random offset and scale, no coordinate system
    m.history = ["made by the test"]
    ts = recon_cli.tiles(m, tile_faces=64)
    assert isinstance(ts, recon_cli.Tileset) and ts.report["units"] == "mesh units"
    assert ts.history[-1].startswith("recon ") and "tiles" in ts.history[-1]
    save(ts, tmp_path / "ts")
    found = check_tileset(tmp_path / "ts")
    doc = found["doc"]
    assert "transform" not in doc["root"] and doc["asset"]["extras"]["recon"]["history"][0] == (
        "made by the test"
    )
    assert max(len(t.get("children", [])) for t, _ in found["tiles"]) > 4  # octree cells
    # the leaves together are the mesh: every face once, at its own coordinates
    leaves = [t for t, _ in found["tiles"] if not t.get("children")]
    faces = sum(len(load(tmp_path / "ts" / t["content"]["uri"]).faces) for t in leaves)
    assert faces == len(m.faces)
    # tight: the mesh's box, grown only where a coarser level's vertex lies outside it (by
    # less than that level's geometric error)
    lo, hi = box_bounds(doc["root"]["boundingVolume"]["box"])
    vlo, vhi = m.vertices.min(0), m.vertices.max(0)
    eps = 1e-6 * np.ptp(m.vertices)
    err = doc["root"]["geometricError"]
    assert (lo <= vlo + eps).all() and (hi >= vhi - eps).all()
    assert (lo >= vlo - err - eps).all() and (hi <= vhi + err + eps).all()


def test_crs_given_places_a_mesh_without_one(tmp_path):
    """``crs`` places a mesh without one on the globe, near Autzen."""
    m = _autzen()
    bare = TriangleMesh(vertices=m.vertices, faces=m.faces[:3000])
    ts, rep = tiles(bare, tile_faces=2000, crs=2992)  # NAD83 / Oregon GIC Lambert (ft)
    assert rep["crs"] is not None and abs(rep["latitude"] - 44.05) < 0.05
    assert "transform" in ts.document["root"]


def test_existing_or_impossible_output_refused_nothing_written(tmp_path, monkeypatch):
    """An existing or impossible output is refused in one line and nothing is written."""
    m = mesh_family(2, np.float32)
    save(m, tmp_path / "m.glb")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    for dest, message in (
        (tmp_path / "out", "exists: give a path that does not exist yet"),
        (tmp_path / "m.glb", "exists"),
        (tmp_path / "no" / "out", "output folder does not exist"),
        ("-", "a folder is written here"),
    ):
        r = subprocess.run(
            [*RECON, "tiles", tmp_path / "m.glb", dest], capture_output=True, timeout=300
        )
        err = r.stderr.decode()
        assert r.returncode == 2 and err.count("\n") == 1 and message in err, err
    assert sorted(os.listdir(tmp_path)) == ["m.glb", "out"]
    assert os.listdir(tmp_path / "out") == ["keep.txt"]
    # a failure while the tiles are written leaves nothing behind
    import recon_cli.io.gltf as gltf

    def broken(*args, **kwargs):
        raise ParameterError("broken on purpose")

    ts = recon_cli.tiles(m, tile_faces=64)
    monkeypatch.setattr(gltf, "emit_gltf", broken)
    with pytest.raises(ParameterError, match="broken on purpose"):
        ts.write(tmp_path / "new")
    assert sorted(os.listdir(tmp_path)) == ["m.glb", "out"]
    with pytest.raises(OutputError, match="exists"):
        ts.write(tmp_path / "out")


def test_command_and_pipeline_stage(tmp_path):
    """``recon tiles`` as a command and as the last stage of a pipeline."""
    m = mesh_family(1, np.float32)
    save(m, tmp_path / "m.ply")
    r = subprocess.run(
        [*RECON, "tiles", "--tile-faces", "100", "--json", tmp_path / "m.ply", tmp_path / "t"],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["tiles"] == len(check_tileset(tmp_path / "t")["contents"]) > 1
    toml = '[[stage]]\nname = "smooth"\niterations = 1\n\n[[stage]]\nname = "tiles"\n'
    (tmp_path / "p.toml").write_text(toml + "tile-faces = 100\n")
    r = subprocess.run(
        [*RECON, "run", tmp_path / "p.toml", tmp_path / "m.ply", tmp_path / "p"],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    doc = check_tileset(tmp_path / "p")["doc"]
    assert any("smooth" in line for line in doc["asset"]["extras"]["recon"]["history"])
    (tmp_path / "bad.toml").write_text('[[stage]]\nname = "tiles"\n\n[[stage]]\nname = "smooth"\n')
    r = subprocess.run(
        [*RECON, "run", "--validate", tmp_path / "bad.toml"], capture_output=True, timeout=300
    )
    assert (
        r.returncode == 2 and b"gives a 3D Tiles tileset (a folder: no stage takes it)" in r.stderr
    ), r.stderr
