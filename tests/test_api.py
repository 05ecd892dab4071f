"""The library (recon_cli.api): a function per stage from its declaration, read/write, the stub.

One function per stage is made from its declaration; ``read``/``write``; the typed stub of the
lazy names.
"""

from __future__ import annotations

import inspect
import pydoc
import subprocess
import sys
import types
import typing

import numpy as np
import open3d as o3d
import pytest
import trimesh
from click.testing import CliRunner

import recon_cli
from recon_cli.api import function_name
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.grid import Grid
from recon_cli.io.tiles import Tileset
from recon_cli.params import Param, StageSpec
from recon_cli.stages import BUILTIN, StageResult, get_spec, register_stage, unregister_stage
from recon_cli.tools import stubs

from shapes import icosphere, random_rotation, shape_cloud
from shared_data import ROOT

_TYPES = {"int": int, "float": float, "bool": bool}


def _alternatives(annotation) -> set:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return {a for x in args for a in _alternatives(x)}
    return {annotation}


# ---- made from the declaration -------------------------------------------------------------------
@pytest.mark.parametrize("stage", BUILTIN)
def test_signature_and_help_are_the_declaration(stage):
    """Each stage's function: signature, annotations, return type and help are its declaration's."""
    spec = get_spec(stage)
    fn = getattr(recon_cli, function_name(stage))
    assert fn is getattr(recon_cli, function_name(stage))  # made once
    assert function_name(stage) in dir(recon_cli) and function_name(stage) in recon_cli.__all__
    sig = inspect.signature(fn)
    params = list(sig.parameters.values())
    first = params[0]
    assert first.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD and first.default is first.empty
    declared = [p for p in params if p.name in spec.defaults()]
    assert [p.name for p in declared] == [p.name for p in spec.params]
    assert {p.name for p in params} - set(spec.defaults()) <= {first.name, "normals", "progress"}
    for q in declared:
        p = spec.param(q.name)
        assert q.kind is inspect.Parameter.KEYWORD_ONLY and q.default == p.default
        alts = _alternatives(q.annotation)
        if p.type in _TYPES:
            assert _TYPES[p.type] in alts, (q.name, q.annotation)
        if p.type == "choice":
            literal = next(a for a in alts if typing.get_origin(a) is typing.Literal)
            assert typing.get_args(literal) == p.choices
        assert (type(None) in alts) == (p.default is None and p.type != "any"), q.name
    ret = sig.return_annotation
    returns = {"mesh": TriangleMesh, "grid": Grid, "tileset": Tileset}
    assert ret is returns.get(spec.gives[0], PointCloud)
    # help() shows every parameter with its type, default and unit
    text = pydoc.render_doc(fn, renderer=pydoc.plaintext)
    for p in spec.params:
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(f"{p.name} : "))
        assert f"default {p.default!r}" in line, line
        if p.unit:
            assert f"Unit: {p.unit}." in " ".join(text.split())
    flat = " ".join(text.split())
    assert "References" in text and "Returns" in text and f"recon {stage} --json" in flat


def test_stub_is_generated_from_the_declarations():
    """``__init__.pyi`` is what ``stubs.render()`` writes, naming every name the package offers."""
    assert (ROOT / "recon_cli" / "__init__.pyi").read_text(encoding="utf-8") == stubs.render(), (
        "recon_cli/__init__.pyi is stale: python -m recon_cli.tools.stubs"
    )
    assert (ROOT / "recon_cli" / "py.typed").exists()
    # every name the package offers is in the stub, and the stub names nothing it lacks
    text = stubs.render()
    for name in recon_cli.__all__:
        assert f'"{name}",' in text
        getattr(recon_cli, name)


def test_a_plugin_stage_becomes_a_function_too():
    """A registered plugin stage is a library function with its parameters until unregistered."""
    toy = StageSpec(
        "toy-shift",
        "Shift a cloud (toy).",
        takes=("cloud",),
        gives=("cloud",),
        params=(Param("dz", "float", 1.0, "Shift along z.", unit="input units", min=0.0),),
    )

    @toy.runner
    def run(data, *, dz, progress=None):
        out = data.copy()
        out.points = out.points + [0.0, 0.0, dz]
        return StageResult(out, {"dz": dz})

    register_stage(toy)
    try:
        fn = recon_cli.toy_shift
        assert list(inspect.signature(fn).parameters) == ["cloud", "normals", "dz", "progress"]
        out = fn(np.zeros((2, 3)), dz=0.5)
        memory = out.report.pop("memory")  # every report's; a plugin has no model
        assert memory["predicted_bytes"] is None and memory["peak_bytes"] > 0
        assert np.allclose(out.points[:, 2], 0.5) and out.report == {
            "dz": 0.5,
            "stage": "toy-shift",
        }
        assert "toy-shift dz=0.5" in out.history[-1]
    finally:
        unregister_stage(toy.name)
    with pytest.raises(AttributeError):
        recon_cli.toy_shift  # noqa: B018


