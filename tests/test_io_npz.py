"""Grid files (.npz): headers checked before use; odd grids give a report or one line.

Grid files (.npz): every header checked before use; `recon info` and `recon mcubes` on
odd grids answer with a report or one line and exit 2, never a traceback (issue 15, items
2, 9 and 14).
"""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from recon_cli.cli.main import main
from recon_cli.errors import InputError
from recon_cli.grid import Grid
from recon_cli.io.npz import read_grid, write_grid


def run(capsys, *args) -> tuple[int, str, str]:
    """``recon ARGS`` in this process: (exit code, stdout, stderr)."""
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def save(path, sdf, origin=(0.0, 0.0, 0.0), voxel_size=0.1, **extra):
    """Write an .npz grid file of ``sdf`` and its frame, with ``extra`` members."""
    np.savez(path, sdf=sdf, origin=np.asarray(origin), voxel_size=np.asarray(voxel_size), **extra)
    return path


def lying_header(path, shape):
    """An .npz whose 'sdf' header claims ``shape`` float32 but holds 64 bytes of data."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {"descr": "<f4", "fortran_order": False, "shape": shape}
    )
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("sdf.npy", head.getvalue() + bytes(64))
        for name, arr in (("origin", np.zeros(3)), ("voxel_size", np.float64(0.1))):
            buf = io.BytesIO()
            np.save(buf, arr)
            zf.writestr(f"{name}.npy", buf.getvalue())
    return path


def planar_cloud_grid(tmp_path, capsys):
    """What `recon sdf` writes for a planar cloud at 16^3 (the issue's crash)."""
    from recon_cli.geometry import PointCloud
    from recon_cli.io import write_ply

    g = np.stack(
        np.meshgrid(np.linspace(0, 1, 30), np.linspace(0, 1, 30), indexing="ij"), -1
    ).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))])
    src = tmp_path / "plane.ply"
    write_ply(PointCloud(points=pts, normals=np.tile([0.0, 0.0, 1.0], (len(pts), 1))), src)
    out = tmp_path / "plane.npz"
    code, _, err = run(capsys, "-q", "sdf", src, out, "--resolution", "16")
    assert code == 0, err
    return out


@pytest.mark.parametrize("kind", ["planar_cloud", "all_nan", "constant", "one_sample", "two_cubed"])
def test_info_on_odd_grids(tmp_path, capsys, kind):
    """`recon info` prints every valid grid (text and --json), whatever its eikonal check finds."""
    path = tmp_path / f"{kind}.npz"
    if kind == "planar_cloud":
        path = planar_cloud_grid(tmp_path, capsys)
    else:
        sdf = {
            "all_nan": np.full((4, 5, 6), np.nan, np.float32),
            "constant": np.full((8, 8, 8), 0.5, np.float32),
            "one_sample": np.zeros((1, 1, 1), np.float32),
            "two_cubed": np.array([-1, 1] * 4, np.float32).reshape(2, 2, 2),
        }[kind]
        save(path, sdf)
    code, out, err = run(capsys, "info", path)
    assert code == 0 and err == "" and "Traceback" not in out, err
    assert "shape" in out and "inside cells" in out
    code, out, err = run(capsys, "info", path, "--json")
    assert code == 0 and '"kind": "grid"' in out


@pytest.mark.parametrize(
    "case, message",
    [
        ("empty_axis", "no samples"),
        ("string_origin", "'origin' must be numeric"),
        ("nan_origin", "'origin' must be finite"),
        ("inf_voxel", "'voxel_size' must be a finite positive"),
        ("zero_voxel", "'voxel_size' must be a finite positive"),
        ("two_d", "3-d float array"),
        ("int_sdf", "3-d float array"),
        ("short_origin", "'origin' must have 3 values"),
        ("claims_4000_cubed", "the file is shorter"),
        ("missing_voxel", "lacks 'voxel_size'"),
        ("truncated", "corrupt grid file"),
        ("flipped_byte", "CRC"),
    ],
)
def test_bad_grid_files_are_refused(tmp_path, capsys, case, message):
    """Each bad grid: info and mcubes exit 2 with one line naming the file, no output written."""
    path = tmp_path / f"{case}.npz"
    ok = np.zeros((4, 4, 4), np.float32)
    if case == "empty_axis":
        save(path, np.zeros((0, 16, 16), np.float32))
    elif case == "string_origin":
        save(path, ok, origin=np.array(["a", "b", "c"]))
    elif case == "nan_origin":
        save(path, ok, origin=(0.0, np.nan, 0.0))
    elif case == "inf_voxel":
        save(path, ok, voxel_size=np.inf)
    elif case == "zero_voxel":
        save(path, ok, voxel_size=0.0)
    elif case == "two_d":
        save(path, np.zeros((4, 4), np.float32))
    elif case == "int_sdf":
        save(path, np.zeros((4, 4, 4), np.int32))
    elif case == "short_origin":
        save(path, ok, origin=(0.0, 0.0))
    elif case == "claims_4000_cubed":
        lying_header(path, (4000, 4000, 4000))
    elif case == "missing_voxel":
        np.savez(path, sdf=ok, origin=np.zeros(3))
    elif case == "truncated":
        save(path, ok)
        path.write_bytes(path.read_bytes()[:200])
    elif case == "flipped_byte":  # one bit of the stored samples changed: the member's CRC says so
        values = np.arange(64, dtype=np.float32).reshape(4, 4, 4)
        save(path, values)
        raw = bytearray(path.read_bytes())
        at = raw.find(values.tobytes()) + 37
        raw[at] ^= 0x10
        path.write_bytes(bytes(raw))
    out = tmp_path / "out.ply"
    for args in (("info", path), ("mcubes", path, out)):
        code, stdout, err = run(capsys, *args)
        assert code == 2, (case, args[0], err)
        assert err.count("\n") == 1 and str(path) in err and message in err, (case, err)
        assert not out.exists()


