"""recon_cli._kernels.numba_setup: one per-user numba cache, set before any kernel is decorated."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import recon_cli
from recon_cli._kernels.numba_setup import kernel_sources_fingerprint

PACKAGE = Path(recon_cli.__file__).resolve().parent
SETUP_IMPORT = "from recon_cli._kernels import numba_setup"


def kernel_files() -> list[Path]:
    """Every module of recon_cli that defines an ``@njit`` kernel."""
    return sorted(
        f
        for f in PACKAGE.rglob("*.py")
        if re.search(r"^@njit", f.read_text(encoding="utf-8"), re.M)
    )


def test_every_kernel_module_imports_numba_setup_before_its_first_kernel():
    """Every kernel module (10 or more) imports numba_setup before it defines a kernel."""
    files = kernel_files()
    assert len(files) >= 10
    for f in files:
        text = f.read_text(encoding="utf-8")
        assert SETUP_IMPORT in text, f"{f.relative_to(PACKAGE)} does not import numba_setup"
        assert text.index(SETUP_IMPORT) < text.index("\n@njit"), (
            f"{f.relative_to(PACKAGE)}: import numba_setup first"
        )
        # the cache fingerprint covers private modules and _kernels/ only
        assert f.name.startswith("_") or f.parent.name == "_kernels", (
            f"{f.relative_to(PACKAGE)}: kernels live in private modules"
        )


def _run(code: str, env: dict) -> str:
    full = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    full.update(env)
    return subprocess.run(
        [sys.executable, "-c", code], env=full, check=True, capture_output=True, text=True
    ).stdout


CALL_KERNEL = (
    "import numpy as np, numba\n"
    "from recon_cli._kernels.arrays import grow1\n"
    "grow1(np.arange(3.0), 5)\n"
    "print(numba.config.CACHE_DIR)\n"
)


def test_cache_goes_to_xdg_cache_home_not_the_package(tmp_path):
    """Compiled kernels are cached under $XDG_CACHE_HOME/recon/numba/<fingerprint>."""
    out = _run(CALL_KERNEL, {"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path / "home")})
    cache = tmp_path / "recon" / "numba" / kernel_sources_fingerprint()
    assert out.strip() == str(cache)
    written = list(cache.rglob("*.nbi"))
    assert any("arrays" in p.name and "grow1" in p.name for p in written), written


def test_numba_cache_dir_is_honoured(tmp_path):
    """NUMBA_CACHE_DIR, when set, is where the kernels are cached, not the XDG folder."""
    mine = tmp_path / "mine"
    out = _run(CALL_KERNEL, {"NUMBA_CACHE_DIR": str(mine), "XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert out.strip() == str(mine)
    assert list(mine.rglob("*grow1*.nbi"))
    assert not (tmp_path / "xdg").exists()


def test_cache_set_even_when_numba_was_imported_first(tmp_path):
    """With numba imported before recon, kernels still cache in recon's folder."""
    code = "import numba\n" + CALL_KERNEL
    out = _run(code, {"XDG_CACHE_HOME": str(tmp_path)})
    cache = tmp_path / "recon" / "numba" / kernel_sources_fingerprint()
    assert out.strip() == str(cache)
    assert list(cache.rglob("*grow1*.nbi"))


def test_any_kernel_source_change_gets_a_cache_of_its_own(tmp_path):
    """Any change to a kernel source moves the fingerprint; other files' changes do not."""
    # numba keys an entry by its own file only: a kernel calling into a changed module would
    # keep stale machine code; the fingerprint moves the whole cache when any kernel source changes
    pkg = tmp_path / "pkg"
    (pkg / "_kernels").mkdir(parents=True)
    (pkg / "stage").mkdir()
    files = {
        "_kernels/arrays.py": "a",
        "stage/_kernel.py": "k",
        "stage/__init__.py": "i",
        "stage/public.py": "p",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    base = kernel_sources_fingerprint(str(pkg))
    assert base == kernel_sources_fingerprint(str(pkg)) and len(base) == 16
    for name in ("_kernels/arrays.py", "stage/_kernel.py"):
        f = pkg / name
        st = f.stat()
        os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
        changed = kernel_sources_fingerprint(str(pkg))
        assert changed != base, name
        base = changed
    (pkg / "stage" / "_more.py").write_text("new")  # a new kernel module
    assert kernel_sources_fingerprint(str(pkg)) != base
    base = kernel_sources_fingerprint(str(pkg))
    for name in ("stage/__init__.py", "stage/public.py"):  # no kernels there: no recompiling
        f = pkg / name
        os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 1_000_000))
        assert kernel_sources_fingerprint(str(pkg)) == base, name


