"""A run stopped after a checkpoint and started again keeps each log record once (issue 81, item 4).

The rerun redoes the updates made after the checkpoint, with the same numbers; ``metrics.jsonl`` is cut back to what
it held at that checkpoint first, so the file ends as an uninterrupted run's does (apart from ``time`` and ``perf/``).
Each test stops a real tiny run with an exception raised from a chosen update (what a kill does, except that the
process lives on), runs the same command again, and compares its records with a run never stopped.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from coworld.agents.coworld import CoWorld
from coworld.agents.dreamerv2 import DreamerV2
from coworld.training.collect import collect_dreamerv2
from coworld.training.logger import Logger, read_metrics
from coworld.training.train import check_job, run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")

COLLECT = (
    "device=cpu",
    "train.prefill=100",
    "train.eval_episodes=1",
    "train.checkpoint_every=100",
    "train.log_every=10",
)
"""50-step toy_reach episodes, 10 updates at once at step 100, then one every 10 steps; a checkpoint at step 100."""
COWORLD = (
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=2",
    "train.train_every=5",
    "train.eval_episodes=1",
    "train.log_every=5",
    "train.checkpoint_every=50",
    "coworld.pretrain_steps=100",
    "coworld.iterations=2",
    "coworld.target_updates=2",
    "coworld.source_updates=15",
    *("offline.updates=4", "offline.log_every=2", "offline.eval_every=2", "offline.checkpoint_every=2"),
    "offline.eval_episodes=1",
)
"""13 pretraining source updates (a source checkpoint at step 50, after 3), then 2 iterations of 2 target and 15
source updates, a record every 5 steps and every target update."""
EVERY_UPDATE = ("coworld.target_updates=4", "train.log_every=1")
EVERY_UPDATE += ("offline.updates=8", "offline.log_every=1", "offline.eval_every=4", "offline.checkpoint_every=4")
"""An offline run of 8 updates, a record at every one and a checkpoint at every 4th."""
FIRST_AT_100 = ("train.checkpoint_every=100",)
"""Source pretraining's first checkpoint at its end, step 100."""


class Killed(BaseException):
    """Stands for the kill: nothing of the run catches it."""


def kill_at(monkeypatch: pytest.MonkeyPatch, cls: type, method: str, call: int) -> None:
    """``cls.method`` as it is, except that its ``call``-th call raises :class:`Killed` instead."""
    original = getattr(cls, method)
    made = {"n": 0}

    def killing(self: Any, *args: Any, **kwargs: Any) -> Any:
        made["n"] += 1
        if made["n"] == call:
            raise Killed
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cls, method, killing)


def records(logdir: Path) -> list[dict[str, Any]]:
    """The run's records without what differs between two runs of one command (``time``, ``perf/`` rates)."""
    return [{k: v for k, v in r.items() if k != "time" and "perf/" not in k} for r in read_metrics(logdir)]


