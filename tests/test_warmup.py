"""recon_cli.cli._warmup / `recon warmup`: after it, no command compiles a kernel.

Run on a copy of the install's numba cache taken before any test compiled into it (on a clean clone:
exactly what the install's warm-up made; warming it up again compiles only what edits made stale; an
empty cache where there is none), then real commands on inputs unlike the warm-up's (the shared scan
and meshes) in a process that counts numba's compile events.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sensors import DepthCamera, depth_image, look_at, tabletop_scene, write_organized_pcd
from shared_data import shared_path

ROOT = Path(__file__).resolve().parents[1]
# kernels no stage calls (kept in the shared helpers' API); the warm-up cannot reach them
UNUSED: set[str] = {
    # degree 2's direct splat of the normals: the solve uses it only for a KERNEL_WIDTH other
    # than 1 (bspline.NormalRHS otherwise); the reference of NormalRHS's test
    "recon_cli.stages.poisson._bspline_rhs.splat_rhs",
    # the block-Jacobi product on its own (the solver inlines its per-block step in the CG update);
    # test_poisson_bspline's entry to that step
    "recon_cli.stages.poisson._bspline_operator.apply_blocks",
}

AFTER = r"""
import io, sys, json
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)
    def on_end(self, ev):
        pass
event.register("numba:compile", L())
from recon_cli.cli.main import cli
d, scan, kitten, depth = sys.argv[1:5]
runs = [
    ["normals", scan, f"{d}/n.ply", "--orient", "camera", "--camera", "0,0,1"],
    ["normals", depth, f"{d}/d.ply", "--orient", "camera"],
    ["normals", scan, f"{d}/n2.ply"],
    ["filter", scan, f"{d}/f.ply", "--radius-outliers", "0.004,4", "--outliers", "20,2",
     "--voxel", "0.002"],
    ["poisson", f"{d}/n.ply", f"{d}/p.ply", "--depth", "6"],
    ["ballpivot", f"{d}/n.ply", f"{d}/b.ply"],
    ["repair", f"{d}/b.ply", f"{d}/r.ply", "--fill-holes", "50"],
    ["simplify", f"{d}/r.ply", f"{d}/s.ply", "--ratio", "0.5"],
    ["smooth", f"{d}/s.ply", f"{d}/sm.ply", "--iterations", "3"],
    ["sdf", kitten, f"{d}/k.npz", "--resolution", "24"],
    ["mcubes", f"{d}/k.npz", f"{d}/m.ply"],
    ["info", kitten, f"{d}/k.npz"],
    ["diff", kitten, f"{d}/m.ply", "--samples", "5000"],
    ["convert", f"{d}/n.ply", f"{d}/n.glb"],
    ["smooth", f"{d}/s.ply", f"{d}/sm.glb", "--iterations", "1"],
    ["convert", f"{d}/sm.glb", f"{d}/sm.gltf"],
    ["info", f"{d}/sm.gltf"],
]
for args in runs:
    cli.main(args=["-q", *args], prog_name="recon", standalone_mode=False)
# the same files from stdin (bytes, not a file read into numpy memory): nothing more to compile
piped = [depth]
for src, ext in ((scan, "obj"), (scan, "xyz"), (kitten, "off"), (kitten, "stl"), (kitten, "obj")):
    piped.append(f"{d}/piped_{len(piped)}.{ext}")
    cli.main(args=["-q", "convert", src, piped[-1]], prog_name="recon", standalone_mode=False)
for path in piped + [scan]:
    with open(path, "rb") as f:
        sys.stdin = io.TextIOWrapper(f)
        cli.main(args=["-q", "info", "-"], prog_name="recon", standalone_mode=False)
with open(scan, "rb") as f:
    sys.stdin = io.TextIOWrapper(f)
    cli.main(
        args=["-q", "normals", "-", f"{d}/piped.ply"], prog_name="recon", standalone_mode=False
    )
