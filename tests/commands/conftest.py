"""A small random toy_reach_shifted dataset for the train / eval command tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def toy_dataset(tmp_path_factory, toy_dataset_writer) -> Path:
    path = tmp_path_factory.mktemp("data") / "toy_reach_shifted-medium_replay.h5"
    return toy_dataset_writer(path, "toy_reach_shifted")
