"""``coworld collect --policy dreamerv2``: datasets made by training a DreamerV2 agent online.

* ``medium-replay`` (the default, D4RL's sense): every transition the agent experiences while it learns, from
  the random prefill on, streamed into the dataset as each episode ends, until the evaluation return reaches
  the medium level (``stop_return``, by default a third of the task's reference return) or ``max_steps`` rows.
* ``medium-expert`` (the later CoWorld paper's, its Appendix B.2): the same stream, continued until the evaluation
  return reaches the expert level, "the maximum score that the DreamerV2 agent can achieve" (``stop_return``, by
  default the task's reference return), or ``max_steps`` rows. The dataset's ``collector`` metadata says what it is
  made of: ``medium_level_episodes`` and ``medium_level_step`` mark where the evaluation first reached the medium
  level, so its first ``medium_level_episodes`` episodes are the run's medium-replay part and the rest were
  recorded between the medium and the expert level (neither is set when the medium level was never reached).
  V-D4RL's medium-expert, the episodes of a medium policy followed by those of an expert one, is
  ``coworld dataset merge`` of a ``medium`` and an ``expert`` dataset.
* ``medium`` / ``expert``: the agent is trained the same way (its own experience goes to
  ``<run>/replay.h5``), then ``episodes`` episodes of the trained policy are recorded into the dataset. For
  ``expert`` there is no default ``stop_return``: the agent trains for all ``max_steps``.

The agent's run folder (checkpoint, logs, config) sits next to the dataset as ``<dataset>.run/``. Killed and
rerun with ``--resume``, the agent comes back from its last checkpoint and the dataset is cut back to the episodes
that checkpoint had seen (to none without one), so the rerun records again what the killed run recorded after it and
ends with the dataset, record, log and agent of a run never stopped (the episodes an agent made can be made again
only by that agent in that state). A dataset whose agent's run folder is gone is not resumed: nothing could make its
episodes go on.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coworld import envs, interrupt
from coworld.config import make_config
from coworld.data import DatasetWriter
from coworld.data.collect import dataset_fields
from coworld.devices import resolve_device
from coworld.errors import CoworldError, DatasetError
from coworld.storage import check_writable
from coworld.text import count
from coworld.training.description import collector_run_info
from coworld.training.logger import Logger
from coworld.training.online import OnlineTrainer
from coworld.training.run import prepare_run_dir, preset_warnings, seed_everything
from coworld.training.train import check_backend

TRAINED_QUALITIES = ("medium-replay", "medium-expert", "medium", "expert")
REPLAY_QUALITIES = ("medium-replay", "medium-expert")
"""The qualities whose dataset is the agent's own experience while it learns (the others record its trained policy)."""


@dataclass
class DreamerCollectSummary:
    path: Path
    episodes: int
    steps: int
    stop_reason: str
    last_eval_return: float | None


def default_stop_return(task: str, quality: str = "medium-replay") -> float | None:
    """When training stops early: at the medium level, a third of the task's reference return
    (:attr:`~coworld.envs.TaskSpec.medium_return`, ``coworld tasks`` lists it), for medium-replay and medium data;
    at the expert level, the reference return itself, for medium-expert data; never for expert data (the agent
    trains for all its steps). None where no reference is known."""
    if quality == "expert":
        return None
    spec = envs.task_spec(task)
    return spec.reference_return if quality == "medium-expert" else spec.medium_return