print(json.dumps(compiled))
"""


@pytest.mark.slow
def test_no_command_compiles_after_warmup(tmp_path):
    """After ``recon warmup`` no command compiles a kernel."""
    # the install's cache, copied at the start of the run (an empty one without it): the warm-up
    # compiles what is missing or stale there
    cache = os.environ.get("RECON_TEST_WARM_CACHE") or str(tmp_path / "cache")
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    warm = subprocess.run(
        [sys.executable, "-m", "recon_cli.cli.main", "warmup", "--json"],
        env=env,
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert warm.returncode == 0, warm.stderr
    report = json.loads(warm.stdout)
    assert report["failed"] == [] and report["cache_dir"] == cache
    assert set(report["uncompiled"]) <= UNUSED, set(report["uncompiled"]) - UNUSED
    assert (
        report["bytecode"] is True
    )  # every module's .pyc written: no command compiles Python source
    # the ballpivot/mcubes kernels compiled ahead of time (a C compiler is on every machine make
    # install runs on)
    assert report["aot_built"] is True, report["aot_reason"]
    assert report["aot_reason"] in (None, "up to date"), report["aot_reason"]
    assert report["aot_dir"].startswith(os.path.join(cache, "aot"))
    for module in (
        "recon_cli/stages/ballpivot/__init__.py",
        "recon_cli/stages/mcubes/_kernel.py",
        "recon_cli/cli/main.py",
    ):
        assert Path(importlib.util.cache_from_source(str(ROOT / module))).is_file(), module
    # a depth camera's organized cloud: NaN pixels, normals from its pixel grid, its viewpoint
    rng = np.random.default_rng(0)
    cam = DepthCamera(
        eye=np.array([0.3, -2.4, 1.1]), rotation=look_at((0.3, -2.4, 1.1), (0, 0.3, 0.2))
    )
    write_organized_pcd(tmp_path / "depth.pcd", depth_image(cam, tabletop_scene(), rng), cam)
    after = subprocess.run(
        [
            sys.executable,
            "-c",
            AFTER,
            str(tmp_path),
            str(ROOT / "sample_data" / "bunny_scan_000.ply"),
            str(shared_path("kitten")),
            str(tmp_path / "depth.pcd"),
        ],
        env=env,
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert after.returncode == 0, after.stderr
    assert json.loads(after.stdout.strip().splitlines()[-1]) == []


KMOD = """
from numba import njit


@njit(cache=True)
def f(x):
    return x + 1
"""

RACE = r"""
import os, sys, time
root, lock_dir, me, other, arg = sys.argv[1:6]
sys.path.insert(0, root)
from numba.core import event
from recon_cli.cli._warmup import serialize_kernel_compiles

serialize_kernel_compiles(lock_dir)
compiled = []


class Slow(event.Listener):
    def on_start(self, ev):
        compiled.append(str(ev.data["args"]))
        time.sleep(1.5)  # long enough for the other process to ask for the kernel meanwhile

    def on_end(self, ev):
        pass


event.register("numba:compile", Slow())
import kmod

open(os.path.join(root, me), "w").close()
while not os.path.exists(os.path.join(root, other)):  # both call the kernel at once
    time.sleep(0.005)
kmod.f(eval(arg))
print(len(compiled))
"""


def _race(tmp_path, args: tuple[str, str]) -> list[int]:
    (tmp_path / "kmod.py").write_text(KMOD)
    (tmp_path / "locks").mkdir(exist_ok=True)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", RACE, str(tmp_path), str(tmp_path / "locks"), me, other, a],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        for me, other, a in (("a", "b", args[0]), ("b", "a", args[1]))
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [e for _, e in outs]
    return [int(o.split()[-1]) for o, _ in outs]


def test_workers_needing_one_kernel_at_once_compile_it_once(tmp_path):
    """Two workers needing one kernel at once: it is compiled once, then loaded from the cache."""
    # the second waits for the first's compile, then loads it from the cache
    assert sorted(_race(tmp_path, ("1", "2"))) == [0, 1]


def test_workers_compiling_two_variants_at_once_keep_both_in_the_cache(tmp_path):
    """Two workers compiling two variants at once keep both in the cache; a third compiles none."""
    assert _race(tmp_path, ("1", "2.5")) == [1, 1]
    # a third process finds both in the kernel's cache index: it compiles nothing
    after = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "import kmod\n"
        "kmod.f(1); kmod.f(2.5)\n"
        "print(sum(kmod.f.stats.cache_misses.values()), len(kmod.f.signatures))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", after, str(tmp_path)],
        env=dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache")),
        capture_output=True,
        text=True,
        check=True,
    )
    assert r.stdout.split() == ["0", "2"]
