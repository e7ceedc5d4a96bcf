"""``coworld train``: check the inputs, prepare the run folder, dispatch to the algorithm.

Everything a user can get wrong is checked before anything is written: the task names, the source and target
action sizes, the dataset (present, readable, of the target task), the config keys. A run folder made by other
settings is refused; one made by the same settings is resumed from its checkpoint.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coworld import envs
from coworld.algorithms import ALGOS, algorithm
from coworld.config import Config, make_config
from coworld.data.collect import default_dataset_path
from coworld.errors import CoworldError, DatasetError
from coworld.training.job import TrainJob, default_logdir, parse_sources


def check_source(algo: str, source: str, target: str) -> list[str]:
    """What ``algo`` requires of a source for ``target`` (one CoworldError line); returns the warnings.

    CoWorld serves any two action sizes (every task here acts in a box ``[-1, 1]^A``; see
    :func:`coworld.agents.coworld.source_model_action_size`). DreamerV2 fine-tuning carries the source agent's
    networks over to the target, so it needs one action size."""
    source_spec, target_spec = envs.task_spec(source), envs.task_spec(target)
    if source == target:  # learning online in the target itself would not be offline RL from its dataset
        paired = envs.paired_source(target) or "a task of the target's body (see `coworld tasks`)"
        raise CoworldError(
            f"source {target} is the target itself, but a source is another domain, learned online beside the"
            f" target's dataset; pass another --source, e.g. --source {paired}"
        )
    if algorithm(algo).source == "carried" and source_spec.action_size != target_spec.action_size:
        raise CoworldError(
            f"source {source} has {source_spec.action_size} action dimensions but target {target} has"
            f" {target_spec.action_size}; {algo} carries the source agent's networks over to the target, so pick a"
            f" source with {target_spec.action_size} (see `coworld tasks`), or use --algo coworld, which serves any two"
        )
    if source_spec.embodiment == target_spec.embodiment or (source, target) in envs.PAIRS:
        return []
    paired = envs.paired_source(target)
    shared = "share an action size" if source_spec.action_size == target_spec.action_size else "share no action size"
    return [
        f"source {source} ({source_spec.embodiment}) and target {target} ({target_spec.embodiment}) are"
        f" different bodies that {shared}; the papers pair tasks of one body, and Meta-World sources with RoboDesk"
        " targets" + (f" ({paired} -> {target})" if paired else "")
    ]


def check_job(
    *,
    algo: str,
    source: str | None,
    target: str,
    dataset: str | Path | None,
    preset: str,
    logdir: str | Path | None,
    seed: int | None,
    device: str | None,
    overrides: Sequence[str],
    force: bool = False,
    keep_pretrained: bool = False,
    pretrained_from: Sequence[str | Path] = (),
) -> TrainJob:
    """Validate a training request without writing anything; raises CoworldError with one line on any problem.

    Everything a run would trip over later is checked here: the config's rules between keys and its memory
    (:func:`check_config`), the dataset against the sequences sampled from it, and a resumed run folder's
    checkpoint. ``force``: a run folder of other settings is started over (:attr:`TrainJob.start_over`).
    ``keep_pretrained``, ``pretrained_from``: CoWorld's shared source pretraining (coworld.training.pretrained).
    """
    from coworld.training.run import check_run_dir, preset_warnings

    if algo not in ALGOS:
        raise CoworldError(f"unknown algorithm {algo!r}; choose one of: {', '.join(ALGOS)}")
    target_spec = envs.task_spec(target)
    extra = list(overrides)
    if seed is not None:
        extra.append(f"seed={seed}")
    if device is not None:
        extra.append(f"device={device}")
    config = make_config(preset, extra)
    warnings: list[str] = []
    record = algorithm(algo)
    if record.needs_source:
        if source is None:
            paired = envs.paired_source(target) or "a task of the target's body (see `coworld tasks`)"
            raise CoworldError(f"{algo} needs an online source domain: pass --source, e.g. --source {paired}")
        sources = parse_sources(source)
        if len(sources) > 1 and record.source != "any":
            raise CoworldError(
                f"{algo} takes one --source; a list ({source}) is CoWorld's automatic source choice (--algo coworld)"
            )
        for name in sources:
            warnings += check_source(algo, name, target)
        source = ",".join(sources)
    check_config(algo, config, target_spec.action_size)
    path = Path(dataset) if dataset is not None else default_dataset_path(target, "medium-replay")
    if not check_dataset(path, target, target_spec.action_size, needed_steps(algo, config)):
        warnings.append(
            f"{path} is not complete (its collection was interrupted or is still running): training uses the"
            " episodes committed so far; finish it with `coworld collect ... --resume` for the whole dataset"
        )
    warnings += longer_than_episodes(path, needed_steps(algo, config))
    warnings += unread_length(algo, config, make_config(preset))
    run_dir = Path(logdir) if logdir is not None else default_logdir(algo, source, target, config.seed)
    job = TrainJob(algo, source if record.needs_source else None, target, path, run_dir, config, preset)
    if force:
        if run_dir.exists() and not run_dir.is_dir():
            raise CoworldError(f"{run_dir} is a file, not a run folder; pass another --logdir")
        resume = False
    else:
        resume = check_run_dir(run_dir, config, job.info())
    if resume:
        check_resumable(run_dir, config, job.info())
    donors = tuple(Path(d) for d in pretrained_from)
    if donors or keep_pretrained:
        from coworld.training.pretrained import check_donors

        check_donors(donors, config=config, info=job.info())
    warnings += preset_warnings(preset, config.device, algo)
    return dataclasses.replace(
        job,
        resume=resume,
        start_over=force,
        warnings=tuple(warnings),
        keep_pretrained=keep_pretrained,
        pretrained_from=donors,
    )


def check_config(algo: str, config: Config, action_size: int) -> None:
    """What ``train`` requires of a config beyond each value's range: the rules between keys that only one algorithm
    reads (:func:`check_schedule`), a memory estimate within this machine's (:mod:`coworld.budget`) and, for the
    world-model algorithms, ``train.backend``'s choice (:func:`check_backend`). ``sweep`` checks every run's config
    with it before its folder exists."""
    from coworld.budget import check_memory

    check_schedule(algo, config)
    check_memory(algo, config)
    if algorithm(algo).world_model:
        check_backend(config, action_size)


def needed_steps(algo: str, config: Config) -> tuple[int, str] | None:
    """The fewest steps a dataset must hold for ``algo``'s sampler and the config key that asks for them: a model's
    sequences of ``train.seq_len`` (the model-free baselines' own samplers take single transitions, stacks padded at
    the start of an episode, so any dataset will do)."""
    return None if algorithm(algo).sampler is not None else (config.train.seq_len, "train.seq_len")


def check_resumable(run_dir: Path, config: Config, info: dict[str, Any]) -> None:
    """The checkpoints a resumed run will load are whole and of this run (one line otherwise), checked before the
    run folder is touched; the main checkpoint, else a source agent's pretraining checkpoint."""
    from coworld.training.checkpoint import refuse_earlier_format
    from coworld.training.coworld import CHECKPOINT_KEYS as COWORLD_CHECKPOINT_KEYS
    from coworld.training.coworld import FORMAT_KEYS
    from coworld.training.loading import load_run_checkpoint
    from coworld.training.offline import CHECKPOINT_KEYS
    from coworld.training.online import CHECKPOINT_KEYS as ONLINE_KEYS
    from coworld.training.online import ONLINE_STATE_KEYS

    main, source = run_dir / "checkpoint.pt", run_dir / "source" / "checkpoint.pt"
    if main.exists():
        collaborative = algorithm(info["algo"]).collaborative
        keys = COWORLD_CHECKPOINT_KEYS if collaborative else CHECKPOINT_KEYS
        state = load_run_checkpoint(main, config, info, keys=keys, mmap=True)
        if collaborative:  # refused here, before the run folder is touched, not once the run has opened it
            refuse_earlier_format(main, state, FORMAT_KEYS)
        return
    sources = parse_sources(info["source"]) if info.get("source") else ()
    if len(sources) > 1:  # CoWorld choosing its source: each candidate's pretraining, the chosen one's once moved
        from coworld.training.chosen_source import candidate_dir, read_choice

        choice = read_choice(run_dir, sources)
        checks = [(candidate_dir(run_dir, name) / "source" / "checkpoint.pt", name) for name in sources]
        if choice is not None:
            checks.append((source, choice.chosen))
    else:
        checks = [(source, info.get("source"))]
    for path, task in checks:
        if path.exists():  # the source agent learned in the source task
            source_info = {**info, "online": True, "target": task, "source": None}
            state = load_run_checkpoint(path, config, source_info, keys=ONLINE_KEYS, mmap=True)
            refuse_earlier_format(path, state, ONLINE_STATE_KEYS)


