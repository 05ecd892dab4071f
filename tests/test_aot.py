"""recon_cli.aot: ahead-of-time kernels give the JIT kernels' results, used only when current.

One build for the whole module, in a temporary cache: the install's own when it is current (a
copy), else one made here (``numba.pycc``, ~40 CPU s) from the kernels this process compiled
(loaded) by running the commands JIT, as ``recon warmup`` does.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from recon_cli import aot
from recon_cli.aot.build import modules_to_build

from shapes import FAR_OFFSETS, SHAPES, random_rotation, shape_cloud, single_view_scan

ROOT = Path(__file__).resolve().parents[1]
BP, MC = "recon_cli.stages.ballpivot._kernel", "recon_cli.stages.mcubes._kernel"
PLY, TOPO = aot.MODULES

pytestmark = pytest.mark.slow


def _write_inputs(d: Path) -> dict[str, Path]:
    from recon_cli.geometry import PointCloud
    from recon_cli.grid import Grid
    from recon_cli.io.npz import write_grid
    from recon_cli.io.ply import write_ply

    rng = np.random.default_rng(7)
    out = {}
    p, n = shape_cloud("torus", 4000, rng)
    for dtype in (np.float32, np.float64):
        out[f"cloud_{np.dtype(dtype).name}"] = d / f"cloud_{np.dtype(dtype).name}.ply"
        write_ply(
            PointCloud(points=p.astype(dtype), normals=n.astype(dtype), point_dtype=dtype),
            out[f"cloud_{np.dtype(dtype).name}"],
        )
    x = np.linspace(-1.3, 1.3, 40)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    sdf = SHAPES["torus"][0](np.stack([X, Y, Z], axis=-1).reshape(-1, 3)).reshape(X.shape)
    out["grid"] = d / "torus.npz"
    write_grid(
        Grid(sdf=sdf.astype(np.float32), origin=np.full(3, -1.3), voxel_size=float(x[1] - x[0])),
        out["grid"],
    )
    return out


def _recon(*args: str) -> None:
    from recon_cli.cli.main import cli

    cli.main(args=["-q", *args], prog_name="recon", standalone_mode=False)


@pytest.fixture(autouse=True)
def _numba_config_restored():
    """Numba's configuration re-read from the environment after each test.

    Numba re-reads its environment at each compile: a test that compiled with the build's
    NUMBA_CACHE_DIR would leave it numba's for every kernel module the worker imports next (they
    would compile into the build's folder instead of loading the install's cache).
    """
    yield
    from numba.core import config as numba_config

    numba_config.reload_config()  # after monkeypatch put the environment back (set up before it)


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """(build report, the cache directory holding it, the inputs): the commands ran JIT here first.

    The xdist workers of one run share one build (the first to take the lock makes it).
    """
    import fcntl

    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:
        made = _build(tmp_path_factory.mktemp("aot"))
    else:
        d = tmp_path_factory.getbasetemp().parent / f"aot-{run}"
        d.mkdir(exist_ok=True)
        with open(d / "lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            made = _build(d)
    aot.reset()
    yield made
    aot.reset()


def _build(d: Path) -> tuple[dict, Path, dict[str, Path]]:
    from recon_cli.cli._warmup import build_ahead_of_time
    from recon_cli.io.ply import compile_ply_kernels

    cache = d / "cache"
    if (d / "report.json").exists():  # made by another worker of this run
        report, files = json.loads((d / "report.json").read_text())
        return report, cache, {k: Path(v) for k, v in files.items()}
    report = _install_build(cache)
    if report is not None:
        files = _write_inputs(d)
        (d / "report.json").write_text(json.dumps([report, {k: str(v) for k, v in files.items()}]))
        return report, cache, files
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RECON_AOT", "0")
        aot.reset()
        files = _write_inputs(d)
        for name in ("cloud_float32", "cloud_float64"):
            _recon("ballpivot", str(files[name]), str(d / "bp.ply"))
        _recon("mcubes", str(files["grid"]), str(d / "mc.ply"))
        _recon("mcubes", str(files["grid"]), str(d / "mc.ply"), "--method", "mt")
        for name in ("cloud_float32", "cloud_float64"):
            _recon("filter", str(files[name]), str(d / "f.ply"), "--voxel", "0.05")
            _recon("filter", str(files[name]), str(d / "f.ply"), "--outliers", "10,2")
        compile_ply_kernels()
        mp.delenv("RECON_AOT")
        mp.setenv(
            "NUMBA_CACHE_DIR", str(cache)
        )  # the build's directory only: numba's own cache was fixed at import
        aot.reset()
        report = (
            build_ahead_of_time()
        )  # what recon warmup builds: the kernels and the signal handler
    (d / "report.json").write_text(json.dumps([report, {k: str(v) for k, v in files.items()}]))
    return report, cache, files


def _install_build(cache: Path) -> dict | None:
    """The build ``make install`` made, when current for these sources (on a clean clone, always).

    Conftest's copy of the install's numba cache holds it. Copied to ``cache``, it is what the
    user's commands load; its report is the build's "up to date". None: build here.
    """
    from recon_cli.cli._warmup import build_ahead_of_time

    snapshot = os.environ.get("RECON_TEST_WARM_CACHE")
    if not snapshot:
        return None
    made = Path(snapshot) / "aot" / aot.fingerprint()
    if not (made / aot.MANIFEST).is_file():  # builds are renamed into place whole
        return None
    shutil.copytree(made, cache / "aot" / made.name)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NUMBA_CACHE_DIR", str(cache))
        mp.delenv("RECON_AOT", raising=False)
        aot.reset()
        report = build_ahead_of_time()
    aot.reset()
    return report if report["reason"] == "up to date" else None


@pytest.fixture
def use_build(build, monkeypatch):
    """Switch this process to the module's build (``jit()`` switches back to the numba kernels)."""
    report, cache, _ = build
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    monkeypatch.delenv("RECON_AOT", raising=False)
    aot.reset()

    def jit() -> None:
        monkeypatch.setenv("RECON_AOT", "0")
        aot.reset()

    yield jit
    aot.reset()


