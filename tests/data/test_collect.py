"""collect_random / `coworld collect`: exact budgets, row alignment, infos, resume, CLI behaviour, a real task."""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import ModuleType

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import collect_random, open_dataset
from coworld.errors import ConfigError, DatasetError


@pytest.fixture
def fake_task(helpers: ModuleType, monkeypatch: pytest.MonkeyPatch) -> str:
    helpers.patch_envs(monkeypatch.setattr)
    return helpers.FAKE_TASK


def _check_rows(path: Path) -> None:
    """Every episode is aligned: frame j shows step j, reward_j = action_j[0], success_j = (j + 1 >= 3)."""
    with open_dataset(path) as data:
        for i in range(data.num_episodes):
            ep = data.episode(i)
            t = len(ep["reward"]) - 1
            np.testing.assert_array_equal(ep["image"][:, 0, 0, 0], np.arange(t + 1))
            np.testing.assert_allclose(ep["reward"][1:], ep["action"][1:, 0])
            np.testing.assert_array_equal(ep["success"][1:], np.arange(1, t + 1) >= 3)
            np.testing.assert_allclose(ep["behavior_log_prob"][1:], -2 * np.log(2.0), rtol=1e-6)
            assert np.abs(ep["action"]).max() <= 1.0
            assert ep["is_terminal"][-1] or t == 12 or i == data.num_episodes - 1  # time limit 12 steps


@pytest.mark.parametrize("same_step", [False, True], ids=["next-step", "same-step"])
def test_collect_writes_exactly_the_requested_episodes(
    tmp_path: Path, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch, same_step: bool
) -> None:
    helpers.patch_envs(monkeypatch.setattr, same_step=same_step)
    summary = collect_random(helpers.FAKE_TASK, tmp_path / "e.h5", episodes=9, workers=3, seed=1, progress=False)
    assert summary.episodes == 9
    _check_rows(tmp_path / "e.h5")
    with open_dataset(tmp_path / "e.h5") as data:
        assert data.complete and data.quality == "random" and data.num_episodes == 9
        assert data.terminated.any() and not data.terminated.all()  # both endings occurred and were kept apart
        assert data.metadata["collector"]["steps"] >= data.num_steps
        assert data.metadata["env_config"]["action_repeat"] == 1 and data.metadata["env_config"]["image_size"] == 64
        assert data.reference == {"random_return": 0.0, "reference_return": 10.0}


def test_collect_max_steps_is_exact_and_cuts_the_last_episode(tmp_path: Path, fake_task: str) -> None:
    summary = collect_random(fake_task, tmp_path / "s.h5", max_steps=50, workers=2, progress=False)
    assert summary.steps == 50
    _check_rows(tmp_path / "s.h5")
    with open_dataset(tmp_path / "s.h5") as data:
        assert data.num_steps == 50 and data.complete


def test_collect_resume_continues_and_refuses_a_finished_dataset(tmp_path: Path, fake_task: str) -> None:
    path = tmp_path / "r.h5"
    collect_random(fake_task, path, episodes=3, progress=False)
    with open_dataset(path) as data:
        first = [data.episode(i)["image"] for i in range(3)]
    with pytest.raises(DatasetError, match="already complete with 3 episodes .* meets 3 episodes; ask for more"):
        collect_random(fake_task, path, episodes=3, resume=True, progress=False)
    collect_random(fake_task, path, episodes=6, resume=True, progress=False)
    with open_dataset(path) as data:
        assert data.num_episodes == 6 and data.complete
        for i, image in enumerate(first):
            np.testing.assert_array_equal(data.episode(i)["image"], image)
        # a resumed run is seeded afresh: its actions are not a replay of the first episodes
        assert not np.array_equal(data.episode(3)["action"][1:4], data.episode(0)["action"][1:4])
    _check_rows(path)


def test_collect_needs_exactly_one_budget(tmp_path: Path, fake_task: str) -> None:
    with pytest.raises(ConfigError, match="exactly one of --episodes and --max-steps"):
        collect_random(fake_task, tmp_path / "x.h5", episodes=2, max_steps=10, progress=False)
    with pytest.raises(ConfigError, match="exactly one"):
        collect_random(fake_task, tmp_path / "x.h5", progress=False)
    assert not (tmp_path / "x.h5").exists()


def test_cli_collect_default_path_progress_and_refusals(
    tmp_path: Path, fake_task: str, monkeypatch: pytest.MonkeyPatch, helpers: ModuleType
) -> None:
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    result = runner.invoke(
        main, ["collect", "--policy", "random", "--task", fake_task, "--episodes", "4", "--seed", "3"]
    )
    assert result.exit_code == 0, result.output
    path = tmp_path / "datasets" / f"{fake_task}-random.h5"
    assert f"wrote {Path('datasets') / f'{fake_task}-random.h5'}: 4 episodes" in result.stdout
    assert "env steps/s" in result.stderr and "episodes=4" in result.stderr  # the tqdm bar: rate, episodes, mean return
    assert "mean_return=" in result.stderr
    before = helpers.file_state(path)
    result = runner.invoke(main, ["collect", "--policy", "random", "--task", fake_task, "--episodes", "4"])
    assert result.exit_code == 2 and result.stderr.strip().startswith("error: ")
    assert "already exists; pass --resume to continue it or --force to overwrite it" in result.stderr
    assert helpers.file_state(path) == before
    result = runner.invoke(
        main, ["collect", "--policy", "random", "--task", fake_task, "--episodes", "2", "--force", "--quiet"]
    )
    assert result.exit_code == 0 and result.stderr == ""
    with open_dataset(path) as data:
        assert data.num_episodes == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--task", "fake_task", "--quality", "medium", "--episodes", "1"], "--quality is for --policy dreamerv2"),
        (["--task", "walker_fly", "--episodes", "1"], "walker_fly"),
        (["--task", "fake_task", "--episodes", "1", "--max-steps", "5"], "exactly one of --episodes and --max-steps"),
    ],
)
def test_cli_collect_bad_input_is_one_line_and_exit_2(
    tmp_path: Path, fake_task: str, args: list[str], message: str
) -> None:
    result = CliRunner().invoke(main, ["collect", "--policy", "random", *args, "--out", str(tmp_path / "x.h5")])
    assert result.exit_code == 2
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


