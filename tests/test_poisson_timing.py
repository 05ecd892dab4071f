"""Poisson's phase timings (recon_cli.stages.poisson.timing)."""

import time

import pytest

from recon_cli.stages.poisson.timing import Timings


def test_phases_in_order_and_total_covers_them():
    """Phases are kept in order and the total covers them."""
    clock = Timings()
    with clock.phase("a"):
        time.sleep(0.01)
    with clock.phase("b"):
        pass
    seconds = clock.total()
    assert list(seconds) == ["a", "b", "total"]
    assert seconds["a"] >= 0.01 and seconds["b"] >= 0.0
    assert seconds["total"] >= seconds["a"] + seconds["b"]


def test_a_phase_that_raises_is_not_recorded():
    """A phase that raises is not recorded."""
    clock = Timings()
    with pytest.raises(ValueError), clock.phase("bad"):
        raise ValueError("x")
    assert "bad" not in clock.seconds
