"""Offline baselines on the target dataset: offline DreamerV2 and its variants, LOMPO, CURL / CURL+CQL and DrQ+BC.

Offline DreamerV2, V-D4RL's penalised DreamerV2, LOMPO and the fine-tuned DreamerV2 (with or without EWC) train for
``offline.updates``, which every preset sets to CoWorld's target updates (``coworld.iterations *
coworld.target_updates``), evaluated and checkpointed once per CoWorld iteration's worth, so they compare at equal
cost; the model-free baselines read their own sections (``curl``, ``drqbc``). The
fine-tuned DreamerV2 first learns online in the source task (:func:`coworld.training.finetune.
pretrain_on_source`); with EWC it then takes its source weights and their Fisher information
(:func:`coworld.training.finetune.consolidate_on_source`).
"""

from __future__ import annotations

from functools import reduce
from typing import Any

import torch

from coworld.agents.factory import import_named, make_agent
from coworld.algorithms import algorithm
from coworld.data import open_dataset
from coworld.envs import task_spec
from coworld.training.job import TrainJob
from coworld.training.logger import EMPTY_MARK, Logger
from coworld.training.offline import OfflineSchedule, OfflineTrainer


def schedule_for(job: TrainJob) -> OfflineSchedule:
    """The run's length and cadence, from the config section its record names (:attr:`Algorithm.schedule`)."""
    c = getattr(job.config, algorithm(job.algo).schedule)
    return OfflineSchedule(
        updates=c.updates,
        log_every=c.log_every,
        eval_every=c.eval_every,
        eval_episodes=c.eval_episodes,
        checkpoint_every=c.checkpoint_every,
    )


def train_offline(job: TrainJob, *, device: torch.device, resumed: bool, progress: bool = True) -> dict[str, Any]:
    config, record = job.config, algorithm(job.algo)
    action_size = task_spec(job.target).action_size
    agent = make_agent(job.algo, config=config, action_size=action_size, device=device)
    dataset = open_dataset(job.dataset)
    if record.sampler is None:

        def make_sampler(seed: int):
            return iter(dataset.sampler(config.train.batch_size, config.train.seq_len, seed=seed))

    else:
        sampler = import_named(record.sampler)

        def make_sampler(seed: int):
            return iter(sampler(dataset, config, seed))

    discount = reduce(getattr, record.discount.split("."), config)
    with Logger(job.logdir) as logger:
        trainer = OfflineTrainer(
            agent=agent,
            kind=record.checkpoint,
            task=job.target,
            config=config,
            schedule=schedule_for(job),
            logdir=job.logdir,
            logger=logger,
            make_sampler=make_sampler,
            discount=discount,
            workers=config.train.envs,
            prefetch=config.train.prefetch,
            prepare=getattr(agent, "prepare", None),
            phase="offline training" if job.source is None else "target phase",
        )
        restored = resumed and trainer.restore()
        if not restored and job.source is None:  # killed before its first checkpoint: it starts over, its log too
            logger.rewind(EMPTY_MARK)
        if job.source is not None and not restored:
            from coworld.training.finetune import consolidate_on_source, pretrain_on_source

            pretrain_on_source(agent, job, logger=logger, progress=progress)
            if hasattr(agent, "consolidate"):  # EWC: the source weights and their Fisher information
                consolidate_on_source(agent, job, logger=logger)
        result = trainer.run(progress=progress)
    dataset.close()
    return {"logdir": str(job.logdir), "updates": result.updates, "last_eval_return": result.last_eval_return}
