"""CoWorld with several candidate sources: which one it trains with (the later paper's multi-source CoWorld).

``coworld train --source A,B,... --target T`` runs, before Algorithm 1:

1. **target warm-up**: the target world model alone, ``coworld.source_updates`` updates on target-dataset batches
   (no alignment: there is no source yet), so that it has latents of its own to compare with. The authors'
   release trains its target world model alone before co-training too (its "Step 2", 2 x 1e4 updates, the
   paper preset's ``source_updates``);
2. **each candidate in the order given**: its source agent pretrained online for ``coworld.pretrain_steps``
   environment steps (as a one-source run pretrains its source), then its :func:`domain_distance` to the target:
   Eq. 3's KL ``KL[sg(e_S(o_T)) || e_T(o_T)]`` between the candidate's and the target's latents on the same
   ``coworld.select_batches`` target-dataset batches (one sampler seed for every candidate), in the form
   ``coworld.align_on`` names, averaged over the batches;
3. **the choice**: the closest candidate (:func:`closest_source`), written with every distance to
   ``source_choice.json`` and logged as ``coworld/source_distance/<task>`` metrics; the chosen candidate's
   pretraining then takes the place a one-source run keeps it in (``source/``, ``source_replay.h5``), and the run
   continues as a one-source CoWorld run of that source, from the warmed-up target agent.

The run folder, meanwhile: ``sources/<task>/`` (each candidate's pretraining checkpoint, replay and metrics),
``selection/target.pt`` (the warmed-up target agent) and ``selection/distances.json`` (the distances measured so
far). Each step is written whole before the next begins, so a killed run resumes where it stopped; a choice once
written is never made again.

The later paper reports multi-source CoWorld near the best single source chosen by hand (Meta-World average 4094
against 4241). Its text names the rule (the source whose latents on the target data lie closest, by a KL between
the world models' latents) but not when it is measured; the release has the distance (``_latent_distance``) but
no call to it. The schedule above is this project's reading: after each model has learned its own domain, before
any alignment has pulled the target towards one of them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from coworld import interrupt
from coworld.agents.coworld import CoWorld
from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import Config, to_dict
from coworld.envs import task_spec
from coworld.errors import CheckpointError
from coworld.losses.coworld import closest_source, domain_distance
from coworld.storage import write_text_atomically
from coworld.training.checkpoint import load_checkpoint, rng_state, save_checkpoint, set_rng_state
from coworld.training.chosen_source import (
    CHOICE_FILE,
    MEASURED_FILE,
    SourceChoice,
    candidate_dir,
    read_choice,
    read_distances,
)
from coworld.training.divergence import Phase
from coworld.training.job import parse_sources
from coworld.training.logger import Logger
from coworld.training.online import pretrain_source, source_phase
from coworld.training.run import seed_everything

WARMUP_KIND = "coworld-warmup"
SELECT_SEED = 7_000
"""Offset of the seed of the batches every candidate's distance is measured on (and of their latent noise)."""
WARMUP_SEED = 8_000
"""Offset of the seed of the target warm-up's batches."""
CANDIDATE_SEED = 9_000
"""Offset of the seed each candidate's networks start from (plus its place in the list)."""


def measure_distance(
    source: DreamerV2, target: DreamerV2, batches: Iterable[Mapping[str, np.ndarray]], *, align_on: str, seed: int
) -> float:
    """:func:`domain_distance` of ``source``'s latents from ``target``'s on each target batch, averaged over the
    batches; the latent samples' noise from a generator seeded with ``seed`` (the same for every candidate)."""
    generator = torch.Generator(target.device).manual_seed(seed)
    values = []
    with torch.no_grad():
        for batch in batches:
            tensors = target.prepare(batch)
            if align_on == "embedding":
                s, t = source.model_path.embed(tensors), target.model_path.embed(tensors)
            else:
                s = source.model_path.observe(tensors, generator=generator, priors=False)[0]["logits"]
                t = target.model_path.observe(tensors, generator=generator, priors=False)[0]["logits"]
            values.append(float(domain_distance(s.float(), t.float(), align_on)))
    return float(np.mean(values))


def _batches(dataset: Any, config: Config, seed: int, count: int) -> list[dict[str, np.ndarray]]:
    sampler = iter(dataset.sampler(config.train.batch_size, config.train.seq_len, seed=seed))
    return [next(sampler) for _ in range(count)]


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomically(path, json.dumps(data, indent=2) + "\n")


def settle_source(job: Any, *, dataset: Any, device: torch.device, progress: bool = True) -> tuple[Any, Path | None]:
    """``job`` with its one source, and the warmed-up target agent's checkpoint to start from (None with one source
    given): where several are given, the closest, chosen by :func:`choose_source`."""
    candidates = parse_sources(str(job.source))
    if len(candidates) == 1:
        return job, None
    choice, warm_target = choose_source(job, candidates, dataset=dataset, device=device, progress=progress)
    return dataclasses.replace(job, source=choice.chosen), warm_target


