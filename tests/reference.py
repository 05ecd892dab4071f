"""Reference-library calls in a process of their own.

Open3D's reconstructions run their own OpenMP threads; in a test worker that has also run numba's
parallel kernels, Open3D's Poisson crashed the whole worker once in a full run (a segfault inside
``create_from_point_cloud_poisson``, not reproducible alone). The cross-checks that call it go
through :func:`isolated`, a freshly spawned process, so such a crash cannot take other tests down
with it.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from typing import Any


def isolated(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` in a spawned child process.

    ``fn`` must be importable, its arguments and result picklable.
    """
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args, kwargs)