def test_collect_a_real_task(tmp_path: Path) -> None:
    summary = collect_random("toy_reach", tmp_path / "toy.h5", episodes=3, workers=1, seed=0, progress=False)
    with open_dataset(summary.path) as data:
        assert data.num_episodes == 3 and data.task == "toy_reach" and data.action_size == 2
        assert data.lengths.tolist() == [50, 50, 50] and not data.terminated.any()
        episode = data.episode(0)
        assert episode["image"].shape == (51, 64, 64, 3) and episode["image"].std() > 0
        assert data.metadata["env_config"]["name"] == "toy_reach"
    assert os.path.getsize(summary.path) > 0


def test_a_collection_that_stores_nothing_leaves_no_file(
    tmp_path: Path, fake_task: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import coworld.envs as envs

    def broken(name: str, num_envs: int, seed: int = 0) -> None:
        raise ConfigError("no renderer")

    monkeypatch.setattr(envs, "make_vector", broken)
    with pytest.raises(ConfigError, match="no renderer"):
        collect_random(fake_task, tmp_path / "n.h5", episodes=2, progress=False)
    assert list(tmp_path.iterdir()) == []  # no dataset, no lock, no temporary file


@pytest.mark.parametrize("workers", [1, 3])
def test_a_resumed_collection_is_the_uninterrupted_one_and_its_record_counts_its_rows(
    tmp_path: Path, fake_task: str, helpers: ModuleType, workers: int
) -> None:
    whole = collect_random(fake_task, tmp_path / "whole.h5", episodes=9, seed=4, workers=workers, progress=False)
    part = tmp_path / "part.h5"
    collect_random(fake_task, part, episodes=4, seed=4, workers=workers, progress=False)
    collect_random(fake_task, part, episodes=9, seed=4, workers=workers, resume=True, progress=False)
    assert helpers.episode_digests(part) == helpers.episode_digests(whole.path)  # frames, actions, rewards, ends
    for path in (whole.path, part):
        with open_dataset(path) as data:
            assert data.metadata["collector"]["steps"] == data.num_steps


def test_a_collection_is_the_same_whatever_its_workers(tmp_path: Path, fake_task: str, helpers: ModuleType) -> None:
    one = collect_random(fake_task, tmp_path / "one.h5", max_steps=70, seed=2, workers=1, progress=False)
    three = collect_random(fake_task, tmp_path / "three.h5", max_steps=70, seed=2, workers=3, progress=False)
    assert helpers.episode_digests(one.path) == helpers.episode_digests(three.path)
    part = tmp_path / "part.h5"  # its first episodes with one worker, the rest with three
    collect_random(fake_task, part, episodes=3, seed=2, workers=1, progress=False)
    collect_random(fake_task, part, max_steps=70, seed=2, workers=3, resume=True, progress=False)
    assert helpers.episode_digests(part) == helpers.episode_digests(one.path)


def test_a_resume_that_would_make_other_episodes_is_refused(
    tmp_path: Path, fake_task: str, helpers: ModuleType
) -> None:
    path = tmp_path / "r.h5"
    collect_random(fake_task, path, episodes=2, seed=1, progress=False)
    before = helpers.file_state(path)
    with pytest.raises(DatasetError, match="made with --seed 1, not 2; resume it with --seed 1"):
        collect_random(fake_task, path, episodes=4, seed=2, resume=True, progress=False)
    assert helpers.file_state(path) == before
    with h5py.File(path, "r+") as f:  # the same shapes, made by another collector
        f.attrs["collector"] = json.dumps({"algorithm": "dreamerv2", "seed": 1})
    before = helpers.file_state(path)
    with pytest.raises(DatasetError, match="made by dreamerv2, not by random actions; choose another --out"):
        collect_random(fake_task, path, episodes=4, seed=1, resume=True, progress=False)
    assert helpers.file_state(path) == before


def test_a_resume_corrects_the_step_count_an_older_collector_left(
    tmp_path: Path, fake_task: str, helpers: ModuleType
) -> None:
    path = tmp_path / "old.h5"
    collect_random(fake_task, path, episodes=3, seed=1, progress=False)
    with h5py.File(path, "r+") as f:  # what a collection stopped by a full disk used to leave
        f.attrs["collector"] = json.dumps({**json.loads(f.attrs["collector"]), "steps": 0})
        f.attrs["complete"] = False
    collect_random(fake_task, path, episodes=3, seed=1, resume=True, progress=False)
    with open_dataset(path) as data:
        assert data.complete and data.metadata["collector"]["steps"] == data.num_steps > 0