def tensorboard_points(logdir: Path) -> list[tuple[str, int]]:
    """Every (tag, step) the run's TensorBoard event files hold, sorted, repeats kept."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    points = []
    for path in sorted((logdir / "tb").glob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            points.extend((value.tag, int(event.step)) for value in event.summary.value)
    return sorted(points)


def job(dataset: Path, logdir: Path, algo: str, *extra: str) -> Any:
    return check_job(
        algo=algo,
        source=None if algo == "dreamerv2" else "toy_reach",
        target="toy_reach_shifted",
        dataset=dataset,
        preset="tiny",
        logdir=logdir,
        seed=0,
        device="cpu",
        overrides=[*COWORLD, *extra],
    )


def stopped_then_resumed(monkeypatch: pytest.MonkeyPatch, run: Any, cls: type, method: str, call: int) -> None:
    with monkeypatch.context() as patch:
        kill_at(patch, cls, method, call)
        with pytest.raises(Killed):
            run()
    run()


@pytest.mark.parametrize(
    ("algo", "cls", "method", "call", "extra"),
    [
        # the checkpoint of update 4 of 8, then updates 5 and 6 logged before the kill in update 7
        pytest.param("dreamerv2", DreamerV2, "train", 7, EVERY_UPDATE, id="offline"),
        # killed in update 3, before the first checkpoint: the rerun starts over
        pytest.param("dreamerv2", DreamerV2, "train", 3, EVERY_UPDATE, id="offline-before-any-checkpoint"),
        # source pretraining's checkpoint at step 50 (3 updates), records of steps 55-70 before the kill in update 7
        pytest.param("coworld", CoWorld, "train_source", 7, (), id="coworld-pretraining"),
        # the combined checkpoint after iteration 1's target phase, then 9 source updates logged, killed in the 10th
        # (call 13 + 10)
        pytest.param("coworld", CoWorld, "train_source", 23, (), id="coworld-source-phase", marks=pytest.mark.slow),
        # the fine-tuned DreamerV2's target phase, after its 13 source updates: as the offline run
        pytest.param(
            "dreamerv2-finetune", DreamerV2, "train", 13 + 7, EVERY_UPDATE, id="finetune-target", marks=pytest.mark.slow
        ),
        # two-phase runs killed in their source pretraining before its first checkpoint (step 100), records of steps
        # 50-65 logged: the rerun starts over, its logs emptied first
        pytest.param("dreamerv2-finetune", DreamerV2, "train", 7, FIRST_AT_100, id="finetune-before-any-checkpoint"),
        pytest.param("coworld", CoWorld, "train_source", 7, FIRST_AT_100, id="coworld-before-any-checkpoint"),
    ],
)
def test_a_resumed_run_logs_each_record_once(
    tmp_path: Path,
    toy_dataset_writer,
    monkeypatch: pytest.MonkeyPatch,
    algo: str,
    cls: type,
    method: str,
    call: int,
    extra: tuple[str, ...],
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    whole = tmp_path / "whole"
    run_job(job(dataset, whole, algo, *extra), progress=False)
    stopped = tmp_path / "stopped"
    stopped_then_resumed(
        monkeypatch, lambda: run_job(job(dataset, stopped, algo, *extra), progress=False), cls, method, call
    )
    assert records(stopped) == records(whole)
    assert tensorboard_points(stopped) == tensorboard_points(whole)


@pytest.mark.parametrize(
    "call",
    [
        # killed in update 15 (step 140), before the episode after the checkpoint of step 100 ends
        pytest.param(15, id="inside-the-episode-after-the-checkpoint"),
        # killed in update 18 (step 170), after the episode of steps 100-150, which the checkpoint had not seen
        pytest.param(18, id="an-episode-past-the-checkpoint"),
        # killed in update 5 of the 10 at step 100, before the first checkpoint, its two episodes recorded
        pytest.param(5, id="before-any-checkpoint"),
    ],
)
def test_a_resumed_collection_is_the_uninterrupted_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, helpers, call: int
) -> None:
    """The rerun goes on from the checkpoint of step 100 (or from the start) with the dataset cut back to it: it
    logs steps 110 on again, once, and ends with the episodes and the agent of a run never stopped."""

    def collect(out: Path) -> None:
        collect_dreamerv2(
            "toy_reach", out, preset="tiny", device="cpu", progress=False, overrides=COLLECT, max_steps=200, resume=True
        )

    whole = tmp_path / "whole" / "toy_reach-medium_replay.h5"
    collect(whole)
    stopped = tmp_path / "stopped" / "toy_reach-medium_replay.h5"
    stopped_then_resumed(monkeypatch, lambda: collect(stopped), DreamerV2, "train", call)
    run = "toy_reach-medium_replay.run"
    assert records(stopped.with_name(run)) == records(whole.with_name(run))
    assert tensorboard_points(stopped.with_name(run)) == tensorboard_points(whole.with_name(run))
    assert helpers.episode_digests(stopped) == helpers.episode_digests(whole)
    states = [torch.load(path.with_name(run) / "checkpoint.pt", weights_only=True) for path in (stopped, whole)]
    for state in states:
        del state["config"], state["metrics_mark"]
    assert not helpers.states_differ(*states)  # the agent, its counters and random states


def test_the_logger_cuts_its_file_back_only_to_a_mark_of_that_file(tmp_path: Path) -> None:
    with Logger(tmp_path, outputs=("jsonl",)) as logger:
        logger.log({"a": 1.0}, 1)
        mark = logger.mark()
        logger.log({"a": 2.0}, 2)
    with Logger(tmp_path, outputs=("jsonl",)) as logger:
        logger.rewind(mark)
        logger.log({"a": 3.0}, 2)
    assert [(r["step"], r["a"]) for r in read_metrics(tmp_path)] == [(1, 1.0), (2, 3.0)]
    other = tmp_path / "other"
    with Logger(other, outputs=("jsonl",)) as logger:
        logger.log({"b": 1.0}, 1)
        logger.log({"b": 2.0}, 2)
        logger.rewind(mark)  # a mark of another file (a pretraining copied from another run): left as it is
        logger.rewind(None)  # a checkpoint from before marks were kept
    assert len(read_metrics(other)) == 2
