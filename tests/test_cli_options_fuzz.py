"""Generated option values, valid and not, alone and together: run, or refused in one line.

Every option of filter, simplify and smooth, and poisson's newest (``--envelope``, ``--grid``,
``--attributes``, ``--boundary free``), and the formats and flags every stage has, given generated
values, valid and not, alone and together.

Each case runs the command in this process (``recon_cli.cli.main.main``) on small generated
inputs: it ends with exit 0 and an output that reads back, or exit 1 or 2 with one stderr line
``recon: error: ...`` and no output (OUT did not exist); never a traceback (an exception out of
``main``), never a hang (:data:`CASE_SECONDS`; a watchdog ends the process past six times that).
``make test`` runs :data:`QUICK` cases a command, ``make fuzz`` :data:`FUZZ`.
"""

from __future__ import annotations

import faulthandler
import os
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io.load import load, save

from shapes import icosphere, torus, torus_cloud

QUICK = 20
FUZZ = 500
CASE_SECONDS = 20.0

# text that is no number or an edge of one
ODD = ["", "x", "nan", "inf", "-inf", "-1", "0", "1e400", "-0", "1e-320", "2", "3.5", "1,2", "none"]


def _number(lo: float, hi: float) -> st.SearchStrategy:
    """A number in [lo, hi] as text, or an odd word."""
    return st.one_of(
        st.floats(lo, hi, allow_nan=False).map(lambda x: f"{x:.6g}"),
        st.integers(int(lo), int(hi)).map(str),
        st.sampled_from(ODD),
    )


def _numbers(k: st.SearchStrategy, lo: float, hi: float) -> st.SearchStrategy:
    """Comma-separated numbers (a count from ``k``), maybe odd ones among them."""
    return k.flatmap(lambda n: st.lists(_number(lo, hi), min_size=n, max_size=n)).map(",".join)


