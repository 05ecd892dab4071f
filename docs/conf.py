"""Sphinx configuration of recon's documentation (``make docs``).

The stage pages and the command-line reference are written from the stage declarations and
the commands at the start of every build (:mod:`recon_cli.tools.docs`), so their parameter
tables and ``--help`` texts are never copied by hand.
"""

from __future__ import annotations

import os
import sys

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)

from recon_cli import __version__  # noqa: E402  (after the repository is on the path)
from recon_cli.cli.reference import write_reference  # noqa: E402
from recon_cli.tools.docs import bench_summary, write_changed, write_pages  # noqa: E402

project = "recon"
author = "the recon developers"
copyright = "the recon developers"  # noqa: A001  (Sphinx's name)
release = version = __version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "_generated"]  # _generated: included by other pages
root_doc = "index"
# options are written --like-this: no en dashes, no curly quotes in commands
smartquotes = False

try:  # the `docs` extra installs furo; a bare Sphinx still builds
    import furo  # noqa: F401

    html_theme = "furo"
except ImportError:  # pragma: no cover
    html_theme = "alabaster"
html_title = f"recon {release}"

autosummary_generate = True
autodoc_typehints = "none"  # the numpydoc sections say the types, in words and shapes
autodoc_member_order = "bysource"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
myst_heading_anchors = 3
# the README's sections, included under a page title, start at a deeper heading level
suppress_warnings = ["myst.header"]
templates_path = ["_templates"]

nitpicky = True
# No network here, so no intersphinx: names of other projects cannot resolve
nitpick_ignore_regex = [
    (
        "py:.*",
        r"(numpy|np|scipy|open3d|trimesh|click|dask|torch|pathlib|os|typing|collections)\..*",
    ),
    ("py:class", r"(optional|callable|array_like|array|file-like|path-like|sequence|mapping)"),
    ("py:class", r"(int|float|str|bool|dict|list|tuple|bytes|None|Any|Path|ndarray)"),
]


def _generated_pages(app) -> None:
    write_pages(os.path.join(app.srcdir, "stages"))
    write_reference(os.path.join(app.srcdir, "cli"))
    with open(os.path.join(ROOT, "bench", "results.md"), encoding="utf-8") as f:
        summary = bench_summary(f.read())
    os.makedirs(os.path.join(app.srcdir, "_generated"), exist_ok=True)
    write_changed(os.path.join(app.srcdir, "_generated"), "bench-summary.md", summary)


def setup(app):
    """Write the stage pages and the command-line reference before Sphinx reads the sources."""
    app.connect("builder-inited", _generated_pages)
