"""Where recon keeps its compiled kernels (no numba import: the ahead-of-time loader uses it too).

See :mod:`recon_cli._kernels.numba_setup` for the layout and why the directory carries a
fingerprint of the kernel sources; :mod:`recon_cli.aot` keeps its builds beneath it.
"""

from __future__ import annotations

import os


def kernel_sources_fingerprint(root: str | None = None) -> str:
    """16 hex digits naming the state of the modules that can hold kernels under ``root``.

    ``root`` defaults to the recon_cli package. The modules are the private ``_*.py`` modules and
    everything in ``_kernels/`` (path, size and modification time; a stat per file, about a
    millisecond).
    """
    import hashlib

    root = root or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.blake2b(digest_size=8)
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        in_kernels = os.path.basename(folder) == "_kernels"
        for name in sorted(files):
            if name.endswith(".py") and (
                in_kernels or (name.startswith("_") and not name.startswith("__"))
            ):
                path = os.path.join(folder, name)
                st = os.stat(path)
                h.update(
                    f"{os.path.relpath(path, root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode()
                )
    return h.hexdigest()


def cache_dir() -> str:
    """The directory of recon's numba cache.

    ``$NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/recon/numba/<fingerprint>``
    (``~/.cache/recon/numba/<fingerprint>``).
    """
    explicit = os.environ.get("NUMBA_CACHE_DIR")
    if explicit:
        return explicit
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "recon", "numba", kernel_sources_fingerprint())
