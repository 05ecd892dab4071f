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


def convert_broken_files(
    cases, tmp_path, capfd, warnings_ok: bool = False, out_name: str = "out.ply"
) -> dict[int, int]:
    """``recon convert`` each ``(label, file name, bytes)`` case in-process to ``out_name``.

    Each must exit 0 (with nothing on stderr, or ``warnings_ok`` only ``recon: warning:`` lines),
    or exit 2 with one stderr line naming the file (or the output, that its format refused) and
    the output that was there before untouched; no temporary file may remain. Returns the count
    of each exit code.
    """
    out = tmp_path / out_name
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
            named = err.startswith((f"recon: error: {src}: ", f"recon: error: {out}: "))
            assert err.count("\n") == 1 and named, f"{label}: {err!r}"
            assert out.read_bytes() == sentinel, f"{label}: output replaced on error"
        else:
            warned = [ln for ln in err.splitlines() if ln.startswith("recon: warning: ")]
            said = [ln for ln in err.splitlines() if not (warnings_ok and ln in warned)]
            assert not said, f"{label}: {err!r}"
            assert out.read_bytes() != sentinel
        src.unlink()
        assert os.listdir(tmp_path) == [out_name], f"{label}: left {os.listdir(tmp_path)}"
    return codes