def check_schedule(algo: str, config: Config) -> None:
    """The rules between config keys that only one algorithm reads (one line on what to change)."""
    from coworld.agents.factory import agent_class

    record = algorithm(algo)
    section = getattr(agent_class(algo), "section", None)  # the agents that learn an ensemble of models first
    if section is not None:
        model_updates = getattr(config, section).model_updates
        total = getattr(config, record.schedule).updates
        if model_updates >= total:
            raise CoworldError(
                f"{section}.model_updates={model_updates} leaves none of the run's {total} updates"
                f" ({record.schedule}.updates) to the actor-critic; lower it or lengthen the run"
            )
    shortest = record.min_seq_len
    if config.train.seq_len < shortest:
        raise CoworldError(
            f"{algo} learns from consecutive steps of the dataset's sequences, so train.seq_len must be at least"
            f" {shortest}"
        )


IMAGE_SHAPE = (64, 64, 3)
"""The frames every model here takes."""


def check_backend(config: Config, action_size: int) -> None:
    """``train.backend``'s choice for the world model ``config`` builds, made before anything is written (a refused
    ``cpu`` raises ConfigError with one line)."""
    from coworld import backends
    from coworld.agents.dreamerv2 import resolve_precision
    from coworld.devices import resolve_device

    device = resolve_device(config.device)
    autocast = resolve_precision(config.precision, device) is not None
    backends.check_config(config, action_size, IMAGE_SHAPE, device, autocast)