def test_build_exports_the_command_kernels(build):
    """The build holds every module warm-up names, the signal handler and the stages' kernels."""
    report, cache, _ = build
    assert report["built"] and report["reason"] in (None, "up to date"), report
    assert sorted(report["modules"]) == sorted(modules_to_build())
    assert {BP, MC, "recon_cli.stages.filter._kernel"} <= set(modules_to_build())
    assert report["libraries"] == ["signal_handler"]
    manifest = json.loads((Path(report["dir"]) / aot.MANIFEST).read_text())
    assert {"ball_pivot", "build_grid", "resolve_pinches"} <= set(
        manifest["modules"][BP]["functions"]
    )
    assert "dense_extract" in manifest["modules"][MC]["functions"]


def test_built_kernels_are_used_and_compiled_by_pycc(use_build):
    """With the build in use, ball pivoting's kernels are pycc's compiled variants, not numba's."""
    k = aot.kernels(BP)
    assert not isinstance(k, types.ModuleType)
    assert k.ball_pivot.aot_variants  # a dispatcher over compiled variants, not the numba kernel
    assert aot.native_library("signal_handler").recon_exit_at_once


def _ballpivot_family():
    rng = np.random.default_rng(11)
    for name in ("sphere", "torus", "thin_plate", "plate_with_hole"):
        for offset in FAR_OFFSETS.values():
            scale = 10.0 ** rng.uniform(-2, 2)
            p, n = shape_cloud(name, 3000, rng, scale=scale, offset=np.asarray(offset))
            yield f"{name} x{scale:.3g} at {offset}", p, n
    for name in ("torus", "rounded_box"):  # partial single-view scans, an open surface
        p, n = single_view_scan(name, 70, rng, direction=random_rotation(rng)[:, 0])
        yield f"{name} scan", p, n


def test_ballpivot_aot_and_jit_give_identical_meshes(use_build):
    """Ball pivoting of scaled, far-off shapes and partial scans: AOT and JIT meshes identical."""
    from recon_cli.stages.ballpivot import ball_pivoting

    cases = list(_ballpivot_family())
    aot_out = [ball_pivoting(p, n) for _, p, n in cases]
    assert not isinstance(aot.kernels(BP), types.ModuleType) and aot.fallbacks() == set()
    use_build()  # JIT from here
    assert isinstance(aot.kernels(BP), types.ModuleType)
    for (name, p, n), a in zip(cases, aot_out, strict=True):
        j = ball_pivoting(p, n)
        assert len(a) > 0, name
        assert np.array_equal(a, j), name


