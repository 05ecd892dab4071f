"""Print the requirements the named extras of the installed ``recon`` add, one a line.

``make install`` installs recon with the dependencies ``recon warmup`` needs first, then
these (``pip install -r``) while the kernels compile: pip then leaves the installed
recon alone (no second build of the editable install under the running warm-up).

Usage: ``python tools/extras.py reference,test,...``
"""

from __future__ import annotations

import importlib.metadata
import sys

try:
    from packaging.requirements import Requirement
except ImportError:  # a bare venv: pip's copy (importing pip turns setuptools' distutils shim off)
    from pip._vendor.packaging.requirements import Requirement


def extra_requirements(extras: list[str], requires: list[str] | None = None) -> list[str]:
    """The requirements that only the ``extras`` bring and this environment's markers select.

    ``requires`` defaults to the installed recon's metadata; markers are dropped.
    """
    out = []
    if requires is None:
        requires = importlib.metadata.requires("recon") or []
    for line in requires:
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate({"extra": ""}):
            continue  # a core requirement: installed already
        if any(req.marker.evaluate({"extra": e}) for e in extras):
            req.marker = None  # its environment markers were evaluated just now
            out.append(str(req))
    return sorted(set(out))


if __name__ == "__main__":
    print("\n".join(extra_requirements([e for e in sys.argv[1].split(",") if e])))
