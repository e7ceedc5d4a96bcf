"""Run folders, seeding and device choice shared by every trainer.

A run folder holds ``config.json`` (the resolved config), ``run.json`` (what was run: algorithm, tasks,
dataset), ``checkpoint.pt``, ``metrics.jsonl`` and TensorBoard files. Rerunning a command on an existing
folder resumes it; a folder made by different settings is refused rather than silently mixed.
"""

from __future__ import annotations

import json
import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from coworld.config import Config, first_difference, from_dict, to_dict, to_json
from coworld.errors import ConfigError, CoworldError
from coworld.storage import write_text_atomically


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def resolve_device(name: str | torch.device) -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cpu' / 'cuda' / 'cuda:1' as given (CUDA must be available)."""
    if isinstance(name, torch.device):
        device = name
    elif name == "auto":
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    else:
        try:
            device = torch.device(name)
        except RuntimeError:
            raise ConfigError(f"unknown device {name!r}; use 'auto', 'cpu' or 'cuda'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but torch sees no CUDA GPU; use --device cpu (or auto)")
    return device


def preset_warnings(preset: str, device: str) -> list[str]:
    """A warning when the GPU-sized paper preset is about to run on a CPU."""
    if preset != "paper" or resolve_device(device).type != "cpu":
        return []
    return [
        "the paper preset is sized for a GPU: on this CPU a paper-size update takes seconds, so a run takes weeks;"
        " pass --preset tiny to try things on a CPU (README, 'Presets')"
    ]


RUN_ARTEFACTS = ("checkpoint.pt", "metrics.jsonl", "tb", "source", "source_replay.h5", "eval.json")
"""What training leaves in a run folder besides its description (``run.json``, then ``config.json``, written
last): a folder holding any of these but no ``config.json`` was not described by ``coworld train``, or was
damaged, and is refused rather than resumed. Other files (a sweep's record, notes) are left alone."""


def check_run_dir(logdir: str | Path, config: Config, info: Mapping[str, Any]) -> bool:
    """Whether ``logdir`` can hold this run, without writing anything.

    Returns:
        True when the folder already holds this run (the caller resumes from its checkpoint), False when it is
        absent or new (no training artefacts, :data:`RUN_ARTEFACTS`).

    Raises:
        CoworldError: the folder holds another run (other settings or tasks), an unreadable description, or
        training artefacts that no ``config.json`` describes (a checkpoint copied in, say).
    """
    logdir = Path(logdir)
    config_path, info_path = logdir / "config.json", logdir / "run.json"
    info = json.loads(json.dumps(dict(info)))  # normalise tuples and paths the way JSON reads them back
    if logdir.exists() and not logdir.is_dir():
        raise CoworldError(f"{logdir} is a file, not a run folder; pass a new --logdir")
    if not config_path.exists():
        found = [name for name in RUN_ARTEFACTS if (logdir / name).exists()]
        if found:
            raise CoworldError(
                f"{logdir} holds {', '.join(found)} but no config.json, so it is not a run folder coworld train"
                " can resume (or it was damaged); nothing was changed: pass a new --logdir"
            )
        return False
    try:
        saved = from_dict(json.loads(config_path.read_text()))
        saved_info = json.loads(info_path.read_text()) if info_path.exists() else {}
    except (json.JSONDecodeError, ConfigError, OSError) as err:
        raise CoworldError(f"{config_path} is unreadable ({err}); nothing was changed: pass a new --logdir") from None
    if saved != config:
        diff = first_difference(to_dict(saved), to_dict(config))
        raise CoworldError(
            f"{logdir} holds a run with other settings ({diff}); rerun with the same settings to resume"
            " or pass a new --logdir"
        )
    for key, value in info.items():
        if key in saved_info and saved_info[key] != value:
            raise CoworldError(
                f"{logdir} holds a run with {key}={saved_info[key]!r}, not {value!r};"
                " rerun with the same settings to resume or pass a new --logdir"
            )
    return True


def prepare_run_dir(logdir: str | Path, config: Config, info: Mapping[str, Any]) -> bool:
    """Create ``logdir`` with its config and run description, or check an existing one matches.

    Everything is checked (:func:`check_run_dir`) before anything is written; each file is written whole under
    a temporary name and renamed, ``config.json`` last.

    Returns:
        True when the folder already held this run (the caller resumes from its checkpoint).
    """
    if check_run_dir(logdir, config, info):
        return True
    logdir = Path(logdir)
    logdir.mkdir(parents=True, exist_ok=True)
    info = json.loads(json.dumps(dict(info)))
    write_text_atomically(logdir / "run.json", json.dumps(info, indent=2, sort_keys=True) + "\n")
    write_text_atomically(logdir / "config.json", to_json(config) + "\n")
    return False


def collector_run_info(task: str, preset: str) -> dict[str, Any]:
    """The run description of the online DreamerV2 agent that ``coworld collect --policy dreamerv2`` trains: a
    dreamerv2 run like any other (``online`` says it learned in its environment, not from a dataset)."""
    return {"algo": "dreamerv2", "source": None, "target": task, "task": task, "preset": preset, "online": True}


def load_run(logdir: str | Path) -> tuple[Config, dict[str, Any]]:
    """The config and run description saved by :func:`prepare_run_dir` (see :func:`run_description`)."""
    logdir = Path(logdir)
    try:
        config = from_dict(json.loads((logdir / "config.json").read_text()))
        info = json.loads((logdir / "run.json").read_text())
    except FileNotFoundError:
        raise CoworldError(f"{logdir} is not a coworld run folder (no config.json / run.json)") from None
    except (json.JSONDecodeError, ConfigError) as err:
        raise CoworldError(f"the run description in {logdir} is unreadable ({err})") from None
    return config, run_description(info)


def run_description(info: Any) -> Any:
    """A run description as read from ``run.json``, with a collector's older description (only its ``task``
    and ``quality``, no ``algo``) completed as the online dreamerv2 run it is; anything else as it is."""
    if isinstance(info, dict) and "algo" not in info and "task" in info and "quality" in info:
        return {**collector_run_info(str(info["task"]), str(info.get("preset", "?"))), **info}
    return info
