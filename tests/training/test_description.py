"""A run's description: read as written; a collector's from before this release refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from coworld.config import make_config, to_dict
from coworld.errors import CoworldError
from coworld.training.description import collector_run_info, run_description
from coworld.training.run import load_run

EARLIER_COLLECTOR = {"task": "toy_reach", "quality": "medium-replay"}
"""What a collector's ``run.json`` held before it described its agent as a dreamerv2 run."""


def test_a_run_description_is_read_as_it_was_written(tmp_path: Path) -> None:
    info = {**collector_run_info("toy_reach", "tiny"), "quality": "medium-replay"}
    assert run_description(info, tmp_path / "run.json") == info
    assert run_description({"something": "else"}, tmp_path / "run.json") == {"something": "else"}


def test_a_collectors_description_from_before_this_release_is_refused_in_one_line(tmp_path: Path) -> None:
    run = tmp_path / "toy_reach-medium_replay.run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(to_dict(make_config("tiny"))))
    (run / "run.json").write_text(json.dumps(EARLIER_COLLECTOR))
    with pytest.raises(CoworldError) as refused:
        load_run(run)
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith(f"{run / 'run.json'} was written by an earlier coworld's collector (no 'algo' entry)")
    assert message.endswith("collect the dataset again, or read the folder with coworld 0.1.0 at commit 81d62fb")
