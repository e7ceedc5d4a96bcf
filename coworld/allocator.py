"""glibc malloc settings for training on a CPU: keep freed memory for reuse instead of giving it back.

A DreamerV2 update allocates and frees the same large temporaries (images, convolution activations) every step.
With glibc's defaults, large blocks are mapped fresh and unmapped when freed and the heap top is trimmed, so each
update faults the same pages in again. :func:`keep_freed_memory` raises the mmap and trim thresholds and pads the
heap (the settings of ``MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824
MALLOC_TOP_PAD_=268435456``, applied at run time through ``mallopt``). It is called by the CLI entry and the
benchmark scripts, never on import. Measured gain: benchmarks/RESULTS.md, "Faster update".
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
_SETTINGS = ((_M_MMAP_THRESHOLD, 1 << 30), (_M_TRIM_THRESHOLD, 1 << 30), (_M_TOP_PAD, 1 << 28))


def keep_freed_memory() -> bool:
    """Apply the settings above to glibc's malloc; True where all were accepted, False off glibc (a no-op)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # no glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return all(mallopt(option, value) == 1 for option, value in _SETTINGS)
