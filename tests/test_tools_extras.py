"""tools/extras.py: what `make install` installs while the warm-up runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from extras import extra_requirements  # noqa: E402

REQUIRES = [
    "numpy>=1.24",
    'tomli>=2.0; python_version < "3.11"',
    'open3d>=0.18; extra == "reference"',
    'pymeshlab>=2023.12; extra == "reference"',
    'pillow>=10.1; extra == "render"',
    'laspy[lazrs]>=2.5; extra == "las"',
    'oldlib>=1; python_version < "3.0" and extra == "reference"',
    'torch==2.13.0; extra == "learned"',
    'pillow>=10.1; extra == "test"',
]


def test_only_the_named_extras_requirements_without_markers():
    """extra_requirements lists the named extras' requirements once, no markers, no core ones."""
    assert extra_requirements(["reference", "las"], REQUIRES) == [
        "laspy[lazrs]>=2.5",
        "open3d>=0.18",
        "pymeshlab>=2023.12",
    ]
    # one requirement of two extras once; the core ones never (installed before)
    assert extra_requirements(["render", "test"], REQUIRES) == ["pillow>=10.1"]
    assert extra_requirements([], REQUIRES) == []


def test_the_installed_metadata_as_pip_reads_it():
    """tools/extras.py reads the installed metadata: the extras' pins, no core package."""
    r = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "extras.py"), "reference,learned"],
        capture_output=True,
        text=True,
        check=True,
    )
    lines = r.stdout.split()
    assert any(x.startswith("open3d") for x in lines) and "torch==2.13.0" in lines
    assert not any(x.startswith(("numpy", "scipy", "numba")) for x in lines)
