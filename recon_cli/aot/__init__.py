"""Ahead-of-time compiled kernels: a command that runs them never imports numba.

``recon warmup`` also compiles the kernel modules of the commands whose work is smaller than
numba's start-up (:func:`.build.modules_to_build`: the PLY reader/writer, mesh topology,
and the ``_kernel`` of every stage whose package sets ``AOT = True``: ball pivoting, marching
cubes, filter) into Python extension modules with ``numba.pycc`` (:mod:`recon_cli.aot.build`), from
the same ``@njit`` functions, for the argument types the warm-up compiled them for. A stage
asks for its kernels through :func:`kernels` instead of importing its ``_kernel`` module:

* when a build for this state of the sources, numba, numpy, Python and CPU exists
  (:func:`build_dir`, beneath the numba cache directory), each public kernel is a small
  Python function that computes the numba type of its arguments (:func:`type_key`: dtype,
  ndim, layout, writeable, aligned of arrays; scalars; tuples) and calls the compiled
  variant made for exactly those types;
* otherwise, for arguments no variant was made for, for keyword calls, or with
  ``RECON_AOT=0`` in the environment, the ``@njit`` kernel runs (its module imported then):
  the same source compiled by the same compiler, so the same results.

Parallel kernels (``parallel=True``) are never built ahead of time (pycc has no threading
layer): they always run JIT. A build whose fingerprint differs (any kernel source edited,
another numba/numpy/Python, another CPU) sits in another directory and is never loaded.
Why (numba's import costs more than some whole commands): ``docs/design/process.md``.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from recon_cli._kernels.cache import cache_dir, kernel_sources_fingerprint

# the kernel modules built ahead of time besides the stages' (build.modules_to_build): reading
# and writing PLY, the mesh topology of the reports
MODULES = (
    "recon_cli.io._ply_kernel",
    "recon_cli.mesh._topology_kernel",
)


MANIFEST = "manifest.json"
# the layout of a build (manifest, signature keys): part of the fingerprint, so a loader
# never reads a build made by another version of this module
FORMAT = "1"

_state: dict[str, Any] = {"manifest": None, "namespaces": {}, "dir": None, "fallbacks": set()}


def enabled() -> bool:
    """False when ``RECON_AOT=0`` is in the environment (every kernel then runs JIT)."""
    return os.environ.get("RECON_AOT", "1") != "0"


def _cpu_id() -> str:
    """The CPU the build targets (``host`` in pycc's terms): model and flags on Linux."""
    import platform

    ident = [platform.machine()]
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key = line.partition(":")[0].strip()
                if key in ("vendor_id", "model name", "flags", "Features", "CPU part"):
                    ident.append(line.strip())
                elif not line.strip() and len(ident) > 1:
                    break  # the first processor's block is enough
    except OSError:
        ident.append(platform.processor())
    return "\n".join(ident)


def _package_stamp(name: str) -> str:
    """Path, size and modification time of an installed package's version files.

    The package is not imported.
    """
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.origin:
        return f"{name}: absent"
    folder = os.path.dirname(spec.origin)
    out = []
    for leaf in ("__init__.py", "_version.py"):
        path = os.path.join(folder, leaf)
        try:
            st = os.stat(path)
        except OSError:
            continue
        out.append(f"{path}\0{st.st_size}\0{st.st_mtime_ns}")
    return "\n".join(out)


def fingerprint() -> str:
    """16 hex digits naming everything a build depends on.

    The kernel sources, numba and llvmlite (their installed files), numpy's version, Python's, and
    the CPU.
    """
    import hashlib

    h = hashlib.blake2b(digest_size=8)
    parts = [
        FORMAT,
        kernel_sources_fingerprint(),
        _package_stamp("numba"),
        _package_stamp("llvmlite"),
        np.__version__,
        sys.version,
        sys.implementation.cache_tag,
        _cpu_id(),
    ]
    h.update("\n\0".join(parts).encode())
    return h.hexdigest()


def build_dir() -> str:
    """Where the build for this state lives.

    ``<numba cache directory>/aot/<fingerprint>`` (computed once per process, ~5 ms; :func:`reset`
    forgets it).
    """
    if _state["dir"] is None:
        _state["dir"] = os.path.join(cache_dir(), "aot", fingerprint())
    return _state["dir"]


def manifest() -> dict:
    """The build's manifest (``{}`` when there is no build for this state, or AOT is off)."""
    if _state["manifest"] is None:
        found: dict = {}
        if enabled():
            import json

            path = os.path.join(build_dir(), MANIFEST)
            try:
                with open(path, encoding="utf-8") as fh:
                    found = json.load(fh)
            except (OSError, ValueError):
                found = {}
        _state["manifest"] = found
    return _state["manifest"]


def reset() -> None:
    """Forget the manifest and the namespaces handed out.

    Called after a build, or to switch ahead-of-time kernels off in a test.
    """
    _state["manifest"] = None
    _state["dir"] = None
    _state["namespaces"].clear()
    _state["fallbacks"].clear()


def fallbacks() -> set[tuple[str, str, str | None]]:
    """The calls of built modules' kernels that ran JIT since the last :func:`reset`.

    Each is (module, kernel, signature key): the build had no variant for those argument types.
    """
    return set(_state["fallbacks"])


def type_key(x: Any) -> str | None:
    """Numba's type of ``x`` as a string, or None for a value no ahead-of-time variant takes.

    The string is the one :func:`recon_cli.aot.build.numba_type_key` writes.
    """
    t = type(x)
    if t is np.ndarray:
        dt = x.dtype
        if dt.kind not in "biufc" or not dt.isnative:
            return None
        f = x.flags
        layout = "C" if f.c_contiguous else ("F" if f.f_contiguous else "A")
        # numba types an unaligned array as an aligned one (its typeof ignores the flag): so do we
        return f"{dt.str}:{x.ndim}{layout}{'' if f.writeable else 'r'}"
    if t is float:
        return "float64"
    if t is complex:
        return "complex128"
    if t is bool:
        return "bool"
    if t is int:
        return "int64" if -(1 << 63) <= x < (1 << 63) else None
    if t is tuple:
        parts = [type_key(v) for v in x]
        return None if None in parts else "(" + ",".join(parts) + ")"  # type: ignore[arg-type]
    if isinstance(x, np.generic):
        dt = x.dtype
        return dt.name if dt.kind in "biufc" else None
    if x is None:
        return "none"
    return None


def signature_key(args: tuple) -> str | None:
    """The key of a call's positional arguments (None if one of them has no key)."""
    parts = [type_key(a) for a in args]
    return None if None in parts else "|".join(parts)  # type: ignore[arg-type]


class _Kernels:
    """A kernel module's public kernels: compiled ahead of time, JIT for any other argument types.

    Functions only: constants of the kernel module are not carried.
    """

    def __init__(self, name: str, ext: Any, table: dict[str, dict[str, str]]):
        self.__name__ = name
        self._ext = ext
        self._table = table

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("_"):
            raise AttributeError(attr)
        # a kernel the build has no variant of gets a dispatcher over none: it imports its
        # module (numba) only if it is called
        variants = self._table.get(attr, {})
        value = _dispatcher(
            self.__name__, attr, {k: getattr(self._ext, v) for k, v in variants.items()}
        )
        setattr(self, attr, value)
        return value

    def __repr__(self) -> str:
        return f"<ahead-of-time kernels of {self.__name__}>"


def _dispatcher(module: str, name: str, variants: dict[str, Callable]) -> Callable:
    def call(*args: Any, **kwargs: Any) -> Any:
        key = None if kwargs else signature_key(args)
        fn = variants.get(key)  # type: ignore[arg-type]
        if fn is not None:
            return fn(*args)
        _state["fallbacks"].add((module, name, "keywords" if kwargs else key))
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__module__ = module
    call.aot_variants = variants  # type: ignore[attr-defined]
    return call


def _load_extension(name: str, path: str) -> Any:
    loader = importlib.machinery.ExtensionFileLoader(name, path)
    spec = importlib.util.spec_from_file_location(name, path, loader=loader)
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    loader.exec_module(module)
    return module


def kernels(name: str) -> Any:
    """The kernels of module ``name`` (e.g. ``"recon_cli.stages.ballpivot._kernel"``).

    Its ahead-of-time build when there is one, else the module itself (numba JIT, from the cache).
    """
    ns = _state["namespaces"].get(name)
    if ns is None:
        entry = manifest().get("modules", {}).get(name)
        ns = None
        if entry is not None:
            try:
                ext = _load_extension(entry["extension"], os.path.join(build_dir(), entry["file"]))
                ns = _Kernels(name, ext, entry["functions"])
            except (ImportError, OSError, KeyError):
                ns = None
        if ns is None:
            ns = importlib.import_module(name)
        _state["namespaces"][name] = ns
    return ns


def native_library(name: str) -> Any:
    """A C library the build made (``ctypes.CDLL``), or None."""
    entry = manifest().get("libraries", {}).get(name)
    if entry is None:
        return None
    import ctypes

    try:
        return ctypes.CDLL(os.path.join(build_dir(), entry))
    except OSError:
        return None
