"""The CLI's malloc settings: freed memory stays with the process for the next update."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import sys
from coworld import allocator
if sys.argv[1] == "tuned":
    assert allocator.keep_freed_memory()
def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096
block = bytearray(64 << 20)  # 64 MiB, touched
before = resident()
del block
print(before - resident())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc settings")
def test_keep_freed_memory_keeps_a_freed_block_resident() -> None:
    def released(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
        return int(out.stdout)

    assert released("default") > 32 << 20  # glibc unmaps a large freed block
    assert released("tuned") < 1 << 20  # with the settings it stays for reuse