def _flag(name: str) -> st.SearchStrategy:
    return st.sampled_from([[f"--{name}"], [f"--no-{name}"], []])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """The inputs: a cloud with normals, colours and attributes, its LAS, meshes, a broken file.

    Meshes closed and open, a cloud, a broken file and a folder serve as envelopes.
    """
    import laspy

    root = tmp_path_factory.mktemp("options")
    rng = np.random.default_rng(5)
    pts, nrm = torus_cloud(600, seed=5)
    cloud = PointCloud(
        points=pts,
        normals=nrm,
        colors=rng.integers(0, 256, (len(pts), 3)).astype(np.uint8),
        attributes={"intensity": rng.random(len(pts)), "label": rng.integers(0, 5, len(pts))},
    )
    save(cloud, str(root / "cloud.ply"))
    h = laspy.LasHeader(point_format=1, version="1.2")
    h.scales = np.array([1e-4] * 3)
    las = laspy.LasData(h)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.classification = rng.integers(0, 8, len(pts))
    las.return_number = rng.integers(1, 4, len(pts))
    las.number_of_returns = np.maximum(las.return_number, rng.integers(1, 4, len(pts)))
    las.write(str(root / "cloud.las"))
    v, f = torus(nu=24, nv=10)
    save(
        TriangleMesh(vertices=v + rng.normal(scale=0.01, size=v.shape), faces=f),
        str(root / "mesh.ply"),
    )
    ev, ef = icosphere(2, radius=1.8)
    save(TriangleMesh(vertices=ev, faces=ef), str(root / "closed.ply"))
    keep = ev[ef].mean(axis=1)[:, 2] > 0.3
    save(TriangleMesh(vertices=ev, faces=ef[keep]), str(root / "open.ply"))
    (root / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    (root / "folder").mkdir()
    return root


def _option(name: str, value: st.SearchStrategy) -> st.SearchStrategy:
    return value.map(lambda v: [f"--{name}", v])


FILTER = [
    _option("crop", _numbers(st.sampled_from([6, 6, 6, 3, 7]), -2, 2)),
    _option(
        "classes",
        st.one_of(
            _numbers(st.integers(1, 4), 0, 300),
            st.sampled_from(["ground", "ground,building", "water,2", "noise", "x"]),
        ),
    ),
    _option("returns", st.sampled_from(["all", "first", "last", "single", "intermediate", "x"])),
    _option("radius-outliers", _numbers(st.sampled_from([2, 2, 1, 3]), 0, 0.5)),
    _option("outliers", _numbers(st.sampled_from([2, 2, 1, 3]), 0, 40)),
    _option("voxel", _number(0, 0.5)),
]
SIMPLIFY = [
    _option("faces", st.one_of(_number(0, 1000), st.just("none"))),
    _option("ratio", st.one_of(_number(0, 1.2), st.just("none"))),
    _option("boundary-weight", _number(0, 1e6)),
]
SMOOTH = [
    _option("iterations", _number(0, 40)),
    _option("step", _number(0, 1)),
    _option("pass-band", _number(0, 1)),
    _flag("fixed-boundary"),
]
ENVELOPES = ["closed.ply", "open.ply", "cloud.ply", "broken.ply", "missing.ply", "folder", ""]
POISSON = [
    st.sampled_from(ENVELOPES).map(lambda e: ["--envelope", "{in}/" + e if e else ""]),
    st.sampled_from(["g.npz", "g.ply", "/nonexistent/g.npz", "-", "", "{in}/folder"]).map(
        lambda g: ["--grid", g]
    ),
    _option(
        "attributes",
        st.sampled_from(
            ["all", "none", "colors", "intensity", "label,intensity", "nope", "colors,nope", ","]
        ),
    ),
    _option("boundary", st.sampled_from(["free", "free", "neumann", "dirichlet", "fre"])),
    st.sampled_from([[], ["--degree", "1"], ["--trim", "auto"], ["--density"], ["--workers", "0"]]),
    st.sampled_from([[], ["--partitions", "2"], ["--memory", "1MB"]]),
]
# the options every stage command has (OUT stays PLY, so that it reads back by its name)
COMMON = st.sampled_from(
    [
        ["--ascii"],
        ["--json"],
        ["--points-only"],
        ["--input-format", "ply"],
        ["--input-format", "xyz"],
        ["--input-format", "nope"],
        ["--output-format", "ply"],
        ["--output-format", ""],
        ["--format", "pcd"],
    ]
)
STAGES = {
    name: [*options, COMMON]
    for name, options in {
        "filter": FILTER,
        "simplify": SIMPLIFY,
        "smooth": SMOOTH,
        "poisson": POISSON,
    }.items()
}


def _run(argv: list[str], capfd) -> tuple[int, str]:
    from recon_cli.cli.main import main

    capfd.readouterr()
    faulthandler.dump_traceback_later(CASE_SECONDS * 6, exit=True)
    t0 = time.perf_counter()
    try:
        main(["-q", *argv])
    except SystemExit as exc:
        code = exc.code
    else:  # pragma: no cover - main always exits
        code = None
    finally:
        faulthandler.cancel_dump_traceback_later()
    took = time.perf_counter() - t0
    assert took < CASE_SECONDS, f"{argv}: {took:.1f} s"
    return code, capfd.readouterr().err


# options every case of a command gets (poisson: a cheap depth)
BASE = {"poisson": ["--depth", "5"]}
SOURCE = {
    "filter": "cloud.ply",
    "simplify": "mesh.ply",
    "smooth": "mesh.ply",
    "poisson": "cloud.ply",
}


def fuzz_stage(stage: str, examples: int, inputs: Path, folder: Path, capfd) -> dict:
    """``examples`` generated option sets for ``stage``; the count of each exit code."""
    codes: dict[int, int] = {}
    out = folder / "out.ply"
    here = os.getcwd()
    os.chdir(folder)  # a relative --grid lands here

    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        derandomize=examples <= QUICK,
        suppress_health_check=[HealthCheck.too_slow],
    )
    @given(data=st.data())
    def run(data):
        choices = STAGES[stage]
        picked = data.draw(
            st.lists(st.integers(0, len(choices) - 1), min_size=1, max_size=4, unique=True)
        )
        options = [
            part.replace("{in}", str(inputs)) for k in picked for part in data.draw(choices[k])
        ]
        src = inputs / SOURCE[stage]
        if stage == "filter" and data.draw(st.booleans()):
            src = inputs / "cloud.las"
        argv = [stage, str(src), str(out), *BASE.get(stage, []), *options]
        code, err = _run(argv, capfd)
        codes[code] = codes.get(code, 0) + 1
        if code == 0:
            got = load(str(out))
            assert len(got.points) > 0, argv
            out.unlink()
        else:
            assert code in (1, 2), (argv, code, err)
            assert err.count("\n") == 1 and err.startswith("recon: error: "), (argv, err)
            assert not out.exists(), argv
        left = set(os.listdir(folder)) - {"g.npz", "g.ply"}
        assert not left, (argv, left)
        for extra in ("g.npz", "g.ply"):
            if (folder / extra).exists():
                (folder / extra).unlink()

    try:
        run()
    finally:
        os.chdir(here)
    return codes


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_generated_options_run_or_are_refused_in_one_line(stage, inputs, tmp_path, capfd):
    """:data:`QUICK` generated option sets a command: an output that reads back, or one line."""
    codes = fuzz_stage(stage, QUICK, inputs, tmp_path, capfd)
    assert sum(codes.values()) >= QUICK


@pytest.mark.fuzz
@pytest.mark.parametrize("stage", sorted(STAGES))
def test_fuzz_generated_options(stage, inputs, tmp_path, capfd):
    """:data:`FUZZ` generated option sets a command, as the quick test; some run, some refused."""
    codes = fuzz_stage(stage, FUZZ, inputs, tmp_path, capfd)
    assert sum(codes.values()) >= FUZZ
    assert codes.get(0, 0) > 0 and codes.get(2, 0) > 0, codes
