"""The D4RL-style API: coworld.data.load and coworld.data.episodes, names and paths, and the README's example."""

from __future__ import annotations

import re
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

import coworld.data
from coworld.errors import DatasetError

README = Path(__file__).parents[2] / "datasets" / "README.md"


@pytest.fixture
def in_project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A current folder with a datasets/ folder, as `coworld collect` leaves it."""
    (tmp_path / "datasets").mkdir()
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_load_gives_the_d4rl_dict(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    data = coworld.data.load(dataset_path)
    assert sorted(data) == [
        "actions",
        "infos/behavior_log_prob",
        "infos/success",
        "observations",
        "rewards",
        "terminals",
        "timeouts",
    ]
    np.testing.assert_array_equal(data["observations"], np.concatenate([ep["observations"][:-1] for ep in episodes]))
    np.testing.assert_array_equal(data["actions"], np.concatenate([ep["actions"] for ep in episodes]))
    np.testing.assert_array_equal(data["rewards"], np.concatenate([ep["rewards"] for ep in episodes]))
    ends = np.cumsum([len(ep["rewards"]) for ep in episodes]) - 1
    terminated = np.array([ep["terminated"] for ep in episodes])
    np.testing.assert_array_equal(np.flatnonzero(data["terminals"]), ends[terminated])
    np.testing.assert_array_equal(np.flatnonzero(data["timeouts"]), ends[~terminated])
    np.testing.assert_array_equal(data["infos/success"], np.concatenate([ep["infos"]["success"] for ep in episodes]))


def test_qlearning_dataset_adds_each_rows_next_observation(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    """D4RL's ``qlearning_dataset`` view: row i's next observation is o_{t+1} of its own episode, the final frame at
    its last row; every other key is :func:`coworld.data.load`'s."""
    data = coworld.data.qlearning_dataset(dataset_path)
    plain = coworld.data.load(dataset_path)
    assert sorted(data) == sorted([*plain, "next_observations"])
    for key, value in plain.items():
        np.testing.assert_array_equal(data[key], value)
    np.testing.assert_array_equal(
        data["next_observations"], np.concatenate([ep["observations"][1:] for ep in episodes])
    )
    assert (
        data["next_observations"].dtype == np.uint8 and data["next_observations"].shape == plain["observations"].shape
    )


def test_episodes_have_minaris_shapes(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    got = list(coworld.data.episodes(dataset_path))
    assert [ep.index for ep in got] == list(range(len(episodes)))
    for ep, want in zip(got, episodes, strict=True):
        t = len(want["rewards"])
        assert ep.length == t and ep.terminated == want["terminated"]
        np.testing.assert_array_equal(ep.observations, want["observations"])  # T + 1 frames
        np.testing.assert_array_equal(ep.actions, want["actions"])
        np.testing.assert_array_equal(ep.rewards, want["rewards"])
        np.testing.assert_array_equal(ep.terminations, (np.arange(t) == t - 1) & want["terminated"])
        np.testing.assert_array_equal(ep.truncations, (np.arange(t) == t - 1) & (not want["terminated"]))
        np.testing.assert_array_equal(ep.infos["behavior_log_prob"], want["infos"]["behavior_log_prob"])


@pytest.mark.parametrize("name", ["fake_task-medium-replay", "fake_task-medium_replay"])
def test_a_name_stands_for_datasets_task_quality(
    in_project: Path, helpers: ModuleType, episodes: list[dict[str, Any]], name: str
) -> None:
    helpers.write_dataset(in_project / "datasets" / "fake_task-medium_replay.h5", episodes, quality="medium-replay")
    assert coworld.data.resolve_dataset(name) == Path("datasets/fake_task-medium_replay.h5")
    assert len(coworld.data.load(name)["rewards"]) == sum(len(ep["rewards"]) for ep in episodes)
    assert sum(1 for _ in coworld.data.episodes(name)) == len(episodes)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("fake_task-expert", "no dataset named 'fake_task-expert': datasets/fake_task-expert.h5 does not exist"),
        ("fake_task-excellent", "is neither a file nor a dataset name; a name is <task>-<quality>"),
        ("nonsense", "is neither a file nor a dataset name"),
        ("missing.h5", "missing.h5: no such file"),
    ],
)
def test_bad_names_are_one_line(in_project: Path, name: str, message: str) -> None:
    with pytest.raises(DatasetError) as err:
        coworld.data.load(name)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_readme_example_runs(
    in_project: Path, helpers: ModuleType, episodes: list[dict[str, Any]], capsys: pytest.CaptureFixture[str]
) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    [snippet] = [block for block in blocks if "coworld.data.load(" in block]
    frames = [ep["observations"] for ep in episodes]
    helpers.write_dataset(in_project / "datasets" / "walker_walk-random.h5", episodes, task="walker_walk")
    exec(snippet, {})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == str(sorted(coworld.data.load("walker_walk-random")))
    rows = sum(len(f) - 1 for f in frames)
    assert lines[1] == f"({rows}, 64, 64, 3) ({rows}, {helpers.ACTION_SIZE})"
    for i, (line, ep) in enumerate(zip(lines[2:], episodes, strict=True)):
        end = "terminated" if ep["terminated"] else "time limit"
        ret = ep["rewards"].sum()
        assert line == f"episode {i}: {len(ep['rewards'])} steps, return {ret:.1f}, {end}"