def collect_dreamerv2(
    task: str,
    out: str | Path,
    *,
    quality: str = "medium-replay",
    preset: str = "paper",
    overrides: Sequence[str] = (),
    max_steps: int | None = None,
    stop_return: float | None = None,
    medium_return: float | None = None,
    episodes: int = 10,
    seed: int = 0,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    compression: str = "gzip",
    progress: bool = True,
    warn: Callable[[str], None] | None = None,
) -> DreamerCollectSummary:
    """Train DreamerV2 online in ``task`` and write the dataset ``out`` (see the module docstring).

    ``warn`` receives one-line warnings (the paper preset on a CPU) once the request is checked, before any work.
    ``medium_return`` (medium-expert only) replaces the task's medium level where the dataset's boundary is marked.
    """
    if quality not in TRAINED_QUALITIES:
        raise CoworldError(f"the dreamerv2 collector makes {', '.join(TRAINED_QUALITIES)} datasets, not {quality!r}")
    spec = envs.task_spec(task)
    config = make_config(preset, [*overrides, f"seed={seed}", f"device={device}"])
    check_backend(config, spec.action_size)
    out = Path(out)
    run_dir = out.with_name(out.name.removesuffix(".h5") + ".run")
    if out.is_dir():
        raise DatasetError(f"{out} is a folder, not a dataset file; name a file such as {out / 'data.h5'}")
    check_writable(out.parent, "--out")
    if out.exists() and not (resume or force):
        raise DatasetError(f"{out} already exists; pass --resume to continue it or --force to overwrite it")
    if force and run_dir.exists():
        shutil.rmtree(run_dir)
    if resume and not force and quality in REPLAY_QUALITIES and not (run_dir / "config.json").exists():
        _check_agent_is_there(out, run_dir)
    if stop_return is None:
        stop_return = default_stop_return(task, quality)
    limit = max_steps if max_steps is not None else config.train.steps
    info = {
        **collector_run_info(task, preset),
        "quality": quality,
        "dataset": str(out),
        "max_steps": limit,
        "stop_return": stop_return,
    }
    for message in preset_warnings(preset, config.device) if warn is not None else ():
        warn(message)
    resumed = prepare_run_dir(run_dir, config, info, start_over=f"pass --force to start {out} and its agent over")
    seed_everything(config.seed)
    from coworld.agents.dreamerv2 import DreamerV2

    agent = DreamerV2(config=config, action_size=spec.action_size, device=resolve_device(config.device))
    collector = {
        "algorithm": "dreamerv2",
        "preset": preset,
        "seed": seed,
        "run": str(run_dir),
        "stop_return": stop_return,
    }
    if quality == "medium-expert":
        medium_return = spec.medium_return if medium_return is None else medium_return
        collector["medium_return"] = medium_return  # where medium_level_* mark the medium-replay part's end
    fields = dataset_fields(task)
    experience = out if quality in REPLAY_QUALITIES else run_dir / "replay.h5"
    writer = DatasetWriter(
        experience,
        task=task,
        quality=quality if quality in REPLAY_QUALITIES else "medium-replay",
        collector=collector,
        action_size=spec.action_size,
        resume=resumed or resume,
        force=force and not resumed,
        compression=compression,
        **fields,
    )
    with Logger(run_dir) as logger, writer:
        trainer = OnlineTrainer(agent=agent, task=task, config=config, logdir=run_dir, writer=writer, logger=logger)
        held = writer.num_episodes
        trainer.restore(rollback=True)
        if writer.num_episodes < held:
            _note_rollback(writer, trainer, held, warn)
        try:
            if quality == "medium-expert":
                result = _train_past_medium(trainer, writer, limit, medium_return, stop_return, progress)
            else:
                result = trainer.run(max_steps=limit, stop_return=stop_return, progress=progress)
        finally:
            trainer.close()
        writer.update_metadata(
            steps=result.steps,
            updates=result.updates,
            stop_reason=result.stop_reason,
            last_eval_return=result.last_eval_return,
        )
        writer.close(complete=True)
    if quality in REPLAY_QUALITIES:
        return DreamerCollectSummary(out, result.episodes, result.steps, result.stop_reason, result.last_eval_return)
    return _record_policy(agent, task, out, quality, episodes, seed, collector, result, fields, resume, compression)