def check_dataset(path: Path, task: str, action_size: int, needed: tuple[int, str] | None = None) -> bool:
    """The dataset exists, opens, was recorded in ``task`` with its action size, has 64 x 64 RGB frames, and holds
    at least ``needed`` = (steps, the config key asking for them) steps.

    Returns whether it is complete (its collection reached its target)."""
    from coworld.data import open_dataset

    if not path.exists():
        raise DatasetError(
            f"no dataset at {path}; make one with `coworld collect --task {task} --preset cpu --out {path}`"
            " (or --preset tiny to try the pipeline) or pass --dataset"
        )
    with open_dataset(path) as data:
        if data.task != task:
            raise DatasetError(f"{path} was recorded in {data.task}, not the target {task}; pass a {task} dataset")
        if data.action_size != action_size:
            raise DatasetError(f"{path} has {data.action_size}-d actions but {task} takes {action_size}")
        if tuple(data.image_shape) != IMAGE_SHAPE:
            h, w, c = data.image_shape
            raise DatasetError(
                f"{path} has {h} x {w} x {c} frames but the models take 64 x 64 x 3 RGB frames; convert it to 64 x 64"
                " (e.g. `coworld dataset import ... --resize 64`)"
            )
        if needed is not None and data.num_frames < needed[0]:
            steps, key = needed
            raise DatasetError(
                f"{path} holds {data.num_frames} steps but {key} needs sequences of {steps}; collect more"
                f" (`coworld collect ... --resume`) or lower {key} with --set"
            )
        return bool(data.complete)


def unread_length(algo: str, config: Config, preset_config: Config) -> list[str]:
    """A warning when ``train.steps``, the length of an online collection (``coworld collect``), was set for a
    ``coworld train`` run, which never reads it; it names the settings that set the run's length."""
    if config.train.steps == preset_config.train.steps:
        return []
    length = algorithm(algo).length(config)
    return [f"train.steps is the length of `coworld collect`'s online run, not of training: {algo} makes {length}"]


def longer_than_episodes(path: Path, needed: tuple[int, str] | None) -> list[str]:
    """A warning when the model's sequences (``needed``: steps, key) are longer than every episode of the dataset:
    then every sequence crosses into the next episode (the model starts afresh there), which is rarely meant."""
    from coworld.data import open_dataset

    if needed is None:
        return []
    with open_dataset(path) as data:
        longest = int(data.lengths.max()) + 1 if data.num_episodes else 0
    steps, key = needed
    if longest == 0 or steps <= longest:
        return []
    return [
        f"{key}={steps} is longer than every episode of {path} (at most {longest} steps with its final frame): every"
        f" sequence crosses into the next episode; lower {key} to {longest} or less unless that is meant"
    ]


def run_job(job: TrainJob, *, progress: bool = True) -> dict[str, Any]:
    """Train as ``job`` says (resuming its run folder if it holds this run); returns a summary."""
    from coworld.devices import resolve_device
    from coworld.training.run import clear_run_dir, prepare_run_dir, seed_everything

    device = resolve_device(job.config.device)
    if job.start_over:
        clear_run_dir(job.logdir)
    resumed = prepare_run_dir(job.logdir, job.config, job.info())
    seed_everything(job.config.seed)
    if algorithm(job.algo).collaborative:
        from coworld.training.coworld import train_coworld

        return train_coworld(job, device=device, resumed=resumed, progress=progress)
    from coworld.training.baselines import train_offline

    return train_offline(job, device=device, resumed=resumed, progress=progress)
