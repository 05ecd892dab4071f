"""What the readers' fuzz tests assert through the CLI (test_io_fuzz.py, test_io_gltf_fuzz.py)."""

from __future__ import annotations

import os

import pytest


def _cli(args, capfd) -> tuple[int, str]:
    from recon_cli.cli.main import main

    with pytest.raises(SystemExit) as ex:
        main(["-q", *map(str, args)])
    _, err = capfd.readouterr()
    return ex.value.code, err


def convert_broken_files(cases, tmp_path, capfd) -> dict[int, int]:
    """``recon convert`` each ``(label, file name, bytes)`` case in-process to ``out.ply``.

    Each must exit 0, or exit 2 with one stderr line naming the file and the output that was
    there before untouched; no temporary file may remain. Returns the count of each exit code.
    """
    out = tmp_path / "out.ply"
    sentinel = b"the output that was there before\n"
    codes = {0: 0, 2: 0}
    for label, name, data in cases:
        src = tmp_path / name
        src.write_bytes(data)
        out.write_bytes(sentinel)
        code, err = _cli(["convert", src, out], capfd)
        assert code in (0, 2), f"{label}: exit {code}: {err}"
        codes[code] += 1
        if code == 2:
            assert err.count("\n") == 1 and err.startswith(f"recon: error: {src}: "), (
                f"{label}: {err!r}"
            )
            assert out.read_bytes() == sentinel, f"{label}: output replaced on error"
        else:
            assert err == "", f"{label}: {err!r}"
            assert out.read_bytes() != sentinel
        src.unlink()
        assert os.listdir(tmp_path) == ["out.ply"], f"{label}: left {os.listdir(tmp_path)}"
    return codes
