"""Large inputs (issue 9): a PLY header promising far more rows is refused before allocating.

Large inputs (issue 9): a PLY file whose header promises far more rows than the file holds is
rejected with a one-line error *before* anything of the promised size is allocated, on every path
that reads a file: ``read_ply``, ``load``, the batch task and the CLI.

The files are real files on disk, a few hundred bytes long, whose header claims 10**12 (or 10**30)
rows; allocating for them would need terabytes. ``tracemalloc`` (numpy reports its buffers to it)
bounds what was allocated while reading.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from recon_cli.errors import InputError

TERA = 10**12
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}


def _lying_file(tmp_path, fmt: str, element: str, count: int):
    """A 3-vertex, 1-triangle file whose ``element`` count in the header is ``count``."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    head = [
        "ply",
        f"format {fmt} 1.0",
        "comment a header that lies",
        f"element vertex {count if element == 'vertex' else 3}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {count if element == 'face' else 1}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    order = FORMATS[fmt]
    if order is None:
        body = b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    else:
        body = (
            verts.astype(order + "f4").tobytes()
            + np.uint8(3).tobytes()
            + np.array([0, 1, 2], order + "i4").tobytes()
        )
    path = tmp_path / f"lying_{element}_{fmt}.ply"
    path.write_bytes(("\n".join(head) + "\n").encode() + body)
    return path


def _peak_while(fn):
    """(exception raised by ``fn``, peak bytes traced while it ran)."""
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as exc:
            fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return exc.value, peak


@pytest.mark.parametrize("fmt", sorted(FORMATS))
@pytest.mark.parametrize("element,count", [("vertex", TERA), ("face", TERA), ("vertex", 10**30)])
def test_lying_header_is_rejected_before_allocating(tmp_path, fmt, element, count):
    """A few-hundred-byte file claiming 10^12 rows or more is refused before allocating for them."""
    from recon_cli.io.load import load
    from recon_cli.io.ply import read_ply

    path = _lying_file(tmp_path, fmt, element, count)
    size = path.stat().st_size
    assert size < 400
    for reader in (read_ply, load):
        err, peak = _peak_while(lambda reader=reader: reader(path))
        msg = str(err)
        assert msg.startswith(f"{path}: truncated: header declares {count} {element!r} rows"), msg
        assert "\n" not in msg
        # a few kB of bookkeeping; one row per promised element would be terabytes
        assert peak < 256 * 1024, (reader.__name__, peak)


def test_the_same_file_with_honest_counts_reads(tmp_path):
    """With honest counts, the same files read.

    The lying files differ from a valid one only in the count (the test files are not broken
    otherwise).
    """
    from recon_cli.io.ply import read_ply

    for fmt in FORMATS:
        mesh = read_ply(_lying_file(tmp_path, fmt, "vertex", 3))
        assert mesh.vertices.shape == (3, 3) and mesh.faces.tolist() == [[0, 1, 2]]


def test_batch_task_and_cli_report_the_lying_file(tmp_path, capsys):
    """The batch task and ``recon info`` report the lying file in one line.

    The batch task records it as failed (InputError, one line) without allocating; ``recon info``
    exits 2.
    """
    from recon_cli import batch
    from recon_cli.cli.main import main
    from recon_cli.pipeline import load_pipeline

    path = _lying_file(tmp_path, "binary_little_endian", "vertex", TERA)
    pipe_file = tmp_path / "p.toml"
    pipe_file.write_text('[[stage]]\nname = "normals"\nknn = 30\n')
    pipe = load_pipeline(str(pipe_file))
    tracemalloc.start()
    try:
        rec = batch.process_one(pipe, str(path), str(tmp_path / "out"))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rec["status"] == "failed" and rec["error_type"] == "InputError"
    assert rec["error"].startswith(f"{path}: truncated: header declares {TERA} 'vertex' rows")
    assert peak < 1 << 20
    assert not list(tmp_path.glob("out*"))

    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["info", str(path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(
        f"recon: error: {path}: truncated: header declares {TERA} 'vertex' rows"
    ), err
    assert len(err.splitlines()) == 1
