"""``coworld collect --policy dreamerv2``: trained-policy qualities, stop rules, and reruns of finished jobs."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from coworld import envs
from coworld.data import open_dataset
from coworld.training.collect import collect_dreamerv2, default_stop_return

FAST = ("train.prefill=100", "train.eval_episodes=1", "train.checkpoint_every=100")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def collect(out: Path, **kwargs):
    options = {"preset": "tiny", "device": "cpu", "progress": False, "overrides": FAST, **kwargs}
    return collect_dreamerv2("toy_reach", out, **options)


def test_default_stop_return_is_the_medium_level_except_for_expert_data() -> None:
    reference = envs.task_spec("toy_reach").reference_return
    assert default_stop_return("toy_reach") == pytest.approx(reference / 3)
    assert default_stop_return("toy_reach", "medium") == pytest.approx(reference / 3)
    assert default_stop_return("toy_reach", "expert") is None


def test_medium_quality_records_episodes_of_the_trained_policy(tmp_path: Path) -> None:
    out = tmp_path / "toy_reach-medium.h5"
    summary = collect(out, quality="medium", max_steps=300, episodes=3)
    assert (summary.episodes, summary.steps) == (3, 150)  # toy_reach episodes are 50 steps
    with open_dataset(out) as data:
        assert data.complete and data.quality == "medium" and data.num_episodes == 3
        collector = data.metadata["collector"]
        assert collector["algorithm"] == "dreamerv2" and collector["training_steps"] == 300
    # What the agent experienced while it learned is kept beside the dataset, not mixed into it.
    with open_dataset(tmp_path / "toy_reach-medium.run" / "replay.h5") as replay:
        assert replay.quality == "medium-replay" and replay.num_steps == 300 and replay.complete
    # A rerun of the finished job with --resume changes nothing.
    again = collect(out, quality="medium", max_steps=300, episodes=3, resume=True)
    assert (again.episodes, again.steps) == (3, 150)
    with open_dataset(out) as data:
        assert data.num_episodes == 3


def test_a_run_stopped_by_its_return_goal_is_not_extended_on_resume(tmp_path: Path) -> None:
    out = tmp_path / "toy_reach-medium_replay.h5"
    overrides = (*FAST, "train.eval_every=100")
    # Any evaluation reaches a goal this low, so training stops at its first evaluation.
    first = collect(out, max_steps=2000, stop_return=-1e9, overrides=overrides)
    assert first.stop_reason.startswith("evaluation return") and first.steps < 2000
    checkpoint = out.with_name("toy_reach-medium_replay.run") / "checkpoint.pt"
    updates = torch.load(checkpoint, weights_only=True)["updates"]
    again = collect(out, max_steps=2000, stop_return=-1e9, overrides=overrides, resume=True)
    assert again.steps == first.steps and again.stop_reason == first.stop_reason
    assert torch.load(checkpoint, weights_only=True)["updates"] == updates
    with open_dataset(out) as data:
        assert data.complete and data.num_steps == first.steps


def test_medium_expert_is_the_learning_stream_on_to_the_expert_level() -> None:
    spec = envs.task_spec("toy_reach")
    assert default_stop_return("toy_reach", "medium-expert") == spec.reference_return


def test_medium_expert_marks_where_its_medium_replay_part_ends_and_resumes_past_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from coworld.data import verify_dataset
    from coworld.training.online import OnlineTrainer

    out = tmp_path / "toy_reach-medium_expert.h5"
    # every evaluation reaches the medium level, none the expert level: the mark is the first evaluation, at the
    # first episode end after the 100-step prefill (toy_reach episodes are 50 steps), and training runs to the end
    options = {
        "quality": "medium-expert",
        "max_steps": 400,
        "medium_return": -1e9,
        "stop_return": 1e9,
        "overrides": (*FAST, "train.eval_every=100"),
    }
    real_run, calls = OnlineTrainer.run, []

    def stopped_in_the_second_part(trainer: OnlineTrainer, **kwargs):
        calls.append(kwargs["stop_return"])
        if len(calls) == 2:  # the expert part: a stop at step 300, as a Ctrl-C there leaves it
            real_run(trainer, **{**kwargs, "max_steps": 300})
            raise KeyboardInterrupt
        return real_run(trainer, **kwargs)

    monkeypatch.setattr(OnlineTrainer, "run", stopped_in_the_second_part)
    with pytest.raises(KeyboardInterrupt):
        collect(out, **options)
    assert calls == [-1e9, 1e9]
    with open_dataset(out) as data:
        assert data.quality == "medium-expert" and not data.complete and data.num_steps == 300
        mark = {key: value for key, value in data.metadata["collector"].items() if key.startswith("medium_level")}
    assert mark["medium_level_step"] == 100 and mark["medium_level_episodes"] == 2

    calls.clear()
    summary = collect(out, resume=True, **options)
    assert calls == [1e9]  # the mark was made: the resumed collection goes straight on to the expert level
    assert (summary.steps, summary.episodes, summary.stop_reason) == (400, 8, "max steps")
    with open_dataset(out) as data:
        assert data.quality == "medium-expert" and data.complete and data.num_steps == 400
        collector = data.metadata["collector"]
    assert {key: collector[key] for key in mark} == mark  # kept as the first run made it
    assert collector["medium_return"] == -1e9 and collector["stop_return"] == 1e9
    assert not (tmp_path / "toy_reach-medium_expert.run" / "replay.h5").exists()  # the dataset is the stream itself
    assert verify_dataset(out) == []


def test_a_dataset_whose_agent_is_gone_is_not_resumed(tmp_path: Path, toy_dataset_writer, helpers) -> None:
    """A resume cuts the dataset back to its agent's checkpoint; without the agent's run folder (deleted, or the
    dataset moved without it) that would be every episode, and a fresh agent would go on with other data: refused."""
    from coworld.errors import DatasetError

    out = toy_dataset_writer(tmp_path / "toy_reach-medium_replay.h5", "toy_reach", episodes=2)
    before = helpers.episode_digests(out)
    with pytest.raises(DatasetError, match=r"its 2 episodes came from an agent whose run folder .* is not there"):
        collect(out, max_steps=200, resume=True)
    assert helpers.episode_digests(out) == before and not out.with_name("toy_reach-medium_replay.run").exists()
