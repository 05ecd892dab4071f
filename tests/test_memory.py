"""recon_cli.memory: the freed heap kept for reuse, or given back."""

from __future__ import annotations

import ctypes
import resource
import sys

import numpy as np
import pytest

from recon_cli import memory


def _glibc() -> bool:
    try:
        ctypes.CDLL("libc.so.6").mallopt  # noqa: B018
    except (OSError, AttributeError):
        return False
    return sys.platform.startswith("linux")


pytestmark = pytest.mark.skipif(not _glibc(), reason="glibc's allocator and Linux page faults")

MB = 1 << 20
# the faults of 64 MB of fresh pages at the least: 2 MiB pages, 32 of them
FAULTED = 32


def _faults_of_a_fresh_array(nbytes: int) -> int:
    """Minor page faults of filling a new array of ``nbytes`` after one of that size was freed."""
    a = np.ones(nbytes // 8)
    del a
    memory.release_free_heap()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    b = np.ones(nbytes // 8)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    del b
    return faults


def test_a_kept_heap_serves_the_next_array_without_faults():
    """Inside heap_kept a freed 64 MB array's pages serve the next one; outside they fault again."""
    # mapped anew, its pages faulted in (4 KiB ones, or 2 MiB ones where numpy asks for them)
    assert _faults_of_a_fresh_array(64 * MB) >= FAULTED
    with memory.heap_kept(True):
        _faults_of_a_fresh_array(64 * MB)  # the heap grows once
        assert _faults_of_a_fresh_array(64 * MB) < 8
    # glibc's thresholds back at its dynamic maximum: a 64 MB array is mapped (and faulted) again
    assert _faults_of_a_fresh_array(64 * MB) >= FAULTED


def test_no_room_keeps_nothing():
    """heap_kept(False) changes nothing: the freed array's pages fault again."""
    with memory.heap_kept(False):
        assert _faults_of_a_fresh_array(64 * MB) >= FAULTED