def test_mcubes_aot_and_jit_give_identical_meshes(use_build):
    """Marching cubes/tetrahedra on rotated grids with NaNs: AOT and JIT meshes are identical."""
    from recon_cli.stages.mcubes import marching_cubes

    rng = np.random.default_rng(5)
    grids = []
    for name, (sdf, ext) in SHAPES.items():
        size = int(rng.integers(12, 48))
        x = np.linspace(-ext, ext, size)
        P = (
            np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
            @ random_rotation(rng).T
        )
        vol = sdf(P).reshape(size, size, size).astype(np.float32)
        vol[rng.random(vol.shape) < 0.002] = np.nan  # unknown samples: their cells are left out
        grids.append((name, vol, float(rng.uniform(-0.05, 0.05))))
    runs = {}
    for mode in ("aot", "jit"):
        for method in ("mc", "mt"):
            runs[mode, method] = [
                marching_cubes(v, iso, spacing=0.1, origin=(1e6, 0, -3), method=method)
                for _, v, iso in grids
            ]
        if mode == "aot":
            assert not isinstance(aot.kernels(MC), types.ModuleType) and aot.fallbacks() == set()
        use_build()  # JIT for the second round
    for method in ("mc", "mt"):
        for (name, *_), a, j in zip(grids, runs["aot", method], runs["jit", method], strict=True):
            assert len(a[1]) > 0, name
            for x, y in zip(a, j, strict=True):
                assert np.array_equal(x, y), (name, method)


def test_arguments_without_a_variant_run_the_jit_kernel(use_build):
    """Fortran-order arrays and keywords fall back to numba, recorded, with the same result."""
    k = aot.kernels(BP)
    pts = np.random.default_rng(0).random((500, 3))
    lo, cell, dims = pts.min(axis=0), 0.1, np.full(3, 11, np.int64)
    a = k.build_grid(pts, lo, cell, dims)  # a compiled variant
    f = k.build_grid(
        np.asfortranarray(pts), lo, cell, dims
    )  # F layout: no variant, numba compiles one
    kw = k.build_grid(pts, lo, cell=cell, dims=dims)  # keywords: the numba kernel
    from recon_cli.stages.ballpivot import _kernel

    j = _kernel.build_grid(pts, lo, cell, dims)
    fortran = aot.signature_key((np.asfortranarray(pts), lo, cell, dims))
    assert aot.fallbacks() == {(BP, "build_grid", fortran), (BP, "build_grid", "keywords")}
    for x in (a, f, kw):
        for u, v in zip(x, j, strict=True):
            assert np.array_equal(u, v)


def test_a_stale_build_is_never_loaded(build, monkeypatch):
    """Kernel sources changed since the build: another build directory, no manifest, JIT kernels."""
    report, cache, _ = build
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    aot.reset()
    assert aot.build_dir() == report["dir"]
    # a kernel source edited since the build: another fingerprint, another directory
    monkeypatch.setattr(aot, "kernel_sources_fingerprint", lambda: "0123456789abcdef")
    aot.reset()
    assert aot.build_dir() != report["dir"] and aot.manifest() == {}
    assert isinstance(aot.kernels(BP), types.ModuleType)
    assert aot.native_library("signal_handler") is None
    aot.reset()


def test_a_missing_extension_falls_back_to_jit(build, tmp_path, monkeypatch):
    """One module's extension deleted: that module runs JIT, the others still load the build."""
    report, _, _ = build
    copy = tmp_path / "cache"
    shutil.copytree(Path(report["dir"]).parent.parent, copy)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(copy))
    aot.reset()
    manifest = aot.manifest()
    os.remove(Path(aot.build_dir()) / manifest["modules"][MC]["file"])
    assert isinstance(aot.kernels(MC), types.ModuleType)
    assert not isinstance(aot.kernels(BP), types.ModuleType)
    aot.reset()


def test_switched_off_by_the_environment(build, monkeypatch):
    """RECON_AOT=0 with a current build: no manifest read and the numba kernels used."""
    _, cache, _ = build
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    monkeypatch.setenv("RECON_AOT", "0")
    aot.reset()
    assert aot.manifest() == {} and isinstance(aot.kernels(BP), types.ModuleType)
    aot.reset()


