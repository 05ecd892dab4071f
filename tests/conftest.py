"""Fixtures shared by every test module (data helpers live in shared_data.py)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
