"""recon: surface reconstruction from point clouds.

The library is free of click and never exits the process; the command line lives in
:mod:`recon_cli.cli`. Names are imported lazily so that ``recon --help`` does not pay
for numpy. Every registered stage is a function here, made from its declaration
(:mod:`recon_cli.api`): ``recon_cli.normals(cloud, knn=30)``, ``recon_cli.poisson(...)``,
``recon_cli.fit_sdf(...)``; ``recon_cli.read(path)`` and ``recon_cli.write(obj, path)`` read
and write every format; ``with recon_cli.run_on(workers=2, memory="6GB"):`` says where the stages
in the block run (:mod:`recon_cli.execution`). ``__init__.pyi`` types them (``python -m
recon_cli.tools.stubs``).
"""

from __future__ import annotations

__version__ = "0.1.0"

_LAZY = {
    "ReconError": "recon_cli.errors",
    "InputError": "recon_cli.errors",
    "OutputError": "recon_cli.errors",
    "NoSpace": "recon_cli.errors",
    "ParameterError": "recon_cli.errors",
    "BackendError": "recon_cli.errors",
    "StageFailed": "recon_cli.errors",
    "PointCloud": "recon_cli.geometry",
    "TriangleMesh": "recon_cli.geometry",
    "geometry_from": "recon_cli.geometry",
    "Grid": "recon_cli.grid",
    "Tileset": "recon_cli.io.tiles",
    "Progress": "recon_cli.progress",
    "read": "recon_cli.api",
    "write": "recon_cli.api",
    "read_ply": "recon_cli.io.ply",
    "write_ply": "recon_cli.io.ply",
    "load": "recon_cli.io.load",
    "save": "recon_cli.io.load",
    "apply_stage": "recon_cli.stages",
    "register_stage": "recon_cli.stages",
    "StageSpec": "recon_cli.params",
    "Param": "recon_cli.params",
    "Execution": "recon_cli.execution",
    "run_on": "recon_cli.execution",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    if name == "__all__":  # the stage functions are known once the registry is read
        from recon_cli.api import function_names

        return ["__version__", *_LAZY, *function_names()]
    # a submodule not imported yet (``from recon_cli import aot``) is the import system's:
    # looking for a stage function would import numpy into commands that start without it
    if not name.startswith("_") and not _is_module(name):
        from recon_cli.api import function_named

        fn = function_named(name)
        if fn is not None:
            return fn
    raise AttributeError(f"module 'recon_cli' has no attribute {name!r}")


def _is_module(name: str) -> bool:
    import os

    where = os.path.join(__path__[0], name)
    return os.path.isdir(where) or os.path.isfile(where + ".py")


def __dir__() -> list[str]:
    from recon_cli.api import function_names

    return sorted({*globals(), *_LAZY, *function_names()})