RUN_COMMAND = (
    "import sys\n"
    "from recon_cli.cli.main import main\n"
    "try:\n"
    "    main(sys.argv[1:])\n"
    "except SystemExit as e:\n"
    "    assert not e.code, e.code\n"
    "print('numba' in sys.modules)\n"
)


@pytest.mark.parametrize(
    "command,args", [("ballpivot", ()), ("mcubes", ()), ("filter", ("--voxel", "0.05"))]
)
def test_the_command_as_a_process_never_loads_numba_and_writes_the_jit_result(
    build, tmp_path, command, args
):
    """A command as a process with the build never imports numba and writes JIT's exact bytes."""
    report, cache, files = build
    src = str(files["grid"] if command == "mcubes" else files["cloud_float32"])
    outs = {}
    for mode in ("aot", "jit"):
        env = dict(os.environ)
        if mode == "aot":
            env["NUMBA_CACHE_DIR"] = str(cache)
            env.pop("RECON_AOT", None)
        else:
            env["RECON_AOT"] = "0"
        outs[mode] = tmp_path / f"{mode}.ply"
        r = subprocess.run(
            [sys.executable, "-c", RUN_COMMAND, "-q", command, src, str(outs[mode]), *args],
            env=env,
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert r.returncode == 0, r.stderr
        assert r.stdout.split()[-1] == ("False" if mode == "aot" else "True"), r.stderr
    assert outs["aot"].read_bytes() == outs["jit"].read_bytes()


def _typeof_cases():
    a = np.arange(24.0).reshape(4, 6)
    ro = np.arange(5, dtype=np.int32)
    ro.flags.writeable = False
    unaligned = np.frombuffer(bytes(81), dtype=np.uint8)[1:].view(np.float64)
    return [
        a,
        a.T,
        a[:, ::2],
        a[0],
        np.zeros((2, 2, 2), np.float32),
        ro,
        np.zeros(3, bool),
        np.zeros(0, np.uint16),
        unaligned,
        np.array(1.5),
        3,
        -(2**62),
        2.5,
        True,
        np.float32(1),
        np.int8(3),
        np.bool_(False),
        np.uint64(5),
        (1, 2, 3),
        (1, 2.0),
        (),
        (a, 1),
        None,
        1 + 2j,
        np.zeros(2, np.complex64),
    ]


@pytest.mark.parametrize("value", _typeof_cases(), ids=lambda v: type(v).__name__)
def test_type_key_is_numbas_type(value):
    """``aot.type_key`` equals the key of ``numba.typeof`` for arrays, scalars, tuples and None."""
    import numba

    from recon_cli.aot.build import numba_type_key

    assert aot.type_key(value) == numba_type_key(numba.typeof(value))
    assert aot.type_key(value) is not None


def test_values_numba_cannot_take_ahead_of_time_have_no_key():
    """Lists, ints past 64 bits, big-endian or string arrays and str arguments have no type key."""
    assert aot.type_key([1, 2]) is None
    assert aot.type_key(2**64) is None
    assert aot.type_key(np.zeros(2, ">f8")) is None
    assert aot.type_key(np.zeros(2, "U3")) is None
    assert aot.signature_key((np.zeros(2), "x")) is None


NO_COMPILER = (
    "import json\n"
    "from recon_cli import aot\n"
    "from recon_cli.cli._warmup import build_ahead_of_time\n"
    "lines = []\n"
    "out = build_ahead_of_time(log=lines.append)\n"
    "print(json.dumps([out['built'], out['reason'], lines, aot.manifest()]))\n"
)


def test_without_a_c_compiler_nothing_is_built_and_warmup_says_why(tmp_path):
    """CC pointing nowhere: warm-up builds nothing, writes no aot folder and logs one line why."""
    env = dict(os.environ, CC=str(tmp_path / "no-such-cc"), NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    r = subprocess.run(
        [sys.executable, "-c", NO_COMPILER], env=env, capture_output=True, text=True, cwd=ROOT
    )
    assert r.returncode == 0, r.stderr
    built, reason, lines, manifest = json.loads(r.stdout)
    assert built is False and "no working C compiler" in reason and manifest == {}
    assert lines == [
        f"ahead-of-time kernels not built ({reason}): ball pivoting and marching cubes run JIT, "
        "with numba's start-up in each command"
    ]
    assert not (tmp_path / "cache" / "aot").exists()