def test_numpy_submodules_numba_would_load_stay_lazy_until_used():
    """numpy.f2py and numpy.testing stay unloaded by numba's start-up, and work when used.

    numba's start-up (through scipy.linalg) star-imports numpy; numpy.f2py and numpy.testing
    are not executed by it, and work as usual when first used.
    """
    code = (
        "import sys, numpy as np\n"
        "from recon_cli._kernels.arrays import grow1\n"
        "grow1(np.arange(3.0), 5)\n"
        "import numba\n"
        "numba.njit(lambda x: x + 1)(1)\n"  # a compile: numba's whole context, its BLAS check too
        "assert 'scipy.linalg' in sys.modules\n"  # numba's BLAS check ran
        "print(sorted(m for m in sys.modules if m.startswith(('numpy.f2py.', 'numpy.testing.'))))\n"
        "np.testing.assert_allclose(np.ma.masked_array([1.0, 2.0], mask=[0, 1]).sum(), 1.0)\n"
        "from numpy.f2py import crackfortran\n"
        "print(sorted(m for m in sys.modules if m.startswith(('numpy.testing.', "
        "'numpy.f2py.')))[:2])\n"
    )
    before, after = _run(code, {}).splitlines()
    assert before == "[]"
    assert after != "[]"


def test_threading_layer_survives_numba_rereading_its_environment(tmp_path):
    """With numba imported before recon, the threading layer stays omp, never Open3D's TBB."""
    # numba imported first (as a library might), then recon: numba's compiler re-reads the
    # NUMBA_* variables at the next compile (NUMBA_CACHE_DIR changed) and must still find omp
    # first, never try the old TBB that Open3D ships (a NumbaWarning)
    code = (
        "import warnings; warnings.simplefilter('error')\n"
        "import numba, numpy as np\n"
        "from recon_cli._kernels import numba_setup\n"
        "from numba.core import config\n"
        "config.reload_config()\n"
        "print(config.THREADING_LAYER_PRIORITY[0])\n"
        "@numba.njit(parallel=True)\n"
        "def f(a):\n"
        "    s = 0.0\n"
        "    for i in numba.prange(len(a)):\n"
        "        s += a[i]\n"
        "    return s\n"
        "f(np.ones(10))\n"
        "print(numba.threading_layer())\n"
    )
    first, layer = _run(code, {"XDG_CACHE_HOME": str(tmp_path)}).split()
    assert first == "omp" and layer in ("omp", "workqueue")


LEAN_LOADS = (
    "import sys, numpy as np, numba\n"
    "from recon_cli._kernels.arrays import grow1\n"
    "from recon_cli.stages.normals._kernel import pca_normals\n"
    "grow1(np.arange(3.0), 5)\n"  # cached: loaded without numba's registries
    "print('arraymath' if 'numba.np.arraymath' in sys.modules else 'lean')\n"
    "rng = np.random.default_rng(0)\n"
    "p = np.c_[rng.random(200), rng.random(200), np.zeros(200)]\n"
    "nbr = np.argsort(((p[:, None] - p[None]) ** 2).sum(-1), axis=1)[:, "
    ":8].astype(np.int64).ravel()\n"
    # a parallel kernel after a lean load
    "nrm = pca_normals(p, np.arange(0, 8 * 200 + 1, 8), nbr, 1e-12)[0]\n"
    "print(np.abs(np.abs(nrm[:, 2]) - 1).max() < 1e-9)\n"
)
LEAN = (
    LEAN_LOADS + "@numba.njit\n"
    "def det(a):\n"
    "    return np.linalg.det(a) + np.sum(a) + len(str(3))\n"
    # compiling afterwards: the full context (LAPACK, unicode)
    "print(round(det(np.eye(3) * 2.0), 6))\n"
)


