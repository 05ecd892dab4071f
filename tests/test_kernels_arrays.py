"""recon_cli._kernels.arrays: growing arrays and the binary search the grid kernels share."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli._kernels.arrays import grow1, grow2, lower_bound


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-50, 50), max_size=40), st.integers(-60, 60))
def test_lower_bound_is_searchsorted_left(values, x):
    """``lower_bound`` equals ``np.searchsorted(side="left")`` on sorted integers."""
    a = np.sort(np.asarray(values, dtype=np.int64))
    assert lower_bound(a, x, 0, len(a)) == np.searchsorted(a, x, side="left")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-50, 50), max_size=40), st.integers(-60, 60), st.data())
def test_lower_bound_searches_only_its_range(values, x, data):
    """``lower_bound`` within [lo, hi) equals searchsorted of that slice, offset by lo."""
    a = np.sort(np.asarray(values, dtype=np.int64))
    lo = data.draw(st.integers(0, len(a)))
    hi = data.draw(st.integers(lo, len(a)))
    assert lower_bound(a, x, lo, hi) == lo + np.searchsorted(a[lo:hi], x, side="left")


def test_lower_bound_on_repeated_keys_finds_the_first():
    """On repeated keys ``lower_bound`` finds the first."""
    a = np.array([1, 3, 3, 3, 7], dtype=np.int64)
    assert [lower_bound(a, x, 0, len(a)) for x in (0, 1, 2, 3, 4, 7, 8)] == [0, 0, 1, 1, 4, 4, 5]


def test_grow_keeps_the_head():
    """``grow1`` and ``grow2`` give the new length, their first rows the old array's."""
    x = np.arange(4.0)
    assert np.array_equal(grow1(x, 9)[:4], x) and grow1(x, 9).shape == (9,)
    y = np.arange(6).reshape(3, 2)
    assert np.array_equal(grow2(y, 5)[:3], y) and grow2(y, 5).shape == (5, 2)