def test_importing_recon_cli_and_calling_a_stage_on_arrays_imports_no_other_library():
    """``recon_cli.normals`` on arrays, in a new process, imports no other geometry library."""
    code = (
        "import sys, numpy as np, recon_cli\n"
        "from recon_cli import aot, memory\n"  # submodules: no stage function looked for
        "assert 'recon_cli.api' not in sys.modules and 'recon_cli.stages' not in sys.modules\n"
        "p = np.random.default_rng(0).normal(size=(200, 3))\n"
        "out = recon_cli.normals(p, knn=10, orient='none')\n"
        "print(sorted(m for m in ('open3d', 'trimesh', 'pymeshlab', 'torch') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


# ---- bad arguments -------------------------------------------------------------------------------
@pytest.mark.parametrize("stage", BUILTIN)
def test_bad_arguments_say_what_the_command_line_says(stage, tmp_path):
    """A bad value of each parameter raises the command line's one-line message, word for word."""
    from recon_cli.cli.main import cli

    spec = get_spec(stage)
    fn = getattr(recon_cli, function_name(stage))
    pts = np.random.default_rng(0).normal(size=(50, 3))
    for p in spec.params:
        if p.type in ("any", "bool"):
            continue
        bad = {"choice": "nope", "vector": "1,2", "floats": "x", "int": "1.5", "float": "x"}[p.type]
        with pytest.raises(ParameterError) as got:
            fn(pts, **{p.name: bad})
        res = CliRunner().invoke(
            cli, [stage, str(tmp_path / "missing.ply"), str(tmp_path / "o.ply"), p.option, bad]
        )
        assert isinstance(res.exception, ParameterError), res.output
        assert str(got.value) == str(res.exception), p.name
        assert "\n" not in str(got.value)
    with pytest.raises(ParameterError, match=f"stage '{stage}' has no parameter 'no-such'"):
        fn(pts, no_such=1)
    with pytest.raises(TypeError, match="positional"):
        fn(pts, 3)


def test_bad_inputs_are_refused_in_one_line():
    """Wrong shapes, non-numbers, mismatched normals and wrong kinds of data: one-line errors."""
    with pytest.raises(InputError, match=r"array of shape \(10, 2\)"):
        recon_cli.normals(np.zeros((10, 2)))
    with pytest.raises(InputError, match="not an array of numbers"):
        recon_cli.normals(["a", "b", "c"])
    with pytest.raises(InputError, match="normals has 3 rows, expected 10"):
        recon_cli.poisson(np.zeros((10, 3)), normals=np.ones((3, 3)))
    with pytest.raises(InputError, match="poisson needs points with normals"):
        recon_cli.poisson(np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(InputError, match="mcubes needs a grid"):
        recon_cli.mcubes(np.zeros((10, 3)))
    with pytest.raises(InputError, match="faces must be an"):
        recon_cli.repair((np.zeros((4, 3)), np.zeros((2, 3), dtype=float)))
    with pytest.raises(ParameterError, match="progress must be true, false or a Progress"):
        recon_cli.normals(np.zeros((10, 3)), progress="yes")


def test_progress_draws_on_the_given_progress(capsys):
    """A given Progress draws the stage's steps; ``progress=True`` off a terminal draws nothing."""
    import io

    from recon_cli.progress import Progress

    stream = io.StringIO()
    p = Progress(stream=stream, enabled=True)
    pts = np.random.default_rng(1).normal(size=(300, 3))
    recon_cli.normals(pts, knn=10, progress=p)
    p.close()
    assert "orienting" in stream.getvalue()
    recon_cli.normals(pts, knn=10, progress=True)  # stderr is no terminal here: nothing drawn
    assert capsys.readouterr().err == ""


# ---- a session, as in trimesh's README -----------------------------------------------------------
def test_the_guide_session_runs(tmp_path, monkeypatch):
    """The user guide's Python session runs as written and gives a closed mesh on the scan.

    Normals, poisson and repair in its history, a trimesh and an Open3D mesh of the same arrays, and
    the OBJ and PLY written read back unchanged.
    """
    # the user guide's Python session, as written: read a scan, normals, poisson, repair, trimesh
    import re

    guide = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    section = guide[guide.index("## A Python session") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "getting-started.md", "exec"), ns)
    cloud, mesh, tm = ns["cloud"], ns["mesh"], ns["tm"]
    assert isinstance(cloud, PointCloud) and cloud.normals is None
    assert ns["oriented"].normals.shape == cloud.points.shape
    assert [h.split()[2] for h in mesh.history[-3:]] == ["normals", "poisson", "repair"]
    assert mesh.report["stage"] == "repair" and mesh.report["faces_out"] == len(mesh.faces) > 10_000
    assert isinstance(tm, trimesh.Trimesh) and tm.is_winding_consistent
    assert np.array_equal(tm.vertices, mesh.vertices) and np.array_equal(tm.faces, mesh.faces)
    o3d_mesh = ns["o3d_mesh"]
    assert isinstance(o3d_mesh, o3d.geometry.TriangleMesh)
    assert np.array_equal(np.asarray(o3d_mesh.triangles), mesh.faces)
    # the mesh stays on the scan (trimmed: no sheet far from it)
    from recon_cli.mesh.distance import closest_points

    d, _, _ = closest_points(mesh.vertices, mesh.faces, cloud.points[::10])
    diag = float(np.linalg.norm(np.ptp(cloud.points, axis=0)))
    assert np.median(d) < 2e-3 * diag
    back = recon_cli.read(tmp_path / "bunny.obj")
    assert np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, mesh.faces)
    recon_cli.write(tm, tmp_path / "tm.ply")  # a trimesh object written by recon
    assert np.array_equal(recon_cli.read(tmp_path / "tm.ply").faces, mesh.faces)


