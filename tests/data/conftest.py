"""Fixtures of the dataset tests: the helpers module, and small datasets written to a temporary folder."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

HELPERS_PATH = Path(__file__).with_name("helpers.py")


def _load_helpers() -> ModuleType:
    spec = importlib.util.spec_from_file_location("coworld_data_test_helpers", HELPERS_PATH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_HELPERS = _load_helpers()


@pytest.fixture(scope="session")
def helpers() -> ModuleType:
    """tests/data/helpers.py: episode makers, the step-space oracle, the fake pixel task."""
    return _HELPERS


@pytest.fixture
def episodes() -> list[dict[str, Any]]:
    """Seven episodes of mixed lengths (two shorter than a 10-step window), alternately terminated."""
    return _HELPERS.make_episodes([14, 3, 25, 8, 30, 5, 17])


@pytest.fixture
def dataset_path(tmp_path: Path, episodes: list[dict[str, Any]]) -> Path:
    """A complete dataset holding :func:`episodes`."""
    return _HELPERS.write_dataset(tmp_path / "data.h5", episodes)
