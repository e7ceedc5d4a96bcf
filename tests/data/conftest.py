"""Fixtures of the dataset tests: small datasets written to a temporary folder (``helpers`` is in tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture
def episodes(helpers: ModuleType) -> list[dict[str, Any]]:
    """Seven episodes of mixed lengths (two shorter than a 10-step window), alternately terminated."""
    return helpers.make_episodes([14, 3, 25, 8, 30, 5, 17])


@pytest.fixture
def dataset_path(tmp_path: Path, episodes: list[dict[str, Any]], helpers: ModuleType) -> Path:
    """A complete dataset holding :func:`episodes`."""
    return helpers.write_dataset(tmp_path / "data.h5", episodes)