@pytest.mark.parametrize("seed", [1])
def test_numpy_open3d_and_trimesh_inputs_give_the_same_mesh(seed):
    """Poisson of a far-off sphere as arrays, Open3D or trimesh: one mesh, within 2 % of r=1."""
    # a sphere at an offset of 1e6 under a random rotation: double in, double out
    rng = np.random.default_rng(seed)
    pts, nrm = shape_cloud("sphere", 4000, rng, offset=1e6)
    colors = rng.integers(0, 256, (len(pts), 3)).astype(np.uint8)
    ours = recon_cli.poisson(pts, normals=nrm, depth=6)
    assert ours.vertices.dtype == np.float64
    r = np.linalg.norm(ours.vertices - 1e6, axis=1)
    assert np.abs(r - 1.0).max() < 0.02
    assert ours.report["faces"] == len(ours.faces) and "recon" in ours.history[-1]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(nrm)
    pc.colors = o3d.utility.Vector3dVector(colors / 255.0)
    from_o3d = recon_cli.poisson(pc, depth=6)
    assert np.array_equal(from_o3d.vertices, ours.vertices) and np.array_equal(
        from_o3d.faces, ours.faces
    )
    tc = PointCloud(points=pts, normals=nrm, colors=colors).to_trimesh()
    from_tm = recon_cli.poisson(tc, depth=6)
    assert np.array_equal(from_tm.vertices, ours.vertices)
    # a stage keeps the colours it was given (Open3D's float colours read back as 8-bit)
    kept = recon_cli.normals(pc, knn=15)
    assert np.array_equal(kept.colors, colors) and np.array_equal(kept.points, pts)


def test_meshes_and_grids_from_trimesh_and_arrays():
    """``sdf``, ``mcubes``, ``repair`` take trimesh meshes, (v, f) tuples and 3-d arrays alike."""
    rng = np.random.default_rng(5)
    v, f = icosphere(4)
    rot = random_rotation(rng)
    v = v @ rot.T * 3.0 + [1e6, -2e6, 5.0]
    tm = trimesh.Trimesh(v, f, process=False)
    grid = recon_cli.sdf(tm, resolution=48)
    assert isinstance(grid, Grid) and grid.report["source"] == "mesh"
    same = recon_cli.sdf((v, f), resolution=48)
    assert np.array_equal(grid.sdf, same.sdf)
    surface = recon_cli.mcubes(grid)
    r = np.linalg.norm(surface.vertices - [1e6, -2e6, 5.0], axis=1)
    assert np.abs(r - 3.0).max() < 0.02 * 3.0 and surface.report["boundary_edges"] == 0
    # a 3-d array is a grid with unit spacing at the origin
    ijk = np.indices((20, 20, 20)).reshape(3, -1).T
    ball = (np.linalg.norm(ijk - 9.5, axis=1) - 6.0).reshape(20, 20, 20)
    m = recon_cli.mcubes(ball)
    assert np.abs(np.linalg.norm(m.vertices - 9.5, axis=1) - 6.0).max() < 0.05
    fixed = recon_cli.repair(tm)
    assert np.array_equal(fixed.vertices, v) and fixed.report["watertight"]


def test_read_and_write_every_format_round_trip(tmp_path):
    """Meshes (PLY, OBJ, OFF) and clouds (PLY, XYZ, PCD) read back exactly; a cloud is no STL."""
    rng = np.random.default_rng(6)
    v, f = icosphere(2)
    mesh = TriangleMesh(vertices=v * 2 + 1e5, faces=f)
    for suffix in (".ply", ".obj", ".off"):
        recon_cli.write(mesh, tmp_path / f"m{suffix}")
        back = recon_cli.read(tmp_path / f"m{suffix}")
        assert np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, f)
    cloud = PointCloud(points=rng.normal(size=(100, 3)) + 1e5)
    for suffix in (".ply", ".xyz", ".pcd"):
        recon_cli.write(cloud, tmp_path / f"c{suffix}")
        assert np.array_equal(recon_cli.read(tmp_path / f"c{suffix}").points, cloud.points)
    recon_cli.write(mesh.to_open3d(), tmp_path / "o.ply")
    assert np.array_equal(recon_cli.read(tmp_path / "o.ply").vertices, mesh.vertices)
    with pytest.raises(ParameterError, match="holds triangles"):
        recon_cli.write(cloud, tmp_path / "c.stl")
