"""What a sweep's child process runs first: ask the kernel to kill it when the sweep dies.

Kept free of imports beyond the standard library's: every child command imports it before anything else. The
sweep passes its PID in :data:`PARENT_ENV`; on Linux the child sets ``PR_SET_PDEATHSIG`` to SIGKILL, then checks
that its parent is still the sweep (if the sweep died before the request, the child exits at once).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PARENT_ENV = "COWORLD_SWEEP_PARENT"
_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Be killed with the process (thread) that started this one, when it says so in ``PARENT_ENV``."""
    parent = os.environ.pop(PARENT_ENV, None)
    if parent is None or not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - no C library to call
        return
    if os.getppid() != int(parent):
        os._exit(1)  # the sweep died before the request took effect
