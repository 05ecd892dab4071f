"""Reference backends: Open3D and PyMeshLab, behind ``--backend``.

All adapters live here and import their library lazily. A missing library raises
:class:`~recon_cli.errors.BackendError` naming the extra to install; the native path
never calls into this package.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from recon_cli.errors import BackendError

_EXTRA_HINT = "install the reference extra: pip install 'recon[reference]'"

# the reference-library calls made in this process, in order: {"call": name, "arguments": {...}}
# (what we pass; the library's own defaults apply to the rest). ``recon compare`` reports them.
CALLS: list[dict] = []


def record(call: str, **arguments) -> None:
    """Note a call into a reference library (see :data:`CALLS`)."""
    CALLS.append({"call": call, "arguments": arguments})


def require(name: str) -> ModuleType:
    """Import ``open3d`` or ``pymeshlab`` or raise :class:`BackendError`."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise BackendError(f"backend {name!r} is not available ({exc}); {_EXTRA_HINT}") from None


def backend_module(backend: str) -> ModuleType:
    """The adapter module for ``backend`` ("open3d" or "pymeshlab")."""
    if backend == "open3d":
        from recon_cli.backends import open3d_backend

        return open3d_backend
    if backend == "pymeshlab":
        from recon_cli.backends import pymeshlab_backend

        return pymeshlab_backend
    raise BackendError(f"unknown backend {backend!r}")
