"""Signals of ``recon``: SIGINT and SIGTERM end it with 130 / 143, one line, no traceback.

Two layers:

* :func:`handlers` (the whole command): Python handlers that raise :class:`Interrupted`
  (a :class:`KeyboardInterrupt`, so ``finally`` blocks and the atomic writer's clean-up
  run); :mod:`recon_cli.cli.main` turns it into the exit code and the one line.
* :func:`immediate` (around a stage's computation): a handler in machine code that exits
  at once, even inside a numba kernel that holds the interpreter for minutes. Only used
  while nothing needs cleaning up. The handler is :data:`HANDLER_C`, compiled by ``recon
  warmup`` with the ahead-of-time kernels (:mod:`recon_cli.aot`), so a process that
  runs those never loads numba; without a C compiler, the same handler as a numba ``cfunc``
  (:mod:`recon_cli.cli._signal_kernel`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)

# the handler of immediate(), as recon_cli.cli._signal_kernel.handler: async-signal-safe write and
# _exit
HANDLER_C = r"""
#include <signal.h>
#include <unistd.h>

void recon_exit_at_once(int signum)
{
    static const char interrupted[] = "recon: interrupted\n";
    static const char terminated[] = "recon: terminated\n";
    if (signum == SIGINT)
        (void)!write(2, interrupted, sizeof interrupted - 1);
    else
        (void)!write(2, terminated, sizeof terminated - 1);
    _exit(128 + signum);
}
"""


class Interrupted(KeyboardInterrupt):
    """The process got ``signum`` (SIGINT: Ctrl-C, SIGTERM: kill)."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


# A raised Interrupted can be lost: inside a ctypes callback (numba compiling) or a __del__,
# Python reports it to sys.unraisablehook and drops it, and the command would go on as if
# nothing happened. The hook below ends the process at once in that case; as a last resort
# (code that catches and ignores KeyboardInterrupt) the process ends itself DEADLINE seconds
# after the signal if the command has not ended by then (time for finally blocks, e.g. a
# Dask cluster closing).
DEADLINE = 5.0

_state: dict = {"signum": None, "done": None, "native": None}


def _raise(signum, frame) -> None:
    if _state["signum"] is not None:  # a second signal: no more waiting
        _exit_now(signum)
    _state["signum"] = signum
    done = _state["done"]
    if done is not None:
        threading.Thread(target=_deadline, args=(signum, done), daemon=True).start()
    raise Interrupted(signum)


def _deadline(signum: int, done: threading.Event) -> None:
    if not done.wait(DEADLINE):
        _exit_now(signum)


def _exit_now(signum: int) -> None:
    """Remove the output's temporary file, say why, and end the process with 128 + signum."""
    # no import here: the signal may have come in the middle of one (a partly initialized module);
    # if the atomic writer was never imported, there is no temporary file to remove
    atomic = sys.modules.get("recon_cli.io.atomic")
    if atomic is not None:
        atomic.remove_temporaries()
    msg = b"recon: interrupted\n" if signum == signal.SIGINT else b"recon: terminated\n"
    with contextlib.suppress(OSError):
        os.write(2, msg)
    os._exit(128 + signum)


def _ours() -> list[int]:
    """The signals this process may take over.

    Main thread only, and not those ignored (a background job of a non-interactive shell ignores
    SIGINT, and must keep doing so).
    """
    if threading.current_thread() is not threading.main_thread():
        return []
    return [s for s in SIGNALS if signal.getsignal(s) is not signal.SIG_IGN]


@contextlib.contextmanager
def handlers() -> Iterator[None]:
    """Raise :class:`Interrupted` on SIGINT and SIGTERM while inside.

    Restore the previous handlers after.
    """
    _state.update(signum=None, done=threading.Event())
    old = {s: signal.signal(s, _raise) for s in _ours()}
    old_hook = sys.unraisablehook

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, Interrupted):
            _exit_now(unraisable.exc_value.signum)
        old_hook(unraisable)

    if old:
        sys.unraisablehook = hook
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if old:
            sys.unraisablehook = old_hook
        _state["done"].set()
        _state.update(signum=None, done=None)


@contextlib.contextmanager
def immediate() -> Iterator[None]:
    """Exit at once (128 + signal number, one line on stderr) on SIGINT/SIGTERM while inside.

    For computations that leave nothing to clean up. Outside :func:`handlers` (a library
    caller, a test calling a command in-process) this does nothing.
    """
    ours = [s for s in _ours() if signal.getsignal(s) is _raise]
    if not ours:
        yield
        return
    import ctypes

    address = _handler_address()
    libc = ctypes.CDLL(None, use_errno=True)
    install = libc.signal
    install.restype = ctypes.c_void_p
    install.argtypes = [ctypes.c_int, ctypes.c_void_p]
    for s in ours:
        install(s, address)
    try:
        yield
    finally:
        for s in ours:
            signal.signal(
                s, _raise
            )  # Python's own handler again (a signal that came meanwhile has exited)


def _handler_address() -> int:
    """The machine-code handler: :data:`HANDLER_C` built by ``recon warmup``, else numba's cfunc."""
    import ctypes

    from recon_cli import aot

    if _state["native"] is None:
        lib = aot.native_library("signal_handler")
        _state["native"] = lib if lib is not None and hasattr(lib, "recon_exit_at_once") else False
    if _state["native"]:
        address = ctypes.cast(_state["native"].recon_exit_at_once, ctypes.c_void_p).value
        assert address is not None  # a loaded symbol
        return int(address)
    from recon_cli.cli._signal_kernel import handler

    return int(handler.address)
