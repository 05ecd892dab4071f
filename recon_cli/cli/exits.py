"""The exit codes that are not an error's own (``ReconError.exit_code``).

For the commands and ``recon_cli.cli.main``.
"""

from __future__ import annotations

EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141
# ``recon batch``: the batch ran to the end but some inputs failed (see DIR/batch.json)
EXIT_BATCH_SOME_FAILED = 4