def _check_agent_is_there(out: Path, run_dir: Path) -> None:
    """Refuse to resume ``out`` where it holds episodes but its agent's run folder is gone (deleted, or the dataset
    moved without it): a fresh agent would go on with other data than the collection's."""
    from coworld.data import open_dataset

    if not out.exists():
        return
    with open_dataset(out) as data:
        held = data.num_episodes
    if held:
        raise DatasetError(
            f"cannot resume {out}: its {count(held, 'episode')} came from an agent whose run folder {run_dir} is not"
            " there, so nothing can go on with them; put that folder back, or pass --force to collect anew"
        )


def _note_rollback(
    writer: DatasetWriter, trainer: OnlineTrainer, held: int, warn: Callable[[str], None] | None
) -> None:
    """After the dataset was cut back to the agent's checkpoint: the record's last evaluation is again the
    checkpoint's, and ``warn`` hears what is collected again."""
    if "last_eval_step" in writer.metadata["collector"]:
        writer.update_metadata(last_eval_return=trainer.last_eval, last_eval_step=trainer.last_eval_step)
    if warn is None:
        return
    kept, again = writer.num_episodes, count(held - writer.num_episodes, "episode")
    said = f"{writer.path} held {count(held, 'episode')}"
    if kept:
        warn(f"{said} and the agent's last checkpoint had seen {kept}: the {again} after it are collected again")
    else:
        warn(f"{said} and the agent had no checkpoint yet: they are collected again from the start")


def _train_past_medium(
    trainer: OnlineTrainer,
    writer: DatasetWriter,
    limit: int,
    medium: float | None,
    stop_return: float | None,
    progress: bool,
) -> Any:
    """Medium-expert collection: train until the medium level, mark it in the dataset, then on to ``stop_return``.

    One run of the trainer in two calls, so the data are the same stream a single call would record; the mark is
    written once, and a resumed collection that has it goes straight on to the second call.
    """
    if medium is not None and "medium_level_step" not in writer.metadata["collector"]:
        first = trainer.run(max_steps=limit, stop_return=medium, progress=progress)
        if first.stop_reason.startswith("evaluation return"):
            writer.update_metadata(
                medium_level_step=trainer.last_eval_step,
                medium_level_episodes=writer.num_episodes,
                medium_level_return=trainer.last_eval,
            )
    return trainer.run(max_steps=limit, stop_return=stop_return, progress=progress)


def _record_policy(
    agent: Any,
    task: str,
    out: Path,
    quality: str,
    episodes: int,
    seed: int,
    collector: dict[str, Any],
    result: Any,
    fields: dict[str, Any],
    resume: bool,
    compression: str,
) -> DreamerCollectSummary:
    """Record ``episodes`` episodes of the trained policy (sampling its actions) into ``out``."""
    spec = envs.task_spec(task)
    collector = {
        **collector,
        "training_steps": result.steps,
        "last_eval_return": result.last_eval_return,
        "stop_reason": result.stop_reason,
    }
    with DatasetWriter(
        out,
        task=task,
        quality=quality,
        collector=collector,
        action_size=spec.action_size,
        resume=resume,
        compression=compression,
        **fields,
    ) as writer:
        env = envs.make(task, seed=seed + 20_000 + writer.num_episodes)
        while writer.num_episodes < episodes:
            obs, _ = env.reset(seed=seed + 20_000 + writer.num_episodes)
            frames, actions, rewards, successes = [obs], [], [], []
            state, terminated, truncated = None, False, False
            while not (terminated or truncated):
                interrupt.check()
                action, state = agent.policy(obs[None], state, mode="train")
                obs, reward, terminated, truncated, info = env.step(action[0])
                frames.append(obs)
                actions.append(action[0])
                rewards.append(reward)
                if "success" in info:
                    successes.append(float(info["success"]))
            infos = {"success": np.asarray(successes, np.float32)} if successes else None
            writer.add_episode(
                observations=np.stack(frames),
                actions=np.stack(actions),
                rewards=np.asarray(rewards, np.float32),
                terminated=terminated,
                infos=infos,
            )
        env.close()
        recorded = writer.num_episodes, writer.num_steps
        writer.close(complete=True)
    return DreamerCollectSummary(out, *recorded, result.stop_reason, result.last_eval_return)
