"""Developer tools that write files from the stage declarations (run with ``python -m``).

- :mod:`recon_cli.tools.docs`: the user guide's stage pages and command-line reference;
- :mod:`recon_cli.tools.stubs`: ``recon_cli/__init__.pyi``, the typed stage functions.

The library never imports these modules.
"""
