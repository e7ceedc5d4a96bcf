"""Run folders, seeding and device choice shared by every trainer.

A run folder holds ``config.json`` (the resolved config), ``run.json`` (what was run: algorithm, tasks,
dataset), ``checkpoint.pt``, ``metrics.jsonl`` and TensorBoard files. Rerunning a command on an existing
folder resumes it; a folder made by different settings is refused rather than silently mixed.
"""

from __future__ import annotations

import json
import random
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from coworld.algorithms import algorithm
from coworld.config import Config, canonical_preset, first_difference, from_dict, split_preset, to_dict, to_json
from coworld.devices import resolve_device
from coworld.errors import ConfigError, CoworldError
from coworld.storage import damaged, read_json_object, write_text_atomically
from coworld.training.description import run_description
from coworld.training.job import START_OVER


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def preset_warnings(preset: str, device: str, algo: str = "dreamerv2") -> list[str]:
    """Warnings of a preset that does not size this run for this machine: the GPU-sized paper preset on a CPU, and
    the cpu preset for a model-free baseline (it sizes the DreamerV2 family only)."""
    size, _ = split_preset(preset)
    record = algorithm(algo)
    if size == "cpu" and not record.world_model:
        section = record.section
        return [
            f"the cpu preset sizes coworld and the dreamerv2 family only: {algo} runs at the paper's size here"
            f" ({section}.updates, {section}.batch_size); pass --preset tiny for a small run, or size it with"
            f" --set {section}.KEY=VALUE"
        ]
    if size != "paper" or resolve_device(device).type != "cpu":
        return []
    return [
        "the paper preset is sized for a GPU: on this CPU a paper-size update takes seconds, so a run takes weeks;"
        " pass --preset cpu to learn on a CPU, or --preset tiny to try things in minutes (README, 'Presets')"
    ]


RUN_ARTEFACTS = (
    "checkpoint.pt",
    "metrics.jsonl",
    "tb",
    "source",
    "source_replay.h5",
    "eval.json",
    "source_choice.json",  # CoWorld choosing among several sources (coworld.training.multi_source)
    "sources",
    "selection",
)
"""What training leaves in a run folder besides its description (``run.json``, then ``config.json``, written
last): a folder holding any of these but no ``config.json`` was not described by ``coworld train``, or was
damaged, and is refused rather than resumed. Other files (a sweep's record, notes) are left alone."""


def check_run_dir(logdir: str | Path, config: Config, info: Mapping[str, Any], start_over: str = START_OVER) -> bool:
    """Whether ``logdir`` can hold this run, without writing anything; every refusal ends with ``start_over``, the
    options of the calling command that start afresh.

    Returns:
        True when the folder already holds this run (the caller resumes from its checkpoint), False when it is
        absent or new (no training artefacts, :data:`RUN_ARTEFACTS`).

    Raises:
        CoworldError: the folder holds another run (other settings or tasks), an unreadable description, training
        artefacts that no ``config.json`` describes (a checkpoint copied in, say), or source experience of another
        task than the run's source (:func:`check_source_replay`).
    """
    logdir = Path(logdir)
    config_path = logdir / "config.json"
    info = json.loads(json.dumps(dict(info)))  # normalise tuples and paths the way JSON reads them back
    if logdir.exists() and not logdir.is_dir():
        raise CoworldError(f"{logdir} is a file, not a run folder; {start_over}")
    if not config_path.exists():
        found = [name for name in RUN_ARTEFACTS if (logdir / name).exists()]
        if found:
            raise CoworldError(
                f"{logdir} holds {', '.join(found)} but no config.json, so it is not a run folder coworld train"
                f" can resume (or it was damaged); nothing was changed: {start_over}"
            )
        return False
    saved, saved_info = load_run(logdir, fix=f"nothing was changed: {start_over}")
    presets = [_preset_name(d.get("preset")) for d in (saved_info, info)]
    if saved != config:
        diff = first_difference(to_dict(saved), to_dict(config))
        made = f", made with --preset {presets[0]} (this command's: {presets[1]})" if presets[0] != presets[1] else ""
        raise CoworldError(
            f"{logdir} holds a run with other settings{made} ({diff}); rerun with the same settings to resume,"
            f" or {start_over}"
        )
    for key, value in info.items():
        if key == "preset" and presets[0] == presets[1]:
            continue  # one preset under two names ('tiny+' is 'tiny')
        if key in saved_info and saved_info[key] != value:
            raise CoworldError(
                f"{logdir} holds a run with {key}={saved_info[key]!r}, not {value!r};"
                f" rerun with the same settings to resume, or {start_over}"
            )
    check_source_replay(logdir, info, start_over)
    return True


