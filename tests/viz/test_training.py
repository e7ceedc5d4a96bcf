"""The open-loop strip every evaluation writes to TensorBoard: the hook alone, then inside real training runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import IMAGES, EventAccumulator

from coworld.training.logger import Logger, read_metrics
from coworld.training.openloop import LENGTH, SEQUENCES, log_open_loop, world_models_of
from coworld.viz.runs import rollout_episodes

from .conftest import SOURCE, TARGET, tiny_agent


def image_tags(logdir) -> dict[str, list]:
    events = EventAccumulator(str(logdir / "tb"), size_guidance={IMAGES: 0})
    events.Reload()
    return {tag: events.Images(tag) for tag in events.Tags()["images"]}


class RecordingLogger:
    def __init__(self) -> None:
        self.images: list[tuple[str, np.ndarray, int]] = []
        self.scalars: list[tuple[dict, int]] = []

    def log_image(self, tag, image, step):
        self.images.append((tag, image, step))

    def log(self, metrics, step, unit="step"):
        self.scalars.append((dict(metrics), step))


@pytest.fixture(scope="module")
def episodes():
    return rollout_episodes(None, TARGET, 5, seed=0, mode="random")


def test_world_models_of_each_kind_of_agent():
    from coworld.agents.coworld import CoWorld
    from coworld.config import make_config

    dreamer = tiny_agent()
    assert world_models_of(dreamer) == {"model": dreamer.world_model}
    coworld = CoWorld(config=make_config("tiny"), action_size=2, device="cpu")
    assert world_models_of(coworld) == {"target": coworld.target.world_model, "source": coworld.source.world_model}
    assert world_models_of(object()) == {}


def test_agents_without_a_world_model_log_nothing_and_read_no_data():
    def sampler(seed):
        raise AssertionError("the data must not be read for an agent without a world model")

    logger = RecordingLogger()
    assert log_open_loop(logger, object(), sampler, 3, tag="openl/x") == {}
    assert logger.images == [] and logger.scalars == []


def test_strip_from_replay_episodes_leaves_the_random_state_alone(episodes):
    logger, agent = RecordingLogger(), tiny_agent()
    torch_state, numpy_state = torch.get_rng_state(), np.random.get_state()[1].copy()
    metrics = log_open_loop(logger, agent, episodes, 40, tag="openl/task")
    assert torch.equal(torch_state, torch.get_rng_state()) and (np.random.get_state()[1] == numpy_state).all()
    assert list(metrics) == ["openl/task/mse"] and 0.0 < metrics["openl/task/mse"] < 1.0
    [(tag, image, step)] = logger.images
    assert (tag, step) == ("openl/task", 40) and logger.scalars == [(metrics, 40)]
    assert image.shape[0] > SEQUENCES * 3 * 64 and image.shape[1] > LENGTH * 64  # 4 x (truth, model, error) x 20
    assert image.std() > 10


def test_strip_from_a_sampler_factory_uses_its_first_batch(episodes):
    from coworld.data.windows import episode_windows

    seeds = []

    def make_sampler(seed):
        seeds.append(seed)
        while True:
            yield episode_windows(episodes * 2, 30)  # 10 windows of 30 steps: cut to 4 of 20

    logger = RecordingLogger()
    agent = tiny_agent()
    log_open_loop(logger, agent, make_sampler, 1, tag="a")
    first = [{key: value[:LENGTH] for key, value in ep.items()} for ep in episodes[:SEQUENCES]]
    log_open_loop(logger, agent, first, 1, tag="b")
    assert seeds == [0]
    np.testing.assert_array_equal(logger.images[0][1][40:], logger.images[1][1][40:])  # same strip below the title


def test_too_short_episodes_give_no_strip(episodes):
    short = [{key: value[:5] for key, value in ep.items()} for ep in episodes]  # only the 5 context steps
    logger = RecordingLogger()
    assert log_open_loop(logger, tiny_agent(), short, 1, tag="x") == {} and logger.images == []


def test_offline_dreamerv2_and_coworld_runs_write_strips(tmp_path, target_dataset):
    from coworld.training.train import check_job, run_job

    fast = [
        "train.eval_episodes=1",
        "train.prefill=50",
        "train.eval_every=100",
        "coworld.pretrain_steps=100",
        "coworld.iterations=1",
        "coworld.target_updates=2",
        "coworld.source_updates=2",
        "offline.updates=2",
        "offline.eval_episodes=1",
        "train.batch_size=4",
    ]
    for algo in ("dreamerv2", "coworld"):
        job = check_job(
            algo=algo,
            source=SOURCE,
            target=TARGET,
            dataset=target_dataset,
            preset="tiny",
            logdir=tmp_path / algo,
            seed=0,
            device="cpu",
            overrides=fast,
        )
        run_job(job, progress=False)
    keys = set().union(*(record.keys() for record in read_metrics(tmp_path / "dreamerv2")))
    assert f"openl/{TARGET}/mse" in keys
    assert list(image_tags(tmp_path / "dreamerv2")) == [f"openl/{TARGET}"]
    keys = set().union(*(record.keys() for record in read_metrics(tmp_path / "coworld")))
    assert {f"openl/{TARGET}/mse_target", f"openl/{TARGET}/mse_source", f"source/openl/{SOURCE}/mse"} <= keys
    tags = image_tags(tmp_path / "coworld")
    assert set(tags) == {f"openl/{TARGET}", f"source/openl/{SOURCE}"}  # the target evaluation, the source one online
    assert [event.step for event in tags[f"openl/{TARGET}"]] == [2]  # after K1 = 2 target updates
    assert tags[f"openl/{TARGET}"][0].height > 2 * tags[f"source/openl/{SOURCE}"][0].height  # two models' rows vs one


def test_logger_outputs_round_trip(tmp_path, episodes):
    with Logger(tmp_path, outputs=("tensorboard", "jsonl")) as logger:
        log_open_loop(logger, tiny_agent(), episodes, 5, tag="openl/t")
    assert [e.step for e in image_tags(tmp_path)["openl/t"]] == [5]
    assert read_metrics(tmp_path)[0]["step"] == 5 and "openl/t/mse" in read_metrics(tmp_path)[0]