def test_grid_whose_memory_cannot_be_had_is_refused_before_reading(tmp_path, monkeypatch):
    """A grid larger than the available memory is refused before it is read."""
    path = save(tmp_path / "g.npz", np.zeros((16, 16, 16), np.float32))
    assert read_grid(path).shape == (16, 16, 16)
    monkeypatch.setattr("recon_cli.memory.available_bytes", lambda: 10_000)
    with pytest.raises(
        InputError,
        match=r"16 x 16 x 16 = 4.1e\+03 samples needs about .* more than the 10 kB available",
    ):
        read_grid(path)


def test_grid_class_checks_its_frame():
    """A Grid with a NaN origin, an infinite or negative voxel size, or no samples is refused."""
    for kw in (
        {"origin": (0, np.nan, 0)},
        {"voxel_size": np.inf},
        {"voxel_size": -1.0},
        {"sdf": np.zeros((0, 2, 2))},
    ):
        args = {"sdf": np.zeros((2, 2, 2)), "origin": (0, 0, 0), "voxel_size": 1.0, **kw}
        with pytest.raises(InputError):
            Grid(**args)


def test_round_trip_and_compressed(tmp_path):
    """Grids round-trip exactly, compressed too, in any layout and byte order numpy writes."""
    g = Grid(
        sdf=np.random.default_rng(0).normal(size=(3, 4, 5)),
        origin=(1.0, 2.0, 3.0),
        voxel_size=0.5,
        history=["a"],
    )
    write_grid(g, tmp_path / "g.npz")
    back = read_grid(tmp_path / "g.npz")
    assert (
        np.array_equal(back.sdf, g.sdf)
        and np.array_equal(back.origin, g.origin)
        and back.history == ["a"]
    )
    np.savez_compressed(tmp_path / "c.npz", sdf=g.sdf, origin=g.origin, voxel_size=np.float64(0.5))
    assert np.array_equal(read_grid(tmp_path / "c.npz").sdf, g.sdf)
    # stored members read straight into the array: any layout and byte order numpy writes
    values = np.random.default_rng(1).normal(size=(3, 4, 5))
    for sdf in (
        np.asfortranarray(values),
        values.astype(">f4"),
        values.astype(np.float64),
        values[:, ::2].copy(),
    ):
        np.savez(tmp_path / "s.npz", sdf=sdf, origin=g.origin, voxel_size=np.float64(0.5))
        back = read_grid(tmp_path / "s.npz")
        assert back.sdf.dtype == np.float32 and np.array_equal(back.sdf, sdf.astype(np.float32))
        assert np.array_equal(read_grid("-", (tmp_path / "s.npz").read_bytes()).sdf, back.sdf)


@pytest.mark.parametrize("kind", ["constant", "all_nan", "one_sample", "nan_where_it_crosses"])
def test_mcubes_refuses_an_empty_level_set(tmp_path, capsys, kind):
    """``recon mcubes`` of a grid with no surface is exit 2 "nothing to mesh".

    A grid with no sign change (or no cell, or only unknown cells where it changes) is
    exit 2 'nothing to mesh', never an empty mesh written with exit 0.
    """
    sdf = {
        "constant": np.full((8, 8, 8), 0.5),
        "all_nan": np.full((4, 4, 4), np.nan),
        "one_sample": np.zeros((1, 1, 1)) - 1,
    }.get(kind)
    if sdf is None:
        sdf = np.ones((6, 6, 6))
        sdf[:3] = -1
        sdf[2:4] = np.nan
    path = save(tmp_path / "g.npz", sdf.astype(np.float32))
    out = tmp_path / "out.ply"
    code, _, err = run(capsys, "mcubes", path, out)
    assert code == 2 and "nothing to mesh" in err and err.count("\n") == 1, err
    assert not out.exists()
    # the iso level moves the question: the constant grid meshes nothing at 0.5 either
    if kind == "constant":
        code, _, err = run(capsys, "mcubes", path, out, "--iso", "0.7")
        assert code == 2 and "no sample is on the other side of iso 0.7" in err


def test_sdf_refuses_grids_that_cannot_be_had(tmp_path, capsys):
    """`recon sdf --voxel-size 1e-9` and friends: exit 2 with the estimate, before allocating."""
    from recon_cli.geometry import TriangleMesh
    from recon_cli.io import write_ply

    from shapes import box_mesh

    v, f = box_mesh()
    src = tmp_path / "box.ply"
    write_ply(TriangleMesh(vertices=v, faces=f), src)
    out = tmp_path / "box.npz"
    for vs in ("1e-9", "1e-4", "1e-300"):
        code, _, err = run(capsys, "sdf", src, out, "--voxel-size", vs)
        assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
        assert "needs" in err and ("it may use" in err or "no machine has it" in err), err
        assert not out.exists()
    code, _, err = run(capsys, "-q", "sdf", src, out, "--voxel-size", "0.25")
    assert code == 0 and read_grid(out).voxel_size == 0.25
