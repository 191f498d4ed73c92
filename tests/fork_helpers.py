"""Waiting for a forked test child that may hang (the bugs the fork tests guard against)."""

from __future__ import annotations

import os
import signal
import time


def exit_code_or_hang(pid: int, timeout: float = 60.0) -> int | None:
    """The exit code of the forked child ``pid``, or None when it has not ended within
    ``timeout`` seconds (it is then killed and reaped, so no test leaves it behind)."""
    deadline = time.monotonic() + timeout
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return None
        time.sleep(0.01)
    return os.waitstatus_to_exitcode(done[1])
