"""Fixtures of the agent tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest


@pytest.fixture(scope="session")
def toy_expert() -> ModuleType:
    """tests/agents/toy_expert.py: scripted toy_reach datasets (``write_dataset``) and ``mean_return``."""
    spec = importlib.util.spec_from_file_location("toy_expert", Path(__file__).with_name("toy_expert.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
