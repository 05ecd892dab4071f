"""recon: surface reconstruction from point clouds.

The library is free of click and never exits the process; the command line lives in
:mod:`recon_cli.cli`.
"""

__version__ = "0.1.0"

from recon_cli.errors import ReconError, InputError, ParameterError, BackendError  # noqa: E402
from recon_cli.geometry import PointCloud, TriangleMesh  # noqa: E402

__all__ = [
    "__version__",
    "ReconError",
    "InputError",
    "ParameterError",
    "BackendError",
    "PointCloud",
    "TriangleMesh",
]
