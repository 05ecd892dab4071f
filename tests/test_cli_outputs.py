"""Output paths of every kind: written right, or one line naming the path and nothing touched.

Errors exit 2 (a full file system exits 1). The matrix: a new regular file, an existing one
(replaced on success keeping its mode, kept on failure), a directory, a missing folder, a
trailing slash, an empty path, an immutable file and folder (``chattr +i``, which binds root
too), a read-only and a full file system (tmpfs mounts, PLY and ``.npz``), a FIFO, a character
device made with ``mknod``, symbolic links (written through), ``/dev/stdout``, a closed stdout,
a process substitution and a broken pipe. Most run the CLI in-process; the shell cases share one
subprocess.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from recon_cli.io.ply import read_ply, write_ply

from shapes import box_mesh

ROOT = os.geteuid() == 0


def _cli(args, capfd) -> tuple[int, str, str]:
    from recon_cli.cli.main import main

    capfd.readouterr()
    with pytest.raises(SystemExit) as ex:
        main(["-q", *map(str, args)])
    out, err = capfd.readouterr()
    return ex.value.code, out, err


@pytest.fixture
def src(tmp_path) -> Path:
    """A 20k-vertex cloud: its PLY (~240 kB) does not fit a 64 kB tmpfs."""
    from recon_cli.geometry import PointCloud

    pts = np.random.default_rng(0).normal(size=(20_000, 3)).astype(np.float32)
    p = tmp_path / "in" / "cloud.ply"
    p.parent.mkdir()
    write_ply(PointCloud(points=pts), p)
    return p


def _one_error_line(err: str, path) -> None:
    assert err.count("\n") == 1 and err.startswith(f"recon: error: {path}: "), repr(err)


def _no_temporaries(folder) -> None:
    left = [n for n in os.listdir(folder) if n.endswith(".tmp")]
    assert not left, left


def test_new_and_existing_regular_file(src, tmp_path, capfd):
    """A new file is written; an existing one replaced keeping its mode, or kept on failure."""
    out = tmp_path / "out.ply"
    code, _, err = _cli(["convert", src, out], capfd)
    assert (code, err) == (0, "")
    np.testing.assert_array_equal(read_ply(out).points, read_ply(src).points)
    # replaced on success, keeping its permission bits
    out.write_bytes(b"old")
    out.chmod(0o600)
    code, _, err = _cli(["convert", src, out], capfd)
    assert (code, err) == (0, "") and out.stat().st_size > 3
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    # kept on failure
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
    out.write_bytes(b"old")
    code, _, err = _cli(["convert", bad, out], capfd)
    assert code == 2 and out.read_bytes() == b"old"
    _one_error_line(err, bad)
    _no_temporaries(tmp_path)


def test_stage_output_checked_before_the_work(src, tmp_path, capfd):
    """A stage's output in a missing folder is refused in one line before the stage runs."""
    code, _, err = _cli(["normals", src, tmp_path / "missing" / "n.ply"], capfd)
    assert code == 2 and "output folder does not exist" in err
    _one_error_line(err, tmp_path / "missing" / "n.ply")


@pytest.mark.parametrize(
    "name, reason",
    [
        ("folder", "is a directory"),
        ("missing/out.ply", "output folder does not exist"),
        ("folder/", "ends with '/'"),
        ("missing/", "ends with '/'"),
        ("", "output path is empty"),
        ("in/cloud.ply/x.ply", "Not a directory"),
    ],
)
def test_unwritable_paths_one_line(src, tmp_path, capfd, name, reason):
    """A directory, missing folder, trailing slash or empty path: exit 2, one line, no temporary."""
    (tmp_path / "folder").mkdir()
    path = str(tmp_path / name) if name else ""
    if name.endswith("/"):
        path += "/"
    code, _, err = _cli(["convert", src, path], capfd)
    assert code == 2 and reason in err, err
    _one_error_line(err, path or "''")
    _no_temporaries(tmp_path)
    _no_temporaries(tmp_path / "folder")


@pytest.mark.skipif(not ROOT or shutil.which("chattr") is None, reason="chattr +i needs root")
def test_immutable_file_and_folder(src, tmp_path, capfd):
    """An immutable file or folder (even for root): exit 2, "Operation not permitted", unchanged."""
    out = tmp_path / "imm.ply"
    out.write_bytes(b"keep")
    folder = tmp_path / "immdir"
    folder.mkdir()
    if subprocess.run(["chattr", "+i", out, folder], capture_output=True).returncode:
        pytest.skip("this file system has no immutable flag")
    try:
        code, _, err = _cli(["convert", src, out], capfd)
        assert code == 2 and "Operation not permitted" in err
        _one_error_line(err, out)
        assert out.read_bytes() == b"keep"
        code, _, err = _cli(["convert", src, folder / "x.ply"], capfd)
        assert code == 2 and "Operation not permitted" in err
        assert os.listdir(folder) == []
    finally:
        subprocess.run(["chattr", "-i", out, folder], check=True)
    _no_temporaries(tmp_path)


@contextlib.contextmanager
def _tmpfs(where: Path, options: str):
    where.mkdir()
    if (
        not ROOT
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", options, "tmpfs", where], capture_output=True
        ).returncode
    ):
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield where
    finally:
        subprocess.run(["umount", where], check=True)


