"""Fixtures shared by every test module (data helpers live in shared_data.py)."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time

import numpy as np
import pytest


@pytest.fixture
def rng():
    """A seeded generator (12345), the same for every test that asks for one."""
    return np.random.default_rng(12345)


# RECON_TEST_COMPILES=FILE: each test's numba compiles (kernels, seconds) appended to FILE as
# JSON lines, to find what a warmed install still compiles (a diagnostic, not a check).
_COMPILES = os.environ.get("RECON_TEST_COMPILES")
_seen: list[tuple[str, float]] = []


def pytest_configure(config):
    """Snapshot the warm kernel cache (in the controller) and, when asked, log numba's compiles.

    The compile log is on when ``_COMPILES`` names a file: each compile's kernel and seconds are
    kept for :func:`pytest_runtest_protocol` to write.
    """
    if not hasattr(config, "workerinput"):
        _snapshot_warm_cache()
    if not _COMPILES:
        return
    from numba.core import event

    class _Listener(event.Listener):
        starts: list[float] = []

        def on_start(self, ev):
            self.starts.append(time.perf_counter())

        def on_end(self, ev):
            took = time.perf_counter() - self.starts.pop()
            _seen.append(
                (ev.data["dispatcher"].py_func.__qualname__, took if not self.starts else 0)
            )

    event.register("numba:compile", _Listener())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Write one JSON line per test that compiled kernels: its id, count, seconds and kernels.

    Only when the compile log is on (``_COMPILES``).
    """
    _seen.clear()
    yield
    if _COMPILES and _seen:
        top = [name for name, _ in _seen if "<locals>" not in name]
        took = round(sum(t for _, t in _seen), 2)
        line = {"test": item.nodeid, "n": len(_seen), "s": took, "kernels": top[:20]}
        with open(_COMPILES, "a") as f:
            f.write(json.dumps(line) + "\n")


# test_warmup's copy of the numba cache as `make install` left it, taken before any test compiles
# into it: warming that copy up again costs what an edit made stale, not a whole warm-up from
# empty (which a clean clone's install has just done).
WARM_CACHE = "RECON_TEST_WARM_CACHE"


def _snapshot_warm_cache() -> None:
    from recon_cli._kernels.numba_setup import CACHE_DIR

    if WARM_CACHE in os.environ or not os.path.isdir(CACHE_DIR):
        return
    copy = os.path.join(tempfile.mkdtemp(prefix="recon-test-cache-"), "cache")
    shutil.copytree(CACHE_DIR, copy, ignore=shutil.ignore_patterns("*.lock", "*.tmp*"))
    os.environ[WARM_CACHE] = copy  # the xdist workers start after this and inherit it


def pytest_unconfigure(config):
    """Remove the warm cache's snapshot this session made (in the controller only)."""
    copy = os.environ.get(WARM_CACHE)
    if copy and not hasattr(config, "workerinput") and "recon-test-cache-" in copy:
        shutil.rmtree(os.path.dirname(copy), ignore_errors=True)