def _preset_name(name: Any) -> Any:
    """A run description's preset by its one name (:func:`~coworld.config.canonical_preset`); anything else as it is."""
    try:
        return canonical_preset(name) if isinstance(name, str) else name
    except CoworldError:
        return name


def check_source_replay(logdir: Path, info: Mapping[str, Any], start_over: str) -> None:
    """The source experience a two-phase run records as its source agent learns (``source_replay.h5``, resumed
    with the run) is of the run's source task: the one it names, or the one it chose among several (none before
    the choice). One line otherwise, ending with ``start_over``; a file that cannot be read is left to the writer
    that resumes it."""
    from coworld.training.chosen_source import CHOICE_FILE, trained_source

    path = logdir / "source_replay.h5"
    if not isinstance(info.get("source"), str) or not path.is_file():
        return
    try:
        with h5py.File(path, "r") as f:
            task = f.attrs.get("task")
    except OSError:
        return
    task = task.decode() if isinstance(task, bytes) else task
    source = trained_source(logdir, info)
    if task == source:
        return
    if source is None:
        whose = f"the run has not chosen among its sources {info['source']} yet ({CHOICE_FILE})"
    else:
        whose = f"the run's source is {source}" + (f" ({CHOICE_FILE})" if "," in info["source"] else "")
    raise CoworldError(
        f"{path} holds {task} experience but {whose}, so one of them comes from another run or was edited; {start_over}"
    )


def prepare_run_dir(logdir: str | Path, config: Config, info: Mapping[str, Any], start_over: str = START_OVER) -> bool:
    """Create ``logdir`` with its config and run description, or check an existing one matches.

    Everything is checked (:func:`check_run_dir`) before anything is written; each file is written whole under
    a temporary name and renamed, ``config.json`` last.

    Returns:
        True when the folder already held this run (the caller resumes from its checkpoint).
    """
    if check_run_dir(logdir, config, info, start_over):
        return True
    logdir = Path(logdir)
    logdir.mkdir(parents=True, exist_ok=True)
    info = json.loads(json.dumps(dict(info)))
    write_text_atomically(logdir / "run.json", json.dumps(info, indent=2, sort_keys=True) + "\n")
    write_text_atomically(logdir / "config.json", to_json(config) + "\n")
    return False


def clear_run_dir(logdir: str | Path) -> None:
    """Remove what training wrote in ``logdir`` (its description and :data:`RUN_ARTEFACTS`), so the run starts over;
    other files in the folder (notes, a sweep's record) are left alone."""
    logdir = Path(logdir)
    for name in ("config.json", "run.json", *RUN_ARTEFACTS):  # the description first: a cut removal is no run
        path = logdir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def load_run(logdir: str | Path, fix: str = "") -> tuple[Config, dict[str, Any]]:
    """The config and run description saved by :func:`prepare_run_dir` (see :func:`run_description`).

    A missing, unreadable or damaged ``config.json`` or ``run.json`` (not UTF-8, not JSON, not an object, a config
    that does not build, a description without its algorithm) raises one CoworldError line naming
    the file, ending with ``fix`` when given.
    """
    logdir = Path(logdir)
    if not (logdir / "config.json").is_file() or not (logdir / "run.json").is_file():
        raise CoworldError(f"{logdir} is not a coworld run folder (no config.json / run.json)")
    config_data = read_json_object(logdir / "config.json", fix)
    if not config_data:  # every key would take its default: the paper preset, not what was run
        raise CoworldError(damaged(logdir / "config.json", "an empty object: it holds none of the run's settings", fix))
    try:
        config = from_dict(config_data)
    except ConfigError as err:
        raise CoworldError(damaged(logdir / "config.json", f"a config that does not build: {err}", fix)) from None
    info = run_description(read_json_object(logdir / "run.json", fix), logdir / "run.json")
    if not isinstance(info.get("algo"), str):
        raise CoworldError(damaged(logdir / "run.json", "no algo: it does not say what was trained", fix))
    return config, info
