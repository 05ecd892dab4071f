"""recon_cli.progress: bars drawn by rich, silent when disabled, and the compile notice."""

from __future__ import annotations

import io
import subprocess
import sys

from numba import njit

from recon_cli.progress import COMPILING, Progress, task


def test_disabled_progress_draws_nothing_and_imports_no_rich():
    code = (
        "import io, sys\n"
        "from recon_cli.progress import Progress, task\n"
        "buf = io.StringIO()\n"
        "p = Progress(stream=buf, enabled=None)\n"  # a StringIO is not a terminal
        "with task(p, 'x', 3) as t:\n"
        "    t.advance(3)\n"
        "with task(None, 'y') as t:\n"
        "    t.update(1)\n"
        "p.close()\n"
        "assert buf.getvalue() == '', buf.getvalue()\n"
        "assert 'rich' not in sys.modules and 'numba' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_bar_weighted_by_work_reaches_100_and_spinner_task_ends():
    buf = io.StringIO()
    p = Progress(stream=buf, enabled=True)
    with task(p, "levels", 100) as t:
        t.advance(10)
        t.advance(90)
    with task(p, "tree") as t:
        pass
    p.close()
    out = buf.getvalue()
    assert "levels" in out and "tree" in out
    assert out.rstrip().count("100%") >= 2  # both end finished
    assert "eta" in out


def test_compiling_is_announced_while_numba_compiles():
    @njit  # not cached: compiles in this process
    def plus_one(x):
        return x + 1

    buf = io.StringIO()
    p = Progress(stream=buf, enabled=True)
    with task(p, "stage", 1) as t:
        assert plus_one(1) == 2
        t.advance(1)
    p.close()
    assert COMPILING in buf.getvalue()

    @njit
    def plus_two(x):
        return x + 2

    # closed: no longer listening
    before = buf.getvalue()
    assert plus_two(1) == 3
    assert buf.getvalue() == before
