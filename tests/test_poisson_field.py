"""Poisson's --grid: the solved field on the finest lattice as recon's own grid file.

Its zero level (recon mcubes) is the stage's surface, and it is negative inside.
"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from recon_cli.cli.main import cli
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import read_ply, write_ply
from recon_cli.io.npz import read_grid
from recon_cli.mesh.distance import closest_points
from recon_cli.mesh.sampling import sample_surface
from recon_cli.stages.mcubes import marching_cubes
from recon_cli.stages.poisson import screened_poisson

from shapes import shape_cloud, single_view_scan


def _chamfer_cells(a: TriangleMesh, b: TriangleMesh, cell: float) -> float:
    """Exact point-to-mesh Chamfer (mean of both ways) in finest cells."""
    sa = sample_surface(a, 30_000, seed=1).points
    sb = sample_surface(b, 30_000, seed=2).points
    da = closest_points(b.vertices, b.faces, sa)[0]
    db = closest_points(a.vertices, a.faces, sb)[0]
    return 0.5 * (da.mean() + db.mean()) / cell


CASES = [
    ("sphere", 2, "neumann", 1e6, 1.0, 0.05),
    ("torus", 1, "neumann", 0.0, 1e-3, 0.05),
    ("rounded_box", 2, "dirichlet", -3.0, 10.0, 0.05),
    ("scan", 2, "free", 0.0, 1.0, 0.2),
    ("scan", 2, "neumann", 5e5, 1.0, 0.5),
]


@pytest.mark.parametrize("name,degree,boundary,offset,scale,bound", CASES)
def test_mcubes_of_the_grid_is_the_surface(rng, name, degree, boundary, offset, scale, bound):
    """Marching cubes of the grid is the stage's surface (Chamfer in cells), negative inside.

    Shapes and a scan, both degrees, every boundary, moved and scaled; the grid on the finest
    lattice.
    """
    if name == "scan":
        p, n = single_view_scan("rounded_box", 80, rng, direction=rng.normal(size=3))
        p = p * scale + offset
    else:
        p, n = shape_cloud(name, 15_000, rng, offset=offset, scale=scale)
    r = screened_poisson(p, n, depth=6, degree=degree, boundary=boundary, with_grid=True)
    g = r.grid
    cell = r.report["finest_cell"]
    assert g.voxel_size == pytest.approx(cell, rel=1e-12)
    assert r.report["grid_shape"] == list(g.shape)
    v, f, _ = marching_cubes(g.sdf, 0.0, spacing=g.voxel_size, origin=g.origin)
    ch = _chamfer_cells(TriangleMesh(v, f), r.mesh, cell)
    assert ch < bound, ch  # the target: within one finest cell
    # negative inside, positive outside: at the samples pushed in and out along their normals
    idx = (np.floor((p - g.origin) / g.voxel_size)).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(g.shape) - 1), axis=1)
    inside = (p + 3 * cell * (-n))[ok]
    outside = (p + 3 * cell * n)[ok]

    def at(q):
        k = np.rint((q - g.origin) / g.voxel_size).astype(int)
        k = np.clip(k, 0, np.array(g.shape) - 1)
        return g.sdf[k[:, 0], k[:, 1], k[:, 2]]

    assert np.mean(at(inside) < 0) > 0.97 and np.mean(at(outside) > 0) > 0.97
    # about a distance next to the surface (|grad| = 1 there; chi levels off farther out)
    near = (p + 0.5 * cell * n)[ok]
    k = (near - g.origin) / g.voxel_size
    from scipy.ndimage import map_coordinates

    vals = map_coordinates(g.sdf.astype(np.float64), k.T, order=1)
    assert np.median(vals) == pytest.approx(0.5 * cell, rel=0.35)


def test_cli_grid_mcubes_info(tmp_path, rng):
    """``recon poisson --grid`` then ``recon mcubes`` gives the mesh; ``recon info`` reads it."""
    p, n = shape_cloud("torus", 8000, rng, offset=1e6)
    src = tmp_path / "in.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    out, grid, mc = tmp_path / "out.ply", tmp_path / "field.npz", tmp_path / "mc.ply"
    r = CliRunner().invoke(
        cli, ["poisson", str(src), str(out), "--depth", "6", "--grid", str(grid), "--json"]
    )
    assert r.exit_code == 0, r.output
    g = read_grid(grid)
    assert g.point_dtype == np.float64
    assert any(line.startswith("poisson: (iso - chi)") for line in g.history)
    r = CliRunner().invoke(cli, ["mcubes", str(grid), str(mc)])
    assert r.exit_code == 0, r.output
    cell = g.voxel_size
    assert _chamfer_cells(read_ply(mc), read_ply(out), cell) < 0.1
    r = CliRunner().invoke(cli, ["info", str(grid), "--json"])
    assert r.exit_code == 0 and '"kind": "grid"' in r.output


@pytest.mark.parametrize(
    "grid,extra,match",
    [
        ("-", [], "file name"),
        ("missing/field.npz", [], "folder does not exist"),
        ("field.npz", ["--backend", "open3d"], "native"),
    ],
)
def test_cli_grid_refused(tmp_path, rng, grid, extra, match):
    """``--grid`` to stdout, into a missing folder or with another backend exits 2."""
    p, n = shape_cloud("sphere", 2000, rng)
    src = tmp_path / "in.ply"
    write_ply(PointCloud(points=p, normals=n), src)
    out = tmp_path / "out.ply"
    r = CliRunner().invoke(
        cli,
        ["poisson", str(src), str(out), "--depth", "5", "--grid", str(tmp_path / grid), *extra]
        if grid != "-"
        else ["poisson", str(src), str(out), "--depth", "5", "--grid", "-"],
    )
    assert r.exception is not None and r.exception.exit_code == 2, r.output
    assert match in str(r.exception)
    assert not out.exists()
