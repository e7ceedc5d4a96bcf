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

from coworld.config import Config, from_dict, to_dict
from coworld.errors import ConfigError, CoworldError


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


def prepare_run_dir(logdir: str | Path, config: Config, info: Mapping[str, Any]) -> bool:
    """Create ``logdir`` with its config and run description, or check an existing one matches.

    Returns:
        True when the folder already held this run (the caller resumes from its checkpoint).
    """
    logdir = Path(logdir)
    config_path, info_path = logdir / "config.json", logdir / "run.json"
    info = json.loads(json.dumps(dict(info)))  # normalise tuples and paths the way JSON reads them back
    if config_path.exists():
        try:
            saved = from_dict(json.loads(config_path.read_text()))
            saved_info = json.loads(info_path.read_text()) if info_path.exists() else {}
        except (json.JSONDecodeError, ConfigError) as err:
            raise CoworldError(f"{config_path} is unreadable ({err}); use a new --logdir") from None
        if saved != config:
            diff = _diff(to_dict(saved), to_dict(config))
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
    logdir.mkdir(parents=True, exist_ok=True)
    config_path.write_text(json.dumps(to_dict(config), indent=2, sort_keys=True) + "\n")
    info_path.write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    return False


def load_run(logdir: str | Path) -> tuple[Config, dict[str, Any]]:
    """The config and run description saved by :func:`prepare_run_dir`."""
    logdir = Path(logdir)
    try:
        config = from_dict(json.loads((logdir / "config.json").read_text()))
        info = json.loads((logdir / "run.json").read_text())
    except FileNotFoundError:
        raise CoworldError(f"{logdir} is not a coworld run folder (no config.json / run.json)") from None
    except (json.JSONDecodeError, ConfigError) as err:
        raise CoworldError(f"the run description in {logdir} is unreadable ({err})") from None
    return config, info


def _diff(a: Mapping[str, Any], b: Mapping[str, Any], prefix: str = "") -> str:
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        if isinstance(va, Mapping) and isinstance(vb, Mapping):
            found = _diff(va, vb, f"{prefix}{key}.")
            if found:
                return found
        elif va != vb:
            return f"{prefix}{key}: saved {va!r}, now {vb!r}"
    return ""
