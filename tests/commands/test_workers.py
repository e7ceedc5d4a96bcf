"""`--workers` of collect and eval is capped at the episodes to run and the CPU cores, with a note."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from click.testing import CliRunner

import coworld.envs.vector as vector
from coworld.cli import main
from coworld.data import open_dataset


@pytest.fixture
def four_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(vector, "available_cores", lambda: 4)


def test_collect_starts_no_more_workers_than_episodes(
    four_cores: None, tmp_path: Path, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    helpers.patch_envs(monkeypatch.setattr)
    import coworld.envs as envs

    started: list[int] = []
    make = envs.make_vector
    monkeypatch.setattr(envs, "make_vector", lambda name, n, seed=0, **kw: started.append(n) or make(name, n, seed))
    out = tmp_path / "a.h5"
    args = ["collect", "--policy", "random", "--task", helpers.FAKE_TASK, "--episodes", "2", "--out", str(out)]
    result = CliRunner().invoke(main, [*args, "--workers", "1000", "--quiet"])
    assert result.exit_code == 0, result.output
    assert result.stderr == "note: --workers 1000 capped to 2: one per episode (2 episodes asked for)\n"
    assert started == [2]
    with open_dataset(out) as data:
        assert data.num_episodes == 2 and data.metadata["collector"]["workers"] == 2


def test_eval_starts_no_more_workers_than_cores(
    four_cores: None, untrained_run: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import coworld.training.evaluate as evaluate

    asked: dict[str, Any] = {}
    run_eval = evaluate.evaluate

    def spy(agent: Any, task: str, **kwargs: Any) -> Any:
        asked.update(kwargs)
        return run_eval(agent, task, **{**kwargs, "episodes": 1, "workers": 1})

    monkeypatch.setattr(evaluate, "evaluate", spy)
    args = ["eval", "--ckpt", str(untrained_run), "--episodes", "50", "--workers", "1000", "--device", "cpu"]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "eval.json")])
    assert result.exit_code == 0, result.output
    assert "note: --workers 1000 capped to 4: one per CPU core (4 cores available)" in result.stderr
    assert asked["workers"] == 4 and asked["episodes"] == 50
