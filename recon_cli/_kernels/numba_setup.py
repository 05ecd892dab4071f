"""Numba settings for every recon kernel: the compile cache's directory and the threading layer.

Every module that defines a numba kernel imports this module *before* ``numba`` (a test
checks it): numba fixes where a ``@njit(cache=True)`` function keeps its cache when the
function is decorated. On import it sets, unless the environment already says otherwise:

- ``NUMBA_CACHE_DIR``: ``$XDG_CACHE_HOME/recon/numba/<fingerprint>`` (else
  ``~/.cache/recon/numba/<fingerprint>``), the fingerprint naming the state of every kernel
  source (:func:`kernel_sources_fingerprint`); exported, so worker processes share it;
- ``NUMBA_THREADING_LAYER``: OpenMP (numba would try Open3D's older TBB first);
- ``GOMP_SPINCOUNT``: :data:`GOMP_SPINCOUNT`, unless ``OMP_WAIT_POLICY`` or
  ``GOMP_SPINCOUNT`` is set.

Why each (stale machine code across modules, TBB's warning, spinning OpenMP threads on a busy
machine): ``docs/design/process.md``.
"""

from __future__ import annotations

import os
import sys
from typing import Any

from recon_cli._kernels.cache import cache_dir, kernel_sources_fingerprint  # noqa: F401  (re-exported)

# numpy submodules recon never uses that numba's start-up loads anyway: numba checks for
# BLAS by importing scipy.linalg, whose array-API layer star-imports numpy (numpy 2 loads its
# submodules on attribute access, so ``from numpy import *`` loads them all): f2py and testing
# are never used by recon (numba itself uses numpy.ma, so that one stays). Registered as
# lazy modules they cost nothing until something reads one of their attributes (then they
# load as usual). About 50 ms of CPU per process, a tenth of numba's floor.
_LAZY_NUMPY = ("numpy.f2py", "numpy.testing")


def _lazy_numpy_submodules() -> None:
    import importlib.util

    import numpy

    for name in _LAZY_NUMPY:
        if name in sys.modules:
            continue
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        setattr(numpy, name.rpartition(".")[2], module)


if "scipy.linalg" not in sys.modules:
    _lazy_numpy_submodules()

CACHE_DIR = cache_dir()
os.environ["NUMBA_CACHE_DIR"] = CACHE_DIR
if "numba" in sys.modules:  # imported before recon (by the user or a library): tell its config too
    sys.modules["numba"].config.CACHE_DIR = CACHE_DIR

import numba  # noqa: E402  (after NUMBA_CACHE_DIR is set)

# numba.config's settings are made at run time: untyped for mypy
_config: Any = numba.config
_config.CACHE_DIR = CACHE_DIR

if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # the priority must name all three; TBB last is only reached when neither other layer loads.
    # Through the environment, not numba.config alone: numba's compiler re-reads the NUMBA_*
    # variables whenever one of them changed since it last looked (ours did, when numba was
    # imported before recon) and would reset an attribute set here to TBB first (a
    # NumbaWarning on stderr, an error under pytest's strict warnings)
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = "omp workqueue tbb"
    _config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

# spin rounds of an idle OpenMP thread before it sleeps (module docstring: Idle OpenMP threads):
# a thirtieth of libgomp's default, so a launch right after the last one still finds it awake
GOMP_SPINCOUNT = "10000"
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["GOMP_SPINCOUNT"] = GOMP_SPINCOUNT


# Loading a cached kernel needs numba's runtime (NRT) only; numba refreshes its whole
# target context first all the same: it imports and installs every typing and lowering
# registry (numba.np.arraymath, which imports scipy.linalg to look for BLAS, unicode,
# typed containers...), ~0.2 CPU s of every process, more than loading all the kernels of a
# stage. Loads skip that refresh (the runtime is initialised as numba's refresh would); a
# cache miss compiles through numba's compiler, which refreshes the context itself, and a
# kernel compiled or loaded afterwards sees the full context. Both run under numba's global
# compiler lock, so no compile sees the shortened refresh.
def _lean_cache_loads() -> None:
    from numba.core.caching import Cache
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.runtime import rtsys

    full = Cache.load_overload
    if getattr(full, "recon_lean", False):
        return

    def load_overload(self, sig, target_context):
        with global_compiler_lock:
            # an instance attribute shadows the method for the length of this load
            target_context.refresh = lambda: rtsys.initialize(target_context)
            try:
                return full(self, sig, target_context)
            finally:
                del target_context.refresh

    load_overload.recon_lean = True  # type: ignore[attr-defined]  # marks the patch as ours
    load_overload.__doc__ = full.__doc__
    Cache.load_overload = load_overload  # type: ignore[method-assign]  # the patch itself


if os.environ.get("RECON_NUMBA_FULL_REFRESH") != "1":
    _lean_cache_loads()


# a progress display made before numba was loaded listens to its compiler from now on
if "recon_cli.progress" in sys.modules:
    sys.modules["recon_cli.progress"].numba_loaded()
