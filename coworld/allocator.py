"""The memory allocator for training on a CPU: tcmalloc where it is installed, else glibc malloc tuned to keep
freed memory.

A DreamerV2 update allocates and frees the same large temporaries (images, convolution activations) every step.
With glibc's defaults, large blocks are mapped fresh and unmapped when freed and the heap top is trimmed, so each
update faults the same pages in again.

* :func:`exec_with_tcmalloc` (the ``coworld`` command's first act) runs the command again with tcmalloc preloaded,
  the allocator PyTorch's CPU performance guide recommends, when the library is installed (Debian's
  ``libtcmalloc-minimal4``, which ``scripts/install.sh`` installs). It reuses freed blocks by size class, so it is
  as fast as tuned glibc and smaller: at the authors' DMC sizes with batch 150 x 50 it peaked at 11.2 GiB against
  13.5 GiB (benchmarks/archive/speed-work-notes.md, "tcmalloc, and NM512/r2dreamer as a third peer").
  ``COWORLD_MALLOC=glibc`` turns it off.
* :func:`keep_freed_memory`, where tcmalloc is not loaded, raises glibc's mmap and trim thresholds and pads the heap
  (the settings of ``MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824
  MALLOC_TOP_PAD_=268435456``, applied at run time through ``mallopt``).

Both are called by the CLI entry and the benchmark scripts, never on import.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

__all__ = ["exec_with_tcmalloc", "keep_freed_memory", "tcmalloc_loaded", "tcmalloc_preload"]

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
_SETTINGS = ((_M_MMAP_THRESHOLD, 1 << 30), (_M_TRIM_THRESHOLD, 1 << 30), (_M_TOP_PAD, 1 << 28))

CHOICE = "COWORLD_MALLOC"
"""Environment variable: ``tcmalloc`` (the default, also when empty: use it where installed) or ``glibc``."""
_TRIED = "COWORLD_MALLOC_PRELOADED"
"""Set in the environment of the re-run, so that a library that did not load is not tried again."""


def tcmalloc_loaded() -> bool:
    """Whether this process runs with tcmalloc (one of its libraries is mapped)."""
    try:
        with open("/proc/self/maps") as f:
            return "libtcmalloc" in f.read()
    except OSError:
        return False


def tcmalloc_preload() -> dict[str, str] | None:
    """The environment variables that preload tcmalloc into a new process, or None where it is not installed,
    not on Linux, or turned off with ``COWORLD_MALLOC=glibc``."""
    choice = os.environ.get(CHOICE) or "tcmalloc"  # set but empty: the default, as for an unset variable
    if choice not in ("tcmalloc", "glibc"):
        raise ValueError(f"{CHOICE}={choice!r}: use tcmalloc or glibc")
    if choice == "glibc" or not sys.platform.startswith("linux"):
        return None
    name = ctypes.util.find_library("tcmalloc_minimal") or ctypes.util.find_library("tcmalloc")
    if name is None:
        return None
    preload = " ".join(filter(None, (name, os.environ.get("LD_PRELOAD"))))
    # tcmalloc reports every allocation over 1 GiB on stderr by default; batches at the paper's sizes make them.
    return {"LD_PRELOAD": preload, "TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD": str(1 << 40), _TRIED: "1"}


def exec_with_tcmalloc() -> None:
    """Replace this process by the same command with tcmalloc preloaded (same PID, arguments and environment
    otherwise); return without doing anything where it is loaded already, was tried already, or is not to be had.
    Call it before anything else happens: the command starts over."""
    if os.environ.get(_TRIED) or tcmalloc_loaded():
        return
    try:
        preload = tcmalloc_preload()
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if preload is None:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    # Ctrl-C or SIGTERM while the new process starts would raise KeyboardInterrupt in its imports (or end it): the
    # signals stay blocked across the exec, pending, until the command's handlers take them
    # (:func:`coworld.interrupt.release_held_signals`).
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], {**os.environ, **preload})
    except OSError:  # no exec: carry on in this process, signals as they were
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def keep_freed_memory() -> bool:
    """Apply the glibc settings above; True where all were accepted, False off glibc or with tcmalloc loaded (a
    no-op: tcmalloc keeps freed memory for reuse itself)."""
    if not sys.platform.startswith("linux") or tcmalloc_loaded():
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # no glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return all(mallopt(option, value) == 1 for option, value in _SETTINGS)