def choose_source(
    job: Any, candidates: Sequence[str], *, dataset: Any, device: torch.device, progress: bool = True
) -> tuple[SourceChoice, Path]:
    """Warm up the target model, pretrain and measure each candidate, choose (resuming whatever of it a killed run
    left); returns the choice and the warmed-up target agent's checkpoint, for Algorithm 1 to start from
    (:func:`coworld.training.coworld.train_coworld`).
    The chosen candidate's pretraining is moved to ``source/`` and ``source_replay.h5`` before this returns."""
    config: Config = job.config
    cfg = config.coworld
    run_dir = Path(job.logdir)
    target_size = task_spec(job.target).action_size
    selection = run_dir / "selection"
    warm_path = selection / "target.pt"
    choice = read_choice(run_dir, candidates)
    if choice is None:
        if not warm_path.exists():
            _warm_up(job, dataset, device, warm_path)
        warm = load_checkpoint(warm_path, map_location=device, keys=("agent", "rng"))
        if warm.get("kind") != WARMUP_KIND or warm.get("task") != job.target:
            raise CheckpointError(f"{warm_path} is not this run's target warm-up; pass --force to start over")
        target = DreamerV2(config=config, action_size=target_size, device=device)
        target.load_state_dict(warm["agent"])
        measured_path = run_dir / MEASURED_FILE
        distances = read_distances(run_dir, candidates)
        batches = _batches(dataset, config, config.seed + SELECT_SEED, cfg.select_batches)
        for index, name in enumerate(candidates):
            if name in distances:
                continue
            # each candidate starts from a seed of its own, so one rerun after a kill starts it as it first started
            seed_everything(config.seed + CANDIDATE_SEED + index)
            candidate = _pretrain(job, name, device, progress)
            distances[name] = measure_distance(
                candidate.source, target, batches, align_on=cfg.align_on, seed=config.seed + SELECT_SEED
            )
            _write_json(measured_path, distances)
            del candidate
        choice = SourceChoice(
            candidates=tuple(candidates),
            distances={name: distances[name] for name in candidates},
            chosen=closest_source({name: distances[name] for name in candidates}),
            align_on=cfg.align_on,
            batches=cfg.select_batches,
        )
        _write_json(run_dir / CHOICE_FILE, choice.to_dict())
        with Logger(run_dir) as logger:
            metrics = {f"coworld/source_distance/{name}": value for name, value in choice.distances.items()}
            metrics["coworld/source_chosen_index"] = float(candidates.index(choice.chosen))
            logger.log(metrics, 0, unit="target_update")
    _move_chosen(run_dir, choice.chosen)
    tqdm.write(choice_line(choice), file=sys.stderr)
    return choice, warm_path


def choice_line(choice: SourceChoice) -> str:
    """The choice in one line, every candidate's distance beside it (what the run prints when it has chosen)."""
    others = ", ".join(f"{name} {choice.distances[name]:.4g}" for name in choice.candidates if name != choice.chosen)
    return (
        f"source choice: {choice.chosen}, the closest to the target (distance {choice.distances[choice.chosen]:.4g};"
        f" {others}), measured on {choice.batches} target batches; {CHOICE_FILE} holds it"
    )


def _warm_up(job: Any, dataset: Any, device: torch.device, path: Path) -> None:
    """The target world model alone on ``coworld.source_updates`` target batches, then its checkpoint at ``path``."""
    config: Config = job.config
    target = DreamerV2(config=config, action_size=task_spec(job.target).action_size, device=device)
    sampler = iter(dataset.sampler(config.train.batch_size, config.train.seq_len, seed=config.seed + WARMUP_SEED))
    phase = Phase(
        name="the target model's warm-up before the source choice",
        agent="the target agent",
        unit="warm-up update",
        kind="coworld",
        config=config,
        resume_from=path,
    )
    with Logger(path.parent) as logger:
        for i in range(config.coworld.source_updates):
            interrupt.check()
            metrics, _ = target.train_world_model(target.prepare(next(sampler)))
            named = {f"target/{k}": v for k, v in metrics.items()}
            phase.check(named, i + 1)
            if (i + 1) % max(1, config.train.log_every) == 0 or i + 1 == config.coworld.source_updates:
                logger.log(named, i + 1, unit="warmup_update")
    with phase.saving(config.coworld.source_updates):
        save_checkpoint(
            path,
            {
                "kind": WARMUP_KIND,
                "task": job.target,
                "config": to_dict(config),
                "agent": target.state_dict(),
                "rng": rng_state(),
            },
        )


def _pretrain(job: Any, name: str, device: torch.device, progress: bool) -> CoWorld:
    """Candidate ``name``'s source agent, pretrained online as a one-source run pretrains its source (resumed from
    its checkpoint in :func:`candidate_dir`); a CoWorld whose target agent is not used."""
    config: Config = job.config
    candidate = CoWorld(
        config=config,
        action_size=task_spec(job.target).action_size,
        source_action_size=task_spec(name).action_size,
        device=device,
    )
    folder = candidate_dir(job.logdir, name)
    folder.mkdir(parents=True, exist_ok=True)
    phase = source_phase(
        f"source pretraining of candidate {name}",
        agent="the source agent",
        kind="coworld-source",
        config=config,
        logdir=folder,
    )
    with Logger(folder) as logger:
        pretrain_source(
            candidate.source,
            name,
            config=config,
            logdir=folder,
            logger=logger,
            algorithm="coworld",
            phase=phase,
            train=candidate.train_source,
            progress=progress,
            cut_episodes=False,
        )
    return candidate


def _move_chosen(run_dir: Path, chosen: str) -> None:
    """Put the chosen candidate's pretraining where a one-source run keeps its source's (each move once; a rerun
    after a kill between the two finishes the other)."""
    folder = candidate_dir(run_dir, chosen)
    for name in ("source", "source_replay.h5"):
        there, here = folder / name, run_dir / name
        if there.exists() and not here.exists():
            os.replace(there, here)


def restore_warm_target(agent: CoWorld, path: Path, device: torch.device) -> None:
    """Start ``agent``'s target from the warm-up :func:`choose_source` made (and the RNG where it left it)."""
    state = load_checkpoint(path, map_location=device, keys=("agent", "rng"))
    agent.target.load_state_dict(state["agent"])
    set_rng_state(state["rng"])