def test_full_file_system_ply_and_npz(src, tmp_path, capfd):
    """A full tmpfs, PLY or grid: exit 1, "No space left on device", old file kept, no temporary."""
    from recon_cli.geometry import TriangleMesh

    v, f = box_mesh()
    mesh = tmp_path / "box.ply"
    write_ply(TriangleMesh(vertices=v, faces=f), mesh)
    with _tmpfs(tmp_path / "full", "size=64k") as mnt:
        (mnt / "out.ply").write_bytes(b"keep")
        code, _, err = _cli(["convert", src, mnt / "out.ply"], capfd)
        assert code == 1 and "No space left on device" in err
        _one_error_line(err, mnt / "out.ply")
        assert (mnt / "out.ply").read_bytes() == b"keep"
        assert os.listdir(mnt) == ["out.ply"]
        # a grid of 40**3 float32 samples (256 kB)
        code, _, err = _cli(["sdf", mesh, mnt / "g.npz", "--resolution", "40"], capfd)
        assert code == 1 and "No space left on device" in err
        _one_error_line(err, mnt / "g.npz")
        assert os.listdir(mnt) == ["out.ply"]


def test_read_only_file_system(src, tmp_path, capfd):
    """A read-only file system: exit 2 "Read-only file system", the old file kept."""
    with _tmpfs(tmp_path / "ro", "size=1m") as mnt:
        (mnt / "out.ply").write_bytes(b"keep")
        subprocess.run(["mount", "-o", "remount,ro", mnt], check=True)
        code, _, err = _cli(["convert", src, mnt / "out.ply"], capfd)
        assert code == 2 and "Read-only file system" in err
        _one_error_line(err, mnt / "out.ply")
        assert (mnt / "out.ply").read_bytes() == b"keep"


def test_fifo_written_directly(src, tmp_path, capfd):
    """A FIFO is written through, not replaced: the reader gets the input's bytes."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    code, _, err = _cli(["convert", src, fifo], capfd)
    reader.join(30)
    assert (code, err) == (0, "")
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    assert got and got[0] == src.read_bytes()


@pytest.mark.skipif(not ROOT, reason="mknod of a device needs root")
def test_character_device_is_not_replaced(src, tmp_path, capfd):
    """A character device (a /dev/null made with mknod) is written to and stays that device."""
    dev = tmp_path / "null"
    os.mknod(dev, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a /dev/null of our own
    code, _, err = _cli(["convert", src, dev], capfd)
    assert (code, err) == (0, "")
    assert stat.S_ISCHR(dev.lstat().st_mode) and dev.lstat().st_rdev == os.makedev(1, 3)
    _no_temporaries(tmp_path)


def test_symlinks_written_through(src, tmp_path, capfd):
    """Symbolic links, dangling ones too, are written through to their targets, and stay links."""
    target = tmp_path / "target.ply"
    target.write_bytes(b"old")
    link = tmp_path / "link.ply"
    link.symlink_to(target.name)
    code, _, err = _cli(["convert", src, link], capfd)
    assert (code, err) == (0, "")
    assert link.is_symlink() and target.read_bytes() == src.read_bytes()
    dangling = tmp_path / "dangling.ply"
    dangling.symlink_to("made.ply")
    code, _, err = _cli(["convert", src, dangling], capfd)
    assert (code, err) == (0, "")
    assert dangling.is_symlink() and (tmp_path / "made.ply").read_bytes() == src.read_bytes()


def test_shell_outputs(src, tmp_path):
    """/dev/stdout, a process substitution, a closed stdout and a broken pipe, in one shell."""
    if shutil.which("bash") is None:
        pytest.skip("needs bash")
    recon = f"{sys.executable} -m recon_cli.cli.main"
    script = f"""
    {recon} -q convert {src} /dev/stdout > stdout.ply 2> e1; echo $? > c1
    {recon} -q convert {src} >(cat > procsub.ply) 2> e2; echo $? > c2
    {recon} -q convert {src} - >&- 2> e3; echo $? > c3
    {recon} -q convert {src} - 2> e4 | head -c 10 > /dev/null; echo ${{PIPESTATUS[0]}} > c4
    wait
    """
    subprocess.run(["bash", "-c", script], cwd=tmp_path, check=True, timeout=300)
    code = {i: int((tmp_path / f"c{i}").read_text()) for i in range(1, 5)}
    err = {i: (tmp_path / f"e{i}").read_text() for i in range(1, 5)}
    data = src.read_bytes()
    assert (code[1], err[1]) == (0, "") and (tmp_path / "stdout.ply").read_bytes() == data
    assert (code[2], err[2]) == (0, "")
    for _ in range(100):  # cat may finish after recon
        if (tmp_path / "procsub.ply").exists() and (tmp_path / "procsub.ply").stat().st_size == len(
            data
        ):
            break
        threading.Event().wait(0.05)
    assert (tmp_path / "procsub.ply").read_bytes() == data
    assert code[3] == 2 and err[3] == "recon: error: <stdout>: standard output is closed\n"
    assert (code[4], err[4]) == (141, "")  # quiet, as a process killed by SIGPIPE
    _no_temporaries(tmp_path)
