"""A signal handler in machine code: leave at once with 128 + the signal number.

Python runs its own signal handlers between bytecodes only, so Ctrl-C during a numba kernel
that computes for a minute would wait that minute (and then surface inside numba's return
path as a ``SystemError``). While a stage computes, the CLI installs :data:`handler`
instead: it writes ``recon: interrupted`` (SIGINT) or ``recon: terminated`` (other
signals) to stderr and calls ``_exit(128 + signum)``, both async-signal-safe. Nothing is
left to clean up at that point: outputs are written after the computation, through
anonymous temporary files (see :mod:`recon_cli.io.atomic`).
"""

from __future__ import annotations

import numpy as np
from numba import cfunc, types  # noqa: E402

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, lean cache loads)

_write = types.ExternalFunction("write", types.intp(types.intc, types.intp, types.uintp))
_exit = types.ExternalFunction("_exit", types.void(types.intc))

_INTERRUPTED = np.frombuffer(b"recon: interrupted\n", dtype=np.uint8)
_TERMINATED = np.frombuffer(b"recon: terminated\n", dtype=np.uint8)
SIGINT = 2


@cfunc(types.void(types.intc), cache=True)
def handler(signum):
    msg = _INTERRUPTED if signum == SIGINT else _TERMINATED
    _write(2, msg.ctypes.data, msg.size)
    _exit(128 + signum)
