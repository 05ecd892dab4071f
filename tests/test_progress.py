"""recon_cli.progress: bars drawn by rich, silent when disabled, and the compile notice."""

from __future__ import annotations

import io
import subprocess
import sys

from numba import njit

from recon_cli.progress import COMPILING, Progress, task


def test_disabled_progress_draws_nothing_and_imports_no_rich():
    """A disabled display draws nothing and imports neither rich nor numba (fresh process)."""
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
    """A bar weighted by work reaches 100 %, with an eta; a spinner task ends finished too."""
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
    """The display announces compiling while numba compiles, and stops listening once closed."""

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


def test_a_display_made_before_numba_loads_announces_compiling_without_importing_numba_itself():
    """A display made before numba loads still announces compiling, without importing numba.

    A command running ahead-of-time kernels never loads numba, even with a progress display; when a
    kernel module loads it later (a JIT fallback), the display still says it compiles.
    """
    code = (
        "import io, sys\n"
        "from recon_cli.progress import COMPILING, Progress, task\n"
        "buf = io.StringIO()\n"
        "p = Progress(stream=buf, enabled=True)\n"
        "assert 'numba' not in sys.modules\n"
        "from recon_cli._kernels import numba_setup\n"
        "from numba import njit\n"
        "@njit\n"
        "def plus_one(x):\n"
        "    return x + 1\n"
        "with task(p, 'stage', 1) as t:\n"
        "    assert plus_one(1) == 2\n"
        "    t.advance(1)\n"
        "p.close()\n"
        "assert COMPILING in buf.getvalue(), buf.getvalue()\n"
    )
    subprocess.run([sys.executable, "-W", "error", "-c", code], check=True)


def test_expected_step_moves_on_the_rate_so_far_and_never_past_its_end():
    """An expected step moves the bar at the rate so far, never backwards, never past its end."""
    import time

    buf = io.StringIO()
    p = Progress(stream=buf, enabled=True)
    with task(p, "levels", 100) as t:
        t.expect(10)  # no work done yet: no rate, the bar waits
        time.sleep(0.3)
        assert p._bars.tasks[0].completed == 0
        t.advance(10)
        t.expect(80)  # a long step: moves at the rate so far (~30 units/s here)
        seen = []
        for _ in range(8):
            time.sleep(0.15)
            seen.append(p._bars.tasks[0].completed)
        assert 10 < seen[-1] <= 10 + 0.95 * 80
        assert seen == sorted(seen)  # never backwards
        t.advance(80)
        assert p._bars.tasks[0].completed == 90
        t.expect(10)
        t.expect(0)  # a new expectation ends the previous one
        assert t._ticker is None
        t.advance(10)
    p.close()
    assert "100%" in buf.getvalue()
    with task(None, "silent") as t:
        t.expect(5)
        t.advance(5)


def test_poisson_solve_bar_is_weighted_by_each_levels_work():
    """The Poisson solve's bar weighs each level by its work, not one unit per level.

    The exact levels and the big fine levels weigh what they cost: the solve's work estimate follows
    the level sizes.
    """
    from types import SimpleNamespace

    from recon_cli.stages.poisson.system import solve_work

    nodes = [8, 27, 125, 729, 4913, 35937, 43845, 149983, 476578]  # the sample scan at depth 8
    levels = [SimpleNamespace(depth=d, n_nodes=n) for d, n in enumerate(nodes)]
    w = solve_work(levels, full_depth=5)
    share = [x / sum(w) for x in w]
    # measured seconds per level on that scan: 0.17 0.11 0.08 0.07 0.12 0.77 0.25 0.60 1.09
    assert max(share[:5]) < 0.06 and share[5] > 0.15 and share[8] > 0.35
    assert share[8] > share[7] > share[6]
