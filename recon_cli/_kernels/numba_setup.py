"""Numba settings for recon's parallel kernels; imported by every kernel module that uses ``parallel=True``.

The threading layer is chosen once per process, at the first parallel launch. Left to its
default, numba tries TBB first; Open3D ships an older libtbb, and when open3d was imported
first numba finds that one and warns that TBB is disabled. OpenMP (then the workqueue)
is what numba would end up using anyway, so ask for it directly. An explicit
``NUMBA_THREADING_LAYER`` in the environment still wins.
"""

from __future__ import annotations

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # the priority must name all three; TBB last is only reached when neither other layer loads
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
