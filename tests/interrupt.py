"""Ctrl-C on a recon command run as its own process (the tests of interrupted runs)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# the head of a ``python -c`` runner: as from an interactive shell, since a runner started in
# the background (nohup, CI) may pass SIGINT down ignored, and then Python never turns it
# into KeyboardInterrupt
SIGINT_AS_A_TERMINAL = (
    "import signal, sys\nsignal.signal(signal.SIGINT, signal.default_int_handler)\n"
)
# its tail: recon's command line on the runner's arguments
RUN_RECON = "from recon_cli.cli.main import main\nmain(sys.argv[1:])\n"


@dataclass
class Interrupted:
    """What an interrupted run left.

    Its exit code, its stderr, the processes it had started when the signal went
    (``psutil.Process``), the seconds from the signal to its exit and its process id.
    """

    returncode: int
    err: str
    family: list[Any]
    seconds: float
    pid: int = 0


def interrupt_when(
    argv: list[str],
    ready: Callable[[], Any],
    what: str,
    group: bool = True,
    signum: int = signal.SIGINT,
) -> Interrupted:
    """Run ``argv`` in its own session, signal it once ``ready()`` holds (within 120 s).

    The signal (``signum``, SIGINT by default) goes to its process group (Ctrl-C on a
    terminal) or, ``group`` False, to the process alone. A run that does not end within 60 s
    after it is killed (the test fails). ``what`` names the awaited state in the failure message.
    """
    import psutil

    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 120
        while not ready():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"{what} after 120 s"
            time.sleep(0.02)
        family = psutil.Process(proc.pid).children(recursive=True)
        if group:
            os.killpg(proc.pid, signum)
        else:
            proc.send_signal(signum)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=60)
        seconds = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return Interrupted(proc.returncode, err.decode(), family, seconds, proc.pid)
