"""Shared test data: the real meshes and scans in ../shared/data, and sampled clouds.

The clouds come with true normals.

Import from here (``from shared_data import load_shared``); conftest.py only holds fixtures.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RECON_SHARED_DATA", ROOT.parent / "shared" / "data"))

CLOSED_MESHES = ["armadillo", "kitten", "mug"]  # watertight, outward
ALL_MESHES = ["armadillo", "bunny_zipper", "kitten", "mug"]
SCANS = ["bunny_scan_000", "stereo_fragment"]


def shared_path(name: str) -> Path:
    """Path of the shared mesh or scan ``name``; FileNotFoundError naming it when missing."""
    p = SHARED / f"{name}.ply"
    if not p.exists():
        raise FileNotFoundError(f"shared data missing: {p} (CI has ../shared beside the checkout)")
    return p


@functools.cache
def _load(name: str):
    from recon_cli.io import read_ply

    return read_ply(shared_path(name))


def load_shared(name: str):
    """A fresh copy of a shared mesh or scan (cached read)."""
    return _load(name).copy()


@functools.cache
def _sample(name: str, n: int, noise: float, seed: int):
    from recon_cli.mesh.sampling import sample_surface

    return sample_surface(_load(name), n, seed=seed, noise=noise)


def sampled_cloud(name: str, n: int = 100_000, noise: float = 0.0, seed: int = 0):
    """Area-uniform samples of a shared mesh with true normals (``noise``: fraction of diagonal)."""
    return _sample(name, n, noise, seed).copy()