@pytest.mark.parametrize("full", [False, True])
def test_cached_kernels_load_without_numba_registries_and_compiling_still_works(full):
    """A cached kernel loads with numba's runtime only; compiling afterwards still works.

    A cached kernel loads with numba's runtime only (no typing/lowering registries, no
    scipy.linalg: ~0.2 CPU s per process); kernels compiled afterwards see the whole context.
    """
    _run(LEAN_LOADS, {})  # cache what LEAN loads (compiled the first time if the cache is cold)
    out = _run(LEAN, {"RECON_NUMBA_FULL_REFRESH": "1"} if full else {}).split()
    assert out == ["arraymath" if full else "lean", "True", "15.0"]


STAGES_WITHOUT_ARRAYMATH = (
    "import sys, numpy as np\n"
    "sys.path.insert(0, %r)\n"
    "from shapes import sphere_cloud\n"
    "from recon_cli.geometry import PointCloud\n"
    "from recon_cli.grid import Grid\n"
    "from recon_cli.stages import apply_stage\n"
    "p, n = sphere_cloud(3000, seed=1)\n"
    "mesh = apply_stage('ballpivot', PointCloud(points=p, normals=n), {}).output\n"
    "x = np.linspace(-1, 1, 20)\n"
    "sdf = np.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2) - 0.7\n"
    "apply_stage('mcubes', Grid(sdf=sdf, origin=np.zeros(3), voxel_size=0.1), {})\n"
    "print(len(mesh.faces) > 0, 'numba.np.arraymath' in sys.modules, 'scipy.linalg' in "
    "sys.modules)\n"
)


def test_ballpivot_and_mcubes_kernels_load_without_numba_arraymath():
    """Ball pivoting's and marching cubes' cached kernels load without numba's arraymath.

    Their cached kernels call no numba.np.arraymath implementation (searchsorted, argmax,
    cumsum are written out): loading them imports neither it nor scipy.linalg (~0.2 CPU s).
    """
    code = STAGES_WITHOUT_ARRAYMATH % str(Path(__file__).resolve().parent)
    _run(code, {})  # cache the kernels (compiled the first time if the cache is cold)
    assert _run(code, {}).split() == ["True", "False", "False"]


SPIN = (
    "import os, numpy as np, numba\n"
    "from recon_cli._kernels import numba_setup\n"
    "@numba.njit(parallel=True)\n"
    "def f(a):\n"
    "    for i in numba.prange(len(a)):\n"
    "        a[i] += 1.0\n"
    "f(np.zeros(10))\n"
    "print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))\n"
)


@pytest.mark.parametrize(
    "env, expected",
    [
        ({}, "10000 None"),  # ours
        ({"GOMP_SPINCOUNT": "123"}, "123 None"),  # the user's wins
        ({"OMP_WAIT_POLICY": "active"}, "None active"),  # the user chose how OpenMP waits
    ],
)
def test_idle_openmp_threads_spin_briefly_unless_the_user_says(tmp_path, env, expected):
    """Idle OpenMP threads spin briefly by default; the user's own setting is kept."""
    full = {
        k: v
        for k, v in os.environ.items()
        if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "GOMP_SPINCOUNT", "OMP_WAIT_POLICY")
    }
    full.update(env, XDG_CACHE_HOME=str(tmp_path))
    out = subprocess.run(
        [sys.executable, "-c", SPIN], env=full, check=True, capture_output=True, text=True
    ).stdout
    assert out.strip() == expected
