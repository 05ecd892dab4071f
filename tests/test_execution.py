"""Where the stages run (recon_cli.execution): the execution object and run_on."""

from __future__ import annotations

import pytest

import recon_cli
from recon_cli.errors import ParameterError
from recon_cli.execution import MIN_MEMORY, Execution, current, parse_size, run_on


@pytest.mark.parametrize(
    "text, nbytes",
    [
        ("6GB", 6 * 10**9),
        ("6GiB", 6 * 2**30),
        ("6 gib", 6 * 2**30),
        ("500MB", 500 * 10**6),
        ("1.5GiB", 3 * 2**29),
        ("1e9", 10**9),
        (2**30, 2**30),
        ("1TB", 10**12),
    ],
)
def test_sizes(text, nbytes):
    """Sizes with decimal or binary units, in any case, or plain numbers parse to their bytes."""
    assert parse_size(text) == nbytes


@pytest.mark.parametrize("bad", ["lots", "6XB", "-1GB", "", "100MB", 1000, True, "nan", "inf"])
def test_bad_sizes_are_refused(bad):
    """Words, unknown units, negatives, empty, below MIN_MEMORY, booleans, NaN and inf: refused."""
    with pytest.raises(ValueError):
        parse_size(bad)


def test_run_on_sets_the_execution_for_the_block_only():
    """``run_on`` sets the current execution inside its block only."""
    assert current() == Execution()
    with run_on(memory="1GiB", partitions=3) as ex:
        assert current() is ex and ex.memory == 2**30 and ex.partitions == 3
        assert ex.budget() == 2**30 and not ex.distributed
        with run_on(workers=2):  # nested: replaces what it gives, keeps the rest
            inner = current()
            assert (inner.workers, inner.memory, inner.partitions) == (2, 2**30, 3)
            assert inner.distributed and inner.worker_memory() == int(2**30 * 0.8) // 2
        assert current() is ex
    assert current() == Execution()
    with recon_cli.run_on(Execution(partitions=2)) as ex:
        assert ex.partitions == 2 and current().memory is None


@pytest.mark.parametrize(
    "options, message",
    [
        ({"workers": 2, "scheduler": "tcp://x:1"}, "give one of them"),
        ({"memory": "10MB"}, f"--memory must be a size of at least {MIN_MEMORY >> 20} MiB"),
        ({"workers": 0}, "--workers must be an integer with 1 <= x <= 1024"),
        ({"partitions": 65}, "--partitions must be an integer with 1 <= x <= 64"),
        ({"temp_dir": "/nonexistent/folder"}, "no such folder"),
        ({"threads": 2}, "no execution option 'threads'"),
    ],
)
def test_bad_options_are_refused_in_one_line(options, message):
    """Bad execution options are refused in one line, the current execution untouched."""
    with pytest.raises(ParameterError, match=message) as err:
        with run_on(**options):
            pass
    assert "\n" not in str(err.value)
    assert current() == Execution()


def test_spill_folder_goes_beside_the_output(tmp_path):
    """The spill folder goes beside the output or in temp_dir; none for stdout or no folder."""
    out = tmp_path / "mesh.ply"
    assert Execution().spill_parent(str(out)) == str(tmp_path)
    assert Execution(temp_dir=str(tmp_path)).spill_parent("/elsewhere/m.ply") == str(tmp_path)
    for other in ("-", "/dev/stdout", None):
        assert Execution().spill_parent(other) is None
    assert Execution().spill_parent(str(tmp_path / "no" / "such" / "m.ply")) is None


def test_budget_is_the_available_memory_by_default():
    """By default the memory budget is the available memory, and no worker limit is set."""
    from recon_cli.memory import available_bytes

    got, avail = Execution().budget(), available_bytes()
    assert got is not None and avail is not None
    assert abs(got - avail) < 0.1 * avail  # read twice: the machine moves a little
    assert Execution().worker_memory() is None  # no local cluster
