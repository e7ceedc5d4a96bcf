"""Fixtures of the sweep tests."""

from __future__ import annotations

import time
from collections.abc import Callable

import psutil
import pytest


def _gone(pid: int, timeout: float = 10.0) -> bool:
    """Whether process ``pid`` ends (or is a zombie waiting to be reaped) within ``timeout`` seconds."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.NoSuchProcess:
            return True
        time.sleep(0.05)
    return False


@pytest.fixture
def process_gone() -> Callable[..., bool]:
    """``process_gone(pid, timeout=10.0)``: True once the process has ended."""
    return _gone
