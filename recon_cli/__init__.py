"""recon: surface reconstruction from point clouds.

The library is free of click and never exits the process; the command line lives in
:mod:`recon_cli.cli`. Names are imported lazily so that ``recon --help`` does not pay
for numpy.
"""

from __future__ import annotations

__version__ = "0.1.0"

_LAZY = {
    "ReconError": "recon_cli.errors",
    "InputError": "recon_cli.errors",
    "ParameterError": "recon_cli.errors",
    "BackendError": "recon_cli.errors",
    "StageFailed": "recon_cli.errors",
    "PointCloud": "recon_cli.geometry",
    "TriangleMesh": "recon_cli.geometry",
    "Grid": "recon_cli.grid",
    "read_ply": "recon_cli.io.ply",
    "write_ply": "recon_cli.io.ply",
    "load": "recon_cli.io.load",
    "save": "recon_cli.io.load",
    "apply_stage": "recon_cli.stages",
    "register_stage": "recon_cli.stages",
    "StageSpec": "recon_cli.params",
    "Param": "recon_cli.params",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'recon_cli' has no attribute {name!r}")
